"""The run folder's front page (``index.html``) and ``manifest.json``."""

import platform
from importlib import metadata
from pathlib import Path

from doe.derived import design_summary
from doe.figures import value_and_limit
from doe.goals import CORRELATION_GOAL, RMSE_GOAL
from doe.infra.errors import InputError
from doe.infra.files import atomic_write_bytes, sha256_file, write_json
from doe.infra.png import png_text
from doe.records.fab_manifest import MANIFEST_NAME, read_fab_manifest
from doe.records.learn import LEARN_JSON, read_learn
from doe.records.retrieval import RETRIEVAL_JSON, read_retrieval
from fab.run.learn_headlines import learn_rows
from fab.templates import render_page

PACKAGES = (
    "doefab",
    "numpy",
    "scipy",
    "nlopt",
    "torch",
    "gdstk",
    "klayout",
    "OpenImageIO",
    "trimesh",
    "manifold3d",
    "build123d",
    "matplotlib",
    "scikit-image",
)

# Headline numbers shown on the front page: (stage, file, key path, label, goal). A
# figure with a goal is shown with the digits that tell it from the goal.
HEADLINES = (
    (
        "retrieve",
        RETRIEVAL_JSON,
        ("quantised", "correlation"),
        "correlation ({quantised})",
        CORRELATION_GOAL,
    ),
    ("retrieve", RETRIEVAL_JSON, ("quantised", "rmse"), "rmse ({quantised})", RMSE_GOAL),
    ("retrieve", RETRIEVAL_JSON, ("quantised", "efficiency"), "efficiency ({quantised})", None),
    ("retrieve", RETRIEVAL_JSON, ("goals", "met"), "correlation and rmse goals met", None),
    (
        "retrieve",
        RETRIEVAL_JSON,
        ("square_pixels", "goals_met"),
        "goals met as a plate of square pixels (their sinc^2 envelope)",
        None,
    ),
    (
        "retrieve",
        RETRIEVAL_JSON,
        ("as_built", "goals_met"),
        "goals met by the plate as built (the pattern over the whole clear aperture)",
        None,
    ),
    ("fab", MANIFEST_NAME, ("level_step_nm",), "level step (nm)", None),
    ("fab", MANIFEST_NAME, ("pixel_pitch_nm",), "mask pixel pitch (nm)", None),
    ("fab", MANIFEST_NAME, ("tiles",), "whole tiles across the aperture", None),
    (
        "fab",
        MANIFEST_NAME,
        ("plate", "patterned_fraction"),
        "patterned fraction of the aperture",
        None,
    ),
    ("fab", MANIFEST_NAME, ("as_built", "goals_met"), "goals met by the plate as made", None),
)


def product_files(run_dir, stages):
    """Every product file of the run's ``stages`` and its front page, sorted.

    The stages' files are those ``run_state.json`` records as theirs: bookkeeping,
    the lab's own files in or beside the stage folders, and the folders of
    stages that this run did not plan (left there by an earlier run with other
    flags) are left out.
    """
    from fab.run.pipeline import load_state

    run_dir = Path(run_dir)
    state = load_state(run_dir)
    out = [run_dir / "index.html"] if (run_dir / "index.html").is_file() else []
    for name in stages:
        out += [run_dir / name / rel for rel in state.get(name, {}).get("files", {})]
    return sorted(out)


def package_versions():
    out = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def write_manifest(run_dir, design, options, stages, timings, stage_seconds):
    """Write ``manifest.json`` (deterministic) and ``timings.json`` (the one varying file).

    ``options`` (``fab.run.stages.RunOptions``) give the config, PSF and seed recorded.

    ``stages`` are the names of the stages this run planned: only their files are listed.

    ``timings`` are the wall-clock seconds of the stages run now; ``stage_seconds``
    the seconds each stage's own reports recorded (see ``pipeline.move_timings``).
    """
    run_dir = Path(run_dir)
    files = [
        {"path": str(p.relative_to(run_dir)), "sha256": sha256_file(p), "bytes": p.stat().st_size}
        for p in product_files(run_dir, stages)
    ]
    seed = options.seed if options.seed is not None else design.learning.seed
    manifest = {
        "tool": "doefab run",
        "config": options.config or "preset:sun2020",
        "design": design_summary(design),
        "psf_source": options.psf or "learn/psf.npy",
        "seeds": {"learn": None if options.psf else seed, "retrieve": seed},
        "versions": package_versions(),
        "files": files,
        "timings_file": "timings.json",
    }
    write_json(run_dir / "manifest.json", manifest)
    write_json(
        run_dir / "timings.json",
        {"seconds_per_stage_this_run": timings, "seconds_reported_by_stages": stage_seconds},
    )


# Each stage file the front page quotes, read through its record: (name) -> JSON object.
_READERS = {
    LEARN_JSON: lambda p: read_learn(p).data,
    RETRIEVAL_JSON: lambda p: read_retrieval(p).as_dict(),
    MANIFEST_NAME: lambda p: read_fab_manifest(p).fields,
}


def _lookup(run_dir, stage, name, path):
    """Return the value at key ``path`` of a stage's file, None where it has none."""
    try:
        value = _READERS[name](Path(run_dir) / stage / name)
        for key in path:
            value = value[key]
        return value
    except (InputError, KeyError, TypeError):
        return None


def write_index(run_dir, design, stages):
    """Write ``index.html`` linking every result of the run, with its figures.

    Parameters
    ----------
    run_dir : path
        The run folder.
    design : doe.design.Design
        The run's design (its name and description head the page).
    stages : sequence of str
        The stages this run planned, in order: only their files are shown.
    """
    run_dir = Path(run_dir)
    page = render_page(
        "run_index.html",
        name=design.name,
        description=design.description,
        headlines=_headline_rows(run_dir, stages),
        stages=_stage_sections(run_dir, stages),
    )
    atomic_write_bytes(run_dir / "index.html", page.encode())


def _headline_rows(run_dir, stages):
    """Return the front page's Summary as (label, value shown) rows, from the stages' files."""
    levels = _lookup(run_dir, "retrieve", RETRIEVAL_JSON, ("levels",))
    quantised = f"{levels} levels" if levels else "quantised"
    rows = learn_rows(run_dir) if "learn" in stages else []
    for stage, name, path, label, goal in HEADLINES:
        value = _lookup(run_dir, stage, name, path) if stage in stages else None
        if value is None:
            continue
        if isinstance(value, bool):
            shown = "yes" if value else f"NO: see {stage}/{name}"
        elif isinstance(value, float):
            shown = f"{value:.6g}" if goal is None else value_and_limit(value, goal, 6)[0]
        else:
            shown = str(value)
        rows.append((label.format(quantised=quantised), shown))
    return rows


def _stage_sections(run_dir, stages):
    """Return one section per stage folder: its report pages, figures and files."""
    products = product_files(run_dir, stages)
    sections = []
    for stage in stages:
        folder = run_dir / stage
        if not folder.is_dir():
            continue
        files = [p for p in products if p.parent.is_relative_to(folder)]
        sections.append(
            {
                "name": stage,
                "reports": [str(p.relative_to(run_dir)) for p in files if p.suffix == ".html"],
                "figures": [_figure(run_dir, p) for p in files if p.suffix == ".png"],
                "files": [(str(p.relative_to(run_dir)), f"{p.stat().st_size:,}") for p in files],
            }
        )
    return sections


def _figure(run_dir, path):
    """Return (path from the run folder, caption): the PNG's ``Description``, else its name.

    The caption states what the image shows, e.g. a mask image's polarity.
    """
    return str(path.relative_to(run_dir)), png_text(path).get("Description", path.name)
