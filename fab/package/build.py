"""Build the fabrication package of a phase tile: :func:`build_package` (``doefab fab``).

Masks -> GDS (+ optional OASIS) -> KLayout read-back check -> design-rule check
(:mod:`fab.package.drc`) -> layer images -> tolerance analysis -> manifest -> report,
all written through a staging folder so that a failed or refused run leaves nothing
behind.
"""

import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

from doe.infra.errors import InputError, first_line
from doe.records.fab_manifest import (
    DRC_DECK,
    DRC_MARKERS,
    GDS_NAME,
    LEVELS_FILE,
    MANIFEST_NAME,
    OASIS_NAME,
    ORIENTATION,
    TARGET_PSF_FILE,
    FabManifest,
    build_fab_manifest,
    previous_package_files,
    write_fab_manifest,
)

STAGES = ("gds", "check", "drc", "images", "tolerance", "manifest", "report")


class PackageCheckFailed(Exception):
    """The written GDS does not read back as the masks: nothing is released (exit 1)."""


@dataclass(frozen=True)
class PackageResult:
    """What :func:`build_package` wrote.

    Attributes
    ----------
    out : pathlib.Path
        The package's folder.
    files : tuple of str
        Every file written, relative to ``out``, sorted.
    manifest : doe.records.fab_manifest.FabManifest
        The manifest written to ``out/fab_manifest.json``.
    report_files : tuple of str
        The report's files (``fab_report.md``, ``fab_report.html``, figures).
    warnings : tuple of str
        What the package's user should know (a tile finer than the process, no
        target PSF, goals missed), one sentence each; the package is written.
    """

    out: Path
    files: tuple[str, ...]
    manifest: FabManifest
    report_files: tuple[str, ...]
    warnings: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class _Tile:
    """A checked tile and what its package is made of."""

    design: object
    derived: object
    levels: object
    target: object  # the design folder's target PSF, or the simulated PSF without one
    simulated: object
    efficiency: float
    masks: list
    kernel_size: int
    pitch_nm: int
    extra: dict  # further manifest keys


def load_design_dir(design_dir, design):
    """Read and validate DESIGN_DIR's levels and target PSF, made for ``design``.

    Returns
    -------
    levels : (N, N) uint8
    target : (K, K) float64 or None
        None when DESIGN_DIR has no target_psf.npy.
    """
    from doe.design_match import TILE_KEYS, design_differences
    from doe.infra.files import read_levels, read_psf
    from doe.records.retrieval import RETRIEVAL_JSON, read_retrieval

    d = Path(design_dir)
    n_levels = design.fabrication.levels
    if not d.is_dir():
        raise InputError(d, "no such design folder (expected doefab retrieve's output)")
    info = d / RETRIEVAL_JSON
    if info.is_file():
        record = read_retrieval(info)  # refuses a 'levels' that is no whole number
        got = record.levels
        if got is not None and got != n_levels:
            raise InputError(
                info,
                f"the design was quantised to {got} levels but the configuration has "
                f"{n_levels}; pass a --config whose [fabrication] levels = {got}",
            )
        # a tile etched for another wavelength, glass or sub-pixel grid is a wrong plate
        differences = design_differences(record.design, design, TILE_KEYS)
        if differences:
            raise InputError(
                info,
                f"the tile was designed for another design than {design.name!r} "
                f"({'; '.join(differences)}); pass the design it was made for with --config",
            )
    if not (d / "levels.npy").is_file():  # e.g. a learn folder
        raise InputError(
            d / "levels.npy", "no such file; fab takes the folder that doefab retrieve wrote"
        )
    levels = read_levels(d / "levels.npy", n_levels)
    target_path = d / "target_psf.npy"
    target = read_psf(target_path) if target_path.exists() else None
    return levels, target


def tile_derived(design, n):
    """Return derive(design) for a tile of N pixels (pitch re-snapped to the grid if N differs)."""
    from doe.derived import derive

    der = derive(design)
    return der if der.tile_pixels == n else derive(design, tile_pixels=n)


def tile_summary(design, der):
    """Return design_summary(design) with its derived optics for the tile actually fabricated."""
    from doe.derived import design_summary

    return design_summary(design, tile_pixels=der.tile_pixels)


def mask_table(masks, counts, pitch_nm):
    """Return the per-mask dicts of the report (depth, fill, polygon count, min feature...)."""
    from fab.package.masks import min_feature_pixels

    return [
        {
            "name": mk.name,
            "gds_layer": mk.gds_layer,
            "etch_depth_nm": mk.etch_depth * 1e9,
            "exposure_order": mk.exposure_order,
            "fill_fraction": mk.fill_fraction,
            "polygon_count": counts[mk.name],
            "min_feature_um": min_feature_pixels(mk.bitmap) * pitch_nm / 1000,
        }
        for mk in masks
    ]


# Whether a build computes the report's camera budget when not told (the test suite,
# which builds some 70 packages, turns it off and on where a test reads the section).
CAMERA_BUDGET = True


def build_package(
    design_dir, out, *, config=None, force=False, oasis=False, progress=True,
    camera_budget=None, camera_psnr=None, tiles=None, whole_tiles=False, keep_aperture=False,
    dies=(1, 1), lane_um=None, allow_drc=False,
):  # fmt: skip
    """Write the fabrication package of DESIGN_DIR's tile into ``out``.

    Parameters
    ----------
    design_dir : path
        ``doefab retrieve``'s output: levels.npy (target_psf.npy and
        retrieval.json optional).
    out : path
        Output folder.
    config : str, path or None
        Design TOML file or preset name (default preset if None).
    force : bool
        Overwrite an earlier package in ``out`` (its files not written again are removed).
    oasis : bool
        Also write mask.oas.
    progress : bool
        Show progress bars on a terminal.
    camera_budget : bool or None
        Add the report's "In the camera" budget (doe.camera_budget; about 1.5 s of
        CPU); None: :data:`CAMERA_BUDGET`.
    camera_psnr : path or None
        ``doefab camera-psnr``'s camera_psnr.json of this tile: its dB budget goes into
        the report too.
    tiles : int or None
        Whole tiles across (at most those that fit the aperture): whole tiles only,
        the clear-aperture frame shrunk to them. Default: the pattern fills the
        clear aperture (whole tiles and clipped edge tiles).
    whole_tiles : bool
        Whole tiles only, as many as fit; the frame shrinks to them.
    keep_aperture : bool
        With ``tiles`` or ``whole_tiles``: keep the design's frame (plain glass
        inside it around the tiles; the warnings and report say what it costs).
    dies : (int, int)
        Plates along x and y on the substrate, dicing lanes between them.
    lane_um : float or None
        Dicing lane width (default 200 um).
    allow_drc : bool
        Write the package even when the design-rule check finds violations
        (``--allow-drc``); the manifest and report then say what was allowed.

    Returns
    -------
    PackageResult

    Raises
    ------
    InputError
        Unusable input (exit 2); :class:`fab.package.drc.DrcRefused` for a package
        with design-rule violations without ``allow_drc``.
    PackageCheckFailed
        The written GDS does not read back as the masks (exit 1).
        In both cases nothing is left in ``out``.
    """
    from tqdm import tqdm

    from doe.design import load_design
    from doe.infra.files import staged_output
    from fab.package.layer_images import layer_image_names
    from fab.package.order import ORDER_FILES
    from fab.package.plate_choice import choose_plate
    from fab.package.report_camera import CAMERA_REPORT_FIGURES

    design = load_design(config)
    levels, target = load_design_dir(design_dir, design)
    der, pitch_nm, k = _check_tile(design, levels, target, Path(design_dir))
    tile, warnings = _plan(design, der, levels, target, k, pitch_nm)
    choice = choose_plate(design, der, tiles, whole_tiles, keep_aperture, dies, lane_um)
    psnr = None if camera_psnr is None else _camera_psnr(camera_psnr, tile.levels)
    bar = tqdm(
        STAGES, desc="doefab fab", file=sys.stderr, disable=not (progress and sys.stderr.isatty())
    )
    known = [GDS_NAME, MANIFEST_NAME, LEVELS_FILE, TARGET_PSF_FILE, DRC_DECK, DRC_MARKERS]
    known += [name for mk in tile.masks for name in layer_image_names(mk.name)]
    known += [OASIS_NAME] if oasis else []
    known += list(ORDER_FILES)
    stale = previous_package_files(Path(out) / MANIFEST_NAME, layer_image_names)
    if stale:  # an earlier package's camera figures, which this build may leave out
        stale = [*stale, *CAMERA_REPORT_FIGURES]
    with staged_output(out, force, names=known, stale=stale) as stage:
        manifest, report_files, more = _write_package(
            stage, tile, choice, Path(design_dir), Path(out), (oasis, allow_drc), bar, progress,
            (CAMERA_BUDGET if camera_budget is None else camera_budget, psnr),
        )  # fmt: skip
        warnings += more
        all_files = sorted(str(p.relative_to(stage)) for p in stage.rglob("*") if p.is_file())
    return PackageResult(
        out=Path(out),
        files=tuple(all_files),
        manifest=FabManifest(Path(out) / MANIFEST_NAME, MappingProxyType(manifest)),
        report_files=tuple(report_files),
        warnings=tuple(warnings),
    )


def _check_tile(design, levels, target, design_dir):
    """Refuse a tile that cannot be made under ``design``; return (derived, pitch_nm, K)."""
    from doe.derived import lattice_problem
    from doe.design import MAX_TILE_PIXELS

    n = levels.shape[0]
    if n > MAX_TILE_PIXELS:  # as doefab retrieve --tile-pixels and the design check refuse
        raise InputError(
            design_dir / "levels.npy",
            f"N = {n} pixels per tile, more than {MAX_TILE_PIXELS} (GDS, tolerance and "
            "mesh time and memory grow as N^2)",
        )
    der = tile_derived(design, n)
    pitch_nm = round(der.mask_pixel_pitch * 1e9)
    if pitch_nm <= 0:
        raise InputError(
            design_dir / "levels.npy",
            f"N = {n} pixels per tile gives a pixel pitch below the "
            f"{design.fabrication.grid * 1e9:.0f} nm grid",
        )
    if target is not None and target.shape[0] > n:
        raise InputError(
            design_dir / "target_psf.npy",
            f"PSF size K = {target.shape[0]} exceeds the tile's N = {n} pixels",
        )
    k = target.shape[0] if target is not None else design.kernel_size
    if k > n:
        raise InputError(
            design_dir / "levels.npy",
            f"the tile's N = {n} pixels is smaller than the design's PSF size K = {k} "
            "(psf.kernel_size; there is no target_psf.npy)",
        )
    problem = lattice_problem(der, k, design.fabrication.grid)
    if problem:
        raise InputError(design_dir / "levels.npy", f"N = {n} pixels per tile: {problem}")
    return der, pitch_nm, k


def _plan(design, der, levels, target, k, pitch_nm):
    """Simulate the tile and cut its masks; return (_Tile, warnings)."""
    from doe.derived import derive
    from doe.fraunhofer import simulate_levels
    from fab.package.masks import masks_from_levels

    n, n_levels = levels.shape[0], design.fabrication.levels
    warnings = []  # given once the package is written: a refusal is one line
    nominal = derive(design).tile_pixels
    if n > nominal:  # finer pixels than the process was chosen for
        warnings.append(
            f"warning: N = {n} gives {pitch_nm} nm mask pixels, finer than the design's "
            f"{design.fabrication.feature_size * 1e6:g} um feature size (N = {nominal}, "
            "[fabrication] feature_size_um); check that the process can print them"
        )
    simulated, efficiency = simulate_levels(levels, n_levels, k)
    extra = {}
    if target is None:
        target = simulated
        extra["target_psf_source"] = "simulated from levels.npy (DESIGN_DIR had no target_psf.npy)"
        warnings.append(
            "no target_psf.npy in the design folder; using the simulated PSF of "
            "levels.npy as the target"
        )
    warnings += _goal_warnings(levels, n_levels, target, simulated)
    masks = masks_from_levels(levels, n_levels, der.level_step)
    tile = _Tile(design, der, levels, target, simulated, efficiency, masks, k, pitch_nm, extra)
    return tile, warnings


def _write_package(
    stage, tile, choice, design_dir, out, flags, bar, progress, camera=(False, None)
):
    """Write the package's files into ``stage``; return (manifest dict, report files, warnings).

    ``flags`` is (oasis, allow_drc)."""
    from doe.aperture import as_built, as_built_record
    from fab.package.drc import run_package_drc
    from fab.package.layer_images import write_layer_images
    from fab.package.manifest import file_records, layout_keys
    from fab.package.order import ORDER_FILES, write_mask_order
    from fab.package.plate_choice import plate_warnings
    from layouts.gds import build_library, write_gds, write_oasis
    from layouts.readback import check_written_gds

    design, der, masks, pitch_nm = tile.design, tile.derived, tile.masks, tile.pitch_nm
    n_levels = design.fabrication.levels
    tiles = choice.plate.tiles
    oasis, allow_drc = flags
    aperture_nm = round(design.fabrication.aperture * 1e9)
    extra = dict(tile.extra)
    bar.set_postfix_str("gds")
    lib, layout = build_library(
        masks, pitch_nm, tiles, design.name, aperture_nm,
        grid_nm=round(design.fabrication.grid * 1e9),
        feature_nm=round(design.fabrication.feature_size * 1e9), mode=choice.mode,
        dies=choice.dies, lane_nm=choice.lane_nm,
    )  # fmt: skip
    write_gds(lib, stage / GDS_NAME)
    try:  # KLayout reads the file back: gdstk truncates it on a full disk without a word
        if oasis:
            write_oasis(stage / GDS_NAME, stage / OASIS_NAME)
            extra["oasis"] = OASIS_NAME
        bar.update()
        bar.set_postfix_str("check")
        problems = check_written_gds(stage / GDS_NAME, layout, masks)
    except RuntimeError as e:
        raise InputError(
            out / GDS_NAME,
            f"KLayout cannot read back the file written ({first_line(e)}); is the disk full?",
        ) from None
    if problems:
        raise PackageCheckFailed("; ".join(problems))
    bar.update()
    bar.set_postfix_str("drc")
    extra["drc"] = run_package_drc(stage, design, masks, allow_drc, out)[1]
    bar.update()
    bar.set_postfix_str("images")
    write_layer_images(
        stage, masks, tiles, pitch_nm, layout.plate_half_nm, layout.frame_half_nm,
        edge_pixels=layout.plate.edge_pixels,
    )  # fmt: skip
    bar.update()
    bar.set_postfix_str("tolerance")
    tolerance = _tolerance(tile.levels, n_levels, tile.target, masks, der, design, progress)
    bar.update()
    bar.set_postfix_str("manifest")
    _write_arrays(stage, tile, design_dir)
    acceptance = tolerance.get("acceptance")
    extra.update(layout_keys(layout, masks, n_levels, der.level_step * 1e9, ORDER_FILES))
    built = as_built(tile.levels, n_levels, layout.plate, tile.target)
    extra["as_built"] = as_built_record(built)
    manifest = build_fab_manifest(design, der, layout, masks, acceptance, extra, tile.kernel_size)
    write_mask_order(stage, manifest, tolerance)
    write_fab_manifest(stage / MANIFEST_NAME, manifest)
    bar.update()
    bar.set_postfix_str("report")
    written = sorted(str(p.relative_to(stage)) for p in stage.rglob("*") if p.is_file())
    context = {
        "design": tile_summary(design, der),
        "manifest": manifest,
        "masks": mask_table(masks, layout.polygon_counts, pitch_nm),
        "levels": tile.levels,
        "target_psf": tile.target,
        "simulated_psf": tile.simulated,
        "efficiency": tile.efficiency,
        "as_built": built,
        "tolerance": tolerance,
        "orientation": ORIENTATION,
        "files": file_records(stage, written),
    }
    context.update(_camera_context(design, tile, *camera))
    report_files = _report(stage, context)
    bar.update()
    bar.close()
    tile_missed = _goal_warnings(tile.levels, n_levels, tile.target, tile.simulated)
    return manifest, report_files, plate_warnings(choice, built, tile_missed)


def _camera_context(design, tile, budget, psnr):
    """The report's "In the camera": the budget (the one tolerance budget's allowance) and dB."""
    from doe.camera_budget import camera_budget
    from fab.plate.budget import RMSE_ALLOWANCE

    out = {"camera_psnr": psnr}
    if budget:
        allowance = RMSE_ALLOWANCE
        out["camera_budget"] = camera_budget(design, tile.levels, tile.target, allowance=allowance)
    return out


def _camera_psnr(path, levels):
    """Read camera_psnr.json (or the folder holding it), refused unless made for ``levels``."""
    from doe.records.camera_psnr import read_camera_psnr

    return read_camera_psnr(path, levels).data


def _write_arrays(stage, tile, design_dir):
    """Write the level map drawn and the target PSF (the design folder's own file if any)."""
    from doe.infra.files import save_npy

    save_npy(stage / LEVELS_FILE, tile.levels)  # exactly the array that was drawn
    if (design_dir / "target_psf.npy").exists():
        shutil.copyfile(design_dir / "target_psf.npy", stage / TARGET_PSF_FILE)
    else:
        save_npy(stage / TARGET_PSF_FILE, tile.target)


def _goal_warnings(levels, n_levels, target, simulated):
    """Say when the nominal plate misses the design goals, as the report's Summary does:
    in the contract's model, or only as a plate of square pixels (whose sinc^2 envelope
    dims the outer orders, which the contract's model does not)."""
    from doe.goals import goals_missed

    missed, plate_missed = goals_missed(levels, n_levels, target, simulated)
    if missed:
        return [f"warning: the nominal plate misses the design goals ({'; '.join(missed)})"]
    if plate_missed:
        return [
            "warning: the design meets the goals, but a plate of square pixels misses them "
            f"({'; '.join(plate_missed)}); see the report's Summary"
        ]
    return []


def _tolerance(levels, n_levels, target, masks, der, design, progress):
    """Run the tolerance analysis of the plate behind a progress bar (terminal only)."""
    from tqdm import tqdm

    from fab.plate.tolerance import tolerance_analysis

    # Seconds at N = 175, minutes at a fine mask pitch (N in the thousands).
    with tqdm(
        desc="tolerance", unit=" plates", file=sys.stderr, leave=False,
        disable=not (progress and sys.stderr.isatty()),
    ) as bar:  # fmt: skip
        return tolerance_analysis(
            levels, n_levels, target, masks,
            pixel_pitch=der.mask_pixel_pitch, level_step=der.level_step,
            wavelength=design.optics.wavelength, refractive_index=der.refractive_index, seed=0,
            on_plate=bar.update,
        )  # fmt: skip


def _report(stage, context):
    from fab.package.report import write_fab_report

    return list(write_fab_report(stage, context))
