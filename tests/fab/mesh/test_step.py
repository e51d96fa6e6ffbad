"""Tests of the STEP solid and assembly (fab.mesh.step) and ``doefab mesh --formats step``."""

import json
import re

import numpy as np
import pytest

pytest.importorskip("build123d")

from mesh_helpers import exact_volume_mm3

from doe.infra.cli import main
from fab.mesh import step
from fab.mesh.relief import Relief, instance_offsets_mm

L, STEP_M, PITCH, THICK = 8, 179.4e-9, 4990e-9, 0.5e-3


def relief_of(n, seed):
    levels = np.random.default_rng(seed).integers(0, L, (n, n)).astype(np.uint8)
    return Relief(levels, L, STEP_M, PITCH, THICK)


def analytic_mm3(relief):
    return exact_volume_mm3(relief.levels, L, STEP_M, PITCH, THICK)  # pixels minus chamfers


def test_step_tile_reimports_as_one_closed_solid_with_exact_volume(tmp_path):
    relief = relief_of(8, seed=1)
    solid = step.tile_solid(relief)
    assert len(solid.faces()) == step.step_face_count(relief.levels)
    data = step.step_bytes(solid)
    path = tmp_path / "tile.step"
    path.write_bytes(data)
    back = step.check_solid(step.read_step(path), validate=True)
    assert back["solids"] == 1 and back["closed"] and back["valid"]
    assert back["volume_mm3"] == pytest.approx(analytic_mm3(relief), rel=1e-6)
    assert abs(back["volume_mm3"] / analytic_mm3(relief) - 1) < 1e-9
    head = data[:2000].decode()
    assert step.STEP_TIMESTAMP in head and "'tile'" in head
    assert step.step_bytes(step.tile_solid(relief)) == data, "rerun must give equal bytes"


def test_a_scene_written_twice_in_one_process_gives_equal_bytes():
    # OCCT numbers assembly occurrences from a counter that lives as long as the process
    solid = step.tile_solid(relief_of(3, seed=2))
    parts = [("piece", solid, [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])]
    first = step.scene_step_bytes(parts, "edge")
    assert step.scene_step_bytes(parts, "edge") == first
    ids = re.findall(rb"NEXT_ASSEMBLY_USAGE_OCCURRENCE\('(\d+)'", first)
    assert ids == [b"1", b"2"]


def test_step_checkerboard_corners_give_a_closed_solid(tmp_path):
    levels = np.tile(np.array([[7, 0], [0, 7]], np.uint8), (2, 2))
    relief = Relief(levels, L, STEP_M, PITCH, THICK)
    path = tmp_path / "c.step"
    path.write_bytes(step.step_bytes(step.tile_solid(relief)))
    back = step.check_solid(step.read_step(path), validate=True)
    assert back["solids"] == 1 and back["closed"] and back["valid"]
    assert back["volume_mm3"] == pytest.approx(analytic_mm3(relief), rel=1e-9)


def test_open_shell_is_reported_not_closed():
    from build123d import Shell, Solid

    solid = step.tile_solid(relief_of(3, seed=2))
    open_shell = Shell(solid.faces()[1:])  # one face missing
    check = step.check_solid(Solid(open_shell))
    assert not check["closed"]


def test_assembly_refuses_a_step_file_that_is_not_one_solid():
    two_products = b"#1 = PRODUCT_DEFINITION('design','',#2,#3);\n" * 2
    for data in (b"ISO-10303-21;\nEND-ISO-10303-21;", two_products):
        with pytest.raises(ValueError, match="not a single-solid STEP file"):
            step.assembly_step_bytes(data, [[0.0, 0.0, 0.0]])


def assembly_bytes(solid, offsets, route):
    """The aperture assembly as STEP bytes, written as text around the tile or by OCCT."""
    if route == "text":
        return step.assembly_step_bytes(step.step_bytes(solid), offsets)
    return step.step_bytes(solid, offsets)


@pytest.mark.parametrize("route", ["text", "xcaf"])
def test_step_aperture_is_an_assembly_of_located_instances(tmp_path, route):
    relief = relief_of(5, seed=3)
    solid = step.tile_solid(relief)
    offsets = instance_offsets_mm(relief, (3, 2), origin_mm=(1.0, 2.0))
    data = assembly_bytes(solid, offsets, route)
    assert data.count(b"MANIFOLD_SOLID_BREP") == 1, "the tile is stored once"
    assert data.count(b"NEXT_ASSEMBLY_USAGE_OCCURRENCE") == 6
    path = tmp_path / "aperture.step"
    path.write_bytes(data)
    shape = step.read_step(path)
    back = step.check_solid(shape, validate=True)
    assert back["solids"] == 6 and back["closed"] and back["valid"]
    assert back["volume_mm3"] == pytest.approx(6 * analytic_mm3(relief), rel=1e-9)
    lows = sorted(
        tuple(np.round((s.bounding_box().min.X, s.bounding_box().min.Y), 6)) for s in shape.solids()
    )
    want = sorted(tuple(np.round(o[:2], 6)) for o in offsets)
    assert lows == want


def step_entities(data):
    """Return the entities of a STEP file as {number: text}, checking the numbers are unique."""
    found = re.findall(rb"^#(\d+) = (.*?);\r?$", data, re.M | re.S)
    numbers = [int(n) for n, _ in found]
    assert len(numbers) == len(set(numbers)), "entity instance names must be unique"
    return {int(n): text.decode() for n, text in found}


def refs(text):
    return [int(v) for v in re.findall(r"#(\d+)", text)]


@pytest.mark.parametrize("route", ["text", "xcaf"])
def test_step_assembly_transforms_map_the_tile_origin_onto_each_offset(route):
    # ISO 10303-42/43: an ITEM_DEFINED_TRANSFORMATION maps its first item, in the related
    # (tile) representation, onto its second, in the relating (assembly) one; OCCT's own
    # assembly writer (the xcaf route) does so. The second item stands at the offset.
    relief = relief_of(3, seed=7)
    solid = step.tile_solid(relief)
    offsets = instance_offsets_mm(relief, (2, 2), origin_mm=(1.0, -2.0))
    offsets[:, 2] = 0.25  # raised too: z is translated like x and y
    data = assembly_bytes(solid, offsets, route)
    ents = step_entities(data)

    def items(rep):
        return set(refs(re.match(r"\w+\('[^']*',\(([^)]*)\)", ents[rep]).group(1)))

    def location(placement):
        point = ents[refs(ents[placement])[0]]
        return [float(v) for v in re.search(r"\(([^()]*)\)\)$", point).group(1).split(",")]

    placed = []
    for text in ents.values():
        rel = re.search(
            r"REPRESENTATION_RELATIONSHIP\('[^']*','[^']*',#(\d+),#(\d+)\)\s*"
            r"REPRESENTATION_RELATIONSHIP_WITH_TRANSFORMATION\(#(\d+)\)",
            text,
        )
        if rel:
            tile_rep, assembly_rep, transform = (int(v) for v in rel.groups())
            first, second = refs(ents[transform])
            assert first in items(tile_rep) and second in items(assembly_rep)
            assert location(first) == [0.0, 0.0, 0.0]
            placed.append(location(second))
    assert len(placed) == 4
    assert np.allclose(sorted(placed), sorted(offsets.tolist()), rtol=0, atol=1e-12)


def write_fab_dir(path, levels, **extra):
    path.mkdir(parents=True)
    np.save(path / "levels.npy", levels)
    manifest = {
        "levels": L,
        "level_step_nm": STEP_M * 1e9,
        "pixel_pitch_nm": PITCH * 1e9,
        "tile_pixels": levels.shape[0],
        "tiles": [2, 2],
        "array_origin_nm": [0, 0],
        "levels_file": "levels.npy",
        "substrate_thickness_mm": THICK * 1e3,
        **extra,
    }
    (path / "fab_manifest.json").write_text(json.dumps(manifest))
    return path


def test_cli_step_writes_checked_solid_and_assembly(tmp_path):
    relief = relief_of(6, seed=4)
    fab = write_fab_dir(tmp_path / "fab", relief.levels)
    out = tmp_path / "out"
    assert main(["mesh", str(fab), "--out", str(out), "--formats", "step"]) == 0
    report = json.loads((out / "mesh_report.json").read_text())
    assert report["step"]["ok"] and report["step"]["solids"] == 1
    assert abs(report["step"]["volume_rel_err"]) < 1e-9
    assert sorted(p.name for p in out.iterdir()) == [
        "aperture.step",
        "mesh_report.json",
        "preview.png",
        "tile.step",
    ]
    aperture = step.read_step(out / "aperture.step")
    lows = sorted(
        tuple(np.round((s.bounding_box().min.X, s.bounding_box().min.Y), 6))
        for s in aperture.solids()
    )
    t = 6 * PITCH * 1e3
    assert lows == [(0.0, 0.0), (0.0, round(t, 6)), (round(t, 6), 0.0), (round(t, 6), round(t, 6))]


def test_cli_step_edge_pieces_and_tiles_cover_the_filled_aperture(tmp_path):
    # 2 x 2 tiles of 6 pixels, and 1 / 2 / 2 / 1 pixel columns and rows of the periodic
    # pattern left / right / below / above them: the clipped edge tiles
    n = 6
    relief = relief_of(n, seed=8)
    edges = {"left": 1, "right": 2, "bottom": 2, "top": 1}
    fab = write_fab_dir(tmp_path / "fab", relief.levels, plate={"edge_pixels": edges})
    out = tmp_path / "out"
    assert main(["mesh", str(fab), "--out", str(out), "--formats", "step"]) == 0
    report = json.loads((out / "mesh_report.json").read_text())
    assert report["aperture"]["edge_scene"] == ["aperture_edge.step"]
    assert report["step"]["ok"] and report["step"]["edge"]["solids"] == 8
    p = PITCH * 1e3
    solids = step.read_step(out / "aperture.step").solids()
    edge_solids = step.read_step(out / "aperture_edge.step").solids()
    assert (
        len(solids) == 4 and len(edge_solids) == 4 + 4 + 4 == report["aperture"]["edge_instances"]
    )
    # the pattern's columns -1 .. 13 and rows -1 .. 13 (row 0: the array's top row)
    cols, rows = np.arange(-1, 2 * n + 2), np.arange(-1, 2 * n + 2)
    pattern = relief.levels[np.ix_(rows % n, cols % n)]
    covered = np.zeros(pattern.shape, int)
    for solid in [*solids, *edge_solids]:
        assert step.check_solid(solid)["closed"]
        box = solid.bounding_box()
        c0, c1 = round(box.min.X / p) + 1, round(box.max.X / p) + 1
        r0, r1 = 2 * n - round(box.max.Y / p) + 1, 2 * n - round(box.min.Y / p) + 1
        covered[r0:r1, c0:c1] += 1
        window = pattern[r0:r1, c0:c1]
        assert solid.volume == pytest.approx(
            exact_volume_mm3(window, L, STEP_M, PITCH, THICK), rel=1e-9
        )
    assert (covered == 1).all()  # every pixel of the filled aperture once, no overlap


def test_cli_step_with_a_crop_writes_the_crop_in_the_mesh_formats_only(tmp_path):
    # The merged crop is a mesh: with step among the formats it is written in the
    # others, beside the STEP tile and aperture (a STEP crop has no encoder).
    relief = relief_of(4, seed=7)
    fab = write_fab_dir(tmp_path / "fab", relief.levels)
    out = tmp_path / "out"
    args = ["mesh", str(fab), "--out", str(out), "--formats", "step,ply", "--crop", "2"]
    assert main(args) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "aperture.step",
        "crop_2x2.ply",
        "mesh_report.json",
        "preview.png",
        "tile.ply",
        "tile.step",
    ]
    report = json.loads((out / "mesh_report.json").read_text())
    assert report["step"]["ok"]
    assert report["crop"]["volume_mm3"] == pytest.approx(4 * analytic_mm3(relief), rel=1e-12)
    assert sorted(report["files"]) == sorted(p.name for p in out.iterdir() if p.suffix != ".json")


def test_cli_step_solid_with_a_wrong_volume_fails_the_check(tmp_path, monkeypatch):
    # A closed single solid whose heights are 0.1 % off must not pass: exit 1, ok false.
    relief = relief_of(4, seed=6)
    fab = write_fab_dir(tmp_path / "fab", relief.levels)
    exact = step.surface_points_mm
    monkeypatch.setattr(step, "surface_points_mm", lambda s, r: exact(s, r) * [1, 1, 1.001])
    out = tmp_path / "out"
    assert main(["mesh", str(fab), "--out", str(out), "--formats", "step"]) == 1
    report = json.loads((out / "mesh_report.json").read_text())["step"]
    assert report["solids"] == 1 and report["closed"] and not report["ok"]
    assert report["volume_rel_err"] == pytest.approx(1e-3, rel=1e-6)


def test_cli_refuses_too_complex_step(tmp_path, capsys, monkeypatch):
    relief = relief_of(6, seed=5)
    fab = write_fab_dir(tmp_path / "fab", relief.levels)
    monkeypatch.setattr(step, "MAX_STEP_FACES", 10)
    out = tmp_path / "out"
    assert main(["mesh", str(fab), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "STEP" in err and "ply" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
