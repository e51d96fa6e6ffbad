"""``doefab mesh``: 3-D models (PLY, GLB, 3MF, STL, STEP) of the tile and the tiled aperture.

Reads FAB_DIR/fab_manifest.json and its levels file; writes into --out:

- ``tile.{ply,glb,3mf,stl,step}``: one tile, lower-left corner at the origin;
- ``aperture.{glb,3mf,step}``: the tile stored once and instanced on the
  tiles [nx, ny] lattice, pitch N p, lower-left tile at the manifest's
  ``array_origin_nm`` (converted to mm; (0, 0) when absent);
- ``crop_CxC.{ply,glb,3mf,stl}`` with ``--crop C``: one merged body of C x C
  tiles, lower-left at the same origin (refused when too large to build);
- ``preview.png`` and ``mesh_report.json``.

Units are mm everywhere (STL stores none: its header says "units mm").
"""

import time
from pathlib import Path

from doe.infra.errors import InputError

FORMATS = ("ply", "glb", "3mf", "stl", "step")
INSTANCED = ("glb", "3mf", "step")
# GLB and STL store float32 coordinates; at z = thickness they round heights by half
# a float32 spacing, which must stay within the 1 nm the mesh checks hold z to
# (float32 spacing is 1.9 nm up to 32 mm, 3.8 nm beyond).
FLOAT32_FORMATS = ("glb", "stl")
Z_ROUNDING_LIMIT_NM = 1.0
# Peak memory per triangle of the upper bound (fab.mesh.relief.triangle_upper_bound): numpy
# arrays plus the Python lists of the builder and the encoders (measured 150-270 B on
# random 300^2 to 1000^2 maps, whose bound is ~1.75 x their triangle count).
BYTES_PER_TRIANGLE = 300
MERGED_MEMORY_LIMIT_BYTES = 2 * 1024**3
# The tile is always built: a 0.25 um pitch design of N = 3494 needs ~43 GiB (over
# 15 min); this limit passes about N = 1500 at worst (a random map), 3000 for a smooth one.
TILE_MEMORY_LIMIT_BYTES = 8 * 1024**3


def register(sub):
    p = sub.add_parser(
        "mesh",
        help="3-D models of the tile and the tiled aperture",
        description=__doc__.split("\n\n", 1)[1],
    )
    p.add_argument("fab_dir", metavar="FAB_DIR", help="folder with fab_manifest.json")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--formats",
        default=",".join(FORMATS),
        help=f"comma-separated subset of {','.join(FORMATS)} (default: all)",
    )
    p.add_argument(
        "--crop",
        type=int,
        metavar="TILES",
        help="also write one merged body of TILES x TILES tiles",
    )
    p.add_argument(
        "--thickness-mm",
        type=float,
        help="substrate thickness (default: the manifest's substrate_thickness_mm)",
    )
    p.add_argument("--force", action="store_true", help="overwrite existing files")
    p.set_defaults(func=run_mesh)


def read_fab_dir(fab_dir, thickness_mm=None):
    """Read the manifest and levels of FAB_DIR; return (Relief, manifest dict).

    The dict's ``thickness_source`` names where the thickness came from (the flag
    or the manifest key), and ``levels_path`` the levels file, for messages about them.
    """
    import numpy as np

    from doe.design import LONGEST_LENGTH, SHORTEST_LENGTH
    from doe.infra.files import LEVEL_COUNT_RULE, is_level_count, read_json, read_levels
    from fab.mesh.relief import Relief

    fab_dir = Path(fab_dir)
    if not fab_dir.is_dir():
        raise InputError(fab_dir, "no such folder (expected the output of doefab fab)")
    path = fab_dir / "fab_manifest.json"
    if not path.is_file():  # e.g. a retrieve folder
        raise InputError(path, "no such file; mesh takes the folder that doefab fab wrote")
    man = read_json(path)
    for key in ("levels", "level_step_nm", "pixel_pitch_nm", "tile_pixels", "tiles", "levels_file"):
        if key not in man:
            raise InputError(path, f"missing key {key!r}")
    try:
        n_levels, n = _whole(man["levels"]), _whole(man["tile_pixels"])
        step, pitch = float(man["level_step_nm"]) * 1e-9, float(man["pixel_pitch_nm"]) * 1e-9
        tiles = [_whole(t) for t in man["tiles"]]
        origin = [float(v) * 1e-6 for v in man.get("array_origin_nm", [0.0, 0.0])]
    except (TypeError, ValueError, OverflowError) as e:  # int(1e400): OverflowError
        raise InputError(path, f"malformed value ({e})") from None
    if len(tiles) != 2 or min(tiles) < 1 or len(origin) != 2:
        raise InputError(path, "tiles must be [nx, ny] >= 1 and array_origin_nm [x0, y0]")
    if not is_level_count(n_levels):
        raise InputError(path, f"levels {n_levels} must be {LEVEL_COUNT_RULE}")
    if not (step > 0 and pitch > 0 and n >= 1):
        raise InputError(path, "level_step_nm > 0, pixel_pitch_nm > 0 required")
    # as every length of a design; 1e-300 nm once divided a volume by 0
    lengths_ok = all(SHORTEST_LENGTH <= x <= LONGEST_LENGTH for x in (step, pitch))
    if not (lengths_ok and np.isfinite(origin).all()):
        raise InputError(
            path,
            "level_step_nm and pixel_pitch_nm must lie between 1 pm and 1 m, "
            "array_origin_nm be finite",
        )
    if thickness_mm is None:
        if "substrate_thickness_mm" not in man:
            raise InputError(
                path, "missing key 'substrate_thickness_mm'; add it or pass --thickness-mm"
            )
        thickness_mm = man["substrate_thickness_mm"]
        where = f"{path}: substrate_thickness_mm"
    else:
        where = "--thickness-mm"
    try:
        thickness = float(thickness_mm) * 1e-3
    except (TypeError, ValueError, OverflowError):
        raise InputError(where, f"not a number: {thickness_mm!r}") from None
    if not np.isfinite(thickness):
        raise InputError(where, f"must be a finite number of mm, got {thickness_mm!r}")
    if thickness <= (n_levels - 1) * step:
        raise InputError(
            where,
            f"{thickness * 1e3:g} mm is not thicker than the deepest etch "
            f"{(n_levels - 1) * step * 1e3:g} mm",
        )
    if not isinstance(man["levels_file"], str):
        raise InputError(path, f"levels_file must be a file name, got {man['levels_file']!r}")
    levels_path = fab_dir / man["levels_file"]
    levels = read_levels(levels_path, n_levels)
    if levels.shape[0] != n:
        raise InputError(
            levels_path, f"shape {levels.shape} does not match tile_pixels {n} of {path}"
        )
    relief = Relief(levels, n_levels, step, pitch, thickness)
    return relief, {
        "tiles": tiles,
        "origin_mm": [v for v in origin],
        "design_name": man.get("design_name"),
        "material": man.get("material"),
        "thickness_source": where,
        "levels_path": levels_path,
    }


def _whole(value):
    """Return ``value`` as an int, refusing 8.9 or True (int() would make them 8 and 1)."""
    if isinstance(value, bool) or float(value) != int(value):
        raise ValueError(f"{value!r} is not a whole number")
    return int(value)


def parse_formats(text):
    """Return the formats named in a comma-separated ``--formats`` value, in FORMATS order."""
    formats = [f.strip().lower() for f in text.split(",") if f.strip()]
    bad = [f for f in formats if f not in FORMATS]
    if bad or not formats:
        raise InputError(
            "--formats", f"unknown format(s) {bad or text!r}; choose from {','.join(FORMATS)}"
        )
    return [f for f in FORMATS if f in formats]


def check_crop(relief, crop, tiles):
    """Refuse a merged crop that exceeds the aperture or the memory limit (InputError)."""
    from fab.mesh.relief import triangle_upper_bound

    if crop < 1:
        raise InputError("--crop", f"must be >= 1 tile, got {crop}")
    if crop > min(tiles):
        raise InputError(
            "--crop", f"{crop} x {crop} tiles exceed the aperture's {tiles[0]} x {tiles[1]} tiles"
        )
    est = triangle_upper_bound(relief.levels, crop)
    need = est * BYTES_PER_TRIANGLE
    if need > MERGED_MEMORY_LIMIT_BYTES:
        raise InputError(
            "--crop",
            f"a merged {crop} x {crop}-tile body needs up to {est:,} "
            f"triangles (~{need / 1024**3:.1f} GiB, limit "
            f"{MERGED_MEMORY_LIMIT_BYTES / 1024**3:.0f} GiB); use the instanced "
            f"aperture.glb / aperture.3mf / aperture.step or a smaller --crop",
        )
    return est


def check_tile_size(relief, levels_path):
    """Refuse a tile whose mesh would exceed the memory limit (InputError)."""
    from fab.mesh.relief import triangle_upper_bound

    est = triangle_upper_bound(relief.levels)
    need = est * BYTES_PER_TRIANGLE
    if need > TILE_MEMORY_LIMIT_BYTES:
        n = relief.levels.shape[0]
        raise InputError(
            levels_path,
            f"the mesh of this {n} x {n}-pixel tile needs up to {est:,} triangles "
            f"(~{need / 1024**3:.0f} GiB, limit {TILE_MEMORY_LIMIT_BYTES / 1024**3:.0f} GiB); "
            "the fab package does not need it (doefab run --formats none skips the mesh)",
        )


def check_float32_heights(thickness_mm, formats, where):
    """Refuse float32 formats whose rounding at the top surface exceeds the z tolerance."""
    import numpy as np

    single = [f for f in formats if f in FLOAT32_FORMATS]
    with np.errstate(over="ignore"):
        rounding_nm = float(np.spacing(np.float32(thickness_mm))) / 2 * 1e6
    if not single or rounding_nm <= Z_ROUNDING_LIMIT_NM:
        return
    detail = (
        f"round heights at that z by up to {rounding_nm:.2g} nm"
        if np.isfinite(rounding_nm)
        else "cannot hold that z"
    )
    raise InputError(
        where,
        f"{thickness_mm:g} mm: {' and '.join(single)} store float32 coordinates, which "
        f"{detail} (limit {Z_ROUNDING_LIMIT_NM:g} nm); use a thinner substrate or drop "
        "them from --formats",
    )


def run_mesh(args):
    import numpy as np

    from doe.infra.files import atomic_write_bytes, previous_files, staged_output, write_json
    from fab.mesh import formats as mesh_io
    from fab.mesh import relief as mesh

    formats = parse_formats(args.formats)
    relief, info = read_fab_dir(args.fab_dir, args.thickness_mm)
    check_float32_heights(relief.thickness * 1e3, formats, info["thickness_source"])
    check_tile_size(relief, info["levels_path"])
    tiles, origin = info["tiles"], info["origin_mm"]
    if args.crop is not None:
        if formats == ["step"]:
            raise InputError(
                "--crop", "the merged crop is a mesh: add ply, glb, 3mf or stl to --formats"
            )
        check_crop(relief, args.crop, tiles)
    if "step" in formats:
        from fab.mesh.step import MAX_STEP_FACES, step_face_count

        faces = step_face_count(relief.levels)
        if faces > MAX_STEP_FACES:
            raise InputError(
                Path(args.fab_dir) / "fab_manifest.json",
                f"the tile needs {faces:,} planar STEP faces (limit "
                f"{MAX_STEP_FACES:,}), too complex to build in time; drop step "
                f"from --formats and use the mesh formats (ply, glb, 3mf, stl)",
            )

    names = [f"tile.{f}" for f in formats] + [f"aperture.{f}" for f in formats if f in INSTANCED]
    if args.crop is not None:
        names += [f"crop_{args.crop}x{args.crop}.{f}" for f in formats if f != "step"]
    names += ["preview.png", "mesh_report.json"]

    encoders = {
        "ply": mesh_io.ply_bytes,
        "stl": mesh_io.stl_bytes,
        "glb": mesh_io.glb_bytes,
        "3mf": mesh_io.threemf_bytes,
    }
    offsets = mesh.instance_offsets_mm(relief, tiles, origin)
    seconds = {}
    stale = previous_files(Path(args.out) / "mesh_report.json", lambda report: report["files"])
    with staged_output(args.out, args.force, names, stale) as stage:
        t0 = time.perf_counter()
        surface = mesh.relief_surface(relief.levels)
        vertices, faces = mesh.surface_points_mm(surface, relief), surface.triangles
        seconds["tile_mesh"] = time.perf_counter() - t0
        volume = mesh.mesh_volume(vertices, faces)
        analytic = relief.analytic_volume() * 1e9
        report = {
            "units": "mm",
            "convention": "z up, back face z=0, row 0 of levels at the largest y (CONVENTIONS.md)",
            "tile": {
                "triangles": len(faces),
                "vertices": len(vertices),
                "size_mm": [
                    relief.levels.shape[1] * relief.pitch * 1e3,
                    relief.levels.shape[0] * relief.pitch * 1e3,
                    relief.thickness * 1e3,
                ],
                "volume_mm3": volume,
                "analytic_volume_mm3": analytic,
                "volume_rel_err": volume / analytic - 1,
            },
            "aperture": {
                "tiles": tiles,
                "instances": len(offsets),
                "origin_mm": origin,
                "pitch_mm": relief.levels.shape[0] * relief.pitch * 1e3,
                "note": "lower-left tile at the manifest's array_origin_nm",
            },
            "files": {},
        }
        for fmt in formats:
            if fmt == "step":
                continue
            t0 = time.perf_counter()
            atomic_write_bytes(stage / f"tile.{fmt}", encoders[fmt](vertices, faces))
            if fmt in INSTANCED:
                atomic_write_bytes(
                    stage / f"aperture.{fmt}", encoders[fmt](vertices, faces, offsets)
                )
            seconds[fmt] = time.perf_counter() - t0
        if args.crop is not None:
            c = args.crop
            t0 = time.perf_counter()
            cv, cf = mesh.tile_mesh(relief.tiled(c, c))
            cv = cv + np.array([origin[0], origin[1], 0.0])
            for fmt in formats:
                if fmt != "step":
                    atomic_write_bytes(stage / f"crop_{c}x{c}.{fmt}", encoders[fmt](cv, cf))
            seconds["crop"] = time.perf_counter() - t0
            report["crop"] = {
                "tiles": [c, c],
                "triangles": len(cf),
                "origin_mm": origin,
                "volume_mm3": mesh.mesh_volume(cv, cf),
                "analytic_volume_mm3": analytic * c * c,
            }
        if "step" in formats:
            report["step"] = _write_step(relief, surface, offsets, stage, seconds)
        atomic_write_bytes(stage / "preview.png", mesh_io.preview_png_bytes(relief))
        report["files"] = {
            p.name: p.stat().st_size
            for p in sorted(stage.iterdir())
            if p.name != "mesh_report.json"
        }
        write_json(stage / "mesh_report.json", report)
    timing = ", ".join(f"{k} {v:.1f} s" for k, v in seconds.items())
    print(
        f"doefab mesh: {len(faces):,} triangles per tile, {len(offsets)} instances, "
        f"volume rel. err {volume / analytic - 1:.1e}; {timing}; wrote {args.out}"
    )
    if "step" in report and not report["step"]["ok"]:
        print(f"doefab mesh: STEP solid check failed: {report['step']}")
        return 1
    return 0


def _write_step(relief, surface, offsets, stage, seconds):
    from doe.infra.files import atomic_write_bytes
    from fab.mesh import step

    t0 = time.perf_counter()
    solid = step.tile_solid(relief, surface)
    seconds["step_solid"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    tile_step = step.step_bytes(solid)
    atomic_write_bytes(stage / "tile.step", tile_step)
    seconds["step_write"] = time.perf_counter() - t0
    atomic_write_bytes(stage / "aperture.step", step.assembly_step_bytes(tile_step, offsets))
    check = step.check_solid(solid)
    analytic = relief.analytic_volume() * 1e9
    rel = check["volume_mm3"] / analytic - 1
    ok = check["solids"] == 1 and check["closed"] and abs(rel) <= 1e-6
    return dict(check, faces=len(solid.faces()), volume_rel_err=rel, ok=ok)
