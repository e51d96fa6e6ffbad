"""Catalogue glasses by any usual name, and custom glasses from a design's [material] table."""

import json

import pytest

from doe.derived import derive, design_summary
from doe.design import _read_preset, load_design, parse_design
from doe.infra.cli import main
from doe.infra.errors import InputError
from doe.materials import MATERIALS, canonical_name, index_source, refractive_index

BK7 = MATERIALS["bk7"]


def with_material(**table):
    raw = _read_preset("sun2020")
    raw["material"] = {"thickness_mm": 0.5, **table}
    return raw


@pytest.mark.parametrize(
    ("name", "canonical"),
    [
        ("fused_silica", "fused_silica"),
        ("Fused Silica", "fused_silica"),
        ("FUSED-SILICA", "fused_silica"),
        ("FS", "fused_silica"),
        ("silica", "fused_silica"),
        ("Corning 7980", "fused_silica"),
        ("HPFS", "fused_silica"),
        ("Suprasil", "fused_silica"),
        ("bk7", "bk7"),
        ("BK7", "bk7"),
        ("N-BK7", "bk7"),
        ("nbk7", "bk7"),
        ("BK-7", "bk7"),
        (" n_bk7 ", "bk7"),
        ("sapphire", None),
        ("", None),
    ],
)
def test_catalogue_glasses_answer_to_their_usual_names(name, canonical):
    assert canonical_name(name) == canonical


@pytest.mark.parametrize(
    ("alias", "canonical"), [("N-BK7", "bk7"), ("Fused Silica", "fused_silica")]
)
def test_an_alias_gives_the_canonical_design_byte_for_byte(alias, canonical):
    by_alias = parse_design(with_material(name=alias), "alias.toml")
    by_name = parse_design(with_material(name=canonical), "alias.toml")
    assert by_alias.material.name == canonical
    assert derive(by_alias).etch_depths == derive(by_name).etch_depths
    assert json.dumps(design_summary(by_alias)) == json.dumps(design_summary(by_name))
    assert refractive_index(alias, 655e-9) == refractive_index(canonical, 655e-9)


def test_config_show_accepts_n_bk7_with_bk7s_etch_depths(tmp_path, capsys):
    depths = {}
    for name in ("bk7", "N-BK7"):
        f = tmp_path / "plate.toml"
        f.write_text(f'[material]\nname = "{name}"\n')
        assert main(["config", "show", "--config", str(f), "--json"]) == 0
        shown = json.loads(capsys.readouterr().out)
        assert shown["material"] == {"name": "bk7", "thickness_mm": 0.5}
        depths[name] = shown["derived"]["etch_depths_nm"]
    assert depths["N-BK7"] == depths["bk7"]


def test_custom_sellmeier_with_bk7s_coefficients_gives_bk7s_etch_depths():
    custom = with_material(
        name="my glass",
        sellmeier_b=list(BK7.B),
        sellmeier_c_um2=list(BK7.C),
        range_nm=[300, 2500],
    )
    d = parse_design(custom, "custom.toml")
    bk7 = parse_design(with_material(name="bk7"), "custom.toml")
    assert d.material.name == "my glass"
    assert derive(d).etch_depths == pytest.approx(derive(bk7).etch_depths, rel=1e-12)
    summary = design_summary(d)["material"]
    assert summary["sellmeier_b"] == list(BK7.B) and summary["range_nm"] == [300.0, 2500.0]
    assert index_source(summary) == "design file: Sellmeier coefficients"
    assert index_source(design_summary(bk7)["material"]) == "Sellmeier, SCHOTT N-BK7 data sheet"


def test_an_index_table_is_interpolated_and_refused_outside_its_range(tmp_path, capsys):
    table = [[450, 1.525], [550, 1.518], [650, 1.514], [700, 1.512]]
    d = parse_design(with_material(name="lab glass", index_table=table), "table.toml")
    assert derive(d).refractive_index == pytest.approx(1.514 - 0.002 * 5 / 50)
    assert d.material.dispersion.index(550e-9) == 1.518
    summary = design_summary(d)["material"]
    assert summary["index_table"] == [[float(nm), n] for nm, n in table]
    assert index_source(summary) == "design file: index table, 4 points"
    f = tmp_path / "short.toml"
    f.write_text('[material]\nname = "lab glass"\nindex_table = [[450, 1.525], [650, 1.514]]\n')
    assert main(["config", "show", "--config", str(f)]) == 2
    err = capsys.readouterr().err
    assert "[optics] wavelength_nm" in err and "outside the index-table range 450-650 nm" in err


@pytest.mark.parametrize(
    ("lines", "key", "message"),
    [
        ('name = "sapphire"', "name", "unknown material 'sapphire'; choose one of bk7"),
        ('name = "N-BK7"\nrange_nm = [300, 2500]', "name", "is the catalogue glass bk7"),
        ('name = ""\nindex_table = [[400, 1.5], [700, 1.4]]', "name", "must name"),
        ('name = "g"\nsellmeier_b = [1.0]\nrange_nm = [300, 900]', "sellmeier_c_um2", "missing"),
        (
            'name = "g"\nsellmeier_b = [1.0, "x"]\nsellmeier_c_um2 = [0.01, 100]\n'
            "range_nm = [300, 900]",
            "sellmeier_b",
            "list of finite numbers",
        ),
        (
            'name = "g"\nsellmeier_b = [1.0, 0.2]\nsellmeier_c_um2 = [0.01]\nrange_nm = [300, 900]',
            "sellmeier_c_um2",
            "list of 2 finite numbers",
        ),
        (
            'name = "g"\nsellmeier_b = [1.0]\nsellmeier_c_um2 = [0.01]\nrange_nm = [900, 300]',
            "range_nm",
            "shortest, longest",
        ),
        (  # a pole at 500 nm inside the range
            'name = "g"\nsellmeier_b = [1.0]\nsellmeier_c_um2 = [0.25]\nrange_nm = [300, 900]',
            "sellmeier_c_um2",
            "no index above 1 at",
        ),
        ('name = "g"\nindex_table = [[500, 1.5]]', "index_table", "at least two"),
        ('name = "g"\nindex_table = [[500, 1.5], [400, 1.6]]', "index_table", "increasing"),
        ('name = "g"\nindex_table = [[400, 1.5], [700, 0.9]]', "index_table", "index must be > 1"),
        ('name = "g"\nindex_table = [[400, 1.5, 3], [700, 1.4]]', "index_table", "list of 2"),
        (
            'name = "g"\nindex_table = [[400, 1.5], [700, 1.4]]\nrange_nm = [300, 900]',
            "index_table",
            "not both",
        ),
    ],
)
def test_bad_material_input_exits_2_naming_the_file_and_key(tmp_path, capsys, lines, key, message):
    f = tmp_path / "bad.toml"
    f.write_text(f"[material]\n{lines}\n")
    assert main(["config", "show", "--config", str(f)]) == 2
    err = capsys.readouterr().err
    assert f"{f}: [material] {key}" in err and message in err
    with pytest.raises(InputError, match=r"\[material\] " + key):
        load_design(f)
