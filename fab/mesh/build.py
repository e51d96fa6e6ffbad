"""Build the 3-D models of a fab package: :func:`build_meshes` (``doefab mesh``).

Reads FAB_DIR/fab_manifest.json and its levels file; writes into ``out``:

- ``tile.{ply,glb,3mf,stl,step}``: one tile, lower-left corner at the origin;
- ``aperture.{glb,3mf,step}``: the tile stored once and instanced on the
  tiles [nx, ny] lattice, pitch N p, lower-left tile at the manifest's
  ``array_origin_nm`` (converted to mm; (0, 0) when absent);
- ``aperture_edge.{glb,3mf,step}`` when the plate has edge pixels: the clipped
  edge tiles that fill the clear aperture around the whole tiles, in the same
  coordinates (``fab.mesh.aperture_scene``), each stored once and instanced;
- ``crop_CxC.{ply,glb,3mf,stl}`` with ``crop=C``: one merged body of C x C
  tiles, lower-left at the same origin (refused when too large to build);
- ``preview.png`` and ``mesh_report.json``.

Units are mm everywhere (STL stores none: its header says "units mm").
"""

import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from doe.infra.errors import InputError
from doe.infra.files import atomic_write_bytes, read_levels, staged_output
from doe.records.fab_manifest import MANIFEST_NAME, read_fab_manifest
from doe.records.mesh_report import (
    APERTURE_NOTE,
    MESH_REPORT_NAME,
    MeshReport,
    previous_mesh_files,
    write_mesh_report,
)
from fab.mesh import formats as mesh_io
from fab.mesh import relief as mesh
from fab.mesh.aperture_scene import EDGE_SCENE, SCENE_ENCODERS, aperture_parts, part_meshes
from fab.mesh.chamfer import CHAMFER_LEG, CHAMFER_NOTE
from fab.mesh.checks import (
    FORMATS,
    INSTANCED,
    check_crop,
    check_float32_heights,
    check_step_size,
    check_tile_size,
    parse_formats,
)


@dataclass(frozen=True)
class MeshResult:
    """What :func:`build_meshes` wrote.

    Attributes
    ----------
    out : pathlib.Path
        The output folder.
    formats : tuple of str
        The formats written, in ``FORMATS`` order.
    files : tuple of str
        Every file written (``mesh_report.json`` included), sorted.
    report : doe.records.mesh_report.MeshReport
        The figures written to ``mesh_report.json``.
    seconds : Mapping of str to float
        Wall time of each step ("tile_mesh", each format, "crop", "step_solid",
        "step_write"), in the order they ran.
    """

    out: Path
    formats: tuple[str, ...]
    files: tuple[str, ...]
    report: MeshReport
    seconds: Mapping[str, float]

    @property
    def step_ok(self):
        """Whether the STEP solid passed its check; None when STEP was not written."""
        return None if self.report.step is None else bool(self.report.step["ok"])


def read_fab_dir(fab_dir, thickness_mm=None):
    """Read the manifest and levels of FAB_DIR; return (Relief, manifest dict).

    The dict holds ``tiles`` [nx, ny], ``origin_mm`` [x0, y0], ``design_name`` and
    ``material`` (None when absent), ``thickness_source`` (where the thickness came
    from: the flag or the manifest key) and ``levels_path``, for messages about them.

    Raises
    ------
    InputError
        Naming the folder, the manifest, its levels file or ``--thickness-mm``.
    """
    fab_dir = Path(fab_dir)
    if not fab_dir.is_dir():
        raise InputError(fab_dir, "no such folder (expected the output of doefab fab)")
    path = fab_dir / MANIFEST_NAME
    if not path.is_file():  # e.g. a retrieve folder
        raise InputError(path, "no such file; mesh takes the folder that doefab fab wrote")
    manifest = read_fab_manifest(path)
    tile = manifest.tile_geometry()
    thickness, where = _substrate_thickness(manifest, tile, thickness_mm)
    levels_path = manifest.levels_path()
    levels = read_levels(levels_path, tile.n_levels)
    if levels.shape[0] != tile.tile_pixels:
        raise InputError(
            levels_path,
            f"shape {levels.shape} does not match tile_pixels {tile.tile_pixels} of {path}",
        )
    relief = mesh.Relief(levels, tile.n_levels, tile.level_step, tile.pixel_pitch, thickness)
    return relief, {
        "tiles": list(tile.tiles),
        "origin_mm": list(tile.array_origin_mm),
        "edge_pixels": list(tile.edge_pixels),
        "design_name": manifest.fields.get("design_name"),
        "material": manifest.fields.get("material"),
        "thickness_source": where,
        "levels_path": levels_path,
    }


def _substrate_thickness(manifest, tile, thickness_mm):
    """Return (thickness in m, where it came from): ``thickness_mm`` or the manifest's."""
    if thickness_mm is None:
        if "substrate_thickness_mm" not in manifest.fields:
            raise InputError(
                manifest.path, "missing key 'substrate_thickness_mm'; add it or pass --thickness-mm"
            )
        thickness_mm = manifest.fields["substrate_thickness_mm"]
        where = f"{manifest.path}: substrate_thickness_mm"
    else:
        where = "--thickness-mm"
    try:
        thickness = float(thickness_mm) * 1e-3
    except (TypeError, ValueError, OverflowError):
        raise InputError(where, f"not a number: {thickness_mm!r}") from None
    if not np.isfinite(thickness):
        raise InputError(where, f"must be a finite number of mm, got {thickness_mm!r}")
    deepest = (tile.n_levels - 1) * tile.level_step
    if thickness <= deepest:
        raise InputError(
            where,
            f"{thickness * 1e3:g} mm is not thicker than the deepest etch {deepest * 1e3:g} mm",
        )
    return thickness, where


def build_meshes(
    fab_dir, out, *, formats=FORMATS, crop=None, thickness_mm=None, force=False, progress=True
):
    """Write the 3-D models of the tile and the tiled aperture of a fab package.

    Parameters
    ----------
    fab_dir : path
        ``doefab fab``'s output folder (``fab_manifest.json`` and its levels file).
    out : path
        Output folder, written through a staging folder: a refused or failed run
        leaves nothing there.
    formats : str or iterable of str
        A subset of ``FORMATS`` (ply, glb, 3mf, stl, step), or its comma-separated text.
    crop : int or None
        Also write one merged body of ``crop`` x ``crop`` tiles (mesh formats only).
    thickness_mm : float or None
        Substrate thickness; default the manifest's ``substrate_thickness_mm``.
    force : bool
        Overwrite the files of an earlier run in ``out``.
    progress : bool
        Show a progress bar on a terminal.

    Returns
    -------
    MeshResult
        Its ``step_ok`` is False when the STEP solid failed its check (the files are
        written all the same, to be looked at).

    Raises
    ------
    InputError
        Unusable input (naming the file or the option), or a model too large to build.
    """
    formats = parse_formats(formats if isinstance(formats, str) else ",".join(formats))
    relief, info = read_fab_dir(fab_dir, thickness_mm)
    check_float32_heights(relief.thickness * 1e3, formats, info["thickness_source"])
    check_tile_size(relief, info["levels_path"])
    if crop is not None:
        if formats == ["step"]:
            raise InputError(
                "--crop", "the merged crop is a mesh: add ply, glb, 3mf or stl to --formats"
            )
        check_crop(relief, crop, info["tiles"])
    if "step" in formats:
        check_step_size(relief, Path(fab_dir) / MANIFEST_NAME)
    names = _file_names(formats, crop, any(info["edge_pixels"]))
    stale = previous_mesh_files(Path(out) / MESH_REPORT_NAME)
    with staged_output(out, force, names, stale) as stage:
        report, seconds = _write_models(stage, relief, info, formats, crop, progress)
        files = tuple(sorted(p.name for p in stage.iterdir()))
    return MeshResult(Path(out), tuple(formats), files, report, seconds)


def _file_names(formats, crop, edges):
    """Return the names a run with these formats and crop writes (``edges``: edge pieces)."""
    names = [f"tile.{f}" for f in formats] + [f"aperture.{f}" for f in formats if f in INSTANCED]
    names += [f"{EDGE_SCENE}.{f}" for f in formats if edges and f in INSTANCED]
    if crop is not None:
        names += [f"crop_{crop}x{crop}.{f}" for f in formats if f != "step"]
    return [*names, "preview.png", MESH_REPORT_NAME]


def _write_models(stage, relief, info, formats, crop, progress):
    """Write every model, the preview and the report into ``stage``.

    Returns
    -------
    report : MeshReport
    seconds : dict
        Wall time of each step, in the order they ran.
    """
    tiles, origin = info["tiles"], info["origin_mm"]
    offsets = mesh.instance_offsets_mm(relief, tiles, origin)
    seconds = {}
    t0 = time.perf_counter()
    surface = mesh.relief_surface(relief.levels, progress=progress)
    vertices, faces = mesh.surface_points_mm(surface, relief), surface.triangles
    seconds["tile_mesh"] = time.perf_counter() - t0
    volume = mesh.mesh_volume(vertices, faces)
    analytic = relief.analytic_volume() * 1e9
    n_rows, n_cols = relief.levels.shape
    tile = {
        "triangles": len(faces),
        "vertices": len(vertices),
        "size_mm": [
            n_cols * relief.pitch * 1e3,
            n_rows * relief.pitch * 1e3,
            relief.thickness * 1e3,
        ],
        "volume_mm3": volume,
        "analytic_volume_mm3": analytic,
        "volume_rel_err": volume / analytic - 1,
        "chamfers": {
            "corners": surface.chamfers,
            "leg_nm": CHAMFER_LEG * relief.pitch * 1e9,
            "volume_mm3": relief.chamfer_volume() * 1e9,
            "note": CHAMFER_NOTE,
        },
    }
    edge_parts = _edge_parts(relief, info)
    scene = part_meshes(edge_parts) if set(formats) & set(SCENE_ENCODERS) else []
    aperture = {
        "tiles": tiles,
        "instances": len(offsets),
        "edge_pieces": len(edge_parts),
        "edge_instances": sum(len(part[2]) for part in edge_parts),
        "edge_scene": [f"{EDGE_SCENE}.{f}" for f in formats if edge_parts and f in INSTANCED],
        "origin_mm": origin,
        "pitch_mm": n_rows * relief.pitch * 1e3,
        "note": APERTURE_NOTE,
    }
    for fmt in formats:
        if fmt == "step":
            continue
        t0 = time.perf_counter()
        encode = _ENCODERS[fmt]
        atomic_write_bytes(stage / f"tile.{fmt}", encode(vertices, faces))
        if fmt in INSTANCED:
            atomic_write_bytes(stage / f"aperture.{fmt}", encode(vertices, faces, offsets))
        if scene and fmt in SCENE_ENCODERS:
            atomic_write_bytes(stage / f"{EDGE_SCENE}.{fmt}", SCENE_ENCODERS[fmt](scene))
        seconds[fmt] = time.perf_counter() - t0
    crop_figures = None
    if crop is not None:
        crop_figures = _write_crop(stage, relief, crop, origin, formats, seconds)
    step = None
    if "step" in formats:
        step = _write_step(relief, surface, offsets, stage, seconds)
        if edge_parts:
            step = _write_edge_step(edge_parts, step, stage, seconds)
    atomic_write_bytes(stage / "preview.png", mesh_io.preview_png_bytes(relief))
    files = {
        p.name: p.stat().st_size for p in sorted(stage.iterdir()) if p.name != MESH_REPORT_NAME
    }
    report = MeshReport(tile, aperture, files, crop=crop_figures, step=step)
    write_mesh_report(stage / MESH_REPORT_NAME, report)
    return report, seconds


def _edge_parts(relief, info):
    """The edge scene's parts [(name, Relief, offsets)], or [] when there are none."""
    if not any(info["edge_pixels"]):
        return []
    parts = aperture_parts(relief, info["tiles"], info["origin_mm"], info["edge_pixels"])
    return parts[1:]  # parts[0]: the whole tile, in aperture.*


_ENCODERS = {
    "ply": mesh_io.ply_bytes,
    "stl": mesh_io.stl_bytes,
    "glb": mesh_io.glb_bytes,
    "3mf": mesh_io.threemf_bytes,
}


def _write_crop(stage, relief, crop, origin, formats, seconds):
    """Write the merged ``crop`` x ``crop``-tile body in the mesh formats; return its figures."""
    c = crop
    t0 = time.perf_counter()
    merged = relief.tiled(c, c)  # its seams may add pinched corners: its own analytic volume
    cv, cf = mesh.tile_mesh(merged)
    cv = cv + np.array([origin[0], origin[1], 0.0])
    for fmt in formats:
        if fmt != "step":
            atomic_write_bytes(stage / f"crop_{c}x{c}.{fmt}", _ENCODERS[fmt](cv, cf))
    seconds["crop"] = time.perf_counter() - t0
    return {
        "tiles": [c, c],
        "triangles": len(cf),
        "origin_mm": origin,
        "volume_mm3": mesh.mesh_volume(cv, cf),
        "analytic_volume_mm3": merged.analytic_volume() * 1e9,
    }


def _write_step(relief, surface, offsets, stage, seconds):
    """Write tile.step and aperture.step; return the solid's check for the report."""
    from fab.mesh import step  # build123d: only when STEP is asked for

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


def _write_edge_step(edge_parts, tile_check, stage, seconds):
    """Write aperture_edge.step; return the STEP check with the edge solids' added."""
    from fab.mesh import step  # build123d: only when STEP is asked for

    t0 = time.perf_counter()
    solids = [(name, step.tile_solid(part), offsets) for name, part, offsets in edge_parts]
    data = step.scene_step_bytes(solids, EDGE_SCENE)
    atomic_write_bytes(stage / f"{EDGE_SCENE}.step", data)
    seconds["step_edge"] = time.perf_counter() - t0
    checks = [step.check_solid(solid) for _, solid, _ in solids]
    errors = [
        c["volume_mm3"] / (part.analytic_volume() * 1e9) - 1
        for c, (_, part, _) in zip(checks, edge_parts, strict=True)
    ]
    ok = all(c["solids"] == 1 and c["closed"] for c in checks) and max(map(abs, errors)) <= 1e-6
    edge = {"solids": len(solids), "volume_rel_err_max": max(errors, key=abs), "ok": ok}
    return dict(tile_check, edge=edge, ok=bool(tile_check["ok"] and ok))
