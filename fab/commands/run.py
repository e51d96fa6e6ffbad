"""``doefab run``: the whole pipeline, sensor to fabrication package, in one command.

The pipeline is ``fab.run.stages.run_pipeline``; this module parses the flags,
hands it the dispatcher to run each stage with, prints its progress and returns
its exit code.
"""

import sys

from fab.run.stages import MESH_FORMATS, NO_MESH, STAGE_NAMES


def register(sub):
    p = sub.add_parser(
        "run",
        help="learn the PSF, retrieve the phase, build masks, GDS, meshes and reports",
        description="Run the whole pipeline on the default preset or a design file. "
        "Re-running skips stages whose inputs did not change; an interrupted run resumes.",
    )
    p.add_argument("--config", help="design TOML file or preset name (default preset if absent)")
    p.add_argument("--out", required=True, help="run folder")
    p.add_argument("--psf", help="use this psf.npy instead of learning one")
    budget = p.add_mutually_exclusive_group()
    budget.add_argument(
        "--minutes",
        type=float,
        help="train for this wall-clock time instead of the design's [learning] steps "
        "(faster or slower machines then give different results)",
    )
    budget.add_argument(
        "--steps", type=int, help="train this many steps instead of the design's [learning] steps"
    )
    p.add_argument("--seed", type=int, help="seed of every stage (default: the design's)")
    p.add_argument(
        "--no-baseline",
        action="store_true",
        help="learn without the no-plate model that the front page compares the plate "
        "with (halves the training time)",
    )
    p.add_argument(
        "--formats",
        default=MESH_FORMATS,
        help=f"mesh formats (default {MESH_FORMATS}); {NO_MESH} skips the mesh stage",
    )
    p.add_argument(
        "--force",
        nargs="?",
        const=True,
        default=False,
        choices=STAGE_NAMES,
        metavar="STAGE",
        help="redo every stage and overwrite; with a STAGE "
        f"({', '.join(STAGE_NAMES)}), redo that stage and those after it",
    )
    p.set_defaults(func=_run)


def _run(args):
    from fab.run.stages import run_pipeline

    result = run_pipeline(
        args.out,
        invoke=args.invoke,  # the dispatcher: each stage is a doefab command
        config=args.config,
        psf=args.psf,
        minutes=args.minutes,
        steps=args.steps,
        seed=args.seed,
        formats=args.formats,
        force=args.force,
        log=_say,
        no_baseline=args.no_baseline,
    )
    if result.exit_code == 0:
        print(f"doefab run: done, open {result.index}", file=sys.stderr)
    return result.exit_code


def _say(line):
    print(line, file=sys.stderr)
