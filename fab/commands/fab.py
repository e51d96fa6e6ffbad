"""``doefab fab DESIGN_DIR --out DIR``: the fabrication package of a phase tile.

Masks -> GDS (+ optional OASIS) -> KLayout read-back check -> layer images ->
tolerance analysis -> manifest -> report, all written through a staging folder
so that a failed or refused run leaves nothing behind.
"""

import shutil
import sys
from pathlib import Path

from doe.infra.errors import InputError, first_line


def register(sub):
    p = sub.add_parser(
        "fab",
        help="write masks (GDSII), layer images, tolerances, manifest and report of a design",
        description=(
            "Turn DESIGN_DIR/levels.npy (uint8 N x N, values 0..L-1) into a fabrication "
            "package: binary masks with Sellmeier etch depths, a GDSII file with the tile "
            "as one cell placed by one AREF over the aperture, alignment marks, layer images, "
            "a tolerance table, fab_manifest.json and fab_report.{md,html}."
        ),
    )
    p.add_argument(
        "design_dir",
        metavar="DESIGN_DIR",
        help="folder with levels.npy "
        "(target_psf.npy and retrieval.json optional), e.g. doefab retrieve's --out",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--config", help="design TOML file or preset name (default preset if absent)")
    p.add_argument("--force", action="store_true", help="overwrite existing files in --out")
    p.add_argument("--oasis", action="store_true", help="also write mask.oas (KLayout)")
    p.set_defaults(func=_fab)


class _CheckFailed(Exception):
    """The written package failed its self-check: nothing is released."""


def _fab(args):
    try:
        result = run_fab(
            args.design_dir, args.out, config=args.config, force=args.force, oasis=args.oasis
        )
    except _CheckFailed as e:
        print(f"doefab fab: FAIL {e}; nothing written", file=sys.stderr)
        return 1
    m = result["manifest"]
    depths = ", ".join(f"{mk['name']} {mk['etch_depth_nm']:.1f} nm" for mk in m["masks"])
    print(
        f"doefab fab: wrote {len(result['files'])} files to {args.out} "
        f"(N={m['tile_pixels']}, pitch {m['pixel_pitch_nm']} nm, tiles {m['tiles']}; {depths})"
    )
    return 0


def load_design_dir(design_dir, design):
    """Read and validate DESIGN_DIR's levels and target PSF, made for ``design``.

    Returns
    -------
    levels : (N, N) uint8
    target : (K, K) float64 or None
        None when DESIGN_DIR has no target_psf.npy.
    """
    from doe.design import TILE_KEYS, design_differences
    from doe.infra.files import read_json, read_levels, read_psf

    d = Path(design_dir)
    n_levels = design.fabrication.levels
    if not d.is_dir():
        raise InputError(d, "no such design folder (expected doefab retrieve's output)")
    info = d / "retrieval.json"
    if info.is_file():
        record = read_json(info)
        got = record.get("levels")
        if got is not None and (not isinstance(got, int) or isinstance(got, bool)):
            raise InputError(info, f"'levels' must be a whole number, got {got!r}")
        if got is not None and got != n_levels:
            raise InputError(
                info,
                f"the design was quantised to {got} levels but the configuration has "
                f"{n_levels}; pass a --config whose [fabrication] levels = {got}",
            )
        # a tile etched for another wavelength, glass or sub-pixel grid is a wrong plate
        differences = design_differences(record.get("design"), design, TILE_KEYS)
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
    from doe.design import derive

    der = derive(design)
    return der if der.tile_pixels == n else derive(design, tile_pixels=n)


def tile_summary(design, der):
    """Return design_summary(design) with its derived optics for the tile actually fabricated."""
    from doe.design import design_summary

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


def run_fab(design_dir, out, config=None, force=False, oasis=False, progress=True):
    """Write the fabrication package; return {"manifest", "files"}.

    Raises InputError for unusable input (exit 2) and _CheckFailed when the
    written GDS does not read back as the masks (exit 1); in both cases
    nothing is left in ``out``.
    """
    from tqdm import tqdm

    from doe.design import MAX_TILE_PIXELS, derive, lattice_problem, load_design
    from doe.fraunhofer import simulate_levels
    from doe.infra.files import previous_files, save_npy, staged_output
    from fab.package import manifest as fm
    from fab.package.layer_images import layer_image_names, write_layer_images
    from fab.package.masks import masks_from_levels
    from layouts.gds import build_library, write_gds, write_oasis
    from layouts.marks import plate_half_size_nm
    from layouts.readback import check_written_gds

    design = load_design(config)
    n_levels = design.fabrication.levels
    levels, target = load_design_dir(design_dir, design)
    n = levels.shape[0]
    if n > MAX_TILE_PIXELS:  # as doefab retrieve --tile-pixels and the design check refuse
        raise InputError(
            Path(design_dir) / "levels.npy",
            f"N = {n} pixels per tile, more than {MAX_TILE_PIXELS} (GDS, tolerance and "
            "mesh time and memory grow as N^2)",
        )
    der = tile_derived(design, n)
    pitch_nm = round(der.mask_pixel_pitch * 1e9)
    if pitch_nm <= 0:
        raise InputError(
            Path(design_dir) / "levels.npy",
            f"N = {n} pixels per tile gives a pixel pitch below the "
            f"{design.fabrication.grid * 1e9:.0f} nm grid",
        )
    if target is not None and target.shape[0] > n:
        raise InputError(
            Path(design_dir) / "target_psf.npy",
            f"PSF size K = {target.shape[0]} exceeds the tile's N = {n} pixels",
        )
    k = target.shape[0] if target is not None else design.kernel_size
    if k > n:
        raise InputError(
            Path(design_dir) / "levels.npy",
            f"the tile's N = {n} pixels is smaller than the design's PSF size K = {k} "
            "(psf.kernel_size; there is no target_psf.npy)",
        )
    problem = lattice_problem(der, k, design.fabrication.grid)
    if problem:
        raise InputError(Path(design_dir) / "levels.npy", f"N = {n} pixels per tile: {problem}")
    notes = []  # printed once the package is written: a refusal is one line
    nominal = derive(design).tile_pixels
    if n > nominal:  # finer pixels than the process was chosen for
        notes.append(
            f"warning: N = {n} gives {pitch_nm} nm mask pixels, finer than the design's "
            f"{design.fabrication.feature_size * 1e6:g} um feature size (N = {nominal}, "
            "[fabrication] feature_size_um); check that the process can print them"
        )
    simulated, efficiency = simulate_levels(levels, n_levels, k)
    extra = {}
    if target is None:
        target = simulated
        extra["target_psf_source"] = "simulated from levels.npy (DESIGN_DIR had no target_psf.npy)"
        notes.append(
            "no target_psf.npy in the design folder; using the simulated PSF of "
            "levels.npy as the target"
        )
    notes += _goal_warnings(levels, n_levels, target, simulated)
    tiles = (der.tiles, der.tiles)
    aperture_nm = round(design.fabrication.aperture * 1e9)
    masks = masks_from_levels(levels, n_levels, der.level_step)

    stages = ["gds", "check", "images", "tolerance", "manifest", "report"]
    bar = tqdm(
        stages, desc="doefab fab", file=sys.stderr, disable=not (progress and sys.stderr.isatty())
    )
    known = [fm.GDS_NAME, fm.MANIFEST_NAME, fm.LEVELS_FILE, fm.TARGET_PSF_FILE]
    known += [name for mk in masks for name in layer_image_names(mk.name)]
    known += [fm.OASIS_NAME] if oasis else []
    stale = previous_files(Path(out) / fm.MANIFEST_NAME, _package_files)
    with staged_output(out, force, names=known, stale=stale) as stage:
        bar.set_postfix_str("gds")
        lib, layout = build_library(
            masks, pitch_nm, tiles, design.name, aperture_nm,
            grid_nm=round(design.fabrication.grid * 1e9),
        )  # fmt: skip
        write_gds(lib, stage / fm.GDS_NAME)
        try:  # KLayout reads the file back: gdstk truncates it on a full disk without a word
            if oasis:
                write_oasis(stage / fm.GDS_NAME, stage / fm.OASIS_NAME)
                extra["oasis"] = fm.OASIS_NAME
            bar.update()
            bar.set_postfix_str("check")
            problems = check_written_gds(stage / fm.GDS_NAME, layout, masks)
        except RuntimeError as e:
            raise InputError(
                Path(out) / fm.GDS_NAME,
                f"KLayout cannot read back the file written ({first_line(e)}); is the disk full?",
            ) from None
        if problems:
            raise _CheckFailed("; ".join(problems))
        bar.update()
        bar.set_postfix_str("images")
        half = max(tiles) * n * pitch_nm // 2 + 1
        aperture_half = max(half, aperture_nm // 2)
        write_layer_images(
            stage, masks, tiles, pitch_nm, plate_half_size_nm(aperture_half), aperture_half
        )
        bar.update()
        bar.set_postfix_str("tolerance")
        tolerance = _tolerance(levels, n_levels, target, masks, der, design, progress)
        bar.update()
        bar.set_postfix_str("manifest")
        save_npy(stage / fm.LEVELS_FILE, levels)  # exactly the array that was drawn
        if (Path(design_dir) / "target_psf.npy").exists():
            shutil.copyfile(Path(design_dir) / "target_psf.npy", stage / fm.TARGET_PSF_FILE)
        else:
            save_npy(stage / fm.TARGET_PSF_FILE, target)
        acceptance = tolerance.get("acceptance")
        manifest = fm.build_manifest(design, der, layout, masks, acceptance, extra, k)
        fm.write_manifest(stage, manifest)
        bar.update()
        bar.set_postfix_str("report")
        written = sorted(str(p.relative_to(stage)) for p in stage.rglob("*") if p.is_file())
        files = fm.file_records(stage, written)
        context = {
            "design": tile_summary(design, der),
            "manifest": manifest,
            "masks": mask_table(masks, layout.polygon_counts, pitch_nm),
            "levels": levels,
            "target_psf": target,
            "simulated_psf": simulated,
            "efficiency": efficiency,
            "tolerance": tolerance,
            "orientation": fm.ORIENTATION,
            "files": files,
        }
        report_files = _report(stage, context)
        bar.update()
        bar.close()
        all_files = sorted(str(p.relative_to(stage)) for p in stage.rglob("*") if p.is_file())
    for note in notes:  # once the package is in place: a refusal stays one line
        print(f"doefab fab: {note}", file=sys.stderr)
    return {"manifest": manifest, "files": all_files, "report_files": report_files}


def _goal_warnings(levels, n_levels, target, simulated):
    """Say when the nominal plate misses the design goals, as the report's Summary does:
    in the contract's model, or only as a plate of square pixels (whose sinc^2 envelope
    dims the outer orders; a report said "met" above a tolerance table that missed)."""
    from doe.retrieval import goals_missed

    missed, plate_missed = goals_missed(levels, n_levels, target, simulated)
    if missed:
        return [f"warning: the nominal plate misses the design goals ({'; '.join(missed)})"]
    if plate_missed:
        return [
            "warning: the design meets the goals, but a plate of square pixels misses them "
            f"({'; '.join(plate_missed)}); see the report's Summary"
        ]
    return []


def _package_files(manifest):
    """Return the files of a fab package whose names depend on it: layer images, OASIS."""
    from fab.package.layer_images import layer_image_names

    names = [name for mk in manifest["masks"] for name in layer_image_names(mk["name"])]
    return names + ([manifest["oasis"]] if "oasis" in manifest else [])


def _tolerance(levels, n_levels, target, masks, der, design, progress):
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
