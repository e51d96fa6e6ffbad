"""What a learned PSF gains over the best fixed one, lever by lever (docs/learn.md, "Levers").

Trains, with one step budget on the Sun-Hays 80 images, the fixed PSFs a plate
could be asked for (no plate, the 4 x 4 box, Gaussians of sigma 1-2 sub-pixels,
and the best non-negative PSF for a linear reconstruction,
:func:`psf_learn.linear_optimum.optimal_psf`, on the training images' spectrum),
then the learned PSF with each lever: where it starts (``--psf-start``), how
long it learns (``--psf-until``, ``--psf-lr``), a 21 x 21 window (the Wiener base
and the real active area: ``bench/learn_variants.py``). Each is
scored on Set5 and Set14 in the SR papers' convention (PSNR-Y), and the table
gives each learned row's margin over the best fixed PSF of each set (target:
0.2 dB), and every PSF's linear PSNR: what a Wiener filter alone makes
of its captures, on the training spectrum.

    python bench/learn_levers.py --steps 6000 --parallel 2      # 30 min, 2 cores
    python bench/learn_levers.py --steps 300 --only box learned  # proves the script
    python bench/learn_levers.py --reuse       # score what --out holds, train the rest
    python bench/learn_levers.py --reprint
"""

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
from learn_runs import ROOT, train_all

from doe.infra import flags

DATA = ROOT.parent / "shared" / "data"
FIXED = [
    ("delta", "no plate (delta)", ["--psf", "delta"]),
    ("box", "4 x 4 box (full fill factor)", ["--psf", "box"]),
    *[(f"g{s:g}", f"Gaussian sigma {s:g}", ["--psf", f"gaussian:{s:g}"]) for s in
      (1.0, 1.25, 1.5, 1.75, 2.0)],
    ("linear", "best PSF for a linear reconstruction", ["--psf", "{linear}"]),
]  # fmt: skip
LEARNED = [
    ("learned", "learned (default start: sigma 0.459 on the axis)", []),
    ("start_g1.5", "learned from Gaussian sigma 1.5", ["--psf-start", "gaussian:1.5"]),
    ("start_box", "learned from the box", ["--psf-start", "box"]),
    ("start_random", "learned from random", ["--psf-start", "random"]),
    ("start_dots", "learned from 6 dots", ["--psf-start", "dots"]),
    ("start_linear", "learned from the linear optimum", ["--psf-start", "{linear}"]),
    ("until_0.5", "learned, PSF frozen after half the run", ["--psf-until", "0.5"]),
    ("psf_lr_0.2", "learned, PSF learning rate 0.2", ["--psf-lr", "0.2"]),
    ("psf_lr_0.01", "learned, PSF learning rate 0.01", ["--psf-lr", "0.01"]),
    (
        "g1.5_until_0.5",
        "learned from sigma 1.5, frozen after half",
        ["--psf-start", "gaussian:1.5", "--psf-until", "0.5"],
    ),
    ("k21", "learned in a 21 x 21 window", ["--config", "{k21}"]),
]
TARGET_DB = 0.2  # the margin over the best fixed PSF a learned one is to earn
SETS = ("set5", "set14")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--steps", type=flags.count, default=6000, help="step budget of every model")
    p.add_argument("--data", default=str(DATA), help="folder holding set5/, set14/, sun_hays80/")
    p.add_argument("--out", default=str(ROOT / "bench" / "out" / "learn_levers"))
    p.add_argument("--parallel", type=flags.count, default=2, help="models trained at once")
    p.add_argument("--only", nargs="+", help="train and score only these rows (keys)")
    p.add_argument("--reuse", action="store_true", help="score the rows in --out, train the rest")
    p.add_argument("--reprint", action="store_true", help="print --out's levers.json again")
    args = p.parse_args(argv)
    out = Path(args.out)
    if args.reprint:
        _print(json.loads((out / "levers.json").read_text()))
        return 0
    known = [key for key, _, _ in FIXED + LEARNED]
    unknown = sorted(set(args.only or ()) - set(known))
    if unknown:
        p.error(f"--only: no row {', '.join(unknown)}; the rows are {', '.join(known)}")
    data = Path(args.data)
    for name in ("sun_hays80", *SETS):
        if not (data / name).is_dir():
            p.error(f"{data / name}: no such folder (--data)")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    spectrum, noise = _training_spectrum(data / "sun_hays80")
    files = _reference_files(out, spectrum, noise)
    rows = [r for r in FIXED + LEARNED if not args.only or r[0] in args.only]
    jobs = [
        (key, [a.format(**files) for a in flags])
        for key, _, flags in rows
        if not (args.reuse and (out / key / "model.pt").exists())
    ]
    common = ["--images", str(data / "sun_hays80"), "--steps", str(args.steps)]
    train_all(out, jobs, args.parallel, [*common, "--no-baseline", "--force", "--restart"])
    results = _score(out, rows, data, spectrum, noise)
    results["seconds"] = round(time.perf_counter() - t0, 1)
    results["steps"] = args.steps
    (out / "levers.json").write_text(json.dumps(results, indent=2) + "\n")
    _print(results)
    return 0


def _training_spectrum(folder):
    """Return (power spectrum of the training images, a pixel's noise variance) at 10^4 counts."""
    from doe.design import load_design
    from psf_learn.images import read_folder
    from psf_learn.linear_optimum import image_spectrum

    _, images = read_folder(folder)
    photons = load_design().learning.photons_per_pixel
    mean = float(np.mean([im.mean() for im in images]))
    return image_spectrum(images), mean / photons  # Poisson: variance = mean / photons


def _reference_files(out, spectrum, noise):
    """Write the linear optimum's PSF and the 21 x 21 design; return {name: path}."""
    from psf_learn.linear_optimum import optimal_psf
    from psf_learn.psf import point_sample_weights

    linear = out / "linear_optimum_psf.npy"
    np.save(linear, optimal_psf(spectrum, point_sample_weights(), noise))
    text = (ROOT / "doe" / "presets" / "sun2020.toml").read_text()
    k21 = out / "sun2020_k21.toml"
    k21.write_text(text.replace("kernel_size = 11", "kernel_size = 21", 1))
    return {"linear": str(linear), "k21": str(k21)}


def _score(out, rows, data, spectrum, noise):
    import torch

    from psf_learn.evaluate import evaluate
    from psf_learn.images import read_folder
    from psf_learn.linear_optimum import linear_psnr
    from psf_learn.sr import load_model

    torch.set_num_threads(2)
    sets = {name: read_folder(data / name) for name in SETS}
    results = {"rows": {}}
    for key, label, _ in rows:
        model = load_model(out / key)
        row = {"label": label, "fixed": key in {k for k, _, _ in FIXED}}
        row["steps"] = model.learn.steps  # --reuse: the model's own, whatever this run asked
        for name, (names, images) in sets.items():
            row[name] = evaluate(model, names, images)["psnr_y"]
        row["linear_psnr"] = linear_psnr(model.psf, spectrum, model.sensor.weights, noise)
        row["psf"] = model.psf.tolist()
        results["rows"][key] = row
        print(f"scored {key}", file=sys.stderr)
    return results


def _print(results):
    rows = results["rows"]
    rivals = [k for k, r in rows.items() if r["fixed"] and k not in ("delta", "linear")]
    best = {s: max((rows[k][s] for k in rivals), default=math.nan) for s in SETS}
    print(
        f"\nPSNR-Y (dB, the SR papers' convention) after {results.get('steps')} steps; "
        "'over best' = the margin over the best of the box and Gaussians sigma 1-2 on that "
        f"set (target {TARGET_DB} dB); 'linear' = PSNR of a Wiener filter alone on "
        "the training spectrum"
    )
    print(f"{'row':54s}{'Set5':>8s}{'Set14':>8s}{'over best':>16s}{'linear':>9s}")
    for r in rows.values():
        margin = (
            "" if r["fixed"] or not rivals else "/".join(f"{r[s] - best[s]:+.2f}" for s in SETS)
        )
        steps = r.get("steps", results["steps"])
        label = r["label"] + ("" if steps == results["steps"] else f" ({steps} steps)")
        print(f"{label[:54]:54s}{r['set5']:8.2f}{r['set14']:8.2f}{margin:>16s}"
              f"{r['linear_psnr']:9.3f}")  # fmt: skip
    learned = [r for r in rows.values() if not r["fixed"]]
    if learned and rivals:
        top = max(learned, key=lambda r: min(r[s] - best[s] for s in SETS))
        worst = min(top[s] - best[s] for s in SETS)
        verdict = "reaches" if worst >= TARGET_DB else "misses"
        print(f"best learned row: {top['label']}, {worst:+.2f} dB on its weaker set: "
              f"{verdict} the {TARGET_DB} dB margin")  # fmt: skip
    if results.get("seconds") is not None:
        print(f"{len(rows)} rows in {results['seconds'] / 60:.1f} min")


if __name__ == "__main__":
    sys.exit(main())
