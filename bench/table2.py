"""Table 2 of Sun et al. 2020: the four sampling schemes under the same training budget.

Trains low fill-factor (delta PSF), full fill-factor (4 x 4 box), Gaussian
(sigma 0.459 sub-pixel as the issue reads the paper, and sigma 0.459 SPAD
pixel = 1.836 sub-pixels, the other reading of the paper's sigma)
and learned-PSF models with ``doefab learn`` on the
same images and the same budget, evaluates them on Set5, Set14 and any extra
folders, and prints PSNR/SSIM beside the paper's numbers. The learned model is
also evaluated with the PSF that its 8-level retrieved plate actually produces
(``doe.retrieval.retrieve_phase`` then ``doe.fraunhofer.simulate_levels``), the
as-fabricated figure.

Models train as separate processes, ``--parallel`` at a time, each with
cores / parallel CPU threads (default: one after another on all cores). The
budget is wall-clock minutes per model, or ``--steps``: a step budget gives
the same models whatever else the machine is doing (45000 steps take 14 min
with 2 threads on the idle 2-core machine).

    python bench/table2.py --minutes 6
    python bench/table2.py --minutes 15 --extra held_back_images/
    python bench/table2.py --minutes 6 -- --photons 10000   # extra `doefab learn` flags
    python bench/table2.py --data DIR --models low_ff learned --no-fab   # a GPU node

``--data`` names the folder with ``set5/``, ``set14/`` and ``sun_hays80/`` where
``../shared/data`` is not beside the checkout. The as-fabricated row needs nlopt;
without it the script stops before training unless ``--no-fab`` is given.
"""

import argparse
import importlib.util
import itertools
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
MODELS = (  # (key, --psf, label)
    ("low_ff", "delta", "low fill-factor"),
    ("full_ff", "box", "full fill-factor"),
    ("gaussian", "gaussian", "Gaussian 0.459 sub-px"),
    ("gaussian_px", "gaussian:1.836", "Gaussian 0.459 SPAD px"),
    ("learned", "learned", "learned PSF"),
)
PAPER = {  # PSNR dB on Set5 / Set14 / BSDS100, Sun et al. 2020, Table 2
    "low_ff": (27.17, 23.97, 23.82),
    "full_ff": (29.77, 26.13, 25.59),
    "gaussian": (30.41, 26.68, 26.05),
    "gaussian_px": (30.41, 26.68, 26.05),
    "learned": (30.76, 26.91, 26.23),
}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--minutes", type=float, default=15.0, help="training budget per model")
    p.add_argument("--steps", type=int, help="fixed step budget per model instead of minutes")
    p.add_argument(
        "--data", default=str(DATA), help="folder holding set5/, set14/ (and sun_hays80/)"
    )
    p.add_argument("--train", help="training images (default: DATA/sun_hays80)")
    p.add_argument("--extra", nargs="*", default=[], help="more evaluation folders")
    p.add_argument("--out", default=str(ROOT / "bench" / "out" / "table2"), help="work folder")
    p.add_argument("--parallel", type=int, default=1, help="models trained at once")
    p.add_argument(
        "--models",
        nargs="+",
        choices=[key for key, _, _ in MODELS],
        default=[key for key, _, _ in MODELS],
        help="which models to train and evaluate (default: all)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--reuse", action="store_true", help="evaluate existing models, no training")
    p.add_argument("--no-fab", action="store_true", help="skip the as-fabricated evaluation")
    p.add_argument("--force", action="store_true", help="retrain over models already in --out")
    p.add_argument("learn_args", nargs=argparse.REMAINDER, help="extra `doefab learn` flags")
    args = p.parse_args(argv)
    if args.learn_args[:1] == ["--"]:
        args.learn_args = args.learn_args[1:]
    args.train = args.train or str(Path(args.data) / "sun_hays80")
    if not args.no_fab and importlib.util.find_spec("nlopt") is None:
        # found before the training, not after it (a GPU node may lack nlopt)
        p.error("the as-fabricated row retrieves a plate with nlopt: install it, or --no-fab")
    out = Path(args.out)
    trained = [key for key in args.models if (out / key).exists()]
    if trained and not (args.reuse or args.force):
        p.error(
            f"{out} holds trained models ({', '.join(trained)}): --reuse evaluates them, "
            "--force retrains over them"
        )
    from doe.infra.errors import InputError

    try:  # every image folder is read before hours of training, not after
        data = _read_sets(args)
    except InputError as e:
        p.error(str(e))
    out.mkdir(parents=True, exist_ok=True)
    if not args.reuse:
        _train_all(args, out)
    results = _evaluate_all(args, out, data)
    (out / "table2.json").write_text(json.dumps(results, indent=2, sort_keys=True) + "\n")
    _print_table(results, args)
    return 0


def _train_all(args, out):
    budget = ["--steps", str(args.steps)] if args.steps else ["--minutes", str(args.minutes)]
    queue = [model for model in MODELS if model[0] in args.models]
    running = []
    while queue or running:
        while queue and len(running) < args.parallel:
            key, psf, _ = queue.pop(0)
            cmd = [
                sys.executable,
                "-m",
                "doe",
                "learn",
                "--out",
                str(out / key),
                "--images",
                args.train,
                "--psf",
                psf,
                "--seed",
                str(args.seed),
                "--force",
                "--restart",
                "--threads",
                str(max(1, (os.cpu_count() or 1) // args.parallel)),
                *budget,
                *args.learn_args,
            ]
            log = open(out / f"{key}.log", "w")  # closed when the process ends
            print(f"training {key}: {' '.join(cmd[2:])}", file=sys.stderr)
            running.append((key, subprocess.Popen(cmd, stdout=log, stderr=log, cwd=ROOT), log))
        time.sleep(2)
        for item in list(running):
            key, proc, log = item
            if proc.poll() is not None:
                log.close()
                running.remove(item)
                if proc.returncode:
                    sys.exit(f"training {key} failed, see {out / (key + '.log')}")
                print(f"trained {key}", file=sys.stderr)


def _as_fabricated_psf(learned_psf):
    """PSF of the 8-level plate retrieved for the learned PSF, and the plate's figures."""
    from doe.derived import derive
    from doe.design import load_design
    from doe.fraunhofer import simulate_levels
    from doe.retrieval import retrieve_phase

    design = load_design()
    n = derive(design).tile_pixels
    levels = design.fabrication.levels
    ret = retrieve_phase(learned_psf, n, n_levels=levels, seed=0)
    psf, efficiency = simulate_levels(ret.levels, levels, learned_psf.shape[0])
    return psf, {"efficiency": efficiency, **ret.quality_quantised}


def _read_sets(args):
    """Return {set name: (names, images)} of Set5, Set14 and the extra folders."""
    from doe.infra.errors import InputError
    from psf_learn.images import read_folder

    sets = {"Set5": Path(args.data) / "set5", "Set14": Path(args.data) / "set14"}
    sets.update({Path(e).name: Path(e) for e in args.extra})
    for folder in (args.train, *sets.values()):
        if not Path(folder).is_dir():
            raise InputError(folder, "no such folder")
    return {name: read_folder(folder) for name, folder in sets.items()}


def _evaluate_all(args, out, data):
    import torch

    from doe.records.learn import LEARN_JSON, read_learn
    from psf_learn.evaluate import evaluate
    from psf_learn.learn_plan import idle_cores
    from psf_learn.sr import load_model

    torch.set_num_threads(idle_cores())
    results = {"sets": list(data), "models": {}}
    for key, _, label in MODELS:
        if key not in args.models:
            continue
        model = load_model(out / key)
        learn = read_learn(out / key / LEARN_JSON)
        row = {
            "label": label,
            "steps": learn.steps,
            "seconds": learn.seconds,
            "psf": model.psf.tolist(),
        }
        for name, (names, images) in data.items():
            row[name] = evaluate(model, names, images)
        results["models"][key] = row
        print(f"evaluated {key}", file=sys.stderr)
    if not args.no_fab and "learned" in args.models:
        learned = load_model(out / "learned")
        t0 = time.perf_counter()
        psf, quality = _as_fabricated_psf(learned.psf)
        row = {
            "label": "learned, as fabricated (8 levels)",
            "quality": quality,
            "retrieval_seconds": time.perf_counter() - t0,
            "psf": psf.tolist(),
        }
        for name, (names, images) in data.items():
            row[name] = evaluate(learned, names, images, psf=psf)
        results["models"]["learned_fab"] = row
    return results


def _print_table(results, args):
    sets = results["sets"]
    budget = f"{args.steps} steps" if args.steps else f"{args.minutes:g} min"
    if args.reuse:  # the models' own budgets, not this command's
        budget = "as trained, steps in brackets"
    m = results["models"]
    steps = f", {m['learned']['steps']} steps for the learned model" if "learned" in m else ""
    print(f"\nTable 2 (PSNR dB / SSIM, 4x SR, budget {budget} per model{steps})")
    head = f"{'model':36s}" + "".join(f"{s:>16s}" for s in sets)
    print(head + f"{'paper Set5/Set14/B100':>26s}{'gap Set5/Set14':>18s}")
    for key, row in results["models"].items():
        cells = "".join(f"{row[s]['psnr']:8.2f}/{row[s]['ssim']:.4f}"[:16].rjust(16) for s in sets)
        paper = PAPER.get(key)
        ref = "/".join(f"{v:.2f}" for v in paper) if paper else ""
        gap = (
            f"{row['Set5']['psnr'] - paper[0]:+.2f}/{row['Set14']['psnr'] - paper[1]:+.2f}"
            if paper
            else ""
        )
        label = f"{row['label']} ({row['steps']})" if "steps" in row else row["label"]
        print(f"{label:36s}{cells}{ref:>26s}{gap:>18s}")
    for s in sets:
        for gauss in [g for g in ("gaussian", "gaussian_px") if g in m] or [None]:
            keys = [k for k in ("learned", gauss, "full_ff", "low_ff") if k in m]
            if len(keys) < 2:
                continue
            order = [m[k][s]["psnr"] for k in keys]
            holds = all(a > b for a, b in itertools.pairwise(order))
            gap = (
                f"; learned - low FF = {m['learned'][s]['psnr'] - m['low_ff'][s]['psnr']:+.2f} dB"
                if {"learned", "low_ff"} <= m.keys()
                else ""
            )
            names = " > ".join(m[k]["label"] for k in keys)
            print(f"{s}: {names}: {'yes' if holds else 'NO'}{gap}")
    if "learned_fab" in m:
        q = m["learned_fab"]["quality"]
        print(
            f"as-fabricated plate: correlation {q['correlation']:.4f}, "
            f"efficiency {q['efficiency']:.3f}; Set5 PSNR as fabricated minus learned PSF "
            f"{m['learned_fab']['Set5']['psnr'] - m['learned']['Set5']['psnr']:+.2f} dB"
        )
    if "learned" in m:
        psf = np.round(np.array(m["learned"]["psf"]) * 1000).astype(int)
        print(f"learned PSF (x1000):\n{psf}")


if __name__ == "__main__":
    sys.exit(main())
