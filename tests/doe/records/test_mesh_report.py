"""``doe.records.mesh_report``: one writer and one reader of ``mesh_report.json``."""

import json

import pytest

from doe.infra.errors import InputError
from doe.infra.files import write_json
from doe.records.mesh_report import (
    MeshReport,
    previous_mesh_files,
    read_mesh_report,
    write_mesh_report,
)

TILE = {
    "triangles": 94,
    "vertices": 40,
    "size_mm": [0.015, 0.015, 0.5],
    "volume_mm3": 1.1e-4,
    "analytic_volume_mm3": 1.1e-4,
    "volume_rel_err": 0.0,
}
APERTURE = {
    "tiles": [2, 2],
    "instances": 4,
    "origin_mm": [0.0, 0.0],
    "pitch_mm": 0.015,
    "note": "lower-left tile at the manifest's array_origin_nm",
}


def test_report_is_written_as_its_dict_and_read_back_the_same(tmp_path):
    report = MeshReport(TILE, APERTURE, {"tile.ply": 1234, "preview.png": 99})
    want = {
        "units": "mm",
        "convention": "z up, back face z=0, row 0 of levels at the largest y (CONVENTIONS.md)",
        "tile": TILE,
        "aperture": APERTURE,
        "files": {"tile.ply": 1234, "preview.png": 99},
    }
    assert report.as_dict() == want  # no "crop" or "step" key when there is none
    write_json(tmp_path / "plain.json", want)
    write_mesh_report(tmp_path / "a.json", report)
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "plain.json").read_bytes()
    back = read_mesh_report(tmp_path / "a.json")
    assert back.as_dict() == want and back.crop is None and back.step is None
    write_mesh_report(tmp_path / "b.json", back)
    assert (tmp_path / "b.json").read_bytes() == (tmp_path / "a.json").read_bytes()


def test_crop_and_step_are_kept(tmp_path):
    step = {"solids": 1, "closed": True, "ok": True}
    report = MeshReport(TILE, APERTURE, {}, crop={"tiles": [1, 1]}, step=step)
    write_mesh_report(tmp_path / "r.json", report)
    back = read_mesh_report(tmp_path / "r.json")
    assert dict(back.step) == step and dict(back.crop) == {"tiles": [1, 1]}


@pytest.mark.parametrize(
    "change, message",
    [
        ({"files": ["tile.ply"]}, "'files' must be an object"),
        ({"files": {"tile.ply": -1}}, "'files' must give each file's size in bytes"),
        ({"tile": None}, "'tile' must be an object"),
        ({"step": 1}, "'step' must be an object"),
    ],
)
def test_read_refuses_a_malformed_report_naming_it(tmp_path, change, message):
    report = {**MeshReport(TILE, APERTURE, {"tile.ply": 3}).as_dict(), **change}
    (tmp_path / "mesh_report.json").write_text(json.dumps(report))
    with pytest.raises(InputError, match=message) as e:
        read_mesh_report(tmp_path / "mesh_report.json")
    assert e.value.source == str(tmp_path / "mesh_report.json")


def test_previous_mesh_files_are_the_files_listed_or_none(tmp_path):
    write_mesh_report(tmp_path / "r.json", MeshReport(TILE, APERTURE, {"a.ply": 1, "b.stl": 2}))
    assert previous_mesh_files(tmp_path / "r.json") == ["a.ply", "b.stl"]
    assert previous_mesh_files(tmp_path / "none.json") == []
    (tmp_path / "bad.json").write_text("{")
    assert previous_mesh_files(tmp_path / "bad.json") == []
