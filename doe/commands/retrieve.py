"""``doefab retrieve``: an 8-level phase tile from a target PSF (see doe.retrieve)."""

import sys


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
    from doe.figures import correlation_text
    from doe.retrieve import retrieve

    result = retrieve(
        args.psf,
        args.out,
        config=args.config,
        levels=args.levels,
        tile_pixels=args.tile_pixels,
        seed=args.seed,
        force=args.force,
    )
    record, q = result.record, result.retrieval.quality_quantised
    print(
        f"retrieve: {record.levels} levels, N = {record.tile_pixels}, K = {record.kernel_size}: "
        f"correlation {correlation_text(q['correlation'])}, "
        f"rmse {q['rmse']:.5f}, efficiency {q['efficiency']:.4f} in "
        f"{result.retrieval.seconds:.1f} s -> {args.out}"
    )
    if result.missed:
        # still a valid plate (exit 0), but not the target: say so before anyone fabricates it
        print(
            f"doefab retrieve: warning: the {record.levels}-level design misses the quality "
            f"goals ({'; '.join(result.missed)}); more --levels or a larger --tile-pixels may "
            "meet them",
            file=sys.stderr,
        )
    elif result.square_pixels_missed:
        # a flat top filling the window: its outer orders are dimmed by the pixels' envelope
        print(
            "doefab retrieve: warning: the design meets the goals, but a plate of square "
            f"pixels, whose sinc^2 envelope dims the outer orders, misses them "
            f"({'; '.join(result.square_pixels_missed)}); more tile pixels (finer features) "
            "flatten the envelope",
            file=sys.stderr,
        )
    elif result.as_built_missed:
        # the tile meets them; the plate's own aperture (partial edge tiles) does not
        print(
            "doefab retrieve: warning: the tile meets the goals, but the plate as built "
            f"(the pattern over its clear aperture) misses them "
            f"({'; '.join(result.as_built_missed)})",
            file=sys.stderr,
        )
    return 0
