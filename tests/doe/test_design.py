"""Design schema, presets and derived optics."""

import json
import math

import pytest

from doe.derived import derive, design_summary
from doe.design import _read_preset, load_design, parse_design, preset_names
from doe.design_match import PSF_GRID_KEYS, TILE_KEYS, design_differences
from doe.infra.cli import main
from doe.infra.errors import InputError
from doe.materials import MATERIALS, refractive_index


def raw_default():
    return _read_preset("sun2020")


def with_value(section, key, value):
    raw = raw_default()
    raw[section] = dict(raw[section], **{key: value})
    return raw


def test_default_preset_matches_the_paper_prototype():
    d = load_design()
    assert d.sensor.columns == 64 and d.sensor.rows == 32
    assert d.sensor.pixel_pitch == pytest.approx(150e-6)
    assert d.optics.wavelength == pytest.approx(655e-9)
    assert d.kernel_size == 11 and d.fabrication.levels == 8
    der = derive(d)
    assert der.fill_factor == pytest.approx(math.pi * 15**2 / 150**2)


def test_derived_quantities_follow_from_first_principles():
    d = load_design()
    der = derive(d)
    wl, f = 655e-9, 50e-3
    assert der.subpixel_pitch == pytest.approx(37.5e-6)
    assert der.tile_size_nominal == pytest.approx(wl * f / 37.5e-6)
    # the most pixels of at least the 5 um feature size: 873.33 um / 5 um = 174.67 -> 174
    n_pix = math.floor(der.tile_size_nominal / 5e-6)
    assert der.tile_pixels == n_pix == 174
    # the pitch lands on the 1 nm grid, is the nearest grid value and not below 5 um
    pitch_nm = der.mask_pixel_pitch * 1e9
    assert pitch_nm == pytest.approx(round(pitch_nm), abs=1e-6)
    assert abs(pitch_nm - der.tile_size_nominal * 1e9 / n_pix) <= 0.5
    assert pitch_nm == pytest.approx(5019) and pitch_nm >= 5000
    assert der.lattice_pitch == pytest.approx(wl * f / (n_pix * der.mask_pixel_pitch))
    assert der.lattice_drift_at_edge == pytest.approx((der.lattice_pitch - 37.5e-6) * 64 * 4 / 2)
    assert der.tiles == math.floor(14e-3 / der.tile_size)
    # binary-weighted etch depths from the Sellmeier index, deepest first
    n = refractive_index("fused_silica", wl)
    step = wl / (n - 1) / 8
    assert der.level_step == pytest.approx(step)
    assert der.etch_depths == pytest.approx((4 * step, 2 * step, step))
    # the paper's numbers to 0.5 nm
    assert [d * 1e9 for d in der.etch_depths] == pytest.approx([717.6, 358.8, 179.4], abs=0.5)


def test_lattice_drift_is_taken_along_the_sensors_longer_side():
    # It used the columns only: a 32 x 128 sensor reported a quarter of its drift.
    raw = raw_default()
    raw["sensor"].update(columns=32, rows=128)
    der = derive(parse_design(raw, "tall.toml"))
    assert der.lattice_drift_at_edge == pytest.approx(der.lattice_mismatch * 128 * 4 / 2)


@pytest.mark.parametrize("tiles", [2, 3, 16])
def test_an_aperture_of_exactly_whole_tiles_holds_them_all(tiles):
    # N * pitch came out 1 ulp above the aperture: "0.873 mm is larger than 0.873 mm";
    # and 2 tiles' width held 1 tile by floor(aperture / tile) alone. The tile is
    # 174 pixels of 5019 nm.
    raw = with_value("fabrication", "aperture_mm", tiles * 0.873306)
    der = derive(parse_design(raw, "whole.toml"))
    assert der.tile_size == pytest.approx(0.873306e-3) and der.tiles == tiles
    assert der.tiled_size == pytest.approx(tiles * 0.873306e-3)


def test_the_mask_pitch_is_the_grid_value_nearest_the_tile_over_n():
    # 873 333.3 nm / 172 = 5077.52 nm: the nearest 1 nm value is 5078, not 5077
    der = derive(load_design(), tile_pixels=172)
    nominal_nm = 655 * 50e-3 / 37.5e-6
    assert der.mask_pixel_pitch * 1e9 == pytest.approx(round(nominal_nm / 172)) == 5078


@pytest.mark.parametrize(
    ("feature_um", "accepted"),
    # N = floor(873 333.3 nm / feature): 11 = K, 4096, 4097
    [(79.39, True), (0.2132, True), (0.21315, False)],
)
def test_tile_pixel_limits_are_inclusive(feature_um, accepted):
    raw = with_value("fabrication", "feature_size_um", feature_um)
    if accepted:
        assert derive(parse_design(raw, "n.toml")).tile_pixels in (11, 4096)
    else:
        with pytest.raises(InputError, match="N = 4097 pixels, more than 4096"):
            parse_design(raw, "n.toml")


def test_glass_exactly_as_thick_as_the_deepest_etch_is_refused():
    deepest = sum(derive(load_design()).etch_depths)  # m
    with pytest.raises(InputError, match="not thicker than the deepest etch"):
        parse_design(with_value("material", "thickness_mm", deepest * 1e3), "thin.toml")


def test_a_square_active_area_fills_its_side_squared():
    raw = raw_default()
    raw["sensor"].update(active_area_shape="square", active_area_um=75.0)
    assert derive(parse_design(raw, "square.toml")).fill_factor == pytest.approx(0.25)


@pytest.mark.parametrize(
    ("material", "wavelength_um", "index"),
    [
        # Malitson's fused silica and SCHOTT N-BK7 catalogue values
        ("fused_silica", 0.6328, 1.45702),
        ("fused_silica", 1.064, 1.44963),
        ("bk7", 0.5876, 1.51680),
        ("bk7", 0.6563, 1.51432),
    ],
)
def test_sellmeier_index_matches_catalogue(material, wavelength_um, index):
    assert refractive_index(material, wavelength_um * 1e-6) == pytest.approx(index, abs=2e-5)


def test_every_material_refuses_wavelengths_outside_its_fit():
    for m in MATERIALS.values():
        with pytest.raises(InputError, match="outside the Sellmeier range"):
            m.index(m.valid[1] * 1.01)


def test_an_unknown_material_is_refused_with_the_known_ones():
    with pytest.raises(InputError, match=r"material.name: .*'sapphire'; choose one of bk7, fused"):
        refractive_index("sapphire", 655e-9)


@pytest.mark.parametrize(
    ("section", "key", "value", "message"),
    [
        ("fabrication", "levels", 6, "power of two"),
        ("fabrication", "levels", 1, "power of two"),
        ("fabrication", "levels", 512, "levels.npy is uint8"),
        ("fabrication", "feature_size_um", 0.1, "N = 8733 pixels, more than 4096"),
        ("fabrication", "aperture_mm", 0.5, "larger than the aperture"),
        # 100 nm of glass under 1256 nm of etch: refused only by the mesh, after training
        ("material", "thickness_mm", 1e-4, r"not thicker than the deepest etch \(1255.8 nm\)"),
        # a 2 um grid snaps the 5019.2 nm pitch to 6000 nm: the PSF 16 % too small
        ("fabrication", "grid_nm", 2000, r"dots land 82% of a sub-pixel off theirs"),
        ("optics", "wavelength_nm", 5000.0, "outside the Sellmeier range"),
        ("sensor", "pixel_pitch_um", -150.0, "must be > 0"),
        # found by hypothesis: a pitch of 1e160 um overflowed the fill factor
        ("sensor", "pixel_pitch_um", 1e160, "between 1 pm and 1 m"),
        ("optics", "focal_length_mm", 1e-300, "between 1 pm and 1 m"),
        ("sensor", "active_offset_um", [0.0, 1e7], "between 1 pm and 1 m"),
        ("psf", "kernel_size", 10, "odd"),
        ("psf", "kernel_size", 401, "exceeds"),
        ("sensor", "active_area_um", 200.0, "larger than the pixel pitch"),
        # once clamped into the pixel's corner cell by the sensor model, without a word
        ("sensor", "active_offset_um", [100.0, 0.0], "leaves its 150 um pixel"),
        ("sensor", "active_offset_um", [0.0, -61.0], "leaves its 150 um pixel"),
        ("material", "name", "unobtainium", "unknown material .unobtainium.; choose one of"),
        ("sensor", "columns", 64.5, "must be int"),
        ("optics", "focal_length_mm", float("nan"), "finite"),
        ("sensor", "active_offset_um", [1.0], r"\[x, y\]"),
        ("sensor", "active_offset_um", ["60", 0.0], "must be a list of numbers"),
        ("sensor", "active_offset_um", [True, 0.0], "must be a list of numbers"),
        ("sensor", "colums", 64, "unknown key"),
        # TOML integers are unbounded: these overflowed float() or the training deadline
        ("optics", "wavelength_nm", 10**400, "at most 2\\^63 - 1, got a number near 10\\^400"),
        ("sensor", "active_offset_um", [0, -(10**30)], "at most 2\\^63 - 1"),
        ("sensor", "rows", 10**19, "at most 2\\^63 - 1"),
        ("learning", "minutes", 1e308, "<= 1e\\+06"),
        ("learning", "steps", 10**9 + 1, "must be 1 .. 1e\\+09"),
    ],
)
def test_impossible_designs_are_refused(section, key, value, message):
    with pytest.raises(InputError, match=message):
        parse_design(with_value(section, key, value), "bad.toml")


def test_more_masks_than_the_marks_beside_the_aperture_fit_is_refused():
    raw = raw_default()
    raw["fabrication"].update(levels=64, aperture_mm=2.0)
    with pytest.raises(InputError, match=r"aperture_mm: the alignment marks of 6 masks"):
        parse_design(raw, "bad.toml")
    raw["fabrication"].update(aperture_mm=3.3)
    assert derive(parse_design(raw, "ok.toml")).masks == 6


@pytest.mark.parametrize(
    ("section", "key", "value", "message"),
    [
        # nm typed for um: blamed K = 11 alone, not the pixel size that left N = 1
        ("fabrication", "feature_size_um", 5000.0, r"N = 1 pixels .*feature_size_um"),
        ("optics", "focal_length_mm", 0.05, r"exceeds .*focal_length_mm"),
        ("fabrication", "grid_nm", 100000, "coarser than a mask pixel of 5 um"),
        (
            "sensor",
            "active_area_um",
            200.0,
            r"\(200 um\) .* pitch \(150 um, \[sensor\] pixel_pitch",
        ),
        ("optics", "wavelength_nm", 0.655, "wavelength 0.655 nm is outside"),  # read 0.7 nm
        ("sensor", "pixel_pitch_um", 0.15, "the active area"),
        ("optics", "focal_length_mm", 900.0, r"larger than the aperture.*pixel_pitch_um"),
    ],
)
def test_a_unit_slip_is_named_with_the_keys_it_could_be(section, key, value, message):
    with pytest.raises(InputError, match=message):
        parse_design(with_value(section, key, value), "bad.toml")


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("opitcs", {"wavelength_nm": 655.0}, "unknown section or key 'opitcs'"),
        ("name", 2020, "name: must be a string"),
        ("description", ["a", "b"], "description: must be a string"),
    ],
)
def test_top_level_keys_are_checked(key, value, message):
    raw = dict(raw_default(), **{key: value})
    with pytest.raises(InputError, match=message):
        parse_design(raw, "bad.toml")


@pytest.mark.parametrize("value", [5, [{"wavelength_nm": 655.0}]])
def test_a_section_that_is_no_table_is_named_so(value):
    raw = raw_default()
    raw["optics"] = value  # optics = 5, or [[optics]]: read "missing table [optics]"
    with pytest.raises(InputError, match=r"\[optics\] must be a table of keys"):
        parse_design(raw, "bad.toml")


def test_an_unknown_preset_lists_the_presets(capsys):
    assert main(["config", "show", "--config", "sun2021"]) == 2
    assert f"presets: {', '.join(preset_names())}" in capsys.readouterr().err


def test_missing_table_is_refused():
    raw = raw_default()
    del raw["optics"]
    with pytest.raises(InputError, match=r"missing table \[optics\]"):
        parse_design(raw, "bad.toml")


def test_partial_file_overrides_the_default(tmp_path):
    f = tmp_path / "bk7.toml"
    f.write_text('name = "bk7-test"\n[material]\nname = "bk7"\n')
    d = load_design(f)
    assert d.name == "bk7-test" and d.material.name == "bk7"
    assert derive(d).refractive_index == pytest.approx(refractive_index("bk7", 655e-9))
    assert d.sensor == load_design().sensor


def test_a_file_that_names_no_design_goes_by_its_own_name(tmp_path):
    # It was labelled "sun2020", with the prototype's description, on every mask.
    f = tmp_path / "my_bk7_plate.toml"
    f.write_text('[material]\nname = "bk7"\n')
    d = load_design(f)
    assert d.name == "my_bk7_plate"
    assert d.description == "the sun2020 preset with the values set in its design file"
    f.write_text('description = "our plate"\n')
    assert load_design(f).description == "our plate"


def test_a_file_named_as_a_preset_is_not_mistaken_for_it(tmp_path, monkeypatch):
    # --config sun2020 loaded the preset although the lab's file "sun2020" lay here.
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sun2020").write_text('[material]\nname = "bk7"\n')
    with pytest.raises(InputError, match=r"names both a preset and a file here; pass \./sun2020"):
        load_design("sun2020")
    assert load_design("./sun2020").material.name == "bk7"


def test_presets_are_listed_and_load():
    assert "sun2020" in preset_names()
    for name in preset_names():
        load_design(name)


def test_config_show_cli(capsys):
    assert main(["config", "show", "--json"]) == 0
    out = capsys.readouterr().out
    assert '"tile_pixels": 174' in out and '"mask_pixel_pitch_nm": 5019' in out


def _table_value(text):
    """A value of the ``config show`` table: a number, a list of numbers or a word."""
    if text.startswith("["):
        return [float(x) for x in text.strip("[]").split(", ")]
    if text in ("true", "false"):
        return text == "true"
    try:
        return float(text)
    except ValueError:
        return text


def test_config_show_table_lists_every_value_of_the_json_under_its_section(capsys):
    assert main(["config", "show", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert main(["config", "show"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"design {summary['name']}: {summary['description']}"
    table, section = {}, None
    for line in lines[1:]:
        if line.startswith("["):
            section = table.setdefault(line.strip("[]"), {})
        else:
            key, value = line.split(maxsplit=1)
            section[key] = _table_value(value)
    expected = {name: part for name, part in summary.items() if isinstance(part, dict)}
    assert table.keys() == expected.keys() and "derived" in table
    for name, part in expected.items():
        assert table[name].keys() == part.keys()
        for key, value in part.items():  # six significant digits, enough to check a plate
            shown = table[name][key]
            assert shown == (
                value if isinstance(value, str | bool) else pytest.approx(value, rel=1e-5)
            )


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("[fabrication]\nlevels = 6\n", "power of two"),
        ("this is = = not toml", "not valid TOML"),
        ("[learning]\nsteps = 1" + "0" * 5000 + "\n", "not valid TOML"),  # past int() digits
        ("[fabrication]\naperture_mm = 0.1\n", "larger than the aperture"),
        # a tile 0.3 um too large read "(0.873 mm) is larger than ... (0.873 mm)"
        (
            "[fabrication]\naperture_mm = 0.873\n",
            "(0.873306 mm) is larger than the aperture (0.873",
        ),
        # 2^63 - 1 columns passed, with a lattice drift of 6.6e16 um at the sensor's edge
        (
            "[sensor]\ncolumns = 9223372036854775807\n",
            "[sensor] columns: 9223372036854775807 "
            "pixels of 150 um make a sensor 1.38e+15 m across, longer than 1 m",
        ),
        ("[sensor]\nrows = 6667\n", "[sensor] rows: 6667 pixels of 150 um make a sensor 1 m"),
    ],
)
def test_config_show_refuses_bad_files_with_exit_2(tmp_path, capsys, content, message):
    f = tmp_path / "design.toml"
    f.write_text(content)
    assert main(["config", "show", "--config", str(f)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(f) in err and message in err


def test_design_files_are_read_as_utf_8(tmp_path, capsys):
    # A BOM (Windows editors) once read as "Invalid statement"; other encodings are
    # named as such rather than as a codec traceback.
    text = 'name = "µ-plate"\n[fabrication]\nfeature_size_um = 20.0\n'
    (tmp_path / "bom.toml").write_bytes(text.encode("utf-8-sig"))
    d = load_design(tmp_path / "bom.toml")
    assert d.name == "µ-plate" and d.fabrication.feature_size == pytest.approx(20e-6)
    (tmp_path / "latin1.toml").write_bytes(text.encode("latin-1"))
    assert main(["config", "show", "--config", str(tmp_path / "latin1.toml")]) == 2
    err = capsys.readouterr().err
    assert "latin1.toml" in err and "not UTF-8" in err and "0xb5" in err


def test_missing_config_file_exits_2(tmp_path, capsys):
    missing = tmp_path / "nope.toml"
    assert main(["config", "show", "--config", str(missing)]) == 2
    assert str(missing) in capsys.readouterr().err


def test_a_folder_given_as_the_design_file_exits_2(tmp_path, capsys):
    assert main(["config", "show", "--config", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path}: cannot read" in err and "Traceback" not in err


@pytest.mark.parametrize("command", [["config", "show"], ["run", "--out", "r"]])
def test_an_empty_config_is_refused_naming_the_flag(tmp_path, capsys, monkeypatch, command):
    # Path("") is the current folder: "cannot read: Is a directory: '.'"
    monkeypatch.chdir(tmp_path)
    assert main([*command, "--config", ""]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--config: is empty" in err
    assert list(tmp_path.iterdir()) == []


def test_active_area_may_touch_the_pixel_edge():
    # 30 um across, offset 60 um: its edge lies on the 150 um pixel's edge.
    d = parse_design(with_value("sensor", "active_offset_um", [60.0, -60.0]), "edge.toml")
    assert d.sensor.active_offset == pytest.approx((60e-6, -60e-6))


def test_design_differences_name_what_changes_the_tile():
    default = load_design()
    recorded = design_summary(default)
    assert design_differences(recorded, default, TILE_KEYS) == []
    # aperture, substrate, sensor size and active area do not change the tile
    for section, key, value in (
        ("fabrication", "aperture_mm", 10.0),
        ("material", "thickness_mm", 1.0),
        ("sensor", "columns", 32),
        ("sensor", "active_area_um", 50.0),
    ):
        same_tile = parse_design(with_value(section, key, value))
        assert design_differences(recorded, same_tile, TILE_KEYS) == []
    green = parse_design(with_value("optics", "wavelength_nm", 532.0))
    assert design_differences(recorded, green, TILE_KEYS) == ["optics.wavelength_nm 655 -> 532"]
    factor3 = parse_design(with_value("sensor", "superres_factor", 3))
    assert design_differences(recorded, factor3, TILE_KEYS) == ["sensor.superres_factor 4 -> 3"]
    # a value read back through the file's units agrees; a record without a key is not compared
    recorded["optics"]["wavelength_nm"] *= 1 + 1e-12
    del recorded["sensor"]["superres_factor"]
    assert design_differences(recorded, factor3, TILE_KEYS) == []
    assert design_differences(None, green, TILE_KEYS) == []
    # a PSF is made for its sub-pixel grid only
    assert design_differences(design_summary(default), green, PSF_GRID_KEYS) == []
    assert design_differences(design_summary(default), factor3, PSF_GRID_KEYS) == [
        "sensor.superres_factor 4 -> 3"
    ]


def test_summary_gives_back_the_typed_values_in_their_units():
    # Each value the design file gives comes back as typed, not with the float
    # noise of its round trip through SI (655 nm -> 6.55e-7 m -> 655.0000000000001).
    raw = raw_default()
    summary = design_summary(load_design())
    for section, keys in (
        ("sensor", ("pixel_pitch_um", "active_area_um")),
        ("optics", ("wavelength_nm", "focal_length_mm")),
        ("material", ("thickness_mm",)),
        ("fabrication", ("feature_size_um", "aperture_mm")),
    ):
        for key in keys:
            assert summary[section][key] == float(raw[section][key]), (section, key)


def test_tiled_size_is_the_whole_tiles_across_the_aperture():
    der = derive(load_design())
    assert der.tiled_size == pytest.approx(der.tiles * der.tile_size, rel=1e-12)
    assert der.tiled_size <= load_design().fabrication.aperture
    assert der.tiled_size + der.tile_size > load_design().fabrication.aperture
