"""``doefab learn``, ``doefab evaluate`` and ``doefab sr``: flags, printing, exit codes.

The work is done by :func:`psf_learn.learn.learn`, :func:`psf_learn.evaluate.evaluate_folder`
and :func:`psf_learn.sr.super_resolve_files`, imported inside the handlers: ``doefab --help``
must not load torch.
"""

import json
import sys

from doe.infra import flags


def register(sub):
    p = sub.add_parser("learn", help="train a PSF and a super-resolution network end to end")
    p.add_argument("--out", required=True, help="output folder (psf.npy, model.pt, learn.json)")
    p.add_argument(
        "--images",
        help="folder of training images (PNG/JPEG/TIFF, grayscale); "
        "default: embedded natural + dead-leaves images",
    )
    p.add_argument(
        "--psf",
        default="learned",
        help="learned (default), delta (low fill factor), box (full fill factor), "
        "gaussian (sigma 0.459 sub-pixel), gaussian:SIGMA (sub-pixels), or a psf.npy file "
        "(fixed)",
    )
    budget = p.add_mutually_exclusive_group()
    budget.add_argument(
        "--minutes", type=float, help="wall-clock budget (default: the design's [learning] minutes)"
    )
    budget.add_argument(
        "--steps", type=int, help="number of steps (resumable; deterministic on the CPU)"
    )
    p.add_argument("--seed", type=int, help="random seed (default: the design's)")
    p.add_argument("--config", help="design TOML file or preset name")
    p.add_argument("--init", metavar="MODEL_DIR", help="start from a trained model (fine-tune)")
    _psf_flags(p)
    p.add_argument("--features", type=int, help="network feature channels (default 24)")
    p.add_argument("--stages", type=int, help="residual blocks / projection stages (default 4)")
    p.add_argument("--arch", choices=("resnet", "dbpn"), help="network design (default resnet)")
    p.add_argument("--batch", type=int, help="patches per step (default 16)")
    p.add_argument(
        "--patch",
        type=int,
        help="patch size in sub-pixels, a multiple of the factor (default: the largest up to 64)",
    )
    p.add_argument("--lr", type=float, help="network learning rate (default 2e-3)")
    p.add_argument("--psf-lr", type=float, help="PSF logit learning rate (default 0.05)")
    p.add_argument(
        "--photons",
        type=float,
        help="counts of a white pixel (default: the design's photons_per_pixel); 0 = no noise",
    )
    p.add_argument("--dark-counts", type=float, default=0.0, help="dark counts per pixel")
    p.add_argument(
        "--threads",
        type=int,
        help="CPU threads (default: 1 with --steps, whose result then depends on neither the "
        "machine's cores nor its load; else the idle cores, from the load average: 1 on a busy "
        "machine, where one thread runs far faster than two fighting for cores)",
    )
    p.add_argument(
        "--device",
        choices=("auto", "cpu", "cuda"),
        default="auto",
        help="where to train (default auto: the GPU if torch sees one); "
        "only CPU runs repeat bit for bit",
    )
    p.add_argument(
        "--eval-images",
        metavar="DIR",
        help="held-back images to score the model and the no-plate model on "
        "(default: the embedded set's held-out photos)",
    )
    p.add_argument(
        "--no-baseline",
        action="store_true",
        help="do not train the no-plate (delta PSF) model the same way to compare with "
        "(it doubles the training time)",
    )
    p.add_argument("--restart", action="store_true", help="ignore an existing checkpoint")
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    p.set_defaults(func=_learn)

    p = sub.add_parser(
        "evaluate",
        help="PSNR/SSIM of a learned model on an image folder (grey, and the SR papers' Y)",
    )
    p.add_argument("model_dir", help="folder written by `doefab learn`")
    p.add_argument("--images", required=True, help="folder of grayscale test images")
    p.add_argument("--psf-file", help="evaluate with this PSF (e.g. the realised plate's)")
    p.add_argument("--seed", type=int, default=None, help="noise seed (default fixed)")
    p.add_argument("--out", help="write the results to this JSON file")
    p.add_argument("--force", action="store_true", help="overwrite the JSON file")
    p.set_defaults(func=_evaluate)

    p = sub.add_parser("sr", help="super-resolve raw SPAD frames (npy or images)")
    p.add_argument("model_dir", help="folder written by `doefab learn`")
    p.add_argument("raw", nargs="+", help="raw frames: .npy (H, W) or (T, H, W), or image files")
    p.add_argument(
        "--out", required=True, help="output folder (<name>_sr.npy, <name>_sr.png, <name>_sr.json)"
    )
    p.add_argument("--photons", type=float, help="counts of white (default: the model's)")
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    p.set_defaults(func=_sr)


def _psf_flags(p):
    """Add the flags of a learned PSF: fixed, where it starts, how long it learns."""
    p.add_argument("--freeze-psf", action="store_true", help="keep the PSF fixed")
    p.add_argument(
        "--psf-start",
        metavar="START",
        help="where a learned PSF starts: delta, box, gaussian[:SIGMA] (centred on the pixel, "
        "as the baselines), random, dots[:N] or a psf.npy file (default: sigma 0.459 "
        "sub-pixel centred on the axis)",
    )
    p.add_argument(
        "--psf-until",
        type=float,
        metavar="FRACTION",
        help="fraction of the run in which the PSF learns (default 1); the network alone "
        "trains on for the rest",
    )


def _learn(args):
    from dataclasses import fields

    from psf_learn.learn import LearnOptions, learn

    options = {f.name: getattr(args, f.name) for f in fields(LearnOptions)}  # flags' names
    result = learn(args.out, config=args.config, on_note=_to_stderr, **options)
    if result.record is None:  # a torchrun process other than rank 0 writes nothing
        return 0
    print(
        f"trained the model for PSF {result.psf_spec}: {result.steps} steps in "
        f"{result.seconds:.0f} s, training-batch PSNR {result.final_psnr_db:.2f} dB "
        f"-> {result.out}"
    )
    print(heldout_line(result.heldout))
    return 0


def heldout_line(held):
    """Return the line that says what the plate buys on the held-back images."""
    n, model, base = len(held["images"]["names"]), held["model"], held["no_plate"]
    line = (
        f"held-back images ({n}): PSNR {model['psnr']:.2f} dB "
        f"(PSNR-Y {model['psnr_y']:.2f} dB, the SR papers' convention)"
    )
    if base is None:
        return line + "; no no-plate model (--no-baseline)"
    gain = held["plate_gain_db"]
    return (
        f"{line}; no plate (delta PSF) {base['psnr']:.2f} dB (PSNR-Y {base['psnr_y']:.2f}): "
        f"the plate buys {gain['psnr']:+.2f} dB (PSNR-Y {gain['psnr_y']:+.2f})"
    )


def _evaluate(args):
    from psf_learn.evaluate import evaluate_folder, results_path, write_evaluation

    # The seed, then --out, are checked before the model is read; the scores are
    # printed before the file is written.
    flags.seed("--seed", args.seed)
    out = results_path(args.out, args.force)
    result = evaluate_folder(
        args.model_dir,
        args.images,
        psf_file=args.psf_file,
        seed=args.seed,
        progress=sys.stderr.isatty(),
    )
    # full-range grey, then the SR papers' MATLAB Y (16-235) of the 8-bit estimate
    print(f"{'':32s} {'grey (full range)':>26s}  {'Y (SR papers)':>26s}")
    rows = [*result.images.items(), ("mean", vars(result))]
    for name, v in rows:
        print(
            f"{name:32s} PSNR {v['psnr']:6.2f} dB  SSIM {v['ssim']:.4f}  "
            f"PSNR {v['psnr_y']:6.2f} dB  SSIM {v['ssim_y']:.4f}"
        )
    if out is not None:
        write_evaluation(out, result)
    return 0


def _sr(args):
    from psf_learn.sr import super_resolve_files

    result = super_resolve_files(
        args.model_dir,
        args.raw,
        args.out,
        photons=args.photons,
        force=args.force,
        on_note=lambda note: _to_stderr(f"doefab sr: {note}"),
        on_frame=lambda f: _to_stderr(f"{f.stem}: {f.input_shape} -> {f.output_shape}"),
    )
    print(json.dumps({"outputs": list(result.outputs)}))
    return 0


def _to_stderr(line):
    print(line, file=sys.stderr)
