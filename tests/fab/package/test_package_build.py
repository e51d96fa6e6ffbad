"""``fab.package.build.build_package`` as a library: its result and its refusals."""

import json

import numpy as np
import pytest
from package_helpers import make_design_dir

from doe.infra.errors import InputError
from doe.records.fab_manifest import MANIFEST_NAME, read_fab_manifest
from fab.package.build import PackageCheckFailed, PackageResult, build_package


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    root = tmp_path_factory.mktemp("build")
    levels = make_design_dir(root / "design", n=21, target=False)
    result = build_package(root / "design", root / "out", oasis=True, progress=False)
    return root, levels, result


def test_result_lists_every_file_written(built):
    root, _, result = built
    out = root / "out"
    assert isinstance(result, PackageResult) and result.out == out
    on_disk = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert list(result.files) == on_disk
    assert {"mask.gds", "mask.oas", MANIFEST_NAME, "levels.npy", "target_psf.npy"} <= set(on_disk)
    assert set(result.report_files) <= set(result.files)
    assert {"fab_report.md", "fab_report.html"} <= set(result.report_files)


def test_result_manifest_is_the_file_written(built):
    root, levels, result = built
    manifest = result.manifest
    assert manifest.path == root / "out" / MANIFEST_NAME
    assert dict(manifest.fields) == json.loads(manifest.path.read_text())
    assert dict(read_fab_manifest(manifest.path).fields) == dict(manifest.fields)
    assert manifest.fields["oasis"] == "mask.oas"
    tile = manifest.tile_geometry()
    assert (tile.tile_pixels, tile.n_levels, tile.tiles) == (21, 8, (16, 16))
    assert np.array_equal(np.load(manifest.levels_path()), levels)


def test_warnings_are_returned_and_nothing_is_printed(tmp_path, capsys):
    make_design_dir(tmp_path / "design", n=15, target=False)
    result = build_package(tmp_path / "design", tmp_path / "out", progress=False)
    assert capsys.readouterr() == ("", "")
    assert any(w.startswith("no target_psf.npy in the design folder") for w in result.warnings)
    assert all("doefab" not in w for w in result.warnings)
    assert "simulated" in result.manifest.fields["target_psf_source"]


def test_a_missing_folder_is_an_input_error_naming_it(tmp_path):
    with pytest.raises(InputError, match="no such design folder") as e:
        build_package(tmp_path / "nope", tmp_path / "out")
    assert e.value.source == str(tmp_path / "nope")
    assert not (tmp_path / "out").exists()


def test_a_bad_level_map_is_an_input_error_naming_the_file(tmp_path):
    d = tmp_path / "design"
    d.mkdir()
    np.save(d / "levels.npy", np.ones((9, 8), np.uint8))
    with pytest.raises(InputError) as e:
        build_package(d, tmp_path / "out")
    assert e.value.source == str(d / "levels.npy")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["design"]


def test_a_missing_config_is_an_input_error_naming_it(tmp_path):
    make_design_dir(tmp_path / "design", n=15)
    with pytest.raises(InputError) as e:
        build_package(tmp_path / "design", tmp_path / "out", config=str(tmp_path / "nope.toml"))
    assert e.value.source == str(tmp_path / "nope.toml")
    assert not (tmp_path / "out").exists()


def test_a_failed_readback_raises_and_releases_nothing(tmp_path, monkeypatch):
    import layouts.readback

    monkeypatch.setattr(layouts.readback, "check_written_gds", lambda *a: ["layer 1: 3 differ"])
    make_design_dir(tmp_path / "design", n=15)
    with pytest.raises(PackageCheckFailed, match="layer 1: 3 differ"):
        build_package(tmp_path / "design", tmp_path / "out", progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["design"]
