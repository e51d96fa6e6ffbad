"""Good plates verified end to end by `doefab verify`, the report's figures, the output."""

import json
import re

import numpy as np
import pytest
from verify_helpers import PITCH_PX, PITCH_UM, K, L, N, run_verify

from doe.fraunhofer import simulate_levels
from doe.infra.cli import main
from doe.infra.files import read_psf
from fab.plate.model import PlateFaults


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(seed=1), "capture.png"),
        (
            dict(seed=2, rotation_deg=3.0, centre=(251.3, 347.8), scale=1.04, hot_pixels=30),
            "capture.png",
        ),
        (
            dict(
                seed=3,
                rotation_deg=-2.0,
                centre=(330.6, 260.2),
                scale=0.97,
                bits=16,
                blur_sigma_px=0.8,
            ),
            "capture.tif",
        ),
    ],
)
def test_good_plate_passes_and_registers_the_lattice(tmp_path, levels, kwargs, name):
    code, report, sim = run_verify(tmp_path, levels, kwargs, name)
    assert code == 0, report["diagnosis"]
    assert report["pass"] is True and report["diagnosis"] == ["ok"]
    lat = report["lattice"]
    assert lat["pitch_px"] == pytest.approx(PITCH_PX * kwargs.get("scale", 1.0), rel=1e-3)
    assert lat["rotation_deg"] == pytest.approx(kwargs.get("rotation_deg", 0.0), abs=0.05)
    assert np.allclose(report["zero_order_px"], sim["zero_order_px"], atol=0.3)
    assert report["lattice"]["centre_px"] == report["zero_order_px"]
    assert report["correlation"] > 0.98
    psf = read_psf(tmp_path / "out" / "measured_psf.npy")  # the contract reader accepts it
    assert psf.shape == (K, K) and psf.dtype == np.float64
    for key in (
        "correlation",
        "rmse",
        "efficiency",
        "zero_order_excess",
        "implied_deep_etch_error",
        "power_outside_window",
        "thresholds",
    ):
        assert key in report
    assert (tmp_path / "out" / "verify_report.html").exists()
    assert (tmp_path / "out" / "verify.png").exists()


def test_every_panel_of_verify_png_has_a_colour_bar(tmp_path, levels, saved_figures):
    # the capture panel had none: its square-root grey scale read as nothing in DN
    assert run_verify(tmp_path, levels, dict(seed=1))[0] == 0
    (fig,) = [f for f in saved_figures if f.axes[0].get_title().startswith("capture")]
    images = [im for ax in fig.axes for im in ax.get_images()]
    assert len(images) == 4 and all(im.colorbar is not None for im in images)
    capture = fig.axes[0].get_images()[0]
    assert capture.colorbar.ax.get_ylabel().startswith("DN")
    assert capture.norm.vmin == 0 and capture.norm.vmax > 1  # DN, not square roots of DN


def test_verify_png_shows_the_psfs_row_0_at_the_top(tmp_path, levels, saved_figures, colour_at):
    # each PSF panel's brightest cell is where the design PSF's is, counted from the
    # top left of the panel as displayed
    assert run_verify(tmp_path, levels, dict(seed=1))[0] == 0
    (fig,) = [f for f in saved_figures if f.axes[0].get_title().startswith("capture")]
    design = simulate_levels(levels, L, K)[0]
    assert not np.allclose(design, design.T) and not np.allclose(design, design[::-1])
    peak = np.unravel_index(np.argmax(design), design.shape)
    for ax in fig.axes:
        if ax.get_title() not in ("measured PSF", "design PSF (simulate_levels)"):
            continue
        light = np.array([[colour_at(ax, (c + 0.5) / K, 1 - (r + 0.5) / K, space="axes").sum()
                           for c in range(K)] for r in range(K)])  # fmt: skip
        assert np.unravel_index(np.argmax(light), light.shape) == peak, ax.get_title()


def test_full_size_tile_n175(tmp_path):
    """The contract's N = 175 tile: the frame holds less than one period of orders."""
    lv = np.random.default_rng(175).integers(0, L, (175, 175)).astype(np.uint8)
    code, report, sim = run_verify(
        tmp_path, lv, dict(seed=20, shape=(700, 700), rotation_deg=1.5, centre=(320.4, 371.1))
    )
    assert code == 0, report["diagnosis"]
    assert np.allclose(report["zero_order_px"], sim["zero_order_px"], atol=0.3)


def test_designed_plate_passes(tmp_path, designed):
    code, report, sim = run_verify(
        tmp_path, designed, dict(seed=21, rotation_deg=-1.5, centre=(280.2, 310.6), scale=1.02)
    )
    assert code == 0, report["diagnosis"]
    assert np.allclose(report["zero_order_px"], sim["zero_order_px"], atol=0.3)
    assert report["efficiency"] == pytest.approx(report["design_efficiency"], abs=0.03)
    assert report["zero_order"] == pytest.approx(report["design_zero_order"], abs=0.005)


def test_report_table_never_shows_a_figure_on_the_wrong_side_of_its_limit(tmp_path, designed):
    # A plate's 0.97648 passed a correlation_min of 0.97646 printed as ">= 0.9765"
    from fab.verify.report import _html

    code, report, _ = run_verify(tmp_path, designed, dict(seed=21))
    assert code == 0, report["diagnosis"]
    t = report["thresholds"]
    for limit in (report["correlation"] - 2e-6, report["correlation"] + 2e-6):
        t["correlation_min"] = limit
        cells = r"<td>correlation</td><td>([^<]*)</td><td>&gt;= ([^<]*)</td>"
        row = re.search(cells, _html(report))
        assert (float(row[1]) >= float(row[2])) == (report["correlation"] >= limit)
    # a design whose deepest mask is all or nothing leaves its depth error no trace
    report["deep_etch_error_fit"] = None
    assert re.search(r"fitted[^<]*</td><td>n/a</td><td>[^<]*</td><td>not judged<", _html(report))


def test_compact_psf_registers_from_a_few_dots(tmp_path):
    """The paper's Gaussian PSF: only the zero order and its neighbours stand out."""
    from doe.retrieval import retrieve_phase
    from doe.targets import make_target

    lv = retrieve_phase(make_target("paper_gaussian", K), N, L, seed=0).levels
    code, report, sim = run_verify(
        tmp_path, lv, dict(seed=24, rotation_deg=2.0, centre=(301.3, 288.9))
    )
    assert code == 0, report["diagnosis"]
    assert report["efficiency"] == pytest.approx(report["design_efficiency"], abs=0.03)
    assert np.allclose(report["zero_order_px"], sim["zero_order_px"], atol=0.3)
    assert report["lattice"]["rotation_deg"] == pytest.approx(2.0, abs=0.3)


def test_a_flat_design_passes_its_flat_plate(tmp_path):
    # A flat tile lights the zero order alone: there is no frame of orders to
    # correlate, and the noise between the dots failed a perfect plate as other_design.
    flat = np.zeros((N, N), np.uint8)
    code, report, _ = run_verify(tmp_path, flat, dict(seed=1))
    assert code == 0 and report["diagnosis"] == ["ok"]
    assert set(report["frame_correlation"].values()) == {None}  # undefined, written as null
    assert report["correlation"] > 0.999
    html = (tmp_path / "out" / "verify_report.html").read_text()
    assert "none: the design lights its zero order alone" in html


@pytest.mark.parametrize("plate", ["flat", "design"])
def test_a_flat_plate_of_a_design_and_a_plate_of_a_flat_design_fail(tmp_path, levels, plate):
    flat = np.zeros((N, N), np.uint8)
    plate_levels, design_levels = (flat, levels) if plate == "flat" else (levels, flat)
    code, report, _ = run_verify(tmp_path, plate_levels, dict(seed=2), design_levels=design_levels)
    assert code == 1 and report["diagnosis"] == ["other_design"]


def test_other_design_fails(tmp_path, levels):
    other = np.random.default_rng(99).integers(0, L, (N, N)).astype(np.uint8)
    code, report, _ = run_verify(
        tmp_path, levels, dict(seed=8, faults=PlateFaults(other_levels=other))
    )
    assert code == 1
    assert report["diagnosis"] == ["other_design"]
    assert report["correlation"] < 0.5
    # another plate's dots still sit on the lattice: no hint at the pitch flags
    assert report["lattice"]["on_lattice_light"] > 0.95
    assert not any("--pixel-pitch-um" in n for n in report["notes"])


def test_designed_plate_of_another_design_fails(tmp_path, designed):
    from doe.retrieval import retrieve_phase
    from doe.targets import make_target

    other = retrieve_phase(make_target("anisotropic", K), N, L, seed=3).levels
    code, report, _ = run_verify(
        tmp_path, designed, dict(seed=25, faults=PlateFaults(other_levels=other))
    )
    assert code == 1 and report["diagnosis"] == ["other_design"]
    assert not any("the orders match the design seen with" in n for n in report["notes"])


@pytest.mark.parametrize("camera_um", [5.86, 1.67])
def test_wrong_camera_pitch_is_exit_2_with_both_numbers(tmp_path, levels, capsys, camera_um):
    # The capture is of the design's plate, taken with a 3.45 um camera, but the flag
    # names another camera's pitch: the capture's own pitch contradicts it. Read on the
    # flag's lattice the good plate would fail as "other_design", sending the lab after
    # the plate, not the flag.
    code, report, _ = run_verify(
        tmp_path, levels, dict(seed=1), flags=("--pixel-pitch-um", str(camera_um))
    )
    assert code == 2 and report is None
    err = capsys.readouterr().err
    assert err.startswith("doefab verify: error: --pixel-pitch-um:")
    measured = float(re.search(r"dots are ([0-9.]+) px apart \(measured\)", err).group(1))
    assert measured == pytest.approx(PITCH_PX, rel=2e-3)
    assert f"give {PITCH_UM / camera_um:.4g} px" in err


def test_overlay_error_within_budget_passes_and_reports_outside_power(tmp_path, levels):
    faults = PlateFaults(overlay=((0.0, 0.0), (0.0, 0.0), (-0.5e-6, 0.5e-6)))
    code, report, _ = run_verify(tmp_path, levels, dict(seed=11, faults=faults, supersample=10))
    assert code == 0, report["diagnosis"]
    # Power on the camera outside the window, and what the design puts there.
    assert report["power_outside_window"] == pytest.approx(
        report["expected_power_outside_window"], abs=0.02
    )


def test_an_efficiency_the_capture_cannot_measure_is_said_to_be_the_design_s(tmp_path, designed):
    # On an 8-bit capture the orders outside the window drown in noise and the beam is
    # taken at the design's share of the window: a faulty plate read its design's
    # efficiency (0.713 for a true 0.551) with nothing said. A 16-bit capture measures it.
    quiet = dict(seed=4, bits=8, read_noise_dn=0.4, peak_fraction=0.75)
    _, report, _ = run_verify(tmp_path / "8", designed, quiet)
    assert report["outside_light_measured"] < 0.1
    assert any("is largely the design's own" in n for n in report["notes"])
    _, report, _ = run_verify(tmp_path / "16", designed, dict(seed=4, bits=16))
    assert report["outside_light_measured"] > 0.2
    assert not any("largely the design's own" in n for n in report["notes"])


def test_verify_json_records_the_flags_and_inputs_it_ran_with(tmp_path, levels):
    # a camera of 5 um pixels, mounted turned by 90 degrees: the record must say so
    pixel_um = 5.0
    code, report, _ = run_verify(
        tmp_path,
        levels,
        dict(seed=10, orientation="rot90", pitch_px=PITCH_UM / pixel_um),
        flags=("--orientation", "rot90", "--pixel-pitch-um", str(pixel_um)),
    )
    assert code == 0, report["diagnosis"]
    assert report["orientation"] == "rot90" and report["pixel_pitch_um"] == pixel_um
    assert report["lattice"]["nominal_pitch_px"] == pytest.approx(PITCH_UM / pixel_um)
    assert report["inputs"]["capture"] == "capture.png" and report["inputs"]["dark"] == "dark.png"


def test_existing_verify_output_is_refused_without_force(tmp_path, levels, capsys):
    code, _, _ = run_verify(tmp_path, levels, dict(seed=1))
    assert code == 0
    out = tmp_path / "out"
    (out / "verify.json").write_text("the lab's notes")
    psf = (out / "measured_psf.npy").read_bytes()
    argv = ["verify", str(tmp_path / "design"), str(tmp_path / "capture.png"),
            "--dark", str(tmp_path / "dark.png"), "--out", str(out)]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--force" in err
    assert (out / "verify.json").read_text() == "the lab's notes"
    assert (out / "measured_psf.npy").read_bytes() == psf
    assert main([*argv, "--force"]) == 0
    assert json.loads((out / "verify.json").read_text())["pass"] is True
