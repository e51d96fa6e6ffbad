"""The relief meshes stay closed 2-manifolds after readers merge vertices by position.

STL stores no vertex indices, so every reader merges by position; the other formats
are merged by trimesh's default loading too. Where two diagonal pixels stand higher
than the other two, the chamfer (``fab.mesh.chamfer``) keeps them apart.
"""

import json

import manifold3d
import numpy as np
import pytest
import trimesh
from mesh_helpers import exact_volume_mm3, pinches

from doe.infra.cli import main
from fab.mesh.chamfer import CHAMFER_LEG, pinched_corners
from fab.mesh.formats import glb_bytes, ply_bytes, stl_bytes, threemf_bytes
from fab.mesh.relief import (
    Relief,
    instance_offsets_mm,
    mesh_volume,
    relief_surface,
    surface_points_mm,
    tile_mesh,
)

STEP, PITCH, THICK = 179.4e-9, 4990e-9, 0.5e-3
ENCODERS = {"stl": stl_bytes, "ply": ply_bytes, "glb": glb_bytes, "3mf": threemf_bytes}
FLOAT32 = ("stl", "glb")


def gaussian_levels(n=16, n_levels=8):
    """Wrapped phase of an off-centre Gaussian bump plus a tilt, quantised."""
    y, x = np.mgrid[0:n, 0:n] + 0.5
    phase = 9 * np.exp(-((x - 6.3) ** 2 + (y - 9.1) ** 2) / 20) + 0.37 * x + 0.21 * y
    return (np.floor(phase * n_levels) % n_levels).astype(np.uint8)


def random_levels(n, n_levels, seed):
    return np.random.default_rng(seed).integers(0, n_levels, (n, n)).astype(np.uint8)


CASES = {
    "gaussian-8": (gaussian_levels(), 8),
    "random-4": (random_levels(12, 4, seed=41), 4),
    "random-8": (random_levels(12, 8, seed=42), 8),
    "checkerboard-4": ((np.indices((8, 8)).sum(0) % 2 * 3).astype(np.uint8), 4),
}


def load_merged(path):
    """Load a file with trimesh's default processing (vertices merged by position)."""
    loaded = trimesh.load(path)
    if isinstance(loaded, trimesh.Scene):
        assert len(loaded.geometry) == 1 and len(loaded.graph.nodes_geometry) == 1
        loaded = loaded.to_geometry()
    return loaded


def manifold_of(vertices, faces):
    """Return a manifold3d Manifold of a mesh (the second, independent reader)."""
    mesh = manifold3d.Mesh(
        vert_properties=np.asarray(vertices, np.float32),
        tri_verts=np.asarray(faces, np.uint32),
    )
    return manifold3d.Manifold(mesh)


def stl_soup_manifold(data):
    """Read a binary STL without trimesh, merge it with manifold3d, return the Manifold."""
    n = int(np.frombuffer(data[80:84], "<u4")[0])
    rec = np.frombuffer(data[84:], dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")])
    assert len(rec) == n
    soup = manifold3d.Mesh(
        vert_properties=np.ascontiguousarray(rec["v"].reshape(-1, 3)),
        tri_verts=np.arange(3 * n, dtype=np.uint32).reshape(-1, 3),
    )
    assert soup.merge(), "the soup's vertices must merge by position"
    return manifold3d.Manifold(soup)


@pytest.mark.parametrize("case", list(CASES))
def test_every_format_loads_watertight_with_the_exact_volume(tmp_path, case):
    levels, n_levels = CASES[case]
    assert len(pinches(levels)) >= 4, "the case must have pinched corners to test"
    relief = Relief(levels, n_levels, STEP, PITCH, THICK)
    v, f = tile_mesh(relief)
    assert len(np.unique(v, axis=0)) == len(v), "no two vertices share a position"
    for fmt, encode in ENCODERS.items():
        path = tmp_path / f"tile.{fmt}"
        path.write_bytes(encode(v, f))
        mesh = load_merged(path)
        assert mesh.is_watertight and mesh.is_winding_consistent, fmt
        assert mesh.euler_number == 2, fmt  # one solid, no handle
        assert len(mesh.vertices) == len(v) and len(mesh.faces) == len(f), fmt
        dtype = np.float32 if fmt in FLOAT32 else np.float64
        exact = exact_volume_mm3(levels, n_levels, STEP, PITCH, THICK, dtype=dtype)
        assert mesh.volume == pytest.approx(exact, rel=1e-9), fmt
        other = manifold_of(mesh.vertices, mesh.faces)
        assert other.status() == manifold3d.Error.NoError, fmt
        assert other.genus() == 0 and other.volume() == pytest.approx(exact, rel=1e-6), fmt
    soup = stl_soup_manifold((tmp_path / "tile.stl").read_bytes())
    assert soup.status() == manifold3d.Error.NoError and soup.genus() == 0


def test_chamfer_volume_is_the_closed_form_with_a_large_leg():
    # a leg of 0.1 pitch makes each chamfer's volume visible at 1e-12
    levels, n_levels = CASES["random-8"]
    relief = Relief(levels, n_levels, STEP, PITCH, THICK)
    surface = relief_surface(levels, progress=False, denom=10)
    v = surface_points_mm(surface, relief)
    assert surface.chamfers == len(pinches(levels)) > 20
    exact = exact_volume_mm3(levels, n_levels, STEP, PITCH, THICK, leg=0.1)
    pixel_sum = exact_volume_mm3(levels, n_levels, STEP, PITCH, THICK, leg=0.0)
    assert mesh_volume(v, surface.triangles) == pytest.approx(exact, rel=1e-12)
    assert abs(exact / pixel_sum - 1) > 1e-7  # the chamfers are there
    mesh = trimesh.Trimesh(v, surface.triangles)  # merged by position
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.euler_number == 2
    assert manifold_of(v, surface.triangles).status() == manifold3d.Error.NoError


def test_pinched_corners_match_the_plain_loop():
    for levels, _ in CASES.values():
        _, top, low = pinched_corners(levels)
        assert sorted(zip(top.tolist(), low.tolist(), strict=True)) == sorted(pinches(levels))
    # the two-high-pixels corner the issue names: levels 3 1 / 2 3
    assert pinches([[3, 1], [2, 3]]) == [(3, 2)]
    assert pinches([[3, 3], [3, 1]]) == [] and pinches([[3, 1], [1, 1]]) == []


@pytest.mark.parametrize("fmt", ["glb", "3mf"])
def test_aperture_scene_instances_a_watertight_tile(tmp_path, fmt):
    levels, n_levels = CASES["random-4"]
    relief = Relief(levels, n_levels, STEP, PITCH, THICK)
    v, f = tile_mesh(relief)
    path = tmp_path / f"aperture.{fmt}"
    path.write_bytes(ENCODERS[fmt](v, f, instance_offsets_mm(relief, (2, 3))))
    scene = trimesh.load(path)
    assert len(scene.graph.nodes_geometry) == 6
    (tile,) = scene.geometry.values()
    assert tile.is_watertight and tile.is_winding_consistent and tile.euler_number == 2


def test_cli_tile_and_crop_files_are_watertight_and_report_the_chamfers(tmp_path):
    levels, n_levels = CASES["random-8"]
    fab = tmp_path / "fab"
    fab.mkdir()
    np.save(fab / "levels.npy", levels)
    manifest = {
        "levels": n_levels, "level_step_nm": STEP * 1e9, "pixel_pitch_nm": PITCH * 1e9,
        "tile_pixels": 12, "tiles": [2, 2], "levels_file": "levels.npy",
        "substrate_thickness_mm": THICK * 1e3,
    }  # fmt: skip
    (fab / "fab_manifest.json").write_text(json.dumps(manifest))
    out = tmp_path / "mesh"
    assert main(["mesh", str(fab), "--out", str(out), "--formats", "ply,stl", "--crop", "2"]) == 0
    report = json.loads((out / "mesh_report.json").read_text())
    chamfers = report["tile"]["chamfers"]
    assert chamfers["corners"] == len(pinches(levels))
    assert chamfers["leg_nm"] == pytest.approx(CHAMFER_LEG * PITCH * 1e9)
    tiled = np.tile(levels, (2, 2))  # the crop has pinched corners on the seams too
    for name, lev, dtype in (
        ("tile.stl", levels, np.float32),
        ("tile.ply", levels, np.float64),
        ("crop_2x2.stl", tiled, np.float32),
        ("crop_2x2.ply", tiled, np.float64),
    ):
        mesh = load_merged(out / name)
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.euler_number == 2
        exact = exact_volume_mm3(lev, n_levels, STEP, PITCH, THICK, dtype=dtype)
        assert mesh.volume == pytest.approx(exact, rel=1e-9), name
    exact_tile = exact_volume_mm3(levels, n_levels, STEP, PITCH, THICK)
    assert report["tile"]["analytic_volume_mm3"] == pytest.approx(exact_tile, rel=1e-12)
    assert report["crop"]["analytic_volume_mm3"] == pytest.approx(
        exact_volume_mm3(tiled, n_levels, STEP, PITCH, THICK), rel=1e-12
    )
