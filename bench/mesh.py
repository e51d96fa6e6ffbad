"""Benchmark of ``doefab mesh`` on the default design: prints times, triangle counts, sizes.

A dense random 8-level tile of the default preset (N = 175) is meshed as the
watertight height field of ``fab.mesh.relief`` and, for comparison, naively as one
closed box per pixel (12 triangles each, concatenated: not one solid, internal
faces everywhere). Every mesh format is encoded for both; the STEP tile (B-rep
solid + file) is timed too, and ``--verify-step`` re-imports it.

Usage: python bench/mesh.py [--repeats 3] [--no-step] [--verify-step] [--seed 0]
"""

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from doe.derived import derive
from doe.design import load_design
from doe.infra import flags
from fab.mesh import formats as mesh_io
from fab.mesh import relief as mesh

ENCODERS = {
    "ply": mesh_io.ply_bytes,
    "glb": mesh_io.glb_bytes,
    "3mf": mesh_io.threemf_bytes,
    "stl": mesh_io.stl_bytes,
}


def naive_box_mesh(relief):
    """One closed axis-aligned box per pixel, from z = 0 to its top (mm)."""
    rows, cols = relief.levels.shape
    p = relief.pitch * 1e3
    tops = relief.level_z()[relief.levels.astype(np.int64)] * 1e3
    corners = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], float)
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    lo = np.stack([c.ravel() * p, (rows - 1 - r.ravel()) * p, np.zeros(r.size)], 1)
    size = np.stack([np.full(r.size, p), np.full(r.size, p), tops.ravel()], 1)
    verts = lo[:, None, :] + corners[None] * size[:, None, :]
    tris = faces[None] + 8 * np.arange(r.size)[:, None, None]
    return verts.reshape(-1, 3), tris.reshape(-1, 3)


def timed(fn, repeats):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=flags.count, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-step", action="store_true")
    ap.add_argument("--verify-step", action="store_true")
    a = ap.parse_args()

    design = load_design(None)
    der = derive(design)
    n, n_levels = der.tile_pixels, design.fabrication.levels
    levels = np.random.default_rng(a.seed).integers(0, n_levels, (n, n)).astype(np.uint8)
    relief = mesh.Relief(
        levels, n_levels, der.level_step, der.mask_pixel_pitch, design.material.thickness
    )
    analytic = relief.analytic_volume() * 1e9
    print(
        f"design {design.name}: N={n}, L={n_levels}, pitch {der.mask_pixel_pitch * 1e9:.0f} nm, "
        f"step {der.level_step * 1e9:.2f} nm, thickness {design.material.thickness * 1e3} mm; "
        f"random tile seed {a.seed}; medians of {a.repeats} (STEP rows: one run)"
    )

    rows = []
    t_tile, (v, f) = timed(lambda: mesh.tile_mesh(relief), a.repeats)
    t_naive, (nv, nf) = timed(lambda: naive_box_mesh(relief), a.repeats)
    for name, t, (vv, ff) in (("height field", t_tile, (v, f)), ("naive boxes", t_naive, (nv, nf))):
        vol = mesh.mesh_volume(vv, ff)
        rows.append((name, "build", t, len(ff), None, vol / analytic - 1))
        for fmt, enc in ENCODERS.items():
            te, data = timed(lambda enc=enc, vv=vv, ff=ff: enc(vv, ff), a.repeats)
            rows.append((name, fmt, te, len(ff), len(data), None))
    offsets = mesh.instance_offsets_mm(relief, (der.tiles, der.tiles))
    for fmt in ("glb", "3mf"):
        te, data = timed(lambda fmt=fmt: ENCODERS[fmt](v, f, offsets), a.repeats)
        rows.append((f"aperture {der.tiles}x{der.tiles}", fmt, te, len(f), len(data), None))

    if not a.no_step:
        from fab.mesh import step

        t_solid, solid = timed(lambda: step.tile_solid(relief), 1)
        t_write, data = timed(lambda: step.step_bytes(solid), 1)
        rows.append(("STEP tile", "solid", t_solid, len(solid.faces()), None, None))
        rows.append(("STEP tile", "write", t_write, len(solid.faces()), len(data), None))
        rows.append(("STEP tile", "total", t_solid + t_write, None, None, None))
        t_asm, asm = timed(lambda: step.assembly_step_bytes(data, offsets), 1)
        rows.append(
            (f"STEP aperture {der.tiles}x{der.tiles}", "write", t_asm, None, len(asm), None)
        )
        if a.verify_step:
            with tempfile.TemporaryDirectory() as tmp:
                path = Path(tmp) / "tile.step"
                path.write_bytes(data)
                t_chk, chk = timed(lambda: step.check_solid(step.read_step(path)), 1)
            rows.append(
                ("STEP tile", "re-import", t_chk, None, None, chk["volume_mm3"] / analytic - 1)
            )
            print(f"STEP re-import: {chk}")

    print(
        f"{'mesh':24s} {'step':9s} {'seconds':>9s} {'triangles*':>11s} {'bytes':>12s} "
        f"{'vol rel err':>12s}"
    )
    for name, what, t, tris, size, err in rows:
        print(
            f"{name:24s} {what:9s} {t:9.3f} {tris if tris is not None else '':>11} "
            f"{size if size is not None else '':>12} {'' if err is None else f'{err:.1e}':>12}"
        )
    print("* B-rep faces on the STEP rows (a solid has faces, not triangles)")
    print(f"ratio naive/height-field triangles: {len(nf) / len(f):.2f}")


if __name__ == "__main__":
    main()
