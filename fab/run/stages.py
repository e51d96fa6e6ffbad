"""The run stage: sensor to fabrication package in one call (``doefab run``).

:func:`run_pipeline` checks every input before the first stage, plans the
stages (learn, retrieve, fab, mesh), runs each one that is not up to date
through ``fab.run.pipeline`` and writes the run folder's ``index.html``,
``manifest.json`` and ``timings.json``. Each stage is a doefab command; the
caller hands over the function that runs one (``invoke``, normally the
dispatcher ``doe.infra.cli.main``), so this library never imports the
command line that imports it.
"""

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

from doe.infra.errors import InputError

MESH_FORMATS = "ply,glb,3mf,stl,step"
NO_MESH = "none"  # formats value that leaves the mesh stage out
STAGE_NAMES = ("learn", "retrieve", "fab", "mesh")  # every stage a run can plan, in order
# The run's own summaries of its stages: rewritten by every run that redoes a stage.
SUMMARY_FILES = ("index.html", "manifest.json", "timings.json")
# The design's fields that learning reads: only they key the learn stage.
LEARN_DESIGN_KEYS = ("sensor", "kernel_size", "learning")


@dataclass(frozen=True)
class RunOptions:
    """The choices of one run, as ``doefab run`` takes them from its flags.

    Attributes
    ----------
    config : str or None
        Design TOML file or preset name (None: the default preset).
    psf : str or None
        A ``psf.npy`` to use instead of learning one.
    minutes : float or None
        Train for this wall-clock time instead of the design's step budget.
    steps : int or None
        Train this many steps instead of the design's step budget.
    seed : int or None
        Seed of every stage (None: the design's).
    formats : str
        Comma-separated mesh formats, or ``"none"`` to leave the mesh stage out.
    no_baseline : bool
        Learn without the no-plate model the front page compares with (half the
        training time; the front page then shows the plate's model alone).
    force : bool or str
        True: redo every stage and overwrite edited outputs. A stage name: redo
        that stage and those after it, overwriting their edited outputs.
    """

    config: str | None = None
    psf: str | None = None
    minutes: float | None = None
    steps: int | None = None
    seed: int | None = None
    formats: str = MESH_FORMATS
    force: bool | str = False
    no_baseline: bool = False


@dataclass(frozen=True)
class RunResult:
    """What :func:`run_pipeline` did.

    Attributes
    ----------
    run_dir : Path
        The run folder.
    exit_code : int
        0, or the exit code of the stage that failed (the run stopped there).
    stages : tuple of str
        The stages planned, in order.
    ran, skipped : tuple of str
        The stages run now and those found up to date.
    failed : str or None
        The stage that failed.
    left_out : tuple of Path
        Folders of stages an earlier run left that this run did not plan; the
        summaries leave them out.
    seconds : dict
        Wall-clock seconds of each stage run now.
    index : Path or None
        The front page, once the run finished.
    """

    run_dir: Path
    exit_code: int
    stages: tuple[str, ...]
    ran: tuple[str, ...] = ()
    skipped: tuple[str, ...] = ()
    failed: str | None = None
    left_out: tuple[Path, ...] = ()
    seconds: dict = field(default_factory=dict)
    index: Path | None = None


def run_pipeline(
    out,
    *,
    invoke,
    config=None,
    psf=None,
    minutes=None,
    steps=None,
    seed=None,
    formats=MESH_FORMATS,
    force=False,
    log=None,
    no_baseline=False,
):
    """Run the whole pipeline into the run folder ``out``; skip what is up to date.

    Re-running skips stages whose inputs did not change; an interrupted run resumes.
    Learn's inputs are its own design keys (:data:`LEARN_DESIGN_KEYS`), images,
    seed, budget and flags: a change of ``[fabrication]`` alone keeps it.

    Parameters
    ----------
    out : path
        The run folder (created; a folder of other files is refused unless ``force``).
    invoke : callable
        ``invoke(argv) -> exit code`` runs one doefab command, such as
        ``doe.infra.cli.main``.
    config, psf, minutes, steps, seed, formats, force, no_baseline
        As :class:`RunOptions`.
    log : callable, optional
        Called with each progress line (``doefab run`` prints them to stderr).

    Returns
    -------
    RunResult

    Raises
    ------
    InputError
        A bad value, design or PSF (before any stage runs), a folder that holds
        no run, an edited output, or another run writing the folder.
    """
    from doe.infra.files import check_out_folder
    from fab.run.pipeline import run_lock

    options = RunOptions(
        config=None if config is None else str(config),
        psf=None if psf is None else str(psf),
        minutes=minutes,
        steps=steps,
        seed=seed,
        formats=formats,
        force=force if isinstance(force, str) else bool(force),
        no_baseline=bool(no_baseline),
    )
    design = _check_inputs(options)
    run_dir = Path(out)
    check_out_folder(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    with run_lock(run_dir):
        return _run_stages(run_dir, design, options, invoke, log or _quiet)


def _check_inputs(options):
    """Check the run's values, design and PSF before any stage; return the design.

    A bad value must stop the run before its first stage, not minutes into it.
    """
    from doe.design import load_design
    from doe.design_match import check_psf_kernel
    from doe.infra import flags
    from doe.infra.files import read_psf
    from doe.records.psf_source import check_psf_grid
    from fab.mesh.checks import check_float32_heights, parse_formats

    flags.positive("--minutes", options.minutes)
    flags.at_most("--minutes", options.minutes, flags.MINUTES_MAX, "two years")
    flags.positive("--steps", options.steps)
    flags.at_most("--steps", options.steps, flags.STEPS_MAX, "years of training")
    if options.minutes is not None and options.steps is not None:
        raise InputError("--minutes", "not with --steps: give one budget")
    flags.seed("--seed", options.seed)
    _check_force(options.force)
    design = load_design(options.config)
    if options.psf:
        psf = read_psf(options.psf)
        check_psf_grid(options.psf, design)
        check_psf_kernel(psf, options.psf, design)  # as learn does
    formats = [] if _no_mesh(options.formats) else parse_formats(options.formats)
    where = f"{options.config or 'default preset'}: [material] thickness_mm"
    check_float32_heights(design.material.thickness * 1e3, formats, where)
    return design


def _check_force(force):
    """Refuse a ``force`` that is neither a bool nor a stage's name (InputError)."""
    if not isinstance(force, bool) and force not in STAGE_NAMES:
        raise InputError("--force", f"{force!r} is no stage: one of {', '.join(STAGE_NAMES)}")


def _forced(options, names):
    """Return the planned stages that ``options.force`` redoes (all, or one and those after)."""
    if options.force is True:
        return set(names)
    if not options.force:
        return set()
    if options.force not in names:
        raise InputError(
            "--force", f"{options.force} is not a stage of this run ({', '.join(names)})"
        )
    return set(names[names.index(options.force) :])


def learn_design(design):
    """The design's values that learning reads, as canonical JSON (the learn stage's key).

    Learning reads the sensor, the PSF kernel and the learning section; the optics,
    material and fabrication shape only the stages after it.
    """
    values = {key: getattr(design, key) for key in LEARN_DESIGN_KEYS}
    return json.dumps(
        {k: dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v for k, v in values.items()},
        sort_keys=True,
    )


def _no_mesh(formats):
    """True when ``formats`` leaves the mesh stage out."""
    return formats.strip().lower() == NO_MESH


def plan_stages(run_dir, design, options):
    """Return the run's stages (``fab.run.pipeline.Stage``) for these options, in order."""
    from doe.records.fab_manifest import LEVELS_FILE, MANIFEST_NAME
    from fab.run.pipeline import Stage

    # The stages that read the design are keyed on its values, not on the file's bytes.
    config = ("--config", options.config) if options.config else ()
    on_design = {"config": config, "design": json.dumps(dataclasses.asdict(design), sort_keys=True)}
    seed = str(options.seed if options.seed is not None else design.learning.seed)
    stages = []
    if options.psf:
        psf = Path(options.psf)
    else:
        # A step budget keeps the run reproducible; --minutes trades that for a time budget.
        # Reproducible means on the CPU: CUDA's gradients sum in a varying order, so two
        # runs on a GPU learn slightly different PSFs, hence two plates.
        steps = options.steps if options.steps is not None else design.learning.steps
        budget = (
            ["--minutes", str(options.minutes)]
            if options.minutes is not None
            else ["--steps", str(steps), "--device", "cpu"]
        )
        # One thread: the thread count changes torch's summation order, hence the bits.
        learn = ("learn", *budget, "--threads", "1", "--seed", seed)
        learn += ("--no-baseline",) if options.no_baseline else ()  # keys the stage too
        stages.append(Stage("learn", learn, config=config, design=learn_design(design)))
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
    if not _no_mesh(options.formats):
        mesh = ("mesh", str(fab), "--formats", options.formats)
        stages.append(Stage("mesh", mesh, (fab / MANIFEST_NAME, fab / LEVELS_FILE)))
    return stages


def _quiet(line):
    """Drop a progress line (the default of a library call)."""


def _load_state(run_dir, force):
    """The run state, with ``force`` too: it tells the run's files from the lab's."""
    from fab.run.pipeline import finish_swaps, load_state

    try:
        state = load_state(run_dir)
    except InputError:
        if not force:
            raise
        state = {}
    finish_swaps(state, run_dir)
    if not state and not force and any(p for p in run_dir.iterdir() if not p.name.startswith(".")):
        raise InputError(
            run_dir, "is not empty and holds no doefab run; use --force or a new --out"
        )
    return state


def _run_stages(run_dir, design, options, invoke, log):
    from fab.run.pipeline import check_overwrite, discard_unfinished, is_current, run_stage

    state = _load_state(run_dir, options.force is True)
    stages = plan_stages(run_dir, design, options)
    names = tuple(s.name for s in stages)
    forced = _forced(options, names)
    # Before any stage runs: an edited output would stop the run half-way.
    for stage in stages:
        check_overwrite(stage, state, run_dir, stage.name in forced)
    timings, ran, skipped = {}, [], []
    summaries_gone = False
    for i, stage in enumerate(stages, 1):
        # inputs of later stages exist only once earlier ones ran: plan lazily
        if stage.name not in forced and is_current(stage, state, run_dir):
            log(f"[{i}/{len(stages)}] {stage.name}: up to date, skipped")
            discard_unfinished(stage, run_dir)
            skipped.append(stage.name)
            continue
        if not summaries_gone:
            # The front page and manifest describe the stages as they were: a run
            # stopped from here on must not leave them presenting a mix as current.
            for name in SUMMARY_FILES:
                (run_dir / name).unlink(missing_ok=True)
            summaries_gone = True
        log(f"[{i}/{len(stages)}] {stage.name}: doefab {' '.join(stage.command)}")
        t0 = time.perf_counter()
        code = run_stage(stage, run_dir, state, invoke, stage.name in forced)
        timings[stage.name] = round(time.perf_counter() - t0, 2)
        ran.append(stage.name)
        if code != 0:
            log(f"doefab run: stage {stage.name} failed (exit {code})")
            return RunResult(
                run_dir=run_dir,
                exit_code=code,
                stages=names,
                ran=tuple(ran),
                skipped=tuple(skipped),
                failed=stage.name,
                seconds=timings,
            )
        # The stage itself reported its staging folder, which is now renamed.
        log(
            f"[{i}/{len(stages)}] {stage.name}: done in {timings[stage.name]:.0f} s "
            f"-> {run_dir / stage.name}"
        )
    left_out = _write_summaries(run_dir, design, options, state, names, timings, log)
    return RunResult(
        run_dir=run_dir,
        exit_code=0,
        stages=names,
        ran=tuple(ran),
        skipped=tuple(skipped),
        left_out=left_out,
        seconds=timings,
        index=run_dir / "index.html",
    )


def _write_summaries(run_dir, design, options, state, names, timings, log):
    """Save the state, write the front page and the manifests; return the folders left out."""
    from fab.run.pipeline import save_state
    from fab.run.summary import write_index, write_manifest

    save_state(run_dir, state)
    left_out = tuple(
        run_dir / old for old in STAGE_NAMES if old not in names and (run_dir / old).is_dir()
    )
    for folder in left_out:
        log(
            f"doefab run: {folder} is from an earlier run and not part of this one; "
            "manifest.json and index.html leave it out"
        )
    write_index(run_dir, design, names)
    seconds = {k: v.get("seconds", {}) for k, v in state.items() if k in names}
    write_manifest(run_dir, design, options, names, timings, seconds)
    return left_out
