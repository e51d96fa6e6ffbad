"""Tests of the relief tile mesh (fab.mesh.relief), its file encoders and ``doefab mesh``."""

import io
import json
import zipfile
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from mesh_helpers import exact_volume_mm3, pinches

from doe.infra.cli import main
from fab.mesh.chamfer import CHAMFER_LEG
from fab.mesh.checks import (
    BYTES_PER_TRIANGLE,
    MERGED_MEMORY_LIMIT_BYTES,
    TILE_MEMORY_LIMIT_BYTES,
    check_crop,
)
from fab.mesh.formats import glb_bytes, ply_bytes, preview_png_bytes, stl_bytes, threemf_bytes
from fab.mesh.relief import (
    Relief,
    instance_offsets_mm,
    mesh_volume,
    relief_surface,
    tile_mesh,
    triangle_upper_bound,
)

L, STEP, PITCH, THICK = 8, 179.4e-9, 4990e-9, 0.5e-3


def relief_of(levels):
    return Relief(np.asarray(levels, np.uint8), L, STEP, PITCH, THICK)


def random_levels(n, seed, n_levels=L):
    return np.random.default_rng(seed).integers(0, n_levels, (n, n)).astype(np.uint8)


def write_fab_dir(path, levels, tiles=(4, 4), origin_nm=(0.0, 0.0), **extra):
    """Write a minimal FAB_DIR like ``doefab fab`` does (manifest + levels.npy)."""
    path.mkdir(parents=True, exist_ok=True)
    np.save(path / "levels.npy", levels)
    manifest = {
        "wavelength_nm": 655.0,
        "refractive_index": 1.4564,
        "levels": L,
        "level_step_nm": STEP * 1e9,
        "pixel_pitch_nm": PITCH * 1e9,
        "tile_pixels": levels.shape[0],
        "tiles": list(tiles),
        "array_origin_nm": list(origin_nm),
        "levels_file": "levels.npy",
        "substrate_thickness_mm": THICK * 1e3,
        "design_name": "test",
        "material": "fused_silica",
    }
    manifest.update(extra)
    (path / "fab_manifest.json").write_text(json.dumps(manifest))
    return path


def edge_counts(faces):
    """Return (undirected edge -> face count, directed edge -> count)."""
    a = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    b = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    und = np.unique(np.sort(np.stack([a, b], 1), 1), axis=0, return_counts=True)[1]
    directed = np.unique(np.stack([a, b], 1), axis=0, return_counts=True)[1]
    return und, directed


def vertex_fans(faces, n_vertices):
    """Return the number of fans (edge-connected face groups) around each vertex."""
    fans = np.zeros(n_vertices, np.int64)
    by_vertex = [[] for _ in range(n_vertices)]
    for f, tri in enumerate(faces.tolist()):
        for v in tri:
            by_vertex[v].append(f)
    for v, fs in enumerate(by_vertex):
        parent = {f: f for f in fs}

        def find(x, parent=parent):
            while parent[x] != x:
                x = parent[x]
            return x

        edge_owner = {}
        for f in fs:
            for u in faces[f].tolist():
                if u != v:
                    if u in edge_owner:
                        parent[find(f)] = find(edge_owner[u])
                    edge_owner[u] = f
        fans[v] = len({find(f) for f in fs})
    return fans


def assert_closed_manifold(vertices, faces):
    und, directed = edge_counts(faces)
    assert np.all(und == 2), "every edge must have exactly two faces"
    assert np.all(directed == 1), "winding must be consistent (each directed edge once)"
    tm = trimesh.Trimesh(vertices, faces, process=False)
    assert tm.is_watertight and tm.is_winding_consistent
    assert np.all(vertex_fans(faces, len(vertices)) == 1), "pinched vertex (two fans)"


def test_single_raised_pixel_at_row0_col0_is_top_left():
    levels = np.zeros((4, 4), np.uint8)
    levels[0, 0] = L - 1
    v, _ = tile_mesh(relief_of(levels))
    top = np.isclose(v[:, 2], THICK * 1e3, atol=1e-12)
    p_mm, n = PITCH * 1e3, 4
    assert top.sum() >= 4
    assert np.all(v[top, 0] <= p_mm + 1e-12), "raised pixel must sit at the smallest x"
    assert np.all(v[top, 1] >= (n - 1) * p_mm - 1e-12), "raised pixel must sit at the largest y"
    assert np.allclose(v.min(0), [0, 0, 0]) and np.allclose(
        v.max(0), [n * p_mm, n * p_mm, THICK * 1e3]
    )


def test_random_8_level_tile_is_closed_oriented_manifold():
    relief = relief_of(random_levels(24, seed=1))
    v, f = tile_mesh(relief)
    assert_closed_manifold(v, f)
    assert mesh_volume(v, f) > 0, "outward normals give a positive volume"


@pytest.mark.parametrize(
    "pattern",
    [
        [[7, 0], [0, 7]],  # checkerboard corner: solids touch along an edge only
        [[5, 2, 7], [2, 5, 2], [7, 2, 5]],  # pinched corners at intermediate heights
        [[0, 7, 0], [7, 0, 7], [0, 7, 0]],
        [[3, 3], [3, 3]],  # flat
    ],
)
def test_corner_touching_cells_stay_manifold(pattern):
    relief = relief_of(np.tile(np.array(pattern, np.uint8), (2, 2)))
    v, f = tile_mesh(relief)
    assert_closed_manifold(v, f)
    assert mesh_volume(v, f) == pytest.approx(relief.analytic_volume() * 1e9, rel=1e-12)


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 5), st.integers(1, 5), st.integers(0, 2**32 - 1), st.integers(2, 8))
def test_any_small_map_is_closed_with_exact_volume(rows, cols, seed, n_levels):
    levels = np.random.default_rng(seed).integers(0, n_levels, (rows, cols)).astype(np.uint8)
    relief = Relief(levels, L, STEP, PITCH, THICK)
    v, f = tile_mesh(relief)
    assert_closed_manifold(v, f)
    assert mesh_volume(v, f) == pytest.approx(relief.analytic_volume() * 1e9, rel=1e-12)
    assert len(f) <= triangle_upper_bound(levels)


@pytest.mark.parametrize("levels", [np.zeros((0, 3)), np.zeros(3), [[1, -1]]])
def test_relief_surface_refuses_a_map_that_is_not_a_level_map(levels):
    with pytest.raises(ValueError, match="non-empty 2-D map of levels >= 0"):
        relief_surface(levels)


def test_volume_matches_analytic_formula():
    levels = random_levels(20, seed=2)
    v, f = tile_mesh(relief_of(levels))
    analytic_mm3 = exact_volume_mm3(levels, L, STEP, PITCH, THICK)  # pixels minus chamfers
    assert mesh_volume(v, f) == pytest.approx(analytic_mm3, rel=1e-12)
    assert trimesh.Trimesh(v, f, process=False).volume == pytest.approx(analytic_mm3, rel=1e-12)


def test_volume_keeps_its_digits_far_from_the_origin():
    # A crop sits at the manifest's array origin, which may lie tens of mm off (a centred
    # aperture): its volume must be as exact as at the origin, not lose digits to the shift.
    relief = relief_of(random_levels(12, seed=18))
    v, f = tile_mesh(relief)
    for shift in ([40.0, -40.0, 0.0], [-35.0, 35.0, 0.0]):
        assert mesh_volume(v + shift, f) == pytest.approx(relief.analytic_volume() * 1e9, rel=1e-12)


def test_faces_are_terraces_and_vertical_walls_with_exact_top_areas():
    levels = random_levels(16, seed=3)
    relief = relief_of(levels)
    v, f = tile_mesh(relief)
    p = v[f]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = np.linalg.norm(n, axis=1) / 2
    nz = n[:, 2] / (2 * area)
    assert np.all(area > 0), "no degenerate triangles"
    assert np.all(np.isclose(np.abs(nz), 1) | np.isclose(nz, 0, atol=1e-12))
    up = np.isclose(nz, 1)
    zl = relief.level_z() * 1e3
    z = p[up][:, 0, 2]
    lev = np.argmin(np.abs(z[:, None] - zl[None]), axis=1)
    assert np.allclose(p[up][..., 2], zl[lev][:, None], atol=1e-12)
    got = np.bincount(lev, weights=area[up], minlength=L)
    want = np.bincount(levels.ravel(), minlength=L) * (PITCH * 1e3) ** 2
    for top, low in pinches(levels):  # a chamfer moves its triangle from top to low
        want[[top, low]] += np.array([-1, 1]) * (CHAMFER_LEG * PITCH * 1e3) ** 2 / 2
    assert np.allclose(got, want, rtol=1e-10, atol=1e-18)
    down = np.isclose(nz, -1)
    assert np.allclose(p[down][..., 2], 0) and area[down].sum() == pytest.approx(
        (16 * PITCH * 1e3) ** 2, rel=1e-12
    )


def test_surface_loops_match_triangles_and_are_planar():
    surface = relief_surface(random_levels(6, seed=4))
    tri_area = 0.0
    g = surface.grid
    assert surface.chamfers == len(pinches(random_levels(6, seed=4))) > 0
    for loop, normal in zip(surface.loops, surface.loop_normals, strict=True):
        pts = g[loop] * [1, 1, 0.5]  # any z scale: loops are vertical or horizontal planes
        unit = normal / np.linalg.norm(normal)
        assert np.ptp(pts @ unit) < 1e-12
        # Newell normal of the loop points along the declared outward normal
        newell = np.cross(pts, np.roll(pts, -1, axis=0)).sum(0) / 2
        assert newell @ unit > 0 and np.allclose(np.cross(newell, unit), 0, atol=1e-15)
        tri_area += newell @ unit
    pts = g[surface.triangles] * [1, 1, 0.5]
    cross = np.cross(pts[:, 1] - pts[:, 0], pts[:, 2] - pts[:, 0])
    assert np.linalg.norm(cross, axis=1).sum() / 2 == pytest.approx(tri_area, rel=1e-12)


def test_tiled_relief_matches_tiled_levels():
    relief = relief_of(random_levels(5, seed=5))
    big = relief.tiled(3, 2)
    assert big.levels.shape == (10, 15)
    v, f = tile_mesh(big)
    assert_closed_manifold(v, f)
    assert mesh_volume(v, f) == pytest.approx(6 * relief.analytic_volume() * 1e9, rel=1e-12)


def test_instance_offsets_lattice():
    relief = relief_of(random_levels(5, seed=6))
    off = instance_offsets_mm(relief, (3, 2), origin_mm=(1.0, -2.0))
    t = 5 * PITCH * 1e3
    assert off.shape == (6, 3)
    assert np.allclose(off[0], [1.0, -2.0, 0]) and np.allclose(off[-1], [1 + 2 * t, -2 + t, 0])


def test_instance_offsets_of_a_non_square_tile_abut_x_fastest():
    # 3 rows x 5 columns: the tile is 5 p wide along x and 3 p high along y, and its
    # neighbours on the lattice touch it edge to edge; x varies fastest.
    relief = relief_of(random_levels(5, seed=19)[:3])
    v, _ = tile_mesh(relief)
    width, height = np.ptp(v[:, 0]), np.ptp(v[:, 1])
    assert (width, height) == pytest.approx((5 * PITCH * 1e3, 3 * PITCH * 1e3), rel=1e-12)
    off = instance_offsets_mm(relief, (3, 2), origin_mm=(1.0, -2.0))
    want_x = 1.0 + np.array([0, 1, 2, 0, 1, 2]) * width
    want_y = -2.0 + np.array([0, 0, 0, 1, 1, 1]) * height
    assert np.allclose(off, np.column_stack([want_x, want_y, np.zeros(6)]), rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "levels",
    [
        np.tile(np.arange(L, dtype=np.uint8), (L, 1)),  # a ramp along x: only x seams
        np.tile(np.arange(L, dtype=np.uint8), (L, 1)).T,  # a ramp along y: only y seams
        random_levels(6, seed=21),
        # a peak in a ring: as a tile, 94 triangles; c^2 bounds of a periodic tile
        # (the seams in place of the outer walls) once said 86
        np.array([[4, 3, 4], [3, 5, 3], [4, 3, 4]], np.uint8),
    ],
)
def test_triangle_bound_covers_a_merged_crop(levels):
    # check_crop sizes a merged c x c body by it: the walls across the tile seams (in x
    # and in y) and around the body must be counted
    for c in (1, 2, 3):
        _, f = tile_mesh(relief_of(levels).tiled(c, c))
        assert len(f) <= triangle_upper_bound(levels, c)


def test_crop_of_flat_tiles_well_within_the_memory_limit_is_accepted():
    # A flat body of c x c tiles of N x N pixels has 2 (cN)^2 top, 8 cN outer wall and
    # 4 cN back triangles (checked on a small one); at N = 10, c = 100 that is 2 M
    # triangles, about a quarter of the merged-body memory limit: it must be accepted.
    flat = np.full((3, 3), L - 1, np.uint8)
    assert len(tile_mesh(relief_of(flat).tiled(2, 2))[1]) == 2 * 6**2 + 12 * 6
    n, c = 10, 100
    need = 2 * (c * n) ** 2 + 12 * c * n
    assert need * BYTES_PER_TRIANGLE < MERGED_MEMORY_LIMIT_BYTES / 3
    assert check_crop(relief_of(np.full((n, n), L - 1, np.uint8)), c, [c, c]) >= need


# --- file encoders ---------------------------------------------------------------------


def load_bytes(data, file_type):
    return trimesh.load(io.BytesIO(data), file_type=file_type, process=False)


@pytest.mark.parametrize(
    "fmt,encode",
    [("ply", ply_bytes), ("stl", stl_bytes), ("3mf", threemf_bytes), ("glb", glb_bytes)],
)
def test_encoders_round_trip_volume(fmt, encode):
    relief = relief_of(random_levels(10, seed=7))
    v, f = tile_mesh(relief)
    loaded = load_bytes(encode(v, f), fmt)
    if isinstance(loaded, trimesh.Scene):
        loaded = next(iter(loaded.geometry.values()))
    lv, lf = np.asarray(loaded.vertices, float), np.asarray(loaded.faces)
    rel = 1e-6 if fmt in ("stl", "glb") else 1e-9  # float32 formats
    assert mesh_volume(lv, lf) == pytest.approx(relief.analytic_volume() * 1e9, rel=rel)
    if fmt != "stl":  # STL stores no shared vertices
        assert len(lf) == len(f)
        assert_closed_manifold(lv, lf)


def test_stl_header_states_units():
    v, f = tile_mesh(relief_of(random_levels(3, seed=8)))
    data = stl_bytes(v, f)
    assert b"units mm" in data[:80]
    assert int(np.frombuffer(data[80:84], "<u4")[0]) == len(f) == (len(data) - 84) // 50


@pytest.mark.parametrize("fmt,encode", [("3mf", threemf_bytes), ("glb", glb_bytes)])
def test_scenes_instance_one_mesh_on_the_lattice(fmt, encode):
    relief = relief_of(random_levels(6, seed=9))
    v, f = tile_mesh(relief)
    off = instance_offsets_mm(relief, (3, 2), origin_mm=(0.5, 0.25))
    scene = load_bytes(encode(v, f, off), fmt)
    nodes = scene.graph.nodes_geometry
    assert len(nodes) == 6
    geoms = {scene.graph[n][1] for n in nodes}
    assert len(geoms) == 1, "one geometry, instanced"
    tr = sorted(tuple(np.round(scene.graph[n][0][:3, 3], 9)) for n in nodes)
    assert np.allclose(tr, sorted(tuple(np.round(o, 9)) for o in off), atol=1e-6)
    if fmt == "3mf":
        with zipfile.ZipFile(io.BytesIO(encode(v, f, off))) as z:
            model = z.read("3D/3dmodel.model").decode()
        assert model.count("<component ") == 6 and model.count("<mesh>") == 1
        assert 'unit="millimeter"' in model


# --- command line ------------------------------------------------------------------------


def test_cli_writes_all_mesh_formats_deterministically(tmp_path, capsys):
    levels = random_levels(12, seed=10)
    fab = write_fab_dir(tmp_path / "fab", levels, tiles=(3, 3), origin_nm=(1e6, 2e6))
    args = ["mesh", str(fab), "--formats", "ply,glb,3mf,stl", "--crop", "2"]
    assert main([*args, "--out", str(tmp_path / "a")]) == 0
    assert main([*args, "--out", str(tmp_path / "b")]) == 0
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert names == sorted(
        [
            "tile.ply",
            "tile.glb",
            "tile.3mf",
            "tile.stl",
            "aperture.glb",
            "aperture.3mf",
            "crop_2x2.ply",
            "crop_2x2.glb",
            "crop_2x2.3mf",
            "crop_2x2.stl",
            "preview.png",
            "mesh_report.json",
        ]
    )
    for name in names:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    report = json.loads((tmp_path / "a" / "mesh_report.json").read_text())
    relief = relief_of(levels)
    assert report["units"] == "mm"
    assert report["tile"]["volume_mm3"] == pytest.approx(relief.analytic_volume() * 1e9, rel=1e-12)
    assert report["aperture"]["instances"] == 9
    assert report["aperture"]["origin_mm"] == pytest.approx([1.0, 2.0])
    crop = trimesh.load(tmp_path / "a" / "crop_2x2.ply", process=False)
    assert_closed_manifold(np.asarray(crop.vertices), np.asarray(crop.faces))
    assert np.allclose(crop.vertices.min(0), [1.0, 2.0, 0.0])
    assert crop.volume == pytest.approx(4 * relief.analytic_volume() * 1e9, rel=1e-12)
    for key in ("volume_mm3", "analytic_volume_mm3"):
        assert report["crop"][key] == pytest.approx(4 * relief.analytic_volume() * 1e9, rel=1e-12)


def test_cli_refuses_merged_full_aperture(tmp_path, capsys):
    fab = write_fab_dir(tmp_path / "fab", random_levels(175, seed=11), tiles=(16, 16))
    out = tmp_path / "out"
    assert main(["mesh", str(fab), "--out", str(out), "--crop", "16"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--crop" in err and "GiB" in err
    assert not out.exists() or not any(out.iterdir())


def test_cli_refuses_a_tile_too_large_to_mesh(tmp_path, capsys):
    # A 0.25 um pitch tile of N = 3494 took 18 GB and over 15 minutes before this check.
    levels = random_levels(1700, seed=12)  # bound ~36 M triangles, ~10 GiB
    fab = write_fab_dir(tmp_path / "fab", levels)
    out = tmp_path / "out"
    assert main(["mesh", str(fab), "--out", str(out), "--formats", "ply"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "levels.npy" in err and "GiB" in err
    assert "--formats none" in err and not out.exists()
    smaller = triangle_upper_bound(levels[:1000, :1000]) * BYTES_PER_TRIANGLE
    assert triangle_upper_bound(levels) * BYTES_PER_TRIANGLE > TILE_MEMORY_LIMIT_BYTES >= smaller


def test_cli_refuses_float32_formats_on_a_thick_substrate(tmp_path, capsys):
    # At 40 mm a float32 z is 3.8 nm coarse: GLB/STL heights would be off by up to
    # 1.9 nm, beyond the 1 nm the independent mesh check allows (it failed at 100 mm).
    levels = random_levels(3, seed=16)
    fab = write_fab_dir(tmp_path / "fab", levels)
    out = tmp_path / "out"
    for formats in ("ply,glb,3mf,stl", "stl"):
        argv = ["mesh", str(fab), "--out", str(out), "--thickness-mm", "40", "--formats", formats]
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "--thickness-mm" in err and "float32" in err
        assert not out.exists()
    for bad in ("nan", "inf", "1e300"):
        assert main(["mesh", str(fab), "--out", str(out), "--thickness-mm", bad]) == 2
        assert "--thickness-mm" in capsys.readouterr().err and not out.exists()
    # PLY (float64) and 3MF (9 decimals) hold the heights at any thickness.
    assert_heights_written(fab, out, levels, 40.0, "ply,3mf", "tile.ply", atol=1e-12)


def test_cli_writes_float32_formats_up_to_32_mm(tmp_path):
    # From 16 to 32 mm the float32 spacing is 1.9 nm, so STL and GLB round heights by
    # at most 0.95 nm, within the 1 nm the mesh checks allow: 30 mm is accepted.
    levels = random_levels(3, seed=16)
    fab = write_fab_dir(tmp_path / "fab", levels)
    assert_heights_written(fab, tmp_path / "out", levels, 30.0, "glb,stl", "tile.stl", atol=1e-6)


def assert_heights_written(fab, out, levels, thickness_mm, formats, name, atol):
    """Write the mesh; the file's heights (mm) must be the back and each level's top."""
    argv = ["mesh", str(fab), "--out", str(out), "--thickness-mm", str(thickness_mm)]
    assert main([*argv, "--formats", formats]) == 0
    z = np.unique(trimesh.load(out / name, process=False).vertices[:, 2])
    tops = thickness_mm - (L - 1 - np.unique(levels)) * STEP * 1e3
    np.testing.assert_allclose(z, np.concatenate([[0.0], tops]), rtol=0, atol=atol)


def test_cli_aperture_scenes_put_nx_by_ny_tiles_at_the_manifest_origin(tmp_path):
    # tiles [nx, ny] = [3, 2] from array_origin_nm (1 mm, -2 mm), pitch N p, one mesh
    levels = random_levels(4, seed=20)
    fab = write_fab_dir(tmp_path / "fab", levels, tiles=(3, 2), origin_nm=(1e6, -2e6))
    out = tmp_path / "out"
    assert main(["mesh", str(fab), "--out", str(out), "--formats", "glb,3mf"]) == 0
    t = 4 * PITCH * 1e3
    want = sorted((1.0 + ix * t, -2.0 + iy * t, 0.0) for ix in range(3) for iy in range(2))
    for name in ("aperture.glb", "aperture.3mf"):
        scene = trimesh.load(out / name, process=False)
        nodes = scene.graph.nodes_geometry
        assert len({scene.graph[n][1] for n in nodes}) == 1, name
        got = sorted(tuple(scene.graph[n][0][:3, 3]) for n in nodes)
        assert len(got) == 6 and np.allclose(got, want, rtol=0, atol=1e-6), name


@pytest.mark.parametrize("tiles", [(2, 2), (3, 2), (2, 3)])
def test_cli_refuses_crop_beyond_aperture(tmp_path, capsys, tiles):
    fab = write_fab_dir(tmp_path / "fab", random_levels(4, seed=12), tiles=tiles)
    assert main(["mesh", str(fab), "--out", str(tmp_path / "o"), "--crop", "3"]) == 2
    assert "exceed" in capsys.readouterr().err


@pytest.mark.parametrize(
    "change,needle",
    [
        ({"substrate_thickness_mm": None}, "substrate_thickness_mm"),
        ({"substrate_thickness_mm": 0.0001}, "deepest etch"),
        ({"tile_pixels": 5}, "tile_pixels"),
        ({"levels": 4}, "levels.npy"),
        ({"tiles": None}, "missing key 'tiles'"),
        ({"level_step_nm": "deep"}, "malformed value"),
        ({"tiles": [4]}, "tiles must be [nx, ny] >= 1"),
        ({"levels": 6}, "levels 6 must be"),
        ({"pixel_pitch_nm": 0}, "pixel_pitch_nm > 0"),
        ({"substrate_thickness_mm": "thick"}, "substrate_thickness_mm: not a number"),
        # numbers past any float: int(inf) and float(10**400) overflowed (exit 3)
        ({"tile_pixels": float("inf")}, "malformed value"),
        ({"level_step_nm": 10**400}, "malformed value"),
        ({"substrate_thickness_mm": 10**400}, "substrate_thickness_mm: not a number"),
        # pixels of 1e-300 nm divided a volume by 0 (exit 3); a plate placed at infinity
        # was written (exit 0)
        ({"pixel_pitch_nm": 1e-300}, "must lie between 1 pm and 1 m"),
        ({"pixel_pitch_nm": float("inf")}, "must lie between 1 pm and 1 m"),
        ({"array_origin_nm": [float("inf"), 0.0]}, "array_origin_nm be finite"),
        # int() made 8.9 levels 8 and 2.7 tiles 2, without a word (exit 0)
        ({"levels": 8.9}, "8.9 is not a whole number"),
        ({"tiles": [2.7, 3]}, "2.7 is not a whole number"),
        ({"tile_pixels": True}, "True is not a whole number"),
    ],
)
def test_cli_bad_manifest_exits_2_naming_the_file(tmp_path, capsys, change, needle):
    levels = random_levels(4, seed=13)
    fab = write_fab_dir(tmp_path / "fab", levels)
    man = json.loads((fab / "fab_manifest.json").read_text())
    for k, val in change.items():
        if val is None:
            man.pop(k)
        else:
            man[k] = val
    (fab / "fab_manifest.json").write_text(json.dumps(man))
    out = tmp_path / "out"
    assert main(["mesh", str(fab), "--out", str(out), "--formats", "ply"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err and str(fab) in err
    assert not out.exists()


def test_cli_refuses_a_crop_of_no_tiles(tmp_path, capsys):
    fab = write_fab_dir(tmp_path / "fab", random_levels(4, seed=12))
    out = tmp_path / "o"
    assert main(["mesh", str(fab), "--out", str(out), "--crop", "0"]) == 2
    assert "--crop: must be >= 1 tile, got 0" in capsys.readouterr().err
    assert not out.exists()


def test_cli_missing_fab_dir_and_bad_format(tmp_path, capsys):
    assert main(["mesh", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    assert "nope" in capsys.readouterr().err
    fab = write_fab_dir(tmp_path / "fab", random_levels(3, seed=14))
    assert main(["mesh", str(fab), "--out", str(tmp_path / "o"), "--formats", "obj"]) == 2
    assert "--formats" in capsys.readouterr().err
    # a folder without the fab manifest, such as retrieve's: the message says which folder
    (tmp_path / "retrieve").mkdir()
    assert main(["mesh", str(tmp_path / "retrieve"), "--out", str(tmp_path / "o")]) == 2
    assert "fab_manifest.json: no such file; mesh takes the folder that doefab fab wrote" in (
        capsys.readouterr().err
    )


def test_cli_refuses_overwrite_without_force(tmp_path, capsys):
    fab = write_fab_dir(tmp_path / "fab", random_levels(3, seed=15))
    out = tmp_path / "out"
    assert main(["mesh", str(fab), "--out", str(out), "--formats", "ply"]) == 0
    before = (out / "tile.ply").read_bytes()
    assert main(["mesh", str(fab), "--out", str(out), "--formats", "ply"]) == 2
    assert "--force" in capsys.readouterr().err
    assert main(["mesh", str(fab), "--out", str(out), "--formats", "ply", "--force"]) == 0
    assert (out / "tile.ply").read_bytes() == before


def test_cli_force_removes_the_old_formats_it_does_not_write_again(tmp_path):
    fab = write_fab_dir(tmp_path / "fab", random_levels(3, seed=15))
    out = tmp_path / "out"
    argv = ["mesh", str(fab), "--out", str(out)]
    assert main([*argv, "--formats", "ply,stl", "--crop", "1"]) == 0
    assert (out / "tile.stl").exists() and (out / "crop_1x1.stl").exists()
    assert main([*argv, "--formats", "ply", "--force"]) == 0
    left = sorted(p.name for p in out.iterdir())
    assert left == ["mesh_report.json", "preview.png", "tile.ply"]


def test_cli_crop_needs_a_mesh_format(tmp_path, capsys):
    fab = write_fab_dir(tmp_path / "fab", random_levels(3, seed=16))
    out = tmp_path / "out"
    assert main(["mesh", str(fab), "--out", str(out), "--formats", "step", "--crop", "1"]) == 2
    assert "--crop" in capsys.readouterr().err
    assert not out.exists()


def test_every_pixel_top_lies_over_its_pixel_at_its_level():
    levels = random_levels(9, seed=17)[:, :7]  # non-square: catches a transpose
    relief = relief_of(levels)
    v, f = tile_mesh(relief)
    p = v[f]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    up = n[:, 2] > 0
    centre = p[up].mean(axis=1)
    p_mm = PITCH * 1e3
    col = np.floor(centre[:, 0] / p_mm).astype(int)
    row = levels.shape[0] - 1 - np.floor(centre[:, 1] / p_mm).astype(int)
    level_of_z = np.rint((centre[:, 2] - THICK * 1e3) / (STEP * 1e3) + L - 1).astype(int)
    area = np.linalg.norm(n[up], axis=1) / 2 / p_mm**2
    top = area > 1e-5  # not a chamfer's triangle at z_lo (1e-3 p legs), which is
    assert len(pinches(levels)) == (~top).sum()
    assert np.array_equal(level_of_z[top], levels[row, col][top])
    hit = np.zeros(levels.shape)
    np.add.at(hit, (row[top], col[top]), area[top])
    assert np.all(np.abs(hit - 1) < 2e-6), "the top triangles of a pixel cover it"


MESH_L, MESH_STEP, MESH_PITCH, MESH_THICK = 8, 179.4e-9, 4990e-9, 0.5e-3


def test_stl_facet_normals_are_outward_and_follow_the_vertex_order():
    # Readers that trust the stored normal (many CAM/slicer tools) must see the same
    # outward side as those that use the counter-clockwise vertex order.
    levels = np.random.default_rng(3).integers(0, MESH_L, (6, 6)).astype(np.uint8)
    v, f = tile_mesh(Relief(levels, MESH_L, MESH_STEP, MESH_PITCH, MESH_THICK))
    rec = np.frombuffer(
        stl_bytes(v, f)[84:], dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")]
    )
    p = rec["v"].astype(float)
    rhr = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    rhr /= np.linalg.norm(rhr, axis=1, keepdims=True)
    assert np.allclose(rec["n"], rhr, atol=1e-3)
    # outward: the unetched top faces (level L-1, z = thickness) up, the back face down
    top = np.isclose(p[:, :, 2], MESH_THICK * 1e3, rtol=0, atol=1e-9).all(axis=1)
    back = np.isclose(p[:, :, 2], 0).all(axis=1)
    assert top.any() and back.any()
    assert np.allclose(rec["n"][top], [0, 0, 1]) and np.allclose(rec["n"][back], [0, 0, -1])


@pytest.mark.parametrize("n,cols", [(8, 8), (3, 7)])  # non-square: x and y extents differ
def test_preview_shows_row_0_at_the_largest_y(saved_figures, n, cols):
    # CONVENTIONS.md: pixel (row 0, col 0) covers x in [0, p], y in [(N-1) p, N p].
    # The preview's axes are x, y in mm: the raised pixel must be drawn there.
    levels = np.zeros((n, cols), np.uint8)
    levels[0, 0] = MESH_L - 1
    preview_png_bytes(Relief(levels, MESH_L, MESH_STEP, MESH_PITCH, MESH_THICK))
    (ax,) = [a for a in saved_figures[0].axes if a.images]
    image = ax.images[0]
    p_mm = MESH_PITCH * 1e3

    def shown_at(x_mm, y_mm):
        x, y = ax.transData.transform((x_mm, y_mm))
        return float(image.get_cursor_data(SimpleNamespace(x=x, y=y)))

    top_left = shown_at(0.5 * p_mm, (n - 0.5) * p_mm)
    bottom_left = shown_at(0.5 * p_mm, 0.5 * p_mm)
    assert top_left == 0.0  # level L-1: the unetched surface, 0 um below it
    assert bottom_left < -1.0  # level 0: (L-1) steps (1.26 um) deep
    assert shown_at((cols - 0.5) * p_mm, (n - 0.5) * p_mm) < -1.0  # top right: level 0
