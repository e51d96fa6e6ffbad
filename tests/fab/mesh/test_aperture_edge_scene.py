"""The meshes of a filled clear aperture: ``aperture.{glb,3mf}`` hold one tile geometry
instanced on the tile lattice (the scene contract of the independent mesh checker), and
``aperture_edge.{glb,3mf}`` the clipped edge tiles, so that both together cover the
plate's pattern exactly: every pixel once, at its level's height."""

import json

import numpy as np
import pytest
import trimesh
from package_helpers import GREEN_FOUR_LEVELS, make_design_dir

import fab.package.report as report
from doe.infra.cli import main
from doe.records.mesh_report import read_mesh_report
from fab.package.build import build_package

# a default-like design (sun2020's 655 nm, 8 levels) on a 3 mm aperture, N = 15
DEFAULT_LIKE = 'name = "small"\n[psf]\nkernel_size = 7\n[fabrication]\naperture_mm = 3.0\n'
# a 532 nm, bk7, 4-level design on a 12.7 mm aperture: 17 x 17 tiles of 0.709 mm, N = 11
FOUR_LEVELS = 'name = "green4"\n' + GREEN_FOUR_LEVELS
DESIGNS = {"default_like": (DEFAULT_LIKE, 15, 8), "four_levels": (FOUR_LEVELS, 11, 4)}


@pytest.fixture(scope="module", params=sorted(DESIGNS))
def meshed(request, tmp_path_factory):
    """A filled plate's fab package and its meshes (GLB and 3MF)."""
    config, n, n_levels = DESIGNS[request.param]
    root = tmp_path_factory.mktemp(request.param)
    levels = make_design_dir(root / "design", n=n, n_levels=n_levels, k=7)
    (root / "design.toml").write_text(config)
    with pytest.MonkeyPatch.context() as mp:  # the figures are tested elsewhere (seconds each)
        mp.setattr(report, "_write_figures", lambda out_dir, context: [])
        build_package(
            root / "design", root / "fab", config=str(root / "design.toml"), progress=False
        )
    argv = ["mesh", str(root / "fab"), "--out", str(root / "mesh"), "--formats", "glb,3mf"]
    assert main(argv) == 0
    manifest = json.loads((root / "fab" / "fab_manifest.json").read_text())
    return root / "mesh", levels, manifest


def placed_bodies(path):
    """Return [(geometry name, vertices placed in mm, faces)] for every node of a scene."""
    scene = trimesh.load(path, process=False)
    out = []
    for node in scene.graph.nodes_geometry:
        matrix, name = scene.graph[node]
        geometry = scene.geometry[name]
        v = np.asarray(geometry.vertices, np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
        out.append((name, v, np.asarray(geometry.faces, np.int64)))
    return scene, out


@pytest.mark.parametrize("fmt", ["glb", "3mf"])
def test_the_whole_tile_scene_is_one_tile_on_the_lattice(meshed, fmt):
    out, levels, manifest = meshed
    nx, ny = manifest["tiles"]
    n, p_mm = levels.shape[0], manifest["pixel_pitch_nm"] * 1e-6
    x0, y0 = (v * 1e-6 for v in manifest["array_origin_nm"])
    scene = trimesh.load(out / f"aperture.{fmt}", process=False)
    # the checker's rule: every geometry the same arrays (here: one), translations only,
    # exactly the NX x NY offsets origin + (i, j) N p
    geometries = list(scene.geometry.values())
    assert all(
        np.array_equal(g.vertices, geometries[0].vertices)
        and np.array_equal(g.faces, geometries[0].faces)
        for g in geometries
    )
    assert len(geometries) == 1
    nodes = scene.graph.nodes_geometry
    matrices = np.array([scene.graph[node][0] for node in nodes])
    assert np.allclose(matrices[:, :3, :3], np.eye(3), atol=1e-12)
    ij = (matrices[:, :2, 3] - [x0, y0]) / (n * p_mm)
    assert np.abs(ij - np.rint(ij)).max() < 1e-5 / (n * p_mm)
    assert np.allclose(matrices[:, 2, 3], 0.0)
    got = sorted(map(tuple, np.rint(ij).astype(int).tolist()))
    assert got == [(i, j) for i in range(nx) for j in range(ny)] and len(nodes) == nx * ny
    # the tile itself has its lower-left corner at the origin
    assert np.allclose(geometries[0].bounds[:, :2], [[0, 0], [n * p_mm] * 2], atol=1e-9)


@pytest.mark.parametrize("fmt", ["glb", "3mf"])
def test_tiles_and_edge_pieces_cover_the_filled_aperture_exactly(meshed, fmt):
    out, levels, manifest = meshed
    plate = manifest["plate"]
    edges = [plate["edge_pixels"][k] for k in ("left", "right", "bottom", "top")]
    assert min(edges) > 0  # the fixture's plates are filled on every side
    n_levels, n = manifest["levels"], levels.shape[0]
    step, p_mm = manifest["level_step_nm"] * 1e-6, manifest["pixel_pitch_nm"] * 1e-6
    thickness = manifest["substrate_thickness_mm"]
    ex0, ey0, ex1, ey1 = (v * 1e-6 for v in plate["pattern_extent_nm"])
    cols, rows = round((ex1 - ex0) / p_mm), round((ey1 - ey0) / p_mm)
    # the periodic pattern over the extent: its column 0 is the tile's column -left
    left, top = edges[0], edges[3]
    want = levels[np.ix_((np.arange(rows) - top) % n, (np.arange(cols) - left) % n)]
    want_top = thickness - (n_levels - 1 - want) * step

    _, tiles = placed_bodies(out / f"aperture.{fmt}")
    edge_scene, pieces = placed_bodies(out / f"aperture_edge.{fmt}")
    assert len(edge_scene.geometry) == 8
    # one mesh of every placed body: closed bodies side by side stay closed (no merging)
    bodies = tiles + pieces
    starts = np.cumsum([0] + [len(v) for _, v, _ in bodies])
    mesh = trimesh.Trimesh(
        np.concatenate([v for _, v, _ in bodies]),
        np.concatenate([f + s for (_, _, f), s in zip(bodies, starts, strict=False)]),
        process=False,
    )
    assert mesh.is_watertight and mesh.is_winding_consistent
    up = mesh.face_normals[:, 2] > 1 - 1e-6
    centre, up_area = mesh.triangles_center[up], mesh.area_faces[up]
    c = np.floor((centre[:, 0] - ex0) / p_mm).astype(int)
    r = np.floor((ey1 - centre[:, 1]) / p_mm).astype(int)  # row 0 at the top
    assert c.min() >= 0 and r.min() >= 0 and c.max() < cols and r.max() < rows
    area = np.zeros((rows, cols))  # up-facing area per pattern pixel, all bodies together
    np.add.at(area, (r, c), up_area)
    at_level = np.zeros((rows, cols))  # the part of it at the pixel's own top height
    level = np.abs(centre[:, 2] - want_top[r, c]) < 1e-6
    np.add.at(at_level, (r[level], c[level]), up_area[level])
    # every pixel covered once (an overlap doubles its area), at its level (chamfers
    # aside: p/1000 legs), and the bodies' volume is the pattern's
    assert np.allclose(area, p_mm**2, rtol=1e-5)
    assert at_level.min() > (1 - 1e-5) * p_mm**2
    assert mesh.volume == pytest.approx(want_top.sum() * p_mm**2, rel=1e-6)  # GLB: float32


def test_the_report_lists_the_edge_scene(meshed):
    out, _, manifest = meshed
    report_ = read_mesh_report(out / "mesh_report.json")
    nx, ny = manifest["tiles"]
    # 4 strips along the array's sides (nx or ny placements each) and 4 corners
    assert report_.aperture["instances"] == nx * ny
    assert report_.aperture["edge_pieces"] == 8
    assert report_.aperture["edge_instances"] == 2 * nx + 2 * ny + 4
    assert list(report_.aperture["edge_scene"]) == ["aperture_edge.glb", "aperture_edge.3mf"]
    assert {"aperture_edge.glb", "aperture_edge.3mf"} <= set(report_.files)
    scene = trimesh.load(out / "aperture_edge.glb", process=False)
    assert len(scene.graph.nodes_geometry) == report_.aperture["edge_instances"]
