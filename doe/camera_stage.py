"""The camera stage: a design folder's plate in a lens, as the SPAD's active areas see it.

:func:`run_camera` reads a ``doefab fab`` or ``doefab retrieve`` output (its
``fab_manifest.json`` or ``retrieval.json``, ``levels.npy`` and ``target_psf.npy``),
computes :func:`doe.camera.effective_psf` for the lens and light given, and writes
``effective_psf.npy`` (the PSF contract), ``camera.json``
(:mod:`doe.records.camera`) and ``camera.png`` into the output folder.
"""

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy

from doe.infra.errors import InputError


@dataclass(frozen=True)
class CameraStageResult:
    """What ``doefab camera`` wrote: the folder, its files, the model's result and record."""

    out: Path
    files: tuple[str, ...]
    camera: object  # doe.camera.CameraResult
    record: dict


def read_plate_folder(design_dir, design):
    """Return (levels, target or None, kind) of a fab or retrieve folder made for ``design``.

    Refuses (InputError) a folder whose record says the tile was made for other
    optics than ``design``'s (wavelength, focal length, glass, sub-pixel grid, levels).
    """
    from doe.design_match import TILE_KEYS, design_differences
    from doe.infra.files import read_levels, read_psf
    from doe.records.fab_manifest import LEVELS_FILE, MANIFEST_NAME, TARGET_PSF_FILE
    from doe.records.retrieval import RETRIEVAL_JSON, read_retrieval

    d = Path(design_dir)
    if not d.is_dir():
        raise InputError(d, "no such design folder (give a doefab fab or retrieve output)")
    n_levels = design.fabrication.levels
    if (d / MANIFEST_NAME).is_file():
        kind = "fab"
        _check_manifest(d / MANIFEST_NAME, design)
    elif (d / RETRIEVAL_JSON).is_file():
        kind = "retrieve"
        record = read_retrieval(d / RETRIEVAL_JSON)
        if record.levels is not None and record.levels != n_levels:
            raise InputError(
                d / RETRIEVAL_JSON,
                f"the tile has {record.levels} levels, the design {n_levels}; "
                "pass the design it was made for with --config",
            )
        differences = design_differences(record.design, design, TILE_KEYS)
        if differences:
            raise InputError(
                d / RETRIEVAL_JSON,
                f"the tile was designed for another design than {design.name!r} "
                f"({'; '.join(differences)}); pass the design it was made for with --config",
            )
    elif (d / LEVELS_FILE).is_file():  # a level map alone: the design is --config's
        kind = "levels"
    else:
        raise InputError(
            d,
            f"neither {MANIFEST_NAME}, {RETRIEVAL_JSON} nor {LEVELS_FILE} found; "
            "give a fab or retrieve output",
        )
    levels = read_levels(d / LEVELS_FILE, n_levels)
    target_path = d / TARGET_PSF_FILE
    target = read_psf(target_path) if target_path.is_file() else None
    if target is not None and target.shape[0] > levels.shape[0]:
        raise InputError(target_path, f"is larger than the tile's N = {levels.shape[0]}")
    return levels, target, kind


def _check_manifest(path, design):
    """Refuse a fab manifest made for other optics than ``design``'s."""
    from doe.derived import derive
    from doe.records.fab_manifest import read_fab_manifest

    fields = read_fab_manifest(path).fields
    checks = (
        ("wavelength_nm", design.optics.wavelength * 1e9),
        ("focal_length_mm", design.optics.focal_length * 1e3),
        ("levels", design.fabrication.levels),
    )
    n = fields.get("tile_pixels")
    if isinstance(n, int) and n > 0:
        checks += (("pixel_pitch_nm", derive(design, n).mask_pixel_pitch * 1e9),)
    for key, value in checks:
        got = fields.get(key)
        if isinstance(got, (int, float)) and not math.isclose(got, value, rel_tol=1e-6):
            raise InputError(
                path,
                f"{key} {got:g} differs from design {design.name!r}'s {value:g}; "
                "pass the design it was made for with --config",
            )


def run_camera(
    design_dir,
    out,
    *,
    config=None,
    bandwidth_nm=0.0,
    spectrum_file=None,
    f_number=None,
    defocus_um=0.0,
    rotation_deg=0.0,
    budget=False,
    force=False,
):
    """Write the effective PSF of DESIGN_DIR's plate in a camera into ``out``.

    Parameters are those of :func:`doe.camera.effective_psf` (``spectrum_file`` a
    two-column text file, :func:`doe.spectrum.read_spectrum`); ``config`` the design
    (file or preset, default the default preset); ``budget`` adds the camera budget
    (:func:`doe.camera_budget.camera_budget`) to camera.json and its figure;
    ``force`` overwrites.

    Raises
    ------
    InputError
        Unusable input (exit 2); nothing is written.
    """
    from doe.camera import effective_psf, psf_figures
    from doe.camera_budget import camera_budget
    from doe.camera_figure import save_budget_figure, save_camera_figure
    from doe.derived import design_summary
    from doe.design import load_design
    from doe.fraunhofer import level_phase, plate_quality, simulate_levels
    from doe.infra.files import save_npy, staged_output
    from doe.records.camera import (
        BUDGET_FIGURE,
        CAMERA_FIGURE,
        CAMERA_JSON,
        EFFECTIVE_PSF,
        write_camera,
    )
    from doe.spectrum import read_spectrum

    start = time.perf_counter()
    design = load_design(config)
    levels, target, kind = read_plate_folder(design_dir, design)
    spectrum = read_spectrum(spectrum_file) if spectrum_file is not None else None
    n_levels = design.fabrication.levels
    k = target.shape[0] if target is not None else design.kernel_size
    target_source = "target_psf.npy"
    if target is None:
        target, target_source = simulate_levels(levels, n_levels, k)[0], "simulated from levels"
    result = effective_psf(
        design,
        levels,
        bandwidth_nm=bandwidth_nm,
        spectrum=spectrum,
        f_number=f_number,
        defocus_um=defocus_um,
        rotation_deg=rotation_deg,
        kernel_size=k,
    )
    figures = psf_figures(result.psf, target)
    record = {
        "settings": result.settings,
        "collected_fraction": result.collected_fraction,
        "correlation": figures["correlation"],
        "rmse": figures["rmse"],
        "window": plate_quality(level_phase(levels, n_levels), target),
        "design_dir": str(design_dir),
        "kind": kind,
        "target_psf": target_source,
        "psf": EFFECTIVE_PSF,
        "seconds": time.perf_counter() - start,
        "design": design_summary(design, tile_pixels=levels.shape[0]),
        "versions": {"numpy": np.__version__, "scipy": scipy.__version__},
    }
    names = [EFFECTIVE_PSF, CAMERA_JSON, CAMERA_FIGURE] + ([BUDGET_FIGURE] if budget else [])
    if budget:
        record["budget"] = camera_budget(design, levels, target)
    with staged_output(out, force, names=names) as stage:
        save_npy(stage / EFFECTIVE_PSF, result.psf)
        write_camera(stage / CAMERA_JSON, record)
        save_camera_figure(stage / CAMERA_FIGURE, result, design, target, figures)
        if budget:
            save_budget_figure(stage / BUDGET_FIGURE, record["budget"])
    return CameraStageResult(Path(out), tuple(names), result, record)
