"""The presets and the tiling check: tiles across the aperture, lattice drift, dot size."""

import json
import math
import re

import numpy as np
import pytest

from doe.design import _read_preset, load_design, parse_design
from doe.infra.cli import main
from doe.infra.errors import InputError
from doe.tiling import TILES_GOOD, own_cell_power, tiling


def _with(name, **tables):
    raw = _read_preset(name)
    for section, values in tables.items():
        raw[section] = dict(raw[section], **values)
    return raw


def _write(tmp_path, name, raw):
    lines = []
    for section, table in raw.items():
        if isinstance(table, dict):
            lines.append(f"[{section}]")
            lines += [f"{k} = {json.dumps(v)}" for k, v in table.items()]
        else:
            lines.insert(0, f"{section} = {json.dumps(table)}")
    path = tmp_path / f"{name}.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_every_preset_loads_with_a_tiling_that_works(preset):
    d = load_design(preset)
    t = tiling(d)
    assert d.name == preset and t.verdict == "ok", t.problems
    assert t.tiles >= TILES_GOOD and t.dot_diameter < d.sensor.active_area
    # the active area fits a sub-pixel: the SPAD samples the super-resolved grid
    assert d.sensor.active_area < d.sensor.pixel_pitch / d.sensor.superres_factor


@pytest.mark.parametrize(
    # preset, wavelength, focal length, sub-pixel, feature, aperture (m), K, tiles, active (m)
    ("name", "wl", "f", "subpixel", "feature", "aperture", "k", "tiles", "active"),
    [
        ("sun2020", 655e-9, 50e-3, 150e-6 / 4, 5e-6, 14e-3, 11, 16, 30e-6),
        ("pf32", 532e-9, 25e-3, 50e-6 / 4, 5e-6, 12.7e-3, 11, 11, 6.95e-6),
        ("swissspad2", 532e-9, 20e-3, 16.38e-6 / 2, 5e-6, 12.7e-3, 11, 9, 5.99e-6),
    ],
)
def test_tiling_figures_match_a_hand_computation(
    name, wl, f, subpixel, feature, aperture, k, tiles, active
):
    t = tiling(load_design(name))
    nominal = wl * f / subpixel  # the tile whose orders lie one sub-pixel apart
    n = math.floor(nominal / feature)  # the most pixels of at least the feature size
    pitch_nm = round(nominal / n * 1e9)  # snapped to the 1 nm grid, not below the feature
    pitch_nm += pitch_nm < round(feature * 1e9)
    tile = n * pitch_nm * 1e-9
    assert t.tile_size == pytest.approx(tile, rel=1e-12)
    assert t.tiles == math.floor(aperture / tile) == tiles
    assert t.tiles_exact == pytest.approx(aperture / tile)
    assert t.f_number == pytest.approx(f / aperture)
    assert t.dot_diameter == pytest.approx(2.44 * wl * f / aperture)
    drift = k // 2 * abs(wl * f / tile - subpixel)  # the outermost PSF dot off its sub-pixel
    assert t.kernel_edge_offset == pytest.approx(drift, rel=1e-9)
    assert t.active_area == pytest.approx(active)


@pytest.mark.parametrize("tiles", [1, 2, 4, 8, 16])
def test_a_dots_power_in_its_sub_pixel_is_the_sinc_squared_integral(tiles):
    # n tiles put zeros s / n apart: the cell +-s/2 spans +-n/2 zeros of sinc^2(x),
    # whose integral over the line is 1; integrated here numerically, per axis.
    x = np.linspace(-tiles / 2, tiles / 2, 200_001)
    one_axis = np.trapezoid(np.sinc(x) ** 2, x)
    assert own_cell_power(tiles) == pytest.approx(one_axis**2, rel=1e-6)


def _numbers(pattern, text):
    return [float(v) for v in re.findall(pattern, text)]


def test_a_16_um_array_at_the_papers_optics_is_refused_with_fixes_that_work(tmp_path, capsys):
    # SwissSPAD2 at 4x and 655 nm x 50 mm: an 8 mm tile, one across 14 mm.
    raw = _with(
        "swissspad2", sensor={"superres_factor": 4}, optics=_read_preset("sun2020")["optics"]
    )
    raw["fabrication"]["aperture_mm"] = 14.0
    assert main(["config", "show", "--config", str(_write(tmp_path, "ss2x4", raw))]) == 2
    err = capsys.readouterr().err
    # 1599 pixels of 5002 nm (the 7.9976 mm tile over the most 5 um pixels, snapped)
    assert "no dot lattice forms: 1 whole tile(s) of 7.998 mm" in err
    assert "[fabrication] aperture_mm" in err  # the key the message names
    (f_max,) = _numbers(r"change \[optics\] focal_length_mm <= ([\d.]+)", err)
    (a_min,) = _numbers(r"aperture_mm >= ([\d.]+)", err)
    (f_at_2,) = _numbers(r"superres_factor = 2 with \[optics\] focal_length_mm <= ([\d.]+)", err)
    # tiles across = aperture x sub-pixel / (lambda f): 8 tiles of s = 4.095 um at 655 nm
    assert f_max == pytest.approx(14e-3 * 4.095e-6 / (655e-9 * 8) * 1e3, abs=0.1)
    for fix in (
        {"optics": {"focal_length_mm": f_max}},
        {"fabrication": {"aperture_mm": a_min}},
        {"sensor": {"superres_factor": 2}, "optics": {"focal_length_mm": f_at_2}},
    ):
        fixed = {s: dict(v, **fix.get(s, {})) if isinstance(v, dict) else v for s, v in raw.items()}
        t = tiling(parse_design(fixed, "fixed.toml"))
        assert t.tiles >= TILES_GOOD and t.verdict == "ok", (fix, t.problems)


def test_a_marginal_tiling_warns_and_names_the_fix(tmp_path, capsys):
    raw = _with("pf32", fabrication={"aperture_mm": 6.0})  # 5 tiles of 1.064 mm
    path = _write(tmp_path, "pf32-small", raw)
    assert main(["config", "show", "--config", str(path)]) == 0
    captured = capsys.readouterr()
    assert "  verdict                      marginal" in captured.out
    assert "warning: the tiling is marginal: 5 whole tile(s)" in captured.err
    (a_min,) = _numbers(r"aperture_mm >= ([\d.]+)", captured.err)
    assert a_min == pytest.approx(8 * 1.063935, abs=0.02)
    assert tiling(parse_design(_with("pf32", fabrication={"aperture_mm": a_min}))).verdict == "ok"


def test_a_dot_wider_than_the_active_area_warns(capsys, tmp_path):
    raw = _with("sun2020", sensor={"active_area_um": 5.0})  # the dot is 5.71 um at f/3.57
    t = tiling(parse_design(raw, "small-spad.toml"))
    assert t.verdict == "marginal" and "wider than the 5 um active area" in t.problems[0]
    (a_min,) = _numbers(r"aperture_mm >= ([\d.]+) for the dot", "; ".join(t.fixes))
    assert a_min == pytest.approx(2.44 * 655e-9 * 50e-3 / 5e-6 * 1e3, abs=0.02)


def test_config_show_and_presets_print_the_verdicts(capsys, preset):
    assert main(["config", "show", "--config", preset]) == 0
    out = capsys.readouterr().out
    assert "[tiling]" in out and re.search(r"\n  verdict +ok\n", out)
    assert main(["config", "show", "--config", preset, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    t = tiling(load_design(preset))
    assert summary["tiling"]["tiles_across"] == t.tiles and summary["tiling_problems"] == []
    assert main(["presets"]) == 0
    listing = capsys.readouterr().out
    assert f"  tiling ok: {t.tiles} tiles of " in listing.split(f"{preset}")[1].splitlines()[1]


def test_outermost_dots_drifting_off_a_tight_active_area_warn():
    # sun2020's grid snap puts the 5th dot 5 x |lambda f / T - s| = 5.9 nm off its
    # sub-pixel; an active area 7 nm wider than the 5.708 um dot leaves 3.6 nm.
    d = parse_design(_with("sun2020", sensor={"active_area_um": 5.715}), "tight.toml")
    t = tiling(d)
    tile = 174 * 5019e-9
    offset = 5 * abs(655e-9 * 50e-3 / tile - 37.5e-6)
    assert t.kernel_edge_offset == pytest.approx(offset)
    assert offset > (5.715e-6 - t.dot_diameter) / 2
    assert t.verdict == "marginal" and "outermost dots drift" in t.problems[0]
    assert tiling(parse_design(_with("sun2020", sensor={"active_area_um": 5.9}))).verdict == "ok"
    # the fix: a tile pixel count whose snapped pitch lands nearer the grid
    (feature,) = _numbers(r"feature_size_um = ([\d.]+) \(N = \d+", t.fixes[0])
    raw = _with(
        "sun2020", sensor={"active_area_um": 5.715}, fabrication={"feature_size_um": feature}
    )
    fixed = tiling(parse_design(raw, "fixed.toml"))
    assert fixed.verdict == "ok" and fixed.kernel_edge_offset < offset / 5


def test_every_stage_refuses_a_design_without_a_dot_lattice(tmp_path):
    # the check is the design's own: load_design (learn, retrieve, fab, run) refuses it
    raw = _with("sun2020", fabrication={"aperture_mm": 1.5})  # 1 tile of 0.873 mm
    with pytest.raises(InputError, match=r"\[fabrication\] aperture_mm: no dot lattice forms: 1 "):
        load_design(_write(tmp_path, "one-tile", raw))
    assert (
        main(["run", "--out", str(tmp_path / "run"), "--config", str(tmp_path / "one-tile.toml")])
        == 2
    )
    assert not (tmp_path / "run").exists()
