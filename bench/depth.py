"""Benchmark of the gated-SPAD depth fit (issue 7): timing error and speed.

On 32 x 64 cubes (200 gate positions, 20 ps shift, the default gate model,
Poisson noise) at high, medium and low photon counts, prints the RMSE of the
arrival time mu of

* the vectorised Poisson fit of ``psf_learn.depth.fit_profiles``,
* a reference least-squares fit that knows the true gate model
  (``scipy.optimize.least_squares`` per pixel, on a subset of pixels), started
  from the histogram argmax and, as a best case, from the true parameters,
* the histogram argmax (argmax time minus the response's peak time),

and the time to process a 64 x 32 x 200 cube (the fit alone, and the whole
``doefab depth`` command with its files and figures).

Issue 47's acceptance, per scan direction (gate, laser) and photon level
(high, medium, low): the timing RMSE (bias included, all 2048 pixels) of the
whole ``doefab depth`` command with default flags (``--scan auto``), of the
least-squares fit that knows the true model (direction, gate; started from the
truth), the Cramer-Rao bound (RMS over the pixels), their ratio (acceptance
<= 1.1) and the command's wall time (acceptance <= 5 s).

Run: ``python bench/depth.py [--subset 300] [--seed 0] [--only directions|calibration|...]``
"""

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from doe.infra import flags
from psf_learn.depth import (
    GateModel,
    cramer_rao_timing,
    fit_profiles,
    gate_response,
    scan_times,
)
from psf_learn.depth_scan import scan_responses
from psf_learn.depth_sim import random_scene, simulate_cube

PS = 1e-12
SHIFT = 20 * PS
T = 200
LEVELS = {  # name -> (peak signal counts A, background counts per sample b)
    "high": (1000.0, 10.0),
    "medium": (100.0, 5.0),
    "low": (10.0, 2.0),
    "very low": (3.0, 1.0),
}


def reference_fit(y, x0, response, t_ps):
    """Least-squares fit of A h(t - mu) + b to one profile; return mu (ps)."""

    def residual(p):
        return p[0] * response((t_ps - p[1]) * PS) + p[2] - y

    scale = [max(x0[0], 1.0), 10.0, max(x0[2], 1.0)]
    bounds = ([0.0, t_ps[0] - 2000.0, 0.0], [np.inf, t_ps[-1] + 2000.0, np.inf])
    return least_squares(residual, x0, x_scale=scale, bounds=bounds).x[1]


def rmse(err):
    """RMSE in ps; a NaN (no return reported) counts as a failure: returns inf."""
    err = np.asarray(err)
    return float(np.sqrt(np.mean(err**2))) if np.all(np.isfinite(err)) else float("inf")


def show(value, err):
    """Format an RMSE; where no-returns make it inf, show the RMSE of the detected pixels + '*'."""
    if np.isfinite(value):
        return f"{value:8.2f} "
    err = np.asarray(err)
    return f"{np.sqrt(np.mean(err[np.isfinite(err)] ** 2)):8.2f}*"


def accuracy(response, subset, seed):
    t_ps = scan_times(T, SHIFT) / PS
    rng = np.random.default_rng(seed)
    print(f"timing error, 32 x 64 cubes, T = {T}, shift 20 ps, default gate, Poisson noise")
    print(f"(reference LS on {subset} random pixels per cube; RMSE in ps)")
    head = (f"{'counts':>9s} {'A':>6s} {'b':>5s} | {'fit(all)':>8s}  {'fit(sub)':>8s}  "
            f"{'LS argmax0':>10s} {'LS true0':>8s} {'argmax':>8s} | {'fit/LS':>6s} "
            f"{'fit/argmax':>10s} {'no return':>9s}")  # fmt: skip
    print(head)
    print("-" * len(head))
    for name, (amp, bg) in LEVELS.items():
        a, mu, b = random_scene((32, 64), amp, bg, SHIFT, T, response, rng)
        cube = simulate_cube(a, mu, b, T, SHIFT, response, rng)
        fit = fit_profiles(cube, SHIFT, response)
        err = (fit.timing - mu) / PS
        y = cube.reshape(-1, T).astype(np.float64)
        mu_ps = mu.ravel() / PS
        idx = rng.choice(y.shape[0], size=min(subset, y.shape[0]), replace=False)
        ref_argmax, ref_true = [], []
        for i in idx:
            k = int(np.argmax(y[i]))
            med = float(np.median(y[i]))
            x0 = [max(y[i, k] - med, 1.0), t_ps[k] - response.peak_time / PS, med]
            ref_argmax.append(reference_fit(y[i], x0, response, t_ps))
            ref_true.append(reference_fit(y[i], [amp, mu_ps[i], bg], response, t_ps))
        ref_a = rmse(np.array(ref_argmax) - mu_ps[idx])
        ref_t = rmse(np.array(ref_true) - mu_ps[idx])
        argmax = rmse(t_ps[np.argmax(cube, axis=-1)] - response.peak_time / PS - mu / PS)
        ours_all, ours_sub = rmse(err), rmse(err.ravel()[idx])
        best_ref = min(ref_a, ref_t)
        cols = show(ours_all, err) + show(ours_sub, err.ravel()[idx])
        # With no-returns the fit's RMSE is undefined, and so are the ratios: "-".
        vs_ls = f"{ours_sub / best_ref:6.3f}" if np.isfinite(ours_sub) else f"{'-':>6s}"
        vs_argmax = f"{ours_all / argmax:10.3f}" if np.isfinite(ours_all) else f"{'-':>10s}"
        print(f"{name:>9s} {amp:6.0f} {bg:5.1f} | {cols}"
              f"{ref_a:10.2f} {ref_t:8.2f} {argmax:8.2f} | {vs_ls} "
              f"{vs_argmax} {int((~fit.valid).sum()):9d}")  # fmt: skip
    print(
        "fit/LS: fit RMSE on the subset over the better of the two reference fits "
        "(acceptance: <= 1.10); fit/argmax: acceptance <= 0.5"
    )


def directions(seed):
    """Issue 47: default flags (auto) against a true-model least-squares fit, both ways."""
    responses = scan_responses()
    t_ps = scan_times(T, SHIFT) / PS
    rng = np.random.default_rng(seed + 3)
    print(f"\nscan directions, 32 x 64 x {T} cubes, shift 20 ps, default gate; timing RMSE "
          "in ps over all 2048 pixels, bias included")  # fmt: skip
    head = (f"{'scan':>5s} {'counts':>6s} {'A':>5s} {'b':>4s} | {'auto':>6s} {'chose':>5s} "
            f"{'dlogL':>8s} | {'LS true':>7s} {'CRB':>6s} | {'auto/LS':>7s} {'s':>5s}")  # fmt: skip
    print(head)
    print("-" * len(head))
    with tempfile.TemporaryDirectory() as tmp:
        for scan, response in responses.items():
            for name in ("high", "medium", "low"):
                amp, bg = LEVELS[name]
                a, mu, b = random_scene((32, 64), amp, bg, SHIFT, T, response, rng)
                cube = simulate_cube(a, mu, b, T, SHIFT, response, rng)
                path, out = Path(tmp) / f"{scan}-{name}.npy", Path(tmp) / f"{scan}-{name}"
                np.save(path, cube.astype(np.uint16))
                cmd = [sys.executable, "-m", "doe", "depth", str(path), "--out", str(out)]
                t0 = time.perf_counter()
                subprocess.run(cmd, check=True, capture_output=True)
                wall = time.perf_counter() - t0
                record = json.loads((out / "depth.json").read_text())["scan"]
                auto = rmse(np.load(out / "timing_ps.npy") - mu / PS)
                y = cube.reshape(-1, T).astype(np.float64)
                starts = zip(a.ravel(), mu.ravel() / PS, b.ravel(), strict=True)
                ref = [
                    reference_fit(yi, list(x0), response, t_ps)
                    for yi, x0 in zip(y, starts, strict=True)
                ]
                ls = rmse(np.array(ref) - mu.ravel() / PS)
                bound = np.sqrt(np.mean(cramer_rao_timing(response, t_ps * PS, a, mu, b) ** 2))
                print(f"{scan:>5s} {name:>6s} {amp:5.0f} {bg:4.0f} | {auto:6.2f} "
                      f"{record['direction']:>5s} {record['log_likelihood_difference']:8.0f} | "
                      f"{ls:7.2f} {bound / PS:6.2f} | {auto / ls:7.3f} {wall:5.2f}")  # fmt: skip
    print("auto: 'doefab depth CUBE --out DIR' (default flags); LS true: least squares with "
          "the true model from the true start; acceptance auto/LS <= 1.10 and s <= 5; "
          f"load average now {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")  # fmt: skip


def speed(response, seed, repeats=5):
    rng = np.random.default_rng(seed + 1)
    a, mu, b = random_scene((64, 32), 100.0, 5.0, SHIFT, T, response, rng)
    cube = simulate_cube(a, mu, b, T, SHIFT, response, rng)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fit_profiles(cube, SHIFT, gate_response(GateModel()))
        times.append(time.perf_counter() - t0)
    print(f"\nspeed, 64 x 32 x 200 cube: gate model + fit median {statistics.median(times):.3f} s "
          f"(min {min(times):.3f}, {repeats} runs)")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "cube.npy"
        np.save(path, cube.astype(np.uint16))
        walls, cpus = [], []
        for k in range(3):
            cmd = [sys.executable, "-m", "doe", "depth", str(path), "--shift-ps", "20",
                   "--out", str(Path(tmp) / f"out{k}")]  # fmt: skip
            t0, c0 = time.perf_counter(), _children_cpu()
            subprocess.run(cmd, check=True, capture_output=True)
            walls.append(time.perf_counter() - t0)
            cpus.append(_children_cpu() - c0)
    print(f"speed, 64 x 32 x 200 cube: whole 'doefab depth' command (start-up, files, figures) "
          f"median {statistics.median(walls):.2f} s wall (min {min(walls):.2f}, 3 runs), "
          f"{statistics.median(cpus):.2f} s CPU; load average now "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")  # fmt: skip


def memory(response, seed):
    """Peak memory of the fit (tracemalloc): it must grow as pixels x samples, not T^2."""
    import tracemalloc

    rng = np.random.default_rng(seed + 2)
    print()
    for pixels, samples in ((16, 1000), (16, 4000), (2048, 200), (2048, 1000)):
        a, mu, b = random_scene((pixels, 1), 100.0, 5.0, SHIFT, samples, response, rng)
        cube = simulate_cube(a, mu, b, samples, SHIFT, response, rng)
        tracemalloc.start()
        fit_profiles(cube, SHIFT, response)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        print(f"memory, {pixels} pixels x {samples} samples: peak {peak / 1e6:.0f} MB "
              f"= {peak / (pixels * samples):.0f} bytes per pixel-sample")  # fmt: skip


def _children_cpu():
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def skewed_array(subset, seed):
    """Print bench/depth_calibration.py's table: a skewed array with and without calibration."""
    script = Path(__file__).with_name("depth_calibration.py")
    subprocess.run(
        [sys.executable, str(script), "--subset", str(subset), "--seed", str(seed)], check=True
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--subset", type=flags.count, default=300, help="pixels for the reference fit"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--only",
        choices=("accuracy", "directions", "calibration", "speed", "memory"),
        help="one part only",
    )
    args = parser.parse_args()
    response = gate_response(GateModel())
    parts = {
        "accuracy": lambda: accuracy(response, args.subset, args.seed),
        "directions": lambda: directions(args.seed),
        "calibration": lambda: skewed_array(args.subset, args.seed),
        "speed": lambda: speed(response, args.seed),
        "memory": lambda: memory(response, args.seed),
    }
    for name, part in parts.items():
        if args.only in (None, name):
            part()


if __name__ == "__main__":
    main()
