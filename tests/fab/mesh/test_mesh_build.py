"""``fab.mesh.build.build_meshes`` as a library: its result and its refusals."""

import json

import numpy as np
import pytest

from doe.infra.errors import InputError
from doe.records.mesh_report import read_mesh_report
from fab.mesh.build import MeshResult, build_meshes
from fab.mesh.relief import Relief

L, STEP, PITCH, THICK = 8, 179.4e-9, 4990e-9, 0.5e-3


def write_fab_dir(path, levels, tiles=(3, 2)):
    """Write a minimal FAB_DIR like ``doefab fab`` does (manifest + levels.npy)."""
    path.mkdir(parents=True, exist_ok=True)
    np.save(path / "levels.npy", levels)
    manifest = {
        "levels": L,
        "level_step_nm": STEP * 1e9,
        "pixel_pitch_nm": PITCH * 1e9,
        "tile_pixels": levels.shape[0],
        "tiles": list(tiles),
        "array_origin_nm": [1e6, -2e6],
        "levels_file": "levels.npy",
        "substrate_thickness_mm": THICK * 1e3,
    }
    (path / "fab_manifest.json").write_text(json.dumps(manifest))
    return path


def random_levels(n, seed):
    return np.random.default_rng(seed).integers(0, L, (n, n)).astype(np.uint8)


def test_result_gives_the_files_and_the_report_written(tmp_path, capsys):
    levels = random_levels(6, seed=1)
    fab = write_fab_dir(tmp_path / "fab", levels)
    out = tmp_path / "out"
    result = build_meshes(fab, out, formats=["stl", "PLY"], crop=2, progress=False)
    assert capsys.readouterr() == ("", "")
    assert isinstance(result, MeshResult) and result.out == out
    assert result.formats == ("ply", "stl")  # in FORMATS order, whatever was asked
    assert result.files == tuple(sorted(p.name for p in out.iterdir()))
    assert result.files == (
        "crop_2x2.ply", "crop_2x2.stl", "mesh_report.json", "preview.png", "tile.ply", "tile.stl",
    )  # fmt: skip
    assert list(result.seconds) == ["tile_mesh", "ply", "stl", "crop"]
    assert result.step_ok is None and result.report.step is None
    written = read_mesh_report(out / "mesh_report.json")
    sizes = {p.name: p.stat().st_size for p in out.iterdir() if p.name != "mesh_report.json"}
    assert dict(written.files) == dict(result.report.files) == sizes
    analytic = Relief(levels, L, STEP, PITCH, THICK).analytic_volume() * 1e9
    assert written.tile["volume_mm3"] == pytest.approx(analytic, rel=1e-12)
    assert written.tile["triangles"] == result.report.tile["triangles"]
    assert written.aperture["instances"] == result.report.aperture["instances"] == 6
    assert written.aperture["origin_mm"] == pytest.approx([1.0, -2.0])
    assert written.crop["tiles"] == [2, 2]


def test_a_missing_folder_is_an_input_error_naming_it(tmp_path):
    with pytest.raises(InputError, match="no such folder") as e:
        build_meshes(tmp_path / "nope", tmp_path / "out")
    assert e.value.source == str(tmp_path / "nope")


def test_a_folder_without_a_manifest_is_an_input_error_naming_the_file(tmp_path):
    (tmp_path / "retrieve").mkdir()
    with pytest.raises(InputError, match="mesh takes the folder that doefab fab wrote") as e:
        build_meshes(tmp_path / "retrieve", tmp_path / "out")
    assert e.value.source == str(tmp_path / "retrieve" / "fab_manifest.json")


def test_a_bad_manifest_is_an_input_error_naming_it(tmp_path):
    fab = write_fab_dir(tmp_path / "fab", random_levels(3, seed=2))
    manifest = json.loads((fab / "fab_manifest.json").read_text())
    del manifest["tiles"]
    (fab / "fab_manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="missing key 'tiles'") as e:
        build_meshes(fab, tmp_path / "out", formats="ply")
    assert e.value.source == str(fab / "fab_manifest.json")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "options, source",
    [
        ({"formats": ["obj"]}, "--formats"),
        ({"formats": "ply", "crop": 0}, "--crop"),
        ({"formats": "stl", "thickness_mm": 40.0}, "--thickness-mm"),
    ],
)
def test_bad_options_are_input_errors_naming_the_option(tmp_path, options, source):
    fab = write_fab_dir(tmp_path / "fab", random_levels(3, seed=3))
    with pytest.raises(InputError) as e:
        build_meshes(fab, tmp_path / "out", **options)
    assert e.value.source == source
    assert not (tmp_path / "out").exists()


def test_step_result_says_whether_the_solid_passed(tmp_path):
    pytest.importorskip("build123d")
    fab = write_fab_dir(tmp_path / "fab", random_levels(4, seed=4), tiles=(2, 2))
    result = build_meshes(fab, tmp_path / "out", formats="step", progress=False)
    assert result.step_ok is True and result.report.step["solids"] == 1
    assert result.files == ("aperture.step", "mesh_report.json", "preview.png", "tile.step")
    assert list(result.seconds) == ["tile_mesh", "step_solid", "step_write"]
