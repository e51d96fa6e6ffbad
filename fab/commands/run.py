"""``doefab run``: the whole pipeline, sensor to fabrication package, in one command."""

import dataclasses
import json
import sys
import time
from pathlib import Path

from doe.infra.errors import InputError

MESH_FORMATS = "ply,glb,3mf,stl,step"
NO_MESH = "none"  # --formats value that leaves the mesh stage out
STAGE_NAMES = ("learn", "retrieve", "fab", "mesh")  # every stage a run can plan, in order
# The run's own summaries of its stages: rewritten by every run that redoes a stage.
SUMMARY_FILES = ("index.html", "manifest.json", "timings.json")


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
    p.add_argument(
        "--minutes",
        type=float,
        help="train for this wall-clock time instead of the design's [learning] steps "
        "(faster or slower machines then give different results)",
    )
    p.add_argument("--seed", type=int, help="seed of every stage (default: the design's)")
    p.add_argument(
        "--formats",
        default=MESH_FORMATS,
        help=f"mesh formats (default {MESH_FORMATS}); {NO_MESH} skips the mesh stage",
    )
    p.add_argument("--force", action="store_true", help="redo every stage and overwrite")
    p.set_defaults(func=_run)


def plan(args, run_dir, design):
    """Return the list of stages for these arguments."""
    from fab.run.pipeline import Stage

    # The stages that read the design are keyed on its values, not on the file's bytes.
    on_design = {
        "config": ("--config", args.config) if args.config else (),
        "design": json.dumps(dataclasses.asdict(design), sort_keys=True),
    }
    seed = str(args.seed if args.seed is not None else design.learning.seed)
    stages = []
    if args.psf:
        psf = Path(args.psf)
    else:
        # A step budget keeps the run reproducible; --minutes trades that for a time budget.
        # Reproducible means on the CPU: CUDA's gradients sum in a varying order, and two
        # runs on an H100 learned PSFs 4e-4 apart, hence two plates.
        budget = (
            ["--minutes", str(args.minutes)]
            if args.minutes is not None
            else ["--steps", str(design.learning.steps), "--device", "cpu"]
        )
        # One thread: the thread count changes torch's summation order, hence the bits.
        learn = ("learn", *budget, "--threads", "1", "--seed", seed)
        stages.append(Stage("learn", learn, **on_design))
        psf = run_dir / "learn" / "psf.npy"
    retrieve = run_dir / "retrieve"
    fab = run_dir / "fab"
    stages += [
        Stage("retrieve", ("retrieve", str(psf), "--seed", seed), (psf,), **on_design),
        Stage(
            "fab",
            ("fab", str(retrieve)),
            (retrieve / "levels.npy", retrieve / "target_psf.npy"),
            **on_design,
        ),
    ]
    if not _no_mesh(args.formats):
        mesh = ("mesh", str(fab), "--formats", args.formats)
        stages.append(Stage("mesh", mesh, (fab / "fab_manifest.json", fab / "levels.npy")))
    return stages


def _no_mesh(formats):
    return formats.strip().lower() == NO_MESH


def _run(args):
    from doe.design import check_psf_grid, check_psf_kernel, load_design
    from doe.infra import flags
    from doe.infra.files import check_out_folder, read_psf
    from fab.mesh.checks import check_float32_heights, parse_formats
    from fab.run.pipeline import run_lock

    # Checked here, not by the stages: a bad value must stop the run before any stage.
    flags.positive("--minutes", args.minutes)
    flags.at_most("--minutes", args.minutes, flags.MINUTES_MAX, "two years")
    flags.seed("--seed", args.seed)
    design = load_design(args.config)
    if args.psf:
        psf = read_psf(args.psf)
        check_psf_grid(args.psf, design)
        check_psf_kernel(psf, args.psf, design)  # as learn does
    formats = [] if _no_mesh(args.formats) else parse_formats(args.formats)
    where = f"{args.config or 'default preset'}: [material] thickness_mm"
    check_float32_heights(design.material.thickness * 1e3, formats, where)
    run_dir = Path(args.out)
    check_out_folder(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    with run_lock(run_dir):
        return _run_stages(args, run_dir, design)


def _run_stages(args, run_dir, design):
    from doe.infra.cli import main as doefab
    from fab.run.pipeline import (
        check_overwrite,
        discard_unfinished,
        finish_swaps,
        is_current,
        load_state,
        run_stage,
        save_state,
    )
    from fab.run.summary import write_index, write_manifest

    try:
        state = load_state(run_dir)  # with --force too: it tells the run's files from the lab's
    except InputError:
        if not args.force:
            raise
        state = {}
    finish_swaps(state, run_dir)
    if (
        not state
        and not args.force
        and any(p for p in run_dir.iterdir() if not p.name.startswith("."))
    ):
        raise InputError(
            run_dir, "is not empty and holds no doefab run; use --force or a new --out"
        )
    timings = {}
    stages = plan(args, run_dir, design)
    # Before any stage runs: an edited output would stop the run half-way.
    for stage in stages:
        check_overwrite(stage, state, run_dir, args.force)
    summaries_gone = False
    for i, stage in enumerate(stages, 1):
        # inputs of later stages exist only once earlier ones ran: plan lazily
        if not args.force and is_current(stage, state, run_dir):
            print(f"[{i}/{len(stages)}] {stage.name}: up to date, skipped", file=sys.stderr)
            discard_unfinished(stage, run_dir)
            continue
        if not summaries_gone:
            # The front page and manifest describe the stages as they were: a run
            # stopped from here on must not leave them presenting a mix as current.
            for name in SUMMARY_FILES:
                (run_dir / name).unlink(missing_ok=True)
            summaries_gone = True
        command = " ".join(stage.command)
        print(f"[{i}/{len(stages)}] {stage.name}: doefab {command}", file=sys.stderr)
        t0 = time.perf_counter()
        code = run_stage(stage, run_dir, state, doefab, args.force)
        timings[stage.name] = round(time.perf_counter() - t0, 2)
        if code != 0:
            print(f"doefab run: stage {stage.name} failed (exit {code})", file=sys.stderr)
            return code
        # The stage itself reported its staging folder, which is now renamed.
        print(
            f"[{i}/{len(stages)}] {stage.name}: done in {timings[stage.name]:.0f} s "
            f"-> {run_dir / stage.name}",
            file=sys.stderr,
        )
    save_state(run_dir, state)
    names = [s.name for s in stages]
    for old in [name for name in STAGE_NAMES if name not in names]:
        if not (run_dir / old).is_dir():
            continue
        print(
            f"doefab run: {run_dir / old} is from an earlier run and not part of this one; "
            "manifest.json and index.html leave it out",
            file=sys.stderr,
        )
    write_index(run_dir, design, names)
    seconds = {k: v.get("seconds", {}) for k, v in state.items() if k in names}
    write_manifest(run_dir, design, args, names, timings, seconds)
    print(f"doefab run: done, open {run_dir / 'index.html'}", file=sys.stderr)
    return 0
