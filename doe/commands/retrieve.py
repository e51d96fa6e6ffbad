"""``doefab retrieve``: an 8-level phase tile from a target PSF (see doe.retrieval)."""

import sys
from pathlib import Path

from doe.infra.errors import InputError

OUTPUTS = ("levels.npy", "phase.npy", "target_psf.npy", "retrieval.json", "retrieval.png")


def register(sub):
    p = sub.add_parser(
        "retrieve",
        help="design an L-level phase tile for a target PSF",
        description="Design an L-level phase tile whose K x K window of "
        "diffraction orders forms the target PSF (psf.npy, CONVENTIONS.md).",
    )
    p.add_argument("psf", help="target PSF: float64 (K, K) .npy, K odd, >= 0, sum 1")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--levels",
        type=int,
        default=None,
        help="phase levels L, a power of two from 2 to 256 (default: the design's)",
    )
    p.add_argument(
        "--tile-pixels",
        type=int,
        default=None,
        help="tile size N in pixels (default: the design's, 175 for sun2020)",
    )
    p.add_argument(
        "--seed",
        type=int,
        help="seed of the random start (default: the design's [learning] seed, as run uses)",
    )
    p.add_argument("--config", help="design TOML file or preset name (default: the default preset)")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    p.set_defaults(func=run)


def run(args):
    import numpy as np

    from doe import fraunhofer
    from doe.derived import derive, design_summary
    from doe.design import MAX_TILE_PIXELS, load_design
    from doe.figures import correlation_text, save_retrieval_figure
    from doe.goals import CORRELATION_GOAL, RMSE_GOAL, missed_goals
    from doe.infra import flags
    from doe.infra.files import (
        LEVEL_COUNT_RULE,
        is_level_count,
        read_psf,
        save_npy,
        sha256_file,
        staged_output,
        write_json,
    )
    from doe.records.psf_source import check_psf_grid
    from doe.retrieval import retrieve_phase

    design = load_design(args.config)
    n_levels = design.fabrication.levels if args.levels is None else args.levels
    if not is_level_count(n_levels):
        raise InputError("--levels", f"must be {LEVEL_COUNT_RULE}, got {n_levels}")
    n = derive(design).tile_pixels if args.tile_pixels is None else args.tile_pixels
    if not 1 <= n <= MAX_TILE_PIXELS:
        raise InputError(
            "--tile-pixels",
            f"must be 1 to {MAX_TILE_PIXELS} pixels (time and memory grow as N^2), got {n}",
        )
    flags.seed("--seed", args.seed)
    if args.seed is None:
        args.seed = design.learning.seed
    target = read_psf(args.psf)
    check_psf_grid(args.psf, design)
    k = target.shape[0]
    if k > n:
        raise InputError(
            args.psf,
            f"kernel size K = {k} exceeds the tile size N = {n}; "
            "use a smaller PSF or a larger --tile-pixels",
        )
    with staged_output(args.out, args.force, names=OUTPUTS) as stage:
        result = retrieve_phase(target, n, n_levels, seed=args.seed, progress=True)
        psf, _ = fraunhofer.simulate_levels(result.levels, n_levels, k)
        missed = missed_goals(result.quality_quantised)
        plate = fraunhofer.plate_quality(fraunhofer.level_phase(result.levels, n_levels), target)
        plate_missed = missed_goals(plate)
        save_npy(stage / "levels.npy", result.levels)
        save_npy(stage / "phase.npy", result.phase.astype(np.float64))
        save_npy(stage / "target_psf.npy", target)
        write_json(
            stage / "retrieval.json",
            {
                "continuous": result.quality_continuous,
                "quantised": result.quality_quantised,
                "goals": {
                    "correlation_min": CORRELATION_GOAL,
                    "rmse_max": RMSE_GOAL,
                    "met": not missed,
                    "missed": missed,
                },
                # the quantised design as fabricated: square pixels, whose sinc^2
                # envelope the contract's figures leave out
                "square_pixels": {**plate, "goals_met": not plate_missed, "missed": plate_missed},
                "seconds": round(result.seconds, 3),
                "seed": args.seed,
                "levels": n_levels,
                "tile_pixels": n,
                "kernel_size": k,
                # name and digest, not the path: the same input gives the same bytes
                "target_psf": Path(args.psf).name,
                "target_psf_sha256": sha256_file(args.psf),
                # the design as this tile realises it: its N and L, where flags set them
                "design": design_summary(_with_levels(design, n_levels), tile_pixels=n),
                "versions": _versions(),
            },
        )
        save_retrieval_figure(
            stage / "retrieval.png", target, psf, result.levels, n_levels, result.quality_quantised
        )
    q = result.quality_quantised
    print(
        f"retrieve: {n_levels} levels, N = {n}, K = {k}: "
        f"correlation {correlation_text(q['correlation'])}, "
        f"rmse {q['rmse']:.5f}, efficiency {q['efficiency']:.4f} in {result.seconds:.1f} s "
        f"-> {args.out}"
    )
    if missed:
        # still a valid plate (exit 0), but not the target: say so before anyone fabricates it
        print(
            f"doefab retrieve: warning: the {n_levels}-level design misses the quality goals "
            f"({'; '.join(missed)}); more --levels or a larger --tile-pixels may meet them",
            file=sys.stderr,
        )
    elif plate_missed:
        # a flat top filling the window: its outer orders are dimmed by the pixels' envelope
        print(
            "doefab retrieve: warning: the design meets the goals, but a plate of square "
            f"pixels, whose sinc^2 envelope dims the outer orders, misses them "
            f"({'; '.join(plate_missed)}); more tile pixels (finer features) flatten the envelope",
            file=sys.stderr,
        )
    return 0


def _versions():
    from importlib import metadata

    import nlopt
    import numpy
    import scipy

    try:
        doefab = metadata.version("doefab")
    except metadata.PackageNotFoundError:
        doefab = "unknown"
    return {
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "nlopt": nlopt.__version__,
        "doefab": doefab,
    }


def _with_levels(design, n_levels):
    """Return ``design`` quantised to ``n_levels`` (``--levels`` may differ from its own)."""
    from dataclasses import replace

    return replace(design, fabrication=replace(design.fabrication, levels=n_levels))
