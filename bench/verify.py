"""Benchmark: verify a 5-megapixel capture (2592 x 1944) of an N = 175 plate.

Prints the median wall time over a few runs of the whole ``doefab verify``
command in a new process, as a user runs it (reading the 16-bit PNG and its
dark frame, registration, photometry, diagnosis, report), and of its stages in
this process, for a retrieved (high-efficiency) design, for a dense random
level map (thousands of bright dots: the most work for registration and
photometry) and for that map with its mid mask 2 um off (a failing plate: the
overlay fit runs). Target: <= 5 s on a 2-core machine.
"""

import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from doe.derived import derive
from doe.design import load_design
from doe.fraunhofer import simulate_levels
from doe.infra.files import save_npy, write_json
from doe.retrieval import retrieve_phase
from doe.targets import make_target
from fab.plate.model import PlateFaults
from fab.verify.analysis import analyse, design_order_power, resolve_thresholds
from fab.verify.capture import read_capture, write_image
from fab.verify.conditioning import repair_pixels
from fab.verify.hot_pixels import repair_hot_pixels
from fab.verify.lattice import register_lattice
from fab.verify.photometry import measure_orders
from fab.verify.simulate import simulate_capture

RUNS = 5
SHAPE = (1944, 2592)
CAMERA_PITCH = 3.45e-6


def main_bench():
    design = load_design()
    der = derive(design)
    n, k, n_levels = der.tile_pixels, design.kernel_size, design.fabrication.levels
    pitch_px = der.lattice_pitch / CAMERA_PITCH
    plates = {
        "retrieved 'asymmetric' design": retrieve_phase(
            make_target("asymmetric", k), n, n_levels, seed=0
        ).levels,
        "dense random levels": np.random.default_rng(0)
        .integers(0, n_levels, (n, n))
        .astype(np.uint8),
    }
    for label, levels in plates.items():
        print(f"== {label} (N={n}, K={k})")
        _bench_plate(levels, n_levels, k, der, pitch_px)
    overlay = PlateFaults(overlay=((0.0, 0.0), (0.0, 2e-6), (0.0, 0.0)))
    print(f"== dense random levels, M2_mid 2 um off (N={n}, K={k}; fails: overlay_error)")
    _bench_plate(plates["dense random levels"], n_levels, k, der, pitch_px, overlay)
    # Two faults at once: neither fit alone explains the PSF, so both are fitted together.
    both = PlateFaults(etch_errors=(0.0, 0.3, 0.0), overlay=((0.0, 3e-6), (0.0, 0.0), (0.0, 0.0)))
    print(
        f"== dense random levels, M1_deep 3 um off and M2_mid 30 % too deep (N={n}, K={k}; "
        "fails: overlay_error, etch_depth_error)"
    )
    _bench_plate(plates["dense random levels"], n_levels, k, der, pitch_px, both)


def _bench_plate(levels, n_levels, k, der, pitch_px, faults=None):
    """Time verify on a capture of ``levels`` (a good plate, or one with ``faults``)."""
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        d = tmp / "design"
        d.mkdir()
        save_npy(d / "levels.npy", levels)
        save_npy(d / "target_psf.npy", simulate_levels(levels, n_levels, k)[0])
        write_json(
            d / "fab_manifest.json",
            {
                "levels": n_levels,
                "kernel_size": k,
                "lattice_pitch_um": der.lattice_pitch * 1e6,
                "masks": [
                    {
                        "name": "M1_deep",
                        "etch_depth_nm": der.etch_depths[0] * 1e9,
                        "exposure_order": 1,
                    }
                ],
            },
        )
        t0 = time.perf_counter()
        sim = simulate_capture(
            levels,
            n_levels,
            shape=SHAPE,
            pitch_px=pitch_px,
            centre=(1001.3, 1247.8),
            rotation_deg=1.2,
            hot_pixels=200,
            seed=1,
            faults=faults or PlateFaults(),
            mask_pixel_pitch=der.mask_pixel_pitch,
            supersample=1 if faults is None else 4,
        )
        print(f"simulated a {SHAPE[1]}x{SHAPE[0]} capture in {time.perf_counter() - t0:.2f} s")
        write_image(tmp / "capture.png", sim["capture"], exposure=0.01)
        write_image(tmp / "dark.png", sim["dark"], exposure=0.01)

        stages = {"read+condition": [], "register": [], "photometry": [], "analyse": []}
        for _ in range(RUNS):
            t = time.perf_counter()
            cap = read_capture(tmp / "capture.png", tmp / "dark.png")
            t1 = time.perf_counter()
            found = repair_pixels(cap.image, cap.hot)
            lattice, _ = register_lattice(found, pitch_px, quantum=cap.quantum)
            t2 = time.perf_counter()
            image, repaired = repair_hot_pixels(cap.image, cap.hot, cap.saturated, lattice)
            grid = measure_orders(image, lattice, cap.saturated & ~repaired, cap.quantum)
            t3 = time.perf_counter()
            _psf, eff = simulate_levels(levels, n_levels, k)
            thr = resolve_thresholds(None, eff, design_order_power(levels, n_levels)[0, 0])
            result, _ = analyse(grid, levels, n_levels, k, "as-designed", thr)
            t4 = time.perf_counter()
            for key, dt in zip(stages, (t1 - t, t2 - t1, t3 - t2, t4 - t3), strict=True):
                stages[key].append(dt)
        for key, times in stages.items():
            print(f"  {key:15s} median {statistics.median(times):.3f} s")
        print(f"  diagnosis: {', '.join(result['diagnosis'])}")

        # The whole command as a user runs it: a new process, which pays for Python,
        # the imports and matplotlib's first figure (timed in this warm process, half
        # as long).
        totals = []
        for i in range(RUNS):
            args = ["verify", str(d), str(tmp / "capture.png"), "--dark", str(tmp / "dark.png")]
            t = time.perf_counter()
            done = subprocess.run(
                [sys.executable, "-m", "doe", *args, "--out", str(tmp / f"out{i}")],
                capture_output=True,
                text=True,
            )
            totals.append(time.perf_counter() - t)
            if done.returncode != (0 if faults is None else 1):
                print(f"verify returned {done.returncode}: {done.stderr}", file=sys.stderr)
        print(
            f"doefab verify (new process), 5 MP 16-bit PNG + dark: median "
            f"{statistics.median(totals):.2f} s over {RUNS} runs (min {min(totals):.2f}, "
            f"max {max(totals):.2f}); target <= 5 s"
        )


if __name__ == "__main__":
    import argparse

    argparse.ArgumentParser(
        description=__doc__.splitlines()[0] + " Run: python bench/verify.py (about 35 s)."
    ).parse_args()
    main_bench()
