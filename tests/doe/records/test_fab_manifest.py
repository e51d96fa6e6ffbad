"""``doe.records.fab_manifest``: one writer and one reader of ``fab_manifest.json``."""

import json

import pytest

from doe.infra.errors import InputError
from doe.infra.files import write_json
from doe.records.fab_manifest import (
    FabManifest,
    PlateReference,
    TileGeometry,
    previous_package_files,
    read_fab_manifest,
    write_fab_manifest,
)

# What doefab fab writes, less the keys no reader needs.
MANIFEST = {
    "wavelength_nm": 655.0,
    "levels": 8,
    "level_step_nm": 179.4,
    "pixel_pitch_nm": 4990,
    "tile_pixels": 175,
    "tiles": [16, 16],
    "array_origin_nm": [-6986000, -6986000],
    "levels_file": "levels.npy",
    "masks": [
        {"name": "M2_mid", "etch_depth_nm": 358.8, "exposure_order": 2},
        {"name": "M1_deep", "etch_depth_nm": 717.6, "exposure_order": 1},
    ],
    "substrate_thickness_mm": 0.5,
    "kernel_size": 11,
    "focal_length_mm": 50.0,
    "lattice_pitch_um": 37.5,
    "target_psf_file": "target_psf.npy",
    "acceptance": {"correlation_min": 0.99},
}


def write_manifest(folder, **change):
    folder.mkdir(parents=True, exist_ok=True)
    manifest = {**MANIFEST, **change}
    for key in [k for k, v in change.items() if v is None]:
        del manifest[key]
    (folder / "fab_manifest.json").write_text(json.dumps(manifest))
    return folder / "fab_manifest.json"


def test_written_bytes_are_write_jsons_and_survive_a_read(tmp_path):
    write_json(tmp_path / "plain.json", MANIFEST)
    write_fab_manifest(tmp_path / "a.json", MANIFEST)
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "plain.json").read_bytes()
    record = read_fab_manifest(tmp_path / "a.json")
    assert isinstance(record, FabManifest) and dict(record.fields) == MANIFEST
    write_fab_manifest(tmp_path / "b.json", record)
    assert (tmp_path / "b.json").read_bytes() == (tmp_path / "a.json").read_bytes()


def test_tile_geometry_is_in_si_units_and_mm_for_the_origin(tmp_path):
    tile = read_fab_manifest(write_manifest(tmp_path)).tile_geometry()
    origin_mm = -6986000 * 1e-6  # nm to mm as the meshes are placed
    assert tile == TileGeometry(8, 179.4 * 1e-9, 4990 * 1e-9, 175, (16, 16), (origin_mm,) * 2)
    plain = read_fab_manifest(write_manifest(tmp_path / "b", array_origin_nm=None))
    assert plain.tile_geometry().array_origin_mm == (0.0, 0.0)
    assert read_fab_manifest(write_manifest(tmp_path)).levels_path() == tmp_path / "levels.npy"


def test_plate_reference_reads_depths_in_exposure_order_beside_the_manifest(tmp_path):
    ref = read_fab_manifest(write_manifest(tmp_path)).plate_reference()
    assert isinstance(ref, PlateReference)
    assert ref.etch_depths == (717.6 * 1e-9, 358.8 * 1e-9)
    assert (ref.n_levels, ref.kernel_size, ref.lattice_pitch) == (8, 11, 37.5 * 1e-6)
    assert ref.mask_pixel_pitch == 4990 * 1e-9 and ref.acceptance == {"correlation_min": 0.99}
    assert ref.levels_file == tmp_path / "levels.npy"
    assert ref.target_psf_file == tmp_path / "target_psf.npy" and ref.target_named


def test_plate_reference_derives_the_lattice_pitch_from_the_tile(tmp_path):
    # lambda f / (N p) when the manifest does not give it
    ref = read_fab_manifest(write_manifest(tmp_path, lattice_pitch_um=None)).plate_reference()
    assert ref.lattice_pitch == pytest.approx(655e-9 * 50e-3 / (175 * 4990e-9), rel=1e-12)


def test_each_view_checks_only_its_own_keys(tmp_path):
    # verify needs no tile geometry, mesh no kernel size: neither is refused for the other's
    record = read_fab_manifest(write_manifest(tmp_path / "v", level_step_nm=None, tiles=None))
    assert record.plate_reference().kernel_size == 11
    with pytest.raises(InputError, match="missing key 'level_step_nm'"):
        record.tile_geometry()
    record = read_fab_manifest(write_manifest(tmp_path / "m", kernel_size=None, masks=None))
    assert record.tile_geometry().tile_pixels == 175
    with pytest.raises(InputError, match=r"malformed manifest \(KeyError\('kernel_size'\)"):
        record.plate_reference()


@pytest.mark.parametrize(
    "change, message",
    [
        ({"tiles": None}, "missing key 'tiles'"),
        ({"levels": 8.9}, "malformed value (8.9 is not a whole number)"),
        ({"tiles": [4]}, "tiles must be [nx, ny] >= 1 and array_origin_nm [x0, y0]"),
        ({"levels": 6}, "levels 6 must be"),
        ({"pixel_pitch_nm": 0}, "level_step_nm > 0, pixel_pitch_nm > 0 required"),
        ({"pixel_pitch_nm": 1e-300}, "must lie between 1 pm and 1 m"),
    ],
)
def test_tile_geometry_refusals_name_the_file(tmp_path, change, message):
    path = write_manifest(tmp_path, **change)
    with pytest.raises(InputError) as e:
        read_fab_manifest(path).tile_geometry()
    assert e.value.source == str(path) and message in e.value.problem


@pytest.mark.parametrize(
    "change, message",
    [
        ({"kernel_size": "eleven"}, 'malformed manifest (ValueError("invalid literal for int()'),
        ({"masks": [{"etch_depth_nm": 717.6}]}, "malformed manifest (KeyError('exposure_order')"),
        ({"levels_file": 3}, "malformed manifest (TypeError("),
    ],
)
def test_plate_reference_refusals_name_the_file(tmp_path, change, message):
    path = write_manifest(tmp_path, **change)
    with pytest.raises(InputError) as e:
        read_fab_manifest(path).plate_reference()
    assert e.value.source == str(path) and e.value.problem.startswith(message)
    assert e.value.problem.endswith(" missing or wrong)")


def test_levels_path_refuses_a_levels_file_that_is_no_name(tmp_path):
    path = write_manifest(tmp_path, levels_file=5)
    with pytest.raises(InputError, match="levels_file must be a file name, got 5") as e:
        read_fab_manifest(path).levels_path()
    assert e.value.source == str(path)


def test_read_refuses_a_missing_file_or_one_that_is_no_object(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_fab_manifest(tmp_path / "fab_manifest.json")
    (tmp_path / "fab_manifest.json").write_text("[1]")
    with pytest.raises(InputError, match="expected a JSON object, got list") as e:
        read_fab_manifest(tmp_path / "fab_manifest.json")
    assert e.value.source == str(tmp_path / "fab_manifest.json")


def test_previous_package_files_are_the_mask_images_and_oasis(tmp_path):
    def images(name):
        return f"{name}_tile.tif", f"{name}_plate.png"

    path = write_manifest(tmp_path, oasis="mask.oas")
    assert previous_package_files(path, images) == [
        "M2_mid_tile.tif", "M2_mid_plate.png", "M1_deep_tile.tif", "M1_deep_plate.png",
        "mask.oas",
    ]  # fmt: skip
    assert previous_package_files(tmp_path / "none.json", images) == []
    assert previous_package_files(write_manifest(tmp_path / "b", masks=3), images) == []
