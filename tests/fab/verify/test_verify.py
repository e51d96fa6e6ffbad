"""Tests of hardware verification: simulated captures verified by `doefab verify`."""

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest

from doe.fraunhofer import simulate_levels
from doe.infra.cli import main
from doe.infra.errors import InputError
from doe.infra.files import read_psf, save_npy, write_json
from fab.plate.model import PlateFaults, plate_far_field, plate_phase
from fab.verify.analysis import analyse, design_order_power, resolve_thresholds
from fab.verify.capture import (
    EXPOSURE_RTOL,
    PLATEAU_PIXELS,
    RawImage,
    check_dark,
    condition_capture,
    hot_pixels_from_dark,
    read_capture,
    read_raw_image,
    repair_pixels,
    write_image,
)
from fab.verify.diagnosis import etched_off
from fab.verify.etch_fit import fit_etch_error, fit_etch_errors, implied_deep_etch_error
from fab.verify.lattice import Lattice, LatticeNotFound, measure_orders, register_lattice
from fab.verify.simulate import simulate_capture

N, K, L = 35, 11, 8
PITCH_UM, CAMERA_UM = 37.504, 3.45
PITCH_PX = PITCH_UM / CAMERA_UM
ACCEPTANCE_KEYS = ("correlation_min", "rmse_max", "efficiency_min", "zero_order_max")
# A lab's acceptance tighter than the defaults: a 2 um overlay error fails it.
STRICT_ACCEPTANCE = dict(
    correlation_min=0.99, rmse_max=0.02, efficiency_min=0.5, zero_order_max=0.05
)


@pytest.fixture(scope="module")
def levels():
    return np.random.default_rng(7).integers(0, L, (N, N)).astype(np.uint8)


def make_design_dir(path, levels, acceptance=None):
    """A minimal fab folder: manifest with the keys verify reads, levels, target PSF."""
    path.mkdir(parents=True, exist_ok=True)
    save_npy(path / "levels.npy", levels)
    save_npy(path / "target_psf.npy", simulate_levels(levels, L, K)[0])
    manifest = {
        "levels": L,
        "kernel_size": K,
        "lattice_pitch_um": PITCH_UM,
        "levels_file": "levels.npy",
        "target_psf_file": "target_psf.npy",
        # listed in any order: exposure_order 1 is the deep etch
        "masks": [
            {"name": "M3_shallow", "etch_depth_nm": 179.4, "exposure_order": 3},
            {"name": "M2_mid", "etch_depth_nm": 358.8, "exposure_order": 2},
            {"name": "M1_deep", "etch_depth_nm": 717.6, "exposure_order": 1},
        ],
    }
    if acceptance is not None:
        manifest["acceptance"] = acceptance
    write_json(path / "fab_manifest.json", manifest)
    return path


def run_verify(
    tmp_path, levels, sim_kwargs, name="capture.png", flags=(), dark=True, design_levels=None
):
    design = make_design_dir(
        tmp_path / "design", levels if design_levels is None else design_levels
    )
    sim = simulate_capture(levels, L, **{"pitch_px": PITCH_PX, **sim_kwargs})
    write_image(tmp_path / name, sim["capture"], exposure=0.01)
    args = ["verify", str(design), str(tmp_path / name), "--out", str(tmp_path / "out"), *flags]
    if dark:
        write_image(tmp_path / ("dark" + name[name.index(".") :]), sim["dark"], exposure=0.01)
        args += ["--dark", str(tmp_path / ("dark" + name[name.index(".") :]))]
    code = main(args)
    report = None
    if (tmp_path / "out" / "verify.json").exists():
        report = json.loads((tmp_path / "out" / "verify.json").read_text())
    return code, report, sim


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


def test_12bit_msb_png_is_detected(tmp_path, levels):
    code, report, _ = run_verify(tmp_path, levels, dict(seed=4, bits=12), dark=False)
    assert code == 0
    assert any("MSB-aligned" in n for n in report["notes"])


def test_deep_etch_error_fails_on_zero_order_with_implied_error(tmp_path, levels):
    code, report, sim = run_verify(
        tmp_path, levels, dict(seed=5, faults=PlateFaults(etch_errors=(0.15, 0.0, 0.0)))
    )
    assert code == 1 and report["pass"] is False
    assert "zero_order_excess" in report["diagnosis"]
    assert report["zero_order"] == pytest.approx(float(sim["order_power"](0, 0)), rel=0.1)
    assert report["implied_deep_etch_error"] == pytest.approx(0.15, abs=0.02)
    assert report["implied_deep_etch_error_nm"] == pytest.approx(0.15 * 717.6, abs=15)


@pytest.mark.parametrize("value", [None, float("nan"), "0.9", True])
def test_an_acceptance_threshold_that_is_no_number_is_refused(value):
    # fab writes a null correlation_min for a 1 x 1 PSF (no correlation): float(None)
    # was a TypeError traceback in verify, and NaN passed every plate
    acceptance = {"correlation_min": value, "rmse_max": 1, "efficiency_min": 0.5}
    acceptance["zero_order_max"] = 0.01
    with pytest.raises(ValueError, match=r"acceptance correlation_min is .*not a finite number"):
        resolve_thresholds(acceptance, 0.9, 0)
    with pytest.raises(ValueError, match="deep_etch_error_max"):
        resolve_thresholds(
            {**acceptance, "correlation_min": 0.9, "deep_etch_error_max": value}, 0.9, 0
        )


def test_zero_order_check_catches_what_correlation_misses(levels):
    """With a lenient correlation threshold the zero order alone must fail the plate."""
    sim = simulate_capture(
        levels, L, pitch_px=PITCH_PX, seed=6, faults=PlateFaults(etch_errors=(0.15, 0.0, 0.0))
    )
    grid = _grid(sim)
    _psf, eff = simulate_levels(levels, L, K)
    thresholds = resolve_thresholds(
        {
            "correlation_min": 0.0,
            "rmse_max": 1.0,
            "efficiency_min": 0.0,
            "zero_order_max": 0.005,
            "deep_etch_error_max": 1.0,
        },
        eff,
        0,
    )
    result, _ = analyse(grid, levels, L, K, "as-designed", thresholds)
    # and the etch that brightened it is named, though within its (here lenient) tolerance
    assert result["diagnosis"] == ["zero_order_excess", "deep_etch_error"]
    assert result["deep_etch_error_fit"] == pytest.approx(0.15, abs=0.005)


def test_conjugate_plate_fails_as_point_reflection(tmp_path, levels, capsys):
    code, report, _ = run_verify(tmp_path, levels, dict(seed=7, faults=PlateFaults(conjugate=True)))
    assert code == 1
    assert "conjugate_plate" in report["diagnosis"]
    # a verdict on the plate, not a capture to take again
    assert capsys.readouterr().out.startswith("FAIL: conjugate_plate")
    fc = report["frame_correlation"]
    assert fc["rot180"] > fc["design"] + 0.3


@pytest.fixture(scope="module")
def half_order_levels():
    """A tile whose PSF is a 6 x 6 apodised window centred half an order off the axis.

    Its point reflection about the zero order is the same window one order
    further up-left: within the K x K window a conjugate plate looks like the
    design shifted by one order.
    """
    from doe.retrieval import retrieve_phase

    taper = np.hanning(8)[1:-1]
    target = np.zeros((K, K))
    target[3:9, 3:9] = np.outer(taper, taper)
    target /= target.sum()
    return retrieve_phase(target, n_pixels=48, n_levels=L, seed=0).levels


def test_conjugate_of_half_order_symmetric_psf_fails(tmp_path, half_order_levels):
    psf, _ = simulate_levels(half_order_levels, L, K)
    # The premise: the reflected PSF is the PSF shifted by one order, not the PSF.
    reflected = psf[::-1, ::-1]
    assert np.corrcoef(psf[1:, 1:].ravel(), reflected[:-1, :-1].ravel())[0, 1] > 0.99
    assert np.corrcoef(psf.ravel(), reflected.ravel())[0, 1] < 0.9
    kwargs = dict(rotation_deg=1.5, centre=(290.4, 310.2))
    code, report, _ = run_verify(tmp_path / "good", half_order_levels, dict(seed=31, **kwargs))
    assert code == 0, report["diagnosis"]
    assert report["zero_order_search"]["delta_chi2"]["rot180"] < -25
    code, report, _ = run_verify(
        tmp_path / "conj",
        half_order_levels,
        dict(seed=32, faults=PlateFaults(conjugate=True), **kwargs),
    )
    assert code == 1
    assert report["diagnosis"] == ["conjugate_plate"]
    assert report["zero_order_search"]["delta_chi2"]["rot180"] > 25
    # A window search alone is fooled (the window one order off matches the design);
    # measured at its own zero order, the plate shows its own, reflected PSF.
    measured = read_psf(tmp_path / "conj" / "out" / "measured_psf.npy")
    assert np.corrcoef(measured.ravel(), reflected.ravel())[0, 1] > 0.99
    assert report["correlation"] < 0.9


def test_ambiguous_zero_order_is_reported_not_passed(tmp_path, half_order_levels):
    # A short exposure: the window stands out of the noise but the orders outside it,
    # which alone tell the design from its reflection, do not.
    code, report, _ = run_verify(
        tmp_path,
        half_order_levels,
        dict(seed=33, peak_fraction=0.06, faults=PlateFaults(conjugate=True)),
    )
    assert code == 1
    assert "zero_order_ambiguous" in report["diagnosis"]
    assert report["window_snr"] > 30  # not merely low signal
    assert any("ambiguous" in note for note in report["notes"])
    # catches handing on its PSF: measured at the wrong zero order, it may be the reflection's
    assert report["measured_psf_usable"] is False


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


@pytest.mark.parametrize("camera_um", [5.86, 1.67])
def test_wrong_camera_pitch_is_pointed_out(tmp_path, levels, capsys, camera_um):
    # The capture is of the design's plate, taken with a 3.45 um camera, but the
    # flag names another camera's pitch: the lattice is fitted at the nominal pitch
    # and "other_design" alone would send the lab after the plate, not the flag.
    code, report, _ = run_verify(
        tmp_path, levels, dict(seed=1), flags=("--pixel-pitch-um", str(camera_um))
    )
    assert code == 1 and report["diagnosis"] == ["other_design"]
    assert report["lattice"]["on_lattice_light"] < 0.5
    err = capsys.readouterr().err
    assert "lies on the fitted lattice" in err and f"--pixel-pitch-um ({camera_um:g} um)" in err
    assert any("--pixel-pitch-um" in n for n in report["notes"])


def test_mirrored_plate_fails(tmp_path, levels):
    # The plate's pattern arrives left-right flipped while the flag says as-designed.
    code, report, _ = run_verify(tmp_path, levels, dict(seed=9, orientation="mirror-x"))
    assert code == 1 and "mirrored" in report["diagnosis"]
    # Its measured PSF is not the plate's in the design's frame: no network is tuned to it.
    from doe.design import load_design
    from doe.infra.errors import InputError
    from doe.records.psf_source import check_psf_grid

    assert report["measured_psf_usable"] is False
    with pytest.raises(InputError, match="could not judge \\(mirrored\\)") as refused:
        check_psf_grid(tmp_path / "out" / "measured_psf.npy", load_design(None))
    assert refused.value.source == str(tmp_path / "out" / "verify.json")


def test_capture_with_no_light_in_the_window_is_unusable(tmp_path, levels, capsys):
    # A lone bright pixel on a dark float frame once divided by a beam power of 0:
    # a ZeroDivisionError and exit 1, which for verify means "the plate fails".
    design = make_design_dir(tmp_path / "design", levels)
    image = np.zeros((200, 200), np.float32)
    image[100, 100] = 1.0
    write_image(tmp_path / "one_dot.exr", image)
    out = tmp_path / "out"
    assert main(["verify", str(design), str(tmp_path / "one_dot.exr"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "one_dot.exr: too little signal" in err and not out.exists()


def test_plate_measured_on_a_bench_lens_hands_its_psf_to_the_design(tmp_path, levels):
    # A bench lens of twice the focal length doubles the dot lattice on the camera;
    # the PSF in orders is the same, and learn once refused it as another grid.
    from doe.design import load_design
    from doe.records.psf_source import check_psf_grid

    code, report, _ = run_verify(
        tmp_path,
        levels,
        dict(seed=1, pitch_px=2 * PITCH_PX),
        flags=("--lattice-pitch-um", str(2 * PITCH_UM)),
    )
    assert code == 0, report["diagnosis"]
    assert report["lattice_pitch_um"] == pytest.approx(2 * PITCH_UM)
    assert report["design_lattice_pitch_um"] == pytest.approx(PITCH_UM)
    assert report["measured_psf_usable"] is True
    check_psf_grid(tmp_path / "out" / "measured_psf.npy", load_design(None))  # 37.5 um grid


@pytest.mark.parametrize(
    "orientation", ["rot90", "rot180", "mirror-y", "transpose", "antitranspose"]
)
def test_orientation_flag_is_applied_never_guessed(tmp_path, levels, orientation):
    kwargs = dict(seed=10, orientation=orientation)
    code, report, _ = run_verify(
        tmp_path / "flag", levels, kwargs, flags=("--orientation", orientation)
    )
    assert code == 0, report["diagnosis"]
    code, report, _ = run_verify(tmp_path / "noflag", levels, kwargs)
    assert code == 1


@pytest.mark.parametrize("orientation", ["rot90", "transpose"])
def test_capture_seen_otherwise_than_the_flag_names_the_orientation_that_fits(
    tmp_path, levels, orientation
):
    code, report, _ = run_verify(tmp_path, levels, dict(seed=10, orientation=orientation))
    assert code == 1 and report["diagnosis"] == ["other_design"]
    hints = [n for n in report["notes"] if "the orders match the design seen with" in n]
    assert len(hints) == 1 and f"--orientation {orientation}:" in hints[0]


@pytest.fixture(scope="module")
def compact_levels():
    """A tile whose PSF is a compact, lopsided blob: every orientation correlates highly."""
    from doe.retrieval import retrieve_phase

    y, x = np.mgrid[-(K // 2) : K // 2 + 1, -(K // 2) : K // 2 + 1]
    target = np.exp(-((x - 1) ** 2 + y**2) / 2.5) + 0.4 * np.exp(
        -((x + 1.5) ** 2 + (y - 2) ** 2) / 1.2
    )
    return retrieve_phase(target / target.sum(), n_pixels=N, n_levels=L, seed=0).levels


@pytest.mark.parametrize("seen", ["rot90", "rot270", "mirror-x"])
def test_compact_design_seen_turned_is_not_left_as_a_mirrored_plate(tmp_path, compact_levels, seen):
    # Seen turned by 90 degrees, a compact design fits a reflection better than
    # itself and failed as "mirrored" with no word of the turn: a lab would remake
    # a good plate. The design seen turned fits far better, and the note says so.
    code, report, _ = run_verify(tmp_path, compact_levels, dict(seed=10, orientation=seen))
    assert code == 1 and {"mirrored", "conjugate_plate"} & set(report["diagnosis"])
    turned = [n for n in report["notes"] if "far better" in n]
    if seen == "mirror-x":  # a mirrored plate (or camera): the reflection is the best fit
        assert turned == []
    else:
        assert len(turned) == 1 and f"--orientation {seen} far better" in turned[0]


def test_overlay_error_within_budget_passes_and_reports_outside_power(tmp_path, levels):
    faults = PlateFaults(overlay=((0.0, 0.0), (0.0, 0.0), (-0.5e-6, 0.5e-6)))
    code, report, _ = run_verify(tmp_path, levels, dict(seed=11, faults=faults, supersample=10))
    assert code == 0, report["diagnosis"]
    # Power on the camera outside the window, and what the design puts there.
    assert report["power_outside_window"] == pytest.approx(
        report["expected_power_outside_window"], abs=0.02
    )


def test_saturated_capture_fails_with_that_reason(tmp_path, levels, capsys):
    code, report, _ = run_verify(tmp_path, levels, dict(seed=12, peak_fraction=4.0))
    assert code == 1 and report["pass"] is False
    assert "saturated" in report["diagnosis"]
    assert report["saturated_dots"] > 0
    # said where the lab reads it, with its remedy: the plate was not judged
    out = capsys.readouterr()
    assert out.out.startswith("FAIL (capture not judged): saturated")
    assert "shorten the exposure" in out.err


def test_low_signal_fails(tmp_path, levels, capsys):
    code, report, _ = run_verify(
        tmp_path, levels, dict(seed=13, peak_fraction=0.01, read_noise_dn=3.0)
    )
    assert code == 1 and "low_signal" in report["diagnosis"]
    out = capsys.readouterr()  # "FAIL: low_signal" and nothing more was printed
    assert out.out.startswith("FAIL (capture not judged): low_signal")
    assert re.search(r"window SNR [\d.]+ is under 30: lengthen the exposure", out.err)
    # an 8-bit capture near full scale is told of the camera's deeper modes (it was told
    # to lengthen the exposure, which saturates it)
    code, report, _ = run_verify(
        tmp_path / "full", levels, dict(seed=13, bits=8, peak_fraction=0.94, read_noise_dn=6.0)
    )
    assert code == 1 and "low_signal" in report["diagnosis"]
    assert re.search(
        r"under 30: the brightest dot is near full scale already: use the camera's 12- or 16-bit",
        capsys.readouterr().err,
    )


def test_hot_pixels_that_may_lie_on_dots_ask_for_a_dark_frame(tmp_path, levels, capsys):
    # 0.15 % of a default capture's pixels hot and no dark frame read a good plate as
    # conjugate_plate, without a word about hot pixels
    run_verify(tmp_path, levels, dict(seed=5, hot_pixels=300), dark=False)
    err = capsys.readouterr().err
    assert re.search(r"about \d+ more hot pixels may lie on dots, .*: give --dark", err)


@pytest.mark.parametrize(("peak", "advice"), [(240.0, "12- or 16-bit mode"), (100.0, "lengthen")])
def test_more_signal_is_not_a_longer_exposure_for_a_capture_near_full_scale(peak, advice):
    # an 8-bit capture at 94 % of full scale was told to lengthen the exposure, which the
    # next capture failed as saturated
    from types import SimpleNamespace

    from fab.commands.verify import _more_signal

    capture = SimpleNamespace(full_scale=255.0, image=np.array([[3.0, peak]]))
    assert advice in _more_signal(capture)


def test_no_orientation_is_hinted_when_every_one_fits_as_well(monkeypatch):
    # a capture that fits every orientation alike (a colour sensor's raw mosaic) listed
    # all seven others
    from types import SimpleNamespace

    from fab.commands import verify as cli_verify
    from fab.verify import analysis as verify

    monkeypatch.setattr(verify, "orientations_matching", lambda *a: list(verify.ORIENTATIONS))
    design = SimpleNamespace(levels=None, n_levels=8, kernel_size=11)
    result = {"diagnosis": ["other_design"]}
    assert cli_verify._orientation_hint(result, None, design, "as-designed") is None
    monkeypatch.setattr(verify, "orientations_matching", lambda *a: ["rot90"])
    assert "--orientation rot90" in cli_verify._orientation_hint(
        result, None, design, "as-designed"
    )


def test_truncated_capture_exits_2_naming_the_file(tmp_path, levels, capsys):
    design = make_design_dir(tmp_path / "design", levels)
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, shape=(200, 200), seed=14)
    write_image(tmp_path / "cap.png", sim["capture"])
    data = (tmp_path / "cap.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    code = main(["verify", str(design), str(tmp_path / "cut.png"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert "cut.png" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "name, save, refusal",
    [
        ("cap.jpg", dict(quality=95), "JPEG image"),
        ("cap.webp", dict(quality=95), "WEBP image"),
        ("cap.gif", {}, "GIF image"),
        ("cap.tif", dict(compression="jpeg"), "TIFF compressed with loss (jpeg)"),
    ],
)
def test_a_capture_stored_with_loss_is_refused(tmp_path, levels, capsys, name, save, refusal):
    # CONVENTIONS names TIFF, PNG and EXR: a JPEG capture's compression moved the weak
    # orders' counts, and verify judged the plate by them.
    from PIL import Image

    design = make_design_dir(tmp_path / "design", levels)
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, bits=8, seed=1)
    Image.fromarray(sim["capture"]).save(tmp_path / name, **save)
    write_image(tmp_path / "cap.png", sim["capture"])
    for capture, dark in ((name, None), ("cap.png", name)):
        argv = ["verify", str(design), str(tmp_path / capture), "--out", str(tmp_path / "o")]
        code = main(argv + (["--dark", str(tmp_path / dark)] if dark else []))
        err = capsys.readouterr().err.strip()
        assert code == 2 and f"{name}: {refusal}; give the capture as TIFF, PNG or EXR" in err
        assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("compression", ["dwaa", "b44"])
def test_an_exr_capture_compressed_with_loss_is_refused(tmp_path, compression):
    import OpenImageIO as oiio

    def exr(name, compression):
        spec = oiio.ImageSpec(32, 32, 1, "float")
        spec.attribute("compression", compression)
        out = oiio.ImageOutput.create(str(tmp_path / name))
        out.open(str(tmp_path / name), spec)
        out.write_image(np.ones((32, 32, 1), np.float32))
        out.close()
        return tmp_path / name

    with pytest.raises(InputError, match=f"EXR compressed with loss \\({compression}\\)"):
        read_capture(exr("cap.exr", compression))
    assert read_capture(exr("zip.exr", "zip")).image.shape == (32, 32)  # lossless: read


def test_dots_too_close_to_measure_exit_2(tmp_path, levels, capsys):
    # At 3 px apart the aperture overlaps its background annulus: this capture of a good
    # plate once failed as conjugate_plate; a pixel pitch in nm (1000x) once ran out of memory.
    design = make_design_dir(tmp_path / "design", levels)
    sim = simulate_capture(levels, L, pitch_px=3.0, shape=(300, 300), seed=16)
    write_image(tmp_path / "cap.png", sim["capture"], exposure=0.01)
    out = tmp_path / "o"
    for pixel_um in (PITCH_UM / 3.0, CAMERA_UM * 1000):
        argv = ["verify", str(design), str(tmp_path / "cap.png"), "--out", str(out)]
        assert main([*argv, "--pixel-pitch-um", str(pixel_um)]) == 2
        err = capsys.readouterr().err.strip()
        assert "cap.png" in err and "px apart" in err and len(err.splitlines()) == 1
        assert not out.exists()
    for flag, value in (("--pixel-pitch-um", "nan"), ("--lattice-pitch-um", "inf")):
        assert main([*argv, flag, value]) == 2
        assert flag in capsys.readouterr().err and not out.exists()


def test_dark_frame_of_another_size_or_exposure_exits_2(tmp_path, levels, capsys):
    design = make_design_dir(tmp_path / "design", levels)
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, shape=(300, 300), seed=15)
    write_image(tmp_path / "cap.png", sim["capture"], exposure=0.01)
    write_image(tmp_path / "small.png", sim["dark"][:200], exposure=0.01)
    write_image(tmp_path / "long.png", sim["dark"], exposure=0.5)
    for dark in ("small.png", "long.png"):
        code = main(
            [
                "verify",
                str(design),
                str(tmp_path / "cap.png"),
                "--dark",
                str(tmp_path / dark),
                "--out",
                str(tmp_path / "o"),
            ]
        )
        err = capsys.readouterr().err
        assert code == 2 and dark in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("mixup", ["swapped", "lit dark"])
def test_a_dark_frame_holding_the_dots_is_named(tmp_path, levels, capsys, mixup):
    # Both failed as "capture.png: no dot stands 8 sigma above the noise", which sent
    # the lab to its plate and camera rather than to the dark frame.
    design = make_design_dir(tmp_path / "design", levels)
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=1)
    other = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=5)["capture"]
    capture, dark = (sim["dark"], sim["capture"]) if mixup == "swapped" else (sim["capture"], other)
    write_image(tmp_path / "cap.png", capture, exposure=0.01)
    write_image(tmp_path / "dark.png", dark, exposure=0.01)
    argv = ["verify", str(design), str(tmp_path / "cap.png"), "--dark", str(tmp_path / "dark.png")]
    assert main([*argv, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "dark.png: the dark frame holds" in err and ("swapped" in err) == (mixup == "swapped")
    assert not (tmp_path / "o").exists()


def test_a_dark_frame_that_saw_light_is_refused(tmp_path, levels, capsys):
    # A dark saturated everywhere was subtracted and the plate passed as if it were one.
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, shape=(300, 300), seed=15)
    raw = RawImage(sim["capture"] >> 4, 4095.0, None, encoding="uint16-msb12")
    dark = sim["dark"] >> 4
    spots = np.random.default_rng(0).random(dark.shape)
    for share, refused in ((0.005, False), (0.02, True), (1.0, True)):
        lit = np.where(spots < share, 4095, dark)
        lit_raw = RawImage(lit, 4095.0, None, encoding="uint16-msb12")
        if refused:
            with pytest.raises(InputError, match=r"dark.png: .* at full scale \(4095\): it saw"):
                check_dark(raw, lit_raw, tmp_path / "dark.png")
        else:  # a few hot pixels at full scale are a dark frame's own
            check_dark(raw, lit_raw, tmp_path / "dark.png")


@pytest.mark.parametrize("rise", [0, 200])
def test_a_dark_floor_above_the_capture_is_noted(levels, rise):
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, shape=(300, 300), seed=15)
    raw = RawImage(sim["capture"] >> 4, 4095.0, None, encoding="uint16-msb12")
    dark = RawImage((sim["dark"] >> 4) + rise, 4095.0, None, encoding="uint16-msb12")
    notes = condition_capture(raw, dark).notes
    assert any(f"floor is {rise} DN above" in n for n in notes) == (rise > 0)


@pytest.mark.parametrize("seconds", [-0.01, float("nan"), float("inf")])
def test_an_exposure_time_that_is_no_time_is_ignored_and_noted(tmp_path, seconds):
    # Equal negative ExposureTimes were refused as "dark exposure -0.01 s differs from
    # the capture's -0.01 s"; a NaN one passed every comparison, an infinite one failed it.
    image = np.full((8, 8), 100, np.float32)
    write_image(tmp_path / "cap.exr", image, exposure=seconds)
    write_image(tmp_path / "dark.exr", image, exposure=seconds)
    capture = read_capture(tmp_path / "cap.exr", tmp_path / "dark.exr")
    assert read_raw_image(tmp_path / "cap.exr").exposure is None
    assert f"cap.exr: the file's ExposureTime {seconds:g} s is no exposure time" in capture.notes[0]


def test_blank_capture_exits_2(tmp_path, levels, capsys):
    design = make_design_dir(tmp_path / "design", levels)
    rng = np.random.default_rng(16)
    write_image(tmp_path / "blank.tif", rng.normal(100, 2, (300, 300)).astype(np.float32))
    code = main(["verify", str(design), str(tmp_path / "blank.tif"), "--out", str(tmp_path / "o")])
    assert code == 2 and "blank.tif" in capsys.readouterr().err


def verify_refusal(tmp_path, design, levels, capsys):
    """Verify a capture of ``levels`` against ``design``: exit 2, one line, nothing left.

    Returns the line.
    """
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, shape=(200, 200), seed=20)
    write_image(tmp_path / "cap.png", sim["capture"])
    out = tmp_path / "o"
    assert main(["verify", str(design), str(tmp_path / "cap.png"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and not out.exists(), err
    return err


@pytest.mark.parametrize("key", ["levels", "kernel_size", "lattice_pitch_um"])
def test_a_manifest_number_beyond_any_float_exits_2(tmp_path, levels, capsys, key):
    # JSON reads 1e400 as infinity, and int() of it raised OverflowError: exit 3
    design = make_design_dir(tmp_path / "design", levels)
    text = (design / "fab_manifest.json").read_text()
    manifest = json.loads(text)
    (design / "fab_manifest.json").write_text(
        text.replace(f'"{key}": {json.dumps(manifest[key])}', f'"{key}": 1e400')
    )
    assert json.loads((design / "fab_manifest.json").read_text())[key] == float("inf")
    assert "fab_manifest.json" in verify_refusal(tmp_path, design, levels, capsys)


@pytest.mark.parametrize(
    "change, culprit",
    [
        ({"levels": 0}, "fab_manifest.json"),
        ({"target_psf_file": "gone.npy"}, "gone.npy"),
        ({"kernel_size": 10}, "fab_manifest.json"),  # even: no centre order
        ({"kernel_size": N + 2}, "fab_manifest.json"),  # a window wider than the tile
        # odd, but no window: a traceback (exit 3) from an empty PSF
        ({"kernel_size": -1}, "fab_manifest.json: kernel_size -1 must be odd, 1 .. N"),
        # the 11 x 11 target was left out of the verdict without a word
        ({"kernel_size": 9}, "target_psf.npy: is 11x11, not the fab_manifest.json's kernel_size 9"),
        ({"acceptance": 0.95}, "fab_manifest.json"),  # not a table of thresholds
        ({"lattice_pitch_um": 0}, "fab_manifest.json"),
        ({"acceptance": dict.fromkeys(ACCEPTANCE_KEYS, "0.9")}, "fab_manifest.json"),  # text
        ({"kernel_size": "eleven"}, "fab_manifest.json: malformed manifest"),
        ({"masks": [{"etch_depth_nm": 717.6}]}, "fab_manifest.json: malformed manifest"),
        (
            {"acceptance": {"correlation_min": 0.9}},
            "fab_manifest.json: acceptance lacks ['efficiency_min', 'rmse_max', 'zero_order_max']",
        ),
    ],
)
def test_inconsistent_manifest_exits_2(tmp_path, levels, capsys, change, culprit):
    # levels 0 was blamed on levels.npy ("must lie in 0..-1"); a target the manifest
    # names but that is missing was skipped, verifying without it.
    design = make_design_dir(tmp_path / "design", levels)
    manifest = json.loads((design / "fab_manifest.json").read_text())
    write_json(design / "fab_manifest.json", {**manifest, **change})
    assert culprit in verify_refusal(tmp_path, design, levels, capsys)


def test_manifest_acceptance_is_used(tmp_path, levels):
    acc = {
        "correlation_min": 0.999999,
        "rmse_max": 0.5,
        "efficiency_min": 0.0,
        "zero_order_max": 1.0,
    }
    design = make_design_dir(tmp_path / "design", levels, acceptance=acc)
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=17)
    write_image(tmp_path / "cap.png", sim["capture"])
    code = main(["verify", str(design), str(tmp_path / "cap.png"), "--out", str(tmp_path / "o")])
    report = json.loads((tmp_path / "o" / "verify.json").read_text())
    assert code == 1 and report["diagnosis"] == ["psf_mismatch"]
    assert report["thresholds"]["correlation_min"] == acc["correlation_min"]


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


def verified_without_dark(tmp_path, design, levels):
    """Verify a simulated capture of ``levels`` (seed 1, no dark) against ``design``."""
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=1)
    write_image(tmp_path / "cap.png", sim["capture"])
    out = tmp_path / "o"
    assert main(["verify", str(design), str(tmp_path / "cap.png"), "--out", str(out)]) == 0
    return json.loads((out / "verify.json").read_text()), out


def test_correlation_target_compares_the_measured_psf_with_the_target_psf(tmp_path, levels):
    # The target the tile was designed for is not the PSF its levels form: correlation
    # judges the plate against its levels, correlation_target the PSF against the target.
    design = make_design_dir(tmp_path / "design", levels)
    other = np.random.default_rng(3).integers(0, L, (N, N)).astype(np.uint8)
    target = simulate_levels(other, L, K)[0]
    save_npy(design / "target_psf.npy", target)
    report, out = verified_without_dark(tmp_path, design, levels)
    measured = np.load(out / "measured_psf.npy")
    pearson = np.corrcoef(measured.ravel(), target.ravel())[0, 1]
    assert report["correlation_target"] == pytest.approx(pearson, abs=1e-9)
    assert report["correlation_target"] < 0.5 < report["correlation"]


def test_a_plate_the_deep_mask_leaves_whole_verified_without_a_target_psf(tmp_path):
    # Levels 4..7 only: the deepest mask etches no pixel, so the zero order does not
    # depend on its depth (no implied error, nor its nm). The folder has no target PSF
    # (none named either): the plate is judged against its levels, with no
    # correlation_target. One run for the two, as each is a key left out.
    upper = np.random.default_rng(7).integers(L // 2, L, (N, N)).astype(np.uint8)
    design = make_design_dir(tmp_path / "design", upper)
    (design / "target_psf.npy").unlink()
    man = json.loads((design / "fab_manifest.json").read_text())
    del man["target_psf_file"]
    write_json(design / "fab_manifest.json", man)
    report, out = verified_without_dark(tmp_path, design, upper)
    assert report["pass"] is True and report["implied_deep_etch_error"] is None
    assert "implied_deep_etch_error_nm" not in report and "correlation_target" not in report
    assert report["inputs"]["design_files"] == ["fab_manifest.json", "levels.npy"]
    assert (out / "verify_report.html").is_file()


def test_manifest_without_lattice_pitch_takes_it_from_the_optics(tmp_path, levels):
    # the contract's keys only: lattice pitch = lambda f / (N p)
    design = make_design_dir(tmp_path / "design", levels)
    man = json.loads((design / "fab_manifest.json").read_text())
    del man["lattice_pitch_um"]
    pitch_nm, wavelength_nm, focal_mm = 24950, 655.0, 50.0
    man.update(
        tile_pixels=N,
        pixel_pitch_nm=pitch_nm,
        wavelength_nm=wavelength_nm,
        focal_length_mm=focal_mm,
    )
    write_json(design / "fab_manifest.json", man)
    report, _ = verified_without_dark(tmp_path, design, levels)
    expected_um = wavelength_nm * 1e-9 * focal_mm * 1e-3 / (N * pitch_nm * 1e-9) * 1e6
    assert report["design_lattice_pitch_um"] == pytest.approx(expected_um, rel=1e-12)
    assert report["lattice_pitch_um"] == pytest.approx(expected_um, rel=1e-12)


def test_retrieve_folder_is_accepted(tmp_path, levels):
    from doe.derived import design_summary
    from doe.design import load_design

    folder = tmp_path / "ret"
    folder.mkdir()
    save_npy(folder / "levels.npy", levels)
    save_npy(folder / "target_psf.npy", simulate_levels(levels, L, K)[0])
    write_json(
        folder / "retrieval.json",
        {"levels": L, "kernel_size": K, "design": design_summary(load_design())},
    )
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=18)
    write_image(tmp_path / "cap.png", sim["capture"])
    # N = 35 snaps the mask pitch to 24.95 um: the same 873.25 um tile, the same lattice.
    code = main(["verify", str(folder), str(tmp_path / "cap.png"), "--out", str(tmp_path / "o")])
    assert code == 0
    # the lattice of the plate fab makes of this tile: its pitch snapped to the GDS grid
    from doe.derived import derive

    design = load_design()
    pitch = derive(design, tile_pixels=N).mask_pixel_pitch
    expected_um = design.optics.wavelength * design.optics.focal_length / (N * pitch) * 1e6
    report = json.loads((tmp_path / "o" / "verify.json").read_text())
    assert report["design_lattice_pitch_um"] == pytest.approx(expected_um, rel=1e-9)


def test_a_design_folder_verify_cannot_read_exits_2_naming_it(tmp_path, levels, capsys):
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, shape=(200, 200), seed=20)
    write_image(tmp_path / "cap.png", sim["capture"])
    learn = tmp_path / "learn"  # a folder of another stage
    learn.mkdir()
    broken = tmp_path / "ret"
    broken.mkdir()
    save_npy(broken / "levels.npy", levels)
    write_json(broken / "retrieval.json", {"levels": L, "kernel_size": K})  # no "design"
    for folder, problem in (
        (tmp_path / "none", "none: no such design folder"),
        (learn, "learn: neither fab_manifest.json nor retrieval.json found"),
        (broken, "retrieval.json: malformed retrieval.json (KeyError('design')"),
    ):
        out = tmp_path / "o"
        assert main(["verify", str(folder), str(tmp_path / "cap.png"), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert problem in err and len(err.splitlines()) == 1 and not out.exists(), err


@pytest.mark.parametrize(
    ("section", "key", "value", "problem"),
    [
        ("fabrication", None, 8, "malformed retrieval.json (AttributeError"),
        ("fabrication", "grid_nm", 0, "malformed retrieval.json (ValueError('grid_nm and"),
        ("fabrication", "grid_nm", [1], "malformed retrieval.json (TypeError"),
        ("derived", "tile_size_nominal_um", {}, "malformed retrieval.json (TypeError"),
        ("fabrication", "grid_nm", 10**5, "its grid_nm is coarser than the mask pixels of N = 35"),
    ],
)
def test_a_retrieval_json_of_a_design_verify_cannot_use_exits_2(
    tmp_path, levels, capsys, section, key, value, problem
):
    # each of these ended in a traceback (exit 3): read after the checks, or divided by 0
    from doe.derived import design_summary
    from doe.design import load_design

    summary = design_summary(load_design())
    if key is None:
        summary[section] = value
    else:
        summary[section][key] = value
    folder = tmp_path / "ret"
    folder.mkdir()
    save_npy(folder / "levels.npy", levels)
    write_json(folder / "retrieval.json", {"levels": L, "kernel_size": K, "design": summary})
    assert f"retrieval.json: {problem}" in verify_refusal(tmp_path, folder, levels, capsys)


def test_a_saturated_pixel_off_the_dots_is_noted_and_does_not_fail(tmp_path, levels):
    design = make_design_dir(tmp_path / "design", levels)
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=1)
    capture = sim["capture"].copy()
    # half a pitch off a lattice site in both directions: as far from any dot as can be
    row, col = np.round(np.array(sim["zero_order_px"]) + 5.5 * PITCH_PX).astype(int)
    capture[row, col] = 4095 << 4  # full scale of the 12-bit data, MSB-aligned
    write_image(tmp_path / "cap.png", capture)
    out = tmp_path / "o"
    assert main(["verify", str(design), str(tmp_path / "cap.png"), "--out", str(out)]) == 0
    report = json.loads((out / "verify.json").read_text())
    assert report["saturated_dots"] == 0
    assert "1 saturated pixel(s) outside the dots" in report["notes"]


@pytest.mark.parametrize("errors", [(-0.15, 0.25, 0.0), (0.0, -0.2, 0.3), (0.3, -0.3, 0.2)])
def test_the_joint_etch_fit_inverts_a_plate_with_every_etch_off(levels, errors):
    orders = np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij")
    window = plate_far_field(plate_phase(levels, L, PlateFaults(etch_errors=errors)))(*orders)
    sigma = 1e-4 * window.max() + 0.01 * window
    fit = fit_etch_errors(window, sigma, levels, L)
    assert fit["eps"] == pytest.approx(errors, abs=2e-3)
    assert fit["masks"] == ["M1_deep", "M2_mid", "M3_shallow"] and not fit["at_search_edge"]
    # a mask whose error is 0 is not needed: holding it at 0 costs (almost) nothing
    for err, chi2 in zip(errors, fit["mask_chi2"], strict=True):
        assert (chi2 > 100) if err else (chi2 < 1e-3)
    assert fit["psf"] == pytest.approx(window / window.sum(), abs=1e-6)


def test_the_joint_etch_fit_finds_a_big_error_past_the_local_minimum_near_0():
    # Started from no error alone, the fit stopped at M1 -9 % on this 4-level design's
    # window of M1 +40 % (a helper's 4-level plate: +25 % read +8 %, and the plate passed).
    from doe.retrieval import retrieve_phase
    from doe.targets import make_target

    levels = retrieve_phase(make_target("asymmetric", K), N, 4, seed=0).levels
    orders = np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij")
    for errors in ((0.4, 0.0), (-0.4, 0.0), (0.1, 0.0)):
        window = plate_far_field(plate_phase(levels, 4, PlateFaults(etch_errors=errors)))(*orders)
        assert fit_etch_errors(window, None, levels, 4)["eps"] == pytest.approx(errors, abs=1e-3)


def test_the_joint_etch_fit_s_sigmas_are_the_spread_of_its_errors_over_noise(
    levels, sigmas_match_spread
):
    orders = np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij")
    errors = (0.1, -0.2, 0.15)
    window = plate_far_field(plate_phase(levels, L, PlateFaults(etch_errors=errors)))(*orders)
    sigma = 0.002 * window.max() + 0.03 * window
    sigmas_match_spread(
        lambda noisy: fit_etch_errors(noisy, sigma, levels, L),
        window, sigma, runs=60, seed=0,
        values=lambda f: f["eps"], sigmas=lambda f: f["eps_sigma"],
    )  # fmt: skip


@pytest.mark.parametrize("joint", [False, True])
def test_the_etch_fits_gains_are_in_units_of_their_reduced_chi_square(levels, joint):
    # Sigmas quoted 2x short inflate chi-square 4x; the gains must not grow with them
    # (the deepest etch's own fit and the joint fit's total were taken as they came).
    orders = np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij")
    window = plate_far_field(plate_phase(levels, L, PlateFaults(etch_errors=(0.1, 0.1, 0.0))))(
        *orders
    )
    sigma = 0.002 * window.max() + 0.03 * window
    noisy = window + np.random.default_rng(4).normal(0, 1, window.shape) * sigma

    def fit(s):
        return (fit_etch_errors if joint else fit_etch_error)(noisy, s, levels, L)

    honest, short, long = fit(sigma), fit(sigma / 2), fit(3 * sigma)
    assert short["chi2"] == pytest.approx(4 * honest["chi2"], rel=1e-3)
    assert short["reduced_chi2"] > 1 > long["reduced_chi2"]
    raw = honest["chi2_drop"] * max(honest["reduced_chi2"], 1.0)
    assert short["chi2_drop"] == pytest.approx(4 * raw / short["reduced_chi2"], rel=1e-3)
    assert long["chi2_drop"] == pytest.approx(raw / 9, rel=1e-3)  # too long: as they are


@pytest.mark.parametrize("eps", [-0.4, 0.3])
def test_the_joint_etch_fit_holds_an_unneeded_error_at_0_where_two_masks_trade_off(eps):
    # Levels 5 and 6 only (a near-delta design's): the window sees 2 eps_M2 - eps_M3
    # alone. M2 40 % too shallow read as M2 -26.7 % with M3 +26.7 %, a point anywhere
    # along the valley; M3 alone cannot explain it within +-50 %, M2 alone can.
    two = np.random.default_rng(9).choice(np.array([5, 6], np.uint8), (N, N), p=[0.75, 0.25])
    orders = np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij")
    window = plate_far_field(plate_phase(two, L, PlateFaults(etch_errors=(0, eps, 0))))(*orders)
    fit = fit_etch_errors(window, 1e-4 * window.max() + 0.01 * window, two, L)
    assert fit["mask_chi2"][1] > 9 > fit["mask_chi2"][2]
    assert fit["eps"] == pytest.approx([0.0, eps, 0.0], abs=0.005)
    assert fit["psf"] == pytest.approx(window / window.sum(), abs=1e-6)


def test_the_joint_etch_fit_of_a_design_using_one_mask():
    # levels 3 and 7 only: the deepest mask alone etches some pixels and not others
    two = np.random.default_rng(5).choice(np.array([3, 7], np.uint8), (N, N))
    orders = np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij")
    window = plate_far_field(plate_phase(two, L, PlateFaults(etch_errors=(0.2, 0.0, 0.0))))(*orders)
    fit = fit_etch_errors(window, 1e-4 * window.max() + 0.01 * window, two, L)
    assert fit["eps"] == pytest.approx([0.2, 0.0, 0.0], abs=2e-3)
    assert fit["mask_chi2"][0] == pytest.approx(fit["chi2_drop"]) and fit["chi2_drop"] > 100
    assert fit_etch_errors(window, None, np.full((N, N), 7, np.uint8), L) is None  # flat
    far = plate_far_field(plate_phase(two, L, PlateFaults(etch_errors=(0.7, 0.0, 0.0))))(*orders)
    assert fit_etch_errors(far, None, two, L)["at_search_edge"]  # beyond the +-50 % searched


@pytest.mark.parametrize("mask", [1, 2])
def test_the_etch_fit_of_each_shallower_mask_inverts_the_simulated_plate(levels, mask):
    orders = np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij")
    for eps in (-0.3, -0.1, 0.05, 0.25):
        errors = tuple(eps if j == mask else 0.0 for j in range(3))
        window = plate_far_field(plate_phase(levels, L, PlateFaults(etch_errors=errors)))(*orders)
        fits = [fit_etch_error(window, None, levels, L, j) for j in range(3)]
        assert fits[mask]["eps"] == pytest.approx(eps, abs=2e-3)
        assert fits[mask]["mask"] == ("M1_deep", "M2_mid", "M3_shallow")[mask]
        # the other masks' fits explain the window worse (an exact fit drops chi2 the most)
        assert max(fits, key=lambda f: f["chi2_drop"]) is fits[mask]


def test_implied_deep_etch_error_inverts_the_simulated_plate(levels):
    for eps in (-0.2, -0.1, 0.05, 0.15):
        far = plate_far_field(plate_phase(levels, L, PlateFaults(etch_errors=(eps, 0.0, 0.0))))
        window = far(*np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij"))
        fit = fit_etch_error(window, None, levels, L)
        assert fit["eps"] == pytest.approx(eps, abs=2e-3)
        assert implied_deep_etch_error(levels, L, float(far(0, 0)), fit["eps"]) == pytest.approx(
            eps, abs=1e-6
        )


def test_deep_etch_fit_is_none_when_the_deep_mask_is_unused():
    upper = np.random.default_rng(4).integers(L // 2, L, (N, N)).astype(np.uint8)
    assert fit_etch_error(np.ones((K, K)), None, upper, L) is None
    # nor does the zero order tell an etch error of a mask that etches nothing
    assert implied_deep_etch_error(upper, L, 0.01) is None


def test_zero_order_follows_the_analytic_deep_etch_law():
    """A balanced random 8-level tile has no zero order; the deep mask etches the pixels
    of levels 0..3 (a quarter of the tile each... half in all), so an error eps leaves
    |C|^2 |exp(-i pi eps) - 1|^2 = 4 |C|^2 sin^2(pi eps / 2) with
    |C| = |sum_{l<4} exp(i pi l / 4)| / 8, i.e. about 1.05 eps^2."""
    n = 64
    lv = np.random.default_rng(3).permutation(np.arange(n * n) % L).reshape(n, n)
    lv = lv.astype(np.uint8)
    c = abs(np.exp(1j * np.pi * np.arange(4) / 4).sum()) / 8
    assert design_order_power(lv, L)[0, 0] == pytest.approx(0, abs=1e-20)
    for eps in (0.02, 0.05, 0.15):
        far = plate_far_field(plate_phase(lv, L, PlateFaults(etch_errors=(eps, 0.0, 0.0))))
        z = float(far(0, 0))
        assert z == pytest.approx(4 * c**2 * np.sin(np.pi * eps / 2) ** 2, rel=1e-9)
        # The zero order alone cannot tell too deep from too shallow here.
        assert abs(implied_deep_etch_error(lv, L, z)) == pytest.approx(eps, rel=1e-6)
    assert c**2 * np.pi**2 == pytest.approx(1.05, abs=0.01)


def test_plate_far_field_conserves_power_and_matches_the_contract(levels):
    # sum_k sinc^2(x + k) = 1: all orders together carry the whole beam; a sum
    # truncated at |m|, |n| <= M n misses about 2 / (pi^2 M) of it (sin^2 averages 1/2).
    small = np.random.default_rng(8).integers(0, L, (8, 8)).astype(np.uint8)
    far = plate_far_field(plate_phase(small, L))
    for reach in (40, 80):
        m = np.arange(-reach * 8, reach * 8 + 1)
        total = far(m[:, None], m[None, :]).sum()
        assert 1 - total == pytest.approx(2 / (np.pi**2 * reach), rel=0.05)
    psf, _ = simulate_levels(levels, L, K)
    far = plate_far_field(plate_phase(levels, L))
    window = far(*np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij"))
    env = np.sinc((np.arange(K) - K // 2) / N) ** 2
    flat = window / np.outer(env, env)
    assert np.allclose(flat / flat.sum(), psf)


def test_capture_with_the_zero_order_far_outside_the_frame_has_every_dot(levels):
    # The orders drawn reached hypot(h, w) / pitch from the zero order, wherever it
    # was: 300 px above and left of a 201 px frame, most of the frame stayed dark.
    from scipy import ndimage

    sim = simulate_capture(
        levels, L, pitch_px=PITCH_PX, shape=(201, 201), centre=(-300.0, -300.0), bits=16,
        full_well_e=1e10, read_noise_dn=0, dark_level_dn=0, seed=0,
    )  # fmt: skip
    # Lattice sites with a whole spot inside the frame: 18 x 18 of them.
    sites = np.arange(-60, 60) * PITCH_PX - 300.0
    inside = np.count_nonzero((sites > 1) & (sites < 199))
    _, dots = ndimage.label(sim["capture"] > 0)
    assert inside == 18 and dots >= 0.95 * inside**2


def test_plate_far_field_refuses_a_tile_that_is_not_square():
    with pytest.raises(ValueError, match="square"):
        plate_far_field(np.zeros((8, 12)))


def test_repair_pixels_uses_the_neighbour_median():
    img = np.arange(25, dtype=np.float32).reshape(5, 5)
    img[1, 1] = 500.0  # a bright neighbour (a dot's peak): a mean of the neighbours follows it
    bad = np.zeros((5, 5), bool)
    bad[2, 2] = True
    img2 = img.copy()
    img2[2, 2] = 1e6
    out = repair_pixels(img2, bad)
    assert out[2, 2] == np.median(np.delete(img[1:4, 1:4].ravel(), 4))
    assert img2[2, 2] == 1e6  # the argument is not modified


def test_hot_pixels_are_flagged_from_the_dark_and_the_dark_subtracted(levels):
    sim = simulate_capture(
        levels, L, pitch_px=PITCH_PX, shape=(300, 300), seed=19, hot_pixels=25, bits=16
    )
    cap = condition_capture(
        RawImage(sim["capture"], 65535.0, None), RawImage(sim["dark"], 65535.0, None)
    )
    assert cap.hot.sum() >= 20
    assert np.array_equal(cap.image, sim["capture"].astype(np.float32) - sim["dark"])


def test_full_size_tile_n175(tmp_path):
    """The contract's N = 175 tile: the frame holds less than one period of orders."""
    lv = np.random.default_rng(175).integers(0, L, (175, 175)).astype(np.uint8)
    code, report, sim = run_verify(
        tmp_path, lv, dict(seed=20, shape=(700, 700), rotation_deg=1.5, centre=(320.4, 371.1))
    )
    assert code == 0, report["diagnosis"]
    assert np.allclose(report["zero_order_px"], sim["zero_order_px"], atol=0.3)


def _grid(sim):
    raw = RawImage(sim["capture"] >> 4, 4095.0, None)
    cap = condition_capture(raw, RawImage(sim["dark"] >> 4, 4095.0, None))
    lattice, _ = register_lattice(cap.image, PITCH_PX)
    return measure_orders(cap.image, lattice, cap.saturated)


@pytest.fixture(scope="module")
def designed():
    """A retrieved, high-efficiency design (most light in the window, weak outside)."""
    from doe.retrieval import retrieve_phase
    from doe.targets import make_target

    return retrieve_phase(make_target("asymmetric", K), N, L, seed=0).levels


def test_designed_plate_passes(tmp_path, designed):
    code, report, sim = run_verify(
        tmp_path, designed, dict(seed=21, rotation_deg=-1.5, centre=(280.2, 310.6), scale=1.02)
    )
    assert code == 0, report["diagnosis"]
    assert np.allclose(report["zero_order_px"], sim["zero_order_px"], atol=0.3)
    assert report["efficiency"] == pytest.approx(report["design_efficiency"], abs=0.03)
    assert report["zero_order"] == pytest.approx(report["design_zero_order"], abs=0.005)


def fitted_plate_panels(saved_figures):
    """Return the title of verify.png's fitted-plate panel and the largest difference of the
    measured PSF from the design and from the fitted plate (each over its peak)."""
    (fig,) = [f for f in saved_figures if f.axes[0].get_title().startswith("capture")]
    panels = {ax.get_title(): ax for ax in fig.axes if ax.get_images()}
    assert len(panels) == 6 and all(ax.get_images()[0].colorbar for ax in panels.values())
    (title,) = [t for t in panels if t.startswith("fitted plate: ")]
    design = np.abs(panels["difference (each / its peak)"].get_images()[0].get_array()).max()
    fitted = panels["difference from the fitted plate (same scale)"].get_images()[0].get_array()
    return title, design, np.abs(fitted).max()


@pytest.mark.parametrize("eps", [0.15, -0.15])
def test_designed_plate_with_deep_etch_error_fails(tmp_path, designed, eps, saved_figures):
    code, report, sim = run_verify(
        tmp_path, designed, dict(seed=22, faults=PlateFaults(etch_errors=(eps, 0.0, 0.0)))
    )
    assert code == 1
    # Which way the zero order moves depends on the design; the window fit sees both.
    assert "deep_etch_error" in report["diagnosis"]
    assert report["deep_etch_error_fit"] == pytest.approx(eps, abs=0.02)
    assert report["implied_deep_etch_error"] == pytest.approx(eps, abs=0.02)
    if float(sim["order_power"](0, 0)) > report["design_zero_order"] + 0.02:
        assert "zero_order_excess" in report["diagnosis"]
    # the report's table gives the fit with its sign (it showed 0.15 for a too shallow etch)
    html = (tmp_path / "out" / "verify_report.html").read_text()
    row = re.search(r"deep-etch depth error fitted[^<]*</td><td>([^<]*)</td>", html)
    assert float(row[1]) == pytest.approx(eps, abs=0.02)
    # verify.png shows the plate with the fitted error: what the design left, it explains
    title, from_design, from_fitted = fitted_plate_panels(saved_figures)
    way = "deep" if eps > 0 else "shallow"
    assert re.fullmatch(rf"fitted plate: the deepest mask etched 1\d\.\d% too {way}", title)
    assert from_fitted < from_design / 3


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


def test_designed_conjugate_plate_fails(tmp_path, designed):
    code, report, _ = run_verify(
        tmp_path, designed, dict(seed=23, faults=PlateFaults(conjugate=True))
    )
    assert code == 1 and report["diagnosis"] == ["conjugate_plate"]


@pytest.mark.parametrize("fault", ["conjugate", "mirrored"])
def test_a_reflected_plate_is_measured_as_what_it_is(tmp_path, designed, fault):
    # Its figures were taken where the design would put its zero order, three orders
    # off: a 20 % "zero order", an "implied deep-etch error" of 338 nm, and a
    # measured_psf.npy that matched neither the design nor the plate.
    from doe.fraunhofer import correlation

    if fault == "conjugate":
        plate, faults, code_name = L - 1 - designed, PlateFaults(conjugate=True), "conjugate_plate"
    else:
        plate = np.ascontiguousarray(designed[:, ::-1])
        faults, code_name = PlateFaults(other_levels=plate), "mirrored"
    sim_kwargs = dict(seed=24, faults=faults, centre=(280.2, 310.6))
    code, report, sim = run_verify(tmp_path, designed, sim_kwargs)
    assert code == 1 and report["diagnosis"] == [code_name]
    assert np.allclose(report["zero_order_px"], sim["zero_order_px"], atol=0.3)
    measured = read_psf(tmp_path / "out" / "measured_psf.npy")
    assert correlation(measured, simulate_levels(plate, L, K)[0]) > 0.99
    assert report["correlation"] < 0.9  # still compared with the design
    # a reflection of the design has its efficiency and zero order
    assert report["efficiency"] == pytest.approx(report["design_efficiency"], abs=0.03)
    assert report["zero_order"] == pytest.approx(report["design_zero_order"], abs=0.005)
    html = (tmp_path / "out" / "verify_report.html").read_text()
    assert html.count("<td>not judged</td>") == 5


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


def test_designed_plate_of_another_design_fails(tmp_path, designed):
    from doe.retrieval import retrieve_phase
    from doe.targets import make_target

    other = retrieve_phase(make_target("anisotropic", K), N, L, seed=3).levels
    code, report, _ = run_verify(
        tmp_path, designed, dict(seed=25, faults=PlateFaults(other_levels=other))
    )
    assert code == 1 and report["diagnosis"] == ["other_design"]
    assert not any("the orders match the design seen with" in n for n in report["notes"])


def test_an_orientation_hint_never_names_the_orientation_given(monkeypatch):
    # The deep mask 12 um off once failed as other_design with the orders outside the
    # window matching the design as seen: "verify again with --orientation as-designed",
    # the flag just used, would have sent the lab round in a circle.
    import fab.verify.analysis
    from fab.commands.verify import _orientation_hint

    design = dataclasses.make_dataclass("D", ["levels", "n_levels", "kernel_size"])(0, L, K)
    result = {"diagnosis": ["other_design"]}
    matching = ["as-designed", "mirror-x"]
    monkeypatch.setattr(fab.verify.analysis, "orientations_matching", lambda *args: matching)
    hint = _orientation_hint(result, None, design, "as-designed")
    assert "--orientation mirror-x" in hint and "as-designed" not in hint
    matching = ["as-designed"]
    assert _orientation_hint(result, None, design, "as-designed") is None


def test_a_mask_12um_off_is_said_to_lie_beyond_the_overlay_reach(tmp_path, designed):
    # 12 um = 2.4 mask pixels: past the 2 an overlay is named in, fitted at 2.49 (the
    # capture simulated on a 1/4 px grid: 2.5). It was other_design, the lab told that
    # another plate had arrived.
    faults = PlateFaults(overlay=((0.0, 12e-6), (0.0, 0.0), (0.0, 0.0)))
    code, report, _ = run_verify(tmp_path, designed, dict(seed=11, faults=faults, supersample=4))
    assert code == 1 and "other_design" not in report["diagnosis"]
    assert "psf_mismatch" in report["diagnosis"] and "overlay_error" not in report["diagnosis"]
    assert report["overlay_error_fit"]["shift_px"] == pytest.approx([2.5, 0.0], abs=0.02)
    assert any("beyond the 2 mask pixels" in note for note in report["notes"])


def verify_faulty_plate(tmp_path, levels, faults, seed, acceptance=None, supersample=1, **manifest):
    """Verify a simulated capture (and dark) of a plate of ``levels`` with ``faults``.

    ``manifest`` adds keys to the design folder's fab_manifest.json. Returns the exit
    code, the verify.json content and the output folder.
    """
    design = make_design_dir(tmp_path / "design", levels, acceptance=acceptance)
    manifest_file = design / "fab_manifest.json"
    write_json(manifest_file, {**json.loads(manifest_file.read_text()), **manifest})
    sim = simulate_capture(
        levels, L, pitch_px=PITCH_PX, seed=seed, faults=faults, supersample=supersample
    )
    write_image(tmp_path / "c.png", sim["capture"], exposure=0.01)
    write_image(tmp_path / "d.png", sim["dark"], exposure=0.01)
    out = tmp_path / "out"
    code = main(["verify", str(design), str(tmp_path / "c.png"), "--dark", str(tmp_path / "d.png"),
                 "--out", str(out)])  # fmt: skip
    return code, json.loads((out / "verify.json").read_text()), out


@pytest.mark.parametrize("mask, name", [(0, "M1_deep"), (1, "M2_mid")])
def test_a_mask_8um_off_is_diagnosed_as_an_overlay_error(
    tmp_path, designed, mask, name, capsys, saved_figures
):
    # It failed as other_design: the lab was told the wrong plate had arrived.
    faults = PlateFaults(
        overlay=tuple((-3e-6, 8e-6) if j == mask else (0.0, 0.0) for j in range(3))
    )
    code, report, out = verify_faulty_plate(
        tmp_path, designed, faults, 11, STRICT_ACCEPTANCE, supersample=4, pixel_pitch_nm=4990
    )
    assert code == 1 and report["diagnosis"][:2] == ["overlay_error", "psf_mismatch"]
    fit = report["overlay_error_fit"]
    # the simulation rounds the shift to quarter pixels: 8 um -> 1.5 px, -3 um -> -0.5 px
    assert fit["mask"] == name and fit["shift_px"] == pytest.approx([1.5, -0.5], abs=0.05)
    assert np.allclose(fit["shift_um"], np.multiply(fit["shift_px"], 4.99))
    assert fit["correlation"] > 0.999 > report["correlation"]
    # recorded, as the etch fits record theirs: the unit of its significance past 1
    assert fit["reduced_chi2"] == pytest.approx(fit["chi2"] / (K * K - 3))
    assert report["measured_psf_usable"] is True  # the real plate's PSF, to calibrate with
    err = capsys.readouterr().err
    sd = fit["shift_sigma_um"]  # quoted with the shift: its 1-sigma from the fit's curvature
    assert 0 < max(sd) < 0.25
    assert re.search(rf"mask {name} printed off the other masks by \+7\.\d\d ± {sd[0]:.2f} um "
                     rf"in y \(up\) and -2\.\d\d ± {sd[1]:.2f} um in x \(right\)", err)  # fmt: skip
    html = (out / "verify_report.html").read_text()
    assert re.search(rf"{name} by y \+1\.5\d, x -0\.\d\d mask pixels "
                     r"\(\+7\.\d\d um, -2\.\d\d um\); correlation 0\.99\d\d with that "
                     r"plate \(frame [01]\.\d\d\d\)", html)  # fmt: skip
    assert fit["frame_correlation"] > 0.99
    title, from_design, from_fitted = fitted_plate_panels(saved_figures)
    assert re.fullmatch(rf"fitted plate: {name} shifted y \+1\.5\d, x -0\.\d\d mask px", title)
    assert from_fitted < from_design / 3


def test_a_dense_design_with_a_mask_off_is_an_overlay_error_not_another_design(tmp_path, levels):
    # Every order of a dense design changes with the overlay: its frame correlation
    # with the design (0.44) called a 2 um overlay another design. The fitted plate's
    # frame correlation is taken too.
    faults = PlateFaults(overlay=((0.0, 0.0), (-1e-6, 2e-6), (0.0, 0.0)))
    code, report, _ = run_verify(tmp_path, levels, dict(seed=13, faults=faults, supersample=4))
    assert code == 1 and report["diagnosis"][:2] == ["overlay_error", "psf_mismatch"]
    fit = report["overlay_error_fit"]
    assert report["frame_correlation"]["design"] < 0.8 < 0.99 < fit["frame_correlation"]
    assert fit["mask"] == "M2_mid" and fit["shift_px"] == pytest.approx([0.5, -0.25], abs=0.05)


def test_an_overlay_within_the_thresholds_is_not_fitted(tmp_path, designed):
    # 1 um of the mid mask: the PSF passes, so nothing needs explaining.
    faults = PlateFaults(overlay=((0.0, 0.0), (0.0, 1e-6), (0.0, 0.0)))
    code, report, _ = run_verify(tmp_path, designed, dict(seed=12, faults=faults, supersample=4))
    assert code == 0 and report["overlay_error_fit"] is None
    html = (tmp_path / "out" / "verify_report.html").read_text()
    assert "not fitted" in html


@pytest.mark.parametrize("eps, way", [(0.2, "deep"), (-0.3, "shallow")])
def test_a_mid_etch_off_its_depth_is_diagnosed_and_named(
    tmp_path, designed, capsys, saved_figures, eps, way
):
    # It failed as a bare psf_mismatch: only the deepest etch was fitted, so the lab
    # was not told which of the three etches to measure.
    faults = PlateFaults(etch_errors=(0.0, eps, 0.0))
    code, report, out = verify_faulty_plate(tmp_path, designed, faults, 22, STRICT_ACCEPTANCE)
    assert code == 1 and report["diagnosis"] == ["etch_depth_error", "psf_mismatch"]
    fit = report["etch_error_fit"]
    assert fit["masks"] == ["M1_deep", "M2_mid", "M3_shallow"]
    assert fit["errors"] == pytest.approx([0.0, eps, 0.0], abs=0.02)
    # the manifest's depths, deepest first
    assert fit["errors_nm"] == pytest.approx(np.multiply(fit["errors"], [717.6, 358.8, 179.4]))
    assert fit["correlation"] > 0.999 > report["correlation"] and fit["frame_correlation"] > 0.99
    assert report["measured_psf_usable"] is True
    hint = re.search(
        r"off their depth: M2_mid (\d+\.\d)% ± (\d\.\d)% too (\w+) \(([+-]\d+\.\d) nm\) \(",
        capsys.readouterr().err,
    )  # fmt: skip  (M2 alone: the others need no error)
    assert hint and float(hint[1]) == pytest.approx(100 * abs(eps), abs=2) and hint[3] == way
    assert float(hint[2]) == pytest.approx(100 * fit["errors_sigma"][1], abs=0.06)
    assert 0 < fit["errors_sigma"][1] < 0.02  # a dense window pins the error down
    assert float(hint[4]) == pytest.approx(fit["errors_nm"][1], abs=0.06)
    html = (out / "verify_report.html").read_text()
    row = re.search(r"M2_mid ([+-]\d+\.\d)% ± \d\.\d% \([+-]\d+\.\d nm\) gain [\d.e+]+, M3_", html)
    assert row and float(row[1]) == pytest.approx(100 * fit["errors"][1], abs=0.06)
    title, from_design, from_fitted = fitted_plate_panels(saved_figures)
    shown = re.fullmatch(r"fitted plate: M2_mid etch ([+-]\d+\.\d)%", title)
    assert shown and float(shown[1]) == pytest.approx(100 * fit["errors"][1], abs=0.06)
    assert from_fitted < from_design / 3


@pytest.mark.parametrize(
    "errors, named",
    [
        ((0.0, 0.3, 0.0), ["M2_mid"]),  # the defaults
        ((0.0, 0.0, 0.3), ["M3_shallow"]),  # the strict acceptance
        ((-0.15, 0.25, 0.0), ["M1_deep", "M2_mid"]),  # two etches off at once
    ],
)
def test_a_dense_design_with_etches_off_names_those_masks(
    tmp_path, levels, saved_figures, errors, named
):
    acceptance = None if errors[1] == 0.3 else STRICT_ACCEPTANCE
    code, report, _ = verify_faulty_plate(
        tmp_path, levels, PlateFaults(etch_errors=errors), 22, acceptance
    )
    # (a random design's efficiency misses the strict acceptance's 0.5 as well)
    assert code == 1 and report["diagnosis"][0] == "etch_depth_error"
    assert ("deep_etch_error" in report["diagnosis"]) == ("M1_deep" in named)
    fit = report["etch_error_fit"]
    assert fit["errors"] == pytest.approx(errors, abs=0.02)
    off = zip(fit["masks"], fit["errors"], strict=True)
    assert etched_off(fit) == [(m, e) for m, e in off if m in named]
    title, from_design, from_fitted = fitted_plate_panels(saved_figures)
    shown = re.findall(r"(M\d_\w+) etch ([+-]\d+\.\d)%", title)
    assert [m for m, _ in shown] == named and from_fitted < from_design / 3


@pytest.mark.parametrize(
    "faults, codes, mask, shift_px, errors",
    [
        (  # M1 8 um off (1.5 px as simulated) with the mid etch 30 % too deep
            PlateFaults(etch_errors=(0.0, 0.3, 0.0),
                        overlay=((0.0, 8e-6), (0.0, 0.0), (0.0, 0.0))),
            ["overlay_error", "etch_depth_error"], "M1_deep", (1.5, 0.0), (0.0, 0.3),
        ),
        (  # M2 5 um up, 3 um left (1, -0.5 px) with the deep etch 20 % too deep
            PlateFaults(etch_errors=(0.2, 0.0, 0.0),
                        overlay=((0.0, 0.0), (-3e-6, 5e-6), (0.0, 0.0))),
            ["overlay_error", "deep_etch_error"], "M2_mid", (1.0, -0.5), (0.2, 0.0),
        ),
    ],
)  # fmt: skip
def test_a_plate_with_an_overlay_and_an_etch_off_names_both(
    tmp_path, designed, capsys, saved_figures, faults, codes, mask, shift_px, errors
):
    # The first failed as a bare psf_mismatch, the second as deep_etch_error alone.
    code, report, _ = verify_faulty_plate(
        tmp_path, designed, faults, 22, STRICT_ACCEPTANCE, supersample=4, pixel_pitch_nm=4990
    )
    assert code == 1 and report["diagnosis"] == [*codes, "psf_mismatch"]
    fit = report["overlay_and_etch_fit"]
    assert fit["mask"] == mask and fit["shift_px"] == pytest.approx(shift_px, abs=0.05)
    assert fit["errors"][:2] == pytest.approx(errors, abs=0.02)
    assert fit["shift_um"] == pytest.approx(np.multiply(fit["shift_px"], 4.99))
    assert fit["errors_nm"] == pytest.approx(np.multiply(fit["errors"], [717.6, 358.8, 179.4]))
    assert (
        fit["correlation"]
        > 0.999
        > max(report["overlay_error_fit"]["correlation"], report["etch_error_fit"]["correlation"])
    )
    err = capsys.readouterr().err
    assert f"mask {mask} printed off the other masks by" in err and "off their depth: " in err
    sd = fit["shift_sigma_um"]  # the shift quoted with its 1-sigma, in um
    assert 0 < max(sd) < 0.5 and f"{fit['shift_um'][0]:+.2f} ± {sd[0]:.2f} um in y" in err
    assert all(0 <= e < 0.02 for e in fit["errors_sigma"])
    title, from_design, from_fitted = fitted_plate_panels(saved_figures)
    assert title.startswith(f"fitted plate: {mask} shifted y +1.") and " etch +" in title
    assert from_fitted < from_design / 3


def _overlay_and_etch_of(window, sigma, levels):
    """The overlay-and-etch fit of a window, started from the two fits alone."""
    from fab.verify.analysis import _overlay_and_etch_fit
    from fab.verify.overlay import fit_overlay_error

    overlay = fit_overlay_error(window, sigma, levels, L)
    etch = fit_etch_errors(window, sigma, levels, L)
    result = {
        "overlay_error_fit": {**overlay, "significance": overlay["chi2_drop"]},
        "etch_error_fit": {"masks": etch["masks"], "errors": list(etch["eps"]),
                           "significance": etch["chi2_drop"], "chi2": etch["chi2"]},
    }  # fmt: skip
    measured = np.clip(window, 0, None) / np.clip(window, 0, None).sum()
    both = _overlay_and_etch_fit(result, measured, (window, sigma), lambda p: 1.0, levels, L)
    return overlay, both


def test_an_overlay_and_etch_fit_of_a_plate_with_an_overlay_alone_is_worth_nothing(designed):
    # Its significance is its gain over the better fit alone: a second fault the plate
    # does not have is worth a chi-square of noise, not the whole window's.
    faults = PlateFaults(overlay=((0.0, 0.0), (-0.5, 1.25), (0.0, 0.0)))
    orders = np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij")
    plate = plate_phase(designed, L, faults, mask_pixel_pitch=1.0, supersample=4)
    window = plate_far_field(plate)(*orders)
    sigma = 1e-4 * window.max() + 0.01 * window
    overlay, fit = _overlay_and_etch_of(window, sigma, designed)
    assert fit["shift_px"] == pytest.approx([1.25, -0.5], abs=0.02)
    assert fit["errors"] == pytest.approx([0, 0, 0], abs=0.01)
    assert fit["significance"] < 9 < overlay["chi2_drop"]
    # and in units of its reduced chi-square, as the fits alone are: with sigmas quoted
    # 2x short, each fit's gain shrinks by its own reduced chi-square, not the same one
    noisy = window + np.random.default_rng(5).normal(0, 1, window.shape) * sigma
    honest, short = (_overlay_and_etch_of(noisy, s, designed)[1] for s in (sigma, sigma / 2))
    raw = honest["significance"] * max(honest["reduced_chi2"], 1.0)
    assert short["reduced_chi2"] > 1
    assert short["significance"] == pytest.approx(4 * raw / short["reduced_chi2"], rel=1e-3)


@pytest.mark.parametrize("eps", [-0.3, 0.45])
def test_a_dense_design_with_its_deep_etch_off_is_a_deep_etch_error_not_another_design(
    tmp_path, levels, eps
):
    # Every order of a dense design changes with the deepest etch: its frame correlation
    # with the design (0.77 at 30 %) called the plate another design, although the etch
    # fit explains its window (0.9998). The fitted plate's frame counts too.
    faults = PlateFaults(etch_errors=(eps, 0.0, 0.0))
    code, report, _ = verify_faulty_plate(tmp_path, levels, faults, 11)
    assert code == 1 and "deep_etch_error" in report["diagnosis"]
    assert "other_design" not in report["diagnosis"]
    assert report["deep_etch_error_fit"] == pytest.approx(eps, abs=0.02)
    assert (
        report["frame_correlation"]["design"] < 0.8 < report["etch_error_fit"]["frame_correlation"]
    )


def test_a_deep_etch_at_its_tolerance_that_fails_a_dense_design_is_named(tmp_path, levels):
    # -10 % failed the PSF (correlation 0.61) as a bare psf_mismatch, and +10 % was named
    # only because the fit's grid read 0.10000000000000053
    for eps in (-0.1, 0.1):
        faults = PlateFaults(etch_errors=(eps, 0.0, 0.0))
        code, report, _ = verify_faulty_plate(tmp_path / str(eps), levels, faults, 11)
        # (+10 % also brightens the zero order; the joint etch fit's 0.6 % of M2 is noise)
        expected = ["deep_etch_error", "psf_mismatch"]
        assert (
            code == 1 and [c for c in report["diagnosis"] if c != "zero_order_excess"] == expected
        )
        assert report["deep_etch_error_fit"] == pytest.approx(eps, abs=0.005)


@pytest.fixture(scope="module")
def sparse():
    from doe.retrieval import retrieve_phase
    from doe.targets import make_target

    return retrieve_phase(make_target("sparse_dots", K), 175, L, seed=0).levels


@pytest.mark.parametrize("eps", [0.3, 0.45])
def test_a_mid_etch_that_only_brightens_the_zero_order_is_named(tmp_path, sparse, eps, capsys):
    # M2 30-45 % too deep leaves a sparse design's PSF within the thresholds (0.97-0.99)
    # and brightens its zero order. The etches were fitted only for a failing PSF, so the
    # lab read zero_order_excess alone; at 45 % the deepest etch's own fit (+10.3 %, past
    # its tolerance) named deep_etch_error, the wrong mask.
    faults = PlateFaults(etch_errors=(0.0, eps, 0.0))
    code, report, _ = verify_faulty_plate(tmp_path, sparse, faults, 11)
    assert report["correlation"] > 0.95 and report["rmse"] < 0.05  # the PSF within
    assert code == 1 and report["diagnosis"] == ["zero_order_excess", "etch_depth_error"]
    fit = report["etch_error_fit"]
    assert [name for name, _ in etched_off(fit)] == ["M2_mid"]
    assert fit["errors"][1] == pytest.approx(eps, abs=0.03)
    assert "M2_mid" in capsys.readouterr().err


@pytest.fixture(scope="module")
def default_design():
    # the default run's levels.npy (doefab run --out out, a3e3e7a): nearly point-symmetric
    return np.load(Path(__file__).parents[2] / "data" / "default_levels.npy")


def test_a_big_etch_error_is_not_read_as_a_mirrored_plate(tmp_path, default_design):
    # The deepest etch 45 % too deep gave the bare design a reduced chi-square of 40; a
    # mirror fitted the frame better, the plate was measured at the mirror's zero order
    # and read as mirrored (or as another design). The lab would have turned the plate.
    faults = PlateFaults(etch_errors=(0.45, 0.0, 0.0))
    code, report, _ = verify_faulty_plate(tmp_path, default_design, faults, 11)
    assert code == 1 and report["diagnosis"] == ["deep_etch_error", "psf_mismatch"]
    assert report["measured_as"] == "design" and report["reflection_set_aside"] == "mirror-y"
    assert report["deep_etch_error_fit"] == pytest.approx(0.45, abs=0.01)
    assert any(
        "(mirror-y)" in note and "measured as the design" in note for note in report["notes"]
    )


def test_a_big_mid_etch_error_does_not_leave_the_zero_order_ambiguous(tmp_path, default_design):
    # M2 45 % too shallow left a mirror within 9 in chi-square of the bare design:
    # zero_order_ambiguous, though the fitted etch explained the window at 0.9999.
    faults = PlateFaults(etch_errors=(0.0, -0.45, 0.0))
    code, report, _ = verify_faulty_plate(tmp_path, default_design, faults, 11, STRICT_ACCEPTANCE)
    assert abs(report["zero_order_search"]["delta_chi2"]["mirror-y"]) < 25  # the mirror near
    assert code == 1 and report["diagnosis"] == ["etch_depth_error", "psf_mismatch"]
    assert report["etch_error_fit"]["errors"][1] == pytest.approx(-0.45, abs=0.01)
    assert report["reflection_set_aside"] is None


def test_a_diagonal_overlay_does_not_leave_the_zero_order_ambiguous(tmp_path, designed):
    # M2 one mask pixel off in y and in x left the conjugate within 3 of the bare design
    faults = PlateFaults(overlay=((0.0, 0.0), (5e-6, 5e-6), (0.0, 0.0)))
    code, report, _ = verify_faulty_plate(
        tmp_path, designed, faults, 11, supersample=4, pixel_pitch_nm=4990
    )
    assert abs(report["zero_order_search"]["delta_chi2"]["rot180"]) < 25
    assert code == 1 and report["diagnosis"][0] == "overlay_error"
    fit = report["overlay_error_fit"]
    assert fit["mask"] == "M2_mid" and fit["shift_px"] == pytest.approx([1.0, 1.0], abs=0.05)


def test_a_conjugate_plate_of_a_nearly_symmetric_design_stays_conjugate(tmp_path, default_design):
    # no fitted fault of the design explains a conjugate plate: the reflection stands
    code, report, _ = verify_faulty_plate(tmp_path, default_design, PlateFaults(conjugate=True), 11)
    assert code == 1 and report["diagnosis"] == ["conjugate_plate"]
    assert report["measured_as"] == "rot180" and report["reflection_set_aside"] is None


def test_a_near_delta_design_s_mid_etch_off_is_named_not_another_design(tmp_path):
    # M2 30 % too shallow put 97.6 % of the beam in the zero order of a near-delta
    # design (0.898); the rest, near the noise, correlated at 0.21 with the design's
    # frame: other_design, though the window matched at 0.9995. The fitted plate lights
    # its zero order alone, which leaves the frame nothing to judge.
    from doe.retrieval import retrieve_phase
    from doe.targets import make_target

    delta = retrieve_phase(make_target("near_delta", K), 175, L, seed=0).levels
    faults = PlateFaults(etch_errors=(0.0, -0.3, 0.0))
    code, report, _ = verify_faulty_plate(tmp_path, delta, faults, 11)
    assert report["frame_correlation"]["design"] < 0.8 < report["correlation"]
    assert code == 1 and report["diagnosis"] == ["zero_order_excess", "etch_depth_error"]
    fit = report["etch_error_fit"]
    assert [name for name, _ in etched_off(fit)] == ["M2_mid"]
    assert abs(fit["errors"][1] + 0.3) < 2 * fit["errors_sigma"][1] < 0.1


def test_a_zero_order_as_bright_as_the_design_s_own_runs_no_fault_fit(tmp_path, sparse):
    # An absolute zero_order_max below the design's own zero order fails a perfect plate;
    # there is no plate fault to look for (a noise fit of a perfect blob plate was named
    # a 0.19 px overlay once the fits ran on the zero order).
    code, report, _ = verify_faulty_plate(tmp_path, sparse, PlateFaults(), 11, STRICT_ACCEPTANCE)
    assert code == 1 and report["diagnosis"] == ["zero_order_excess"]
    assert report["zero_order"] > STRICT_ACCEPTANCE["zero_order_max"]
    assert report["overlay_error_fit"] is None and report["etch_error_fit"] is None


@pytest.mark.parametrize("design", ["blob", "random"])
def test_an_overlay_beyond_the_fit_reach_is_not_named_but_said(tmp_path, levels, design, capsys):
    # 11 um of a mask (2.25 mask pixels, past the 2 an overlay is named in). On a search
    # that ended at 2 px the fit stopped at or inside it: on the blob the mid etch's fit
    # (0.998, within the strict thresholds) was named instead; on a random design the
    # overlay was named 0.3 px short. The search now goes to 2.5 px and finds 2.25.
    from doe.retrieval import retrieve_phase
    from doe.targets import make_target

    if design == "blob":
        tile = retrieve_phase(make_target("compact_blob", K), 175, L, seed=0).levels
        mask, acceptance = 0, STRICT_ACCEPTANCE
    else:
        tile, mask, acceptance = levels, 1, None
    faults = PlateFaults(overlay=tuple((0.0, 11e-6) if j == mask else (0.0, 0.0) for j in range(3)))
    code, report, _ = verify_faulty_plate(
        tmp_path, tile, faults, 11, acceptance, supersample=4, pixel_pitch_nm=4990
    )
    fit = report["overlay_error_fit"]
    assert fit["mask"] == ("M1_deep", "M2_mid")[mask]
    truth = round(11 / 4.99 * 4) / 4  # the shift as simulated, on the 1/4 px grid
    assert fit["shift_px"] == pytest.approx([truth, 0.0], abs=0.05)
    assert code == 1 and "psf_mismatch" in report["diagnosis"]
    named = {"etch_depth_error", "overlay_error", "deep_etch_error", "other_design"}
    assert not named & set(report["diagnosis"])
    err = capsys.readouterr().err
    assert f"mask {fit['mask']} printed off the other masks by +{truth * 4.99:.1f}" in err
    assert "beyond the 2 mask pixels" in err


def test_clipped_14bit_capture_is_flagged_saturated(tmp_path, levels):
    """A 16-bit file from a 14-bit sensor (LSB-aligned): clipping shows as a plateau."""
    sim = simulate_capture(
        levels, L, pitch_px=PITCH_PX, seed=26, bits=16, peak_fraction=3.0, full_well_e=16383 * 2.0
    )
    clipped = np.minimum(sim["capture"], 16383).astype(np.uint16)
    design = make_design_dir(tmp_path / "design", levels)
    write_image(tmp_path / "cap.tif", clipped)
    code = main(["verify", str(design), str(tmp_path / "cap.tif"), "--out", str(tmp_path / "o")])
    report = json.loads((tmp_path / "o" / "verify.json").read_text())
    assert code == 1 and "saturated" in report["diagnosis"]


@pytest.mark.parametrize("bits", [10, 8])
def test_clipped_capture_msb_aligned_from_fewer_bits_is_flagged_saturated(tmp_path, levels, bits):
    """10-bit data shifted into 16 bits (low 6 bits zero), or 8-bit data scaled by 256."""
    top = (1 << bits) - 1
    sim = simulate_capture(
        levels, L, pitch_px=PITCH_PX, seed=27, bits=16, peak_fraction=3.0, full_well_e=top * 2.0
    )
    codes = np.minimum(sim["capture"], top).astype(np.uint16)
    clipped = int(np.count_nonzero(codes == top))
    assert clipped >= 3
    write_image(tmp_path / "cap.tif", codes << (16 - bits))
    raw = read_raw_image(tmp_path / "cap.tif")
    assert raw.full_scale == top << (12 - bits)  # the sensor's top code in 12-bit DN
    assert raw.quantum == 1 << (12 - bits)  # and its step
    assert np.count_nonzero(condition_capture(raw).saturated) == clipped
    design = make_design_dir(tmp_path / "design", levels)
    code = main(["verify", str(design), str(tmp_path / "cap.tif"), "--out", str(tmp_path / "o")])
    report = json.loads((tmp_path / "o" / "verify.json").read_text())
    assert code == 1 and "saturated" in report["diagnosis"]


@pytest.mark.parametrize("dark", [False, True])
def test_quiet_8bit_capture_of_a_good_plate_passes(tmp_path, levels, dark):
    """Read noise well below 1 DN: nearly all the background is one code (spread 0)."""
    kwargs = dict(seed=29, bits=8, read_noise_dn=0.2, dark_level_dn=3.0)
    code, report, sim = run_verify(tmp_path, levels, kwargs, dark=dark)
    background = sim["capture"][:40, :40]
    assert np.mean(background == np.median(background)) > 0.9
    assert code == 0, report and report["diagnosis"]
    assert report["window_snr"] > 10


# How a camera sees an image array: (orientation, image transform, centre transform).
CAMERAS = [
    ("as-designed", lambda a: a, lambda rc, hw: rc),
    ("transpose", lambda a: a.T, lambda rc, hw: (rc[1], rc[0])),
    (
        "antitranspose",
        lambda a: a[::-1, ::-1].T,
        lambda rc, hw: (hw[1] - 1 - rc[1], hw[0] - 1 - rc[0]),
    ),
]


@pytest.mark.parametrize("orientation, seen, centre_seen", CAMERAS, ids=[c[0] for c in CAMERAS])
def test_orientation_against_the_foundation_renderer(tmp_path, orientation, seen, centre_seen):
    """A blazed tile sends most light to order (m, n) = (-2, +3): up 2, right 3.

    The capture comes from doe.fraunhofer.dot_lattice_image (not this package's
    simulator), seen by the camera as numpy turns the array; with the camera's
    --orientation, the measured PSF must peak at [K//2 - 2, K//2 + 3] as simulate_levels.
    """
    from doe.fraunhofer import dot_lattice_image, level_phase

    r, c = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    blaze = (-2 * r + 3 * c) / N  # phase ramp of order (-2, 3), in cycles
    lv = np.floor(np.mod(blaze, 1) * L).astype(np.uint8)
    design_psf, _ = simulate_levels(lv, L, K)
    assert np.unravel_index(np.argmax(design_psf), design_psf.shape) == (K // 2 - 2, K // 2 + 3)
    img = dot_lattice_image(level_phase(lv, L), (500, 520), PITCH_PX, centre=(240.3, 262.8))
    img = img / img.max() * 3000 + np.random.default_rng(27).normal(20, 1.0, img.shape)
    design = make_design_dir(tmp_path / "design", lv)
    write_image(tmp_path / "cap.exr", np.ascontiguousarray(seen(img)).astype(np.float32))
    out = tmp_path / "o"
    args = ["--orientation", orientation, "--out", str(out)]
    code = main(["verify", str(design), str(tmp_path / "cap.exr"), *args])
    report = json.loads((out / "verify.json").read_text())
    psf = read_psf(out / "measured_psf.npy")
    assert np.unravel_index(np.argmax(psf), psf.shape) == (K // 2 - 2, K // 2 + 3)
    assert np.allclose(report["zero_order_px"], centre_seen((240.3, 262.8), img.shape), atol=0.3)
    assert report["correlation"] > 0.99
    assert code == 0, report["diagnosis"]


def test_hot_pixels_without_a_dark_frame_do_not_fail_a_good_plate(tmp_path, designed):
    code, report, sim = run_verify(tmp_path, designed, dict(seed=28, hot_pixels=150), dark=False)
    assert code == 0, report["diagnosis"]
    assert np.allclose(report["zero_order_px"], sim["zero_order_px"], atol=0.3)
    assert any("hot pixel" in n for n in report["notes"])
    assert report["efficiency"] == pytest.approx(report["design_efficiency"], abs=0.03)


@pytest.fixture(scope="module")
def registered_capture(levels):
    """A 16-bit capture of the plate (float32, read-only) and its registered lattice."""
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=29, shape=(300, 300), bits=16)
    image = sim["capture"].astype(np.float32)
    image.flags.writeable = False  # shared: each test works on its own copy
    return image, register_lattice(image, PITCH_PX)[0]


def test_spike_repair_keeps_dots_and_removes_stray_pixels(registered_capture):
    from fab.verify.lattice import repair_stray_spikes

    image, lattice = registered_capture
    spiked = image.copy()
    spiked[150 + 5, 150 + 5] += 5000  # half a pitch from every dot
    fixed, repaired = repair_stray_spikes(spiked, lattice)
    assert repaired[155, 155]
    assert abs(fixed[155, 155] - image[155, 155]) < 50
    # Real dots are untouched.
    u, v = np.meshgrid(np.arange(-5, 6), np.arange(-5, 6), indexing="ij")
    r, c = lattice.positions(u, v)
    r, c = np.rint(r).astype(int), np.rint(c).astype(int)
    assert np.array_equal(fixed[r, c], spiked[r, c])


def test_hot_pixel_of_the_dark_frame_on_a_dot_keeps_the_dot_light(tmp_path, levels):
    """Dark subtraction already takes a hot pixel's dark signal away; repairing it
    as well (median of neighbours) would take away the dot's peak."""
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=30, bits=16)
    design = make_design_dir(tmp_path / "design", levels)
    reports = []
    for name, hot in (("clean", 0), ("hot", 15000)):
        capture, dark = sim["capture"].astype(np.int64), sim["dark"].astype(np.int64)
        # the core pixel of the brightest dot in the K x K window of orders
        r0, c0 = np.rint(sim["zero_order_px"]).astype(int)
        reach = int(K // 2 * PITCH_PX) + 2
        box = capture[r0 - reach : r0 + reach + 1, c0 - reach : c0 + reach + 1]
        r, c = np.unravel_index(np.argmax(box), box.shape)
        r, c = r + r0 - reach, c + c0 - reach
        capture[r, c] += hot
        dark[r, c] += hot
        assert capture.max() < sim["full_scale"]
        write_image(tmp_path / f"{name}.tif", capture.astype(np.uint16))
        write_image(tmp_path / f"{name}_dark.tif", dark.astype(np.uint16))
        out = tmp_path / f"out_{name}"
        args = [str(tmp_path / f"{name}.tif"), "--dark", str(tmp_path / f"{name}_dark.tif")]
        assert main(["verify", str(design), *args, "--out", str(out)]) == 0
        reports.append(np.load(out / "measured_psf.npy"))
    clean, hot = reports
    assert np.abs(hot - clean).max() < 0.01 * clean.max()


def test_background_gradient_leaves_the_lattice_right(tmp_path, levels):
    """Stray light rising 400 DN across the frame (dots peak near 2900 DN)."""
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=31, centre=(301.3, 297.6))
    ramp = np.linspace(0.0, 400.0, sim["capture"].shape[1])[None, :]
    capture = np.rint((sim["capture"] >> 4) + ramp).astype(np.uint16)  # 12-bit DN
    assert capture.max() < 4095
    design = make_design_dir(tmp_path / "design", levels)
    write_image(tmp_path / "cap.png", capture)
    code = main(["verify", str(design), str(tmp_path / "cap.png"), "--out", str(tmp_path / "o")])
    report = json.loads((tmp_path / "o" / "verify.json").read_text())
    assert code == 0, report["diagnosis"]
    assert np.allclose(report["zero_order_px"], sim["zero_order_px"], atol=0.2)
    assert report["lattice"]["pitch_px"] == pytest.approx(PITCH_PX, rel=1e-3)


def test_spike_repair_leaves_the_wings_of_blurred_dots_alone(levels):
    from fab.verify.lattice import repair_stray_spikes

    sim = simulate_capture(
        levels, L, pitch_px=PITCH_PX, seed=32, shape=(300, 300), bits=16, blur_sigma_px=0.8
    )
    image = sim["capture"].astype(np.float32)
    lattice, _ = register_lattice(image, PITCH_PX)
    fixed, repaired = repair_stray_spikes(image, lattice)
    assert not repaired.any()
    assert np.array_equal(fixed, image)


def test_spike_repair_leaves_a_bright_scene_alone(registered_capture):
    # Stray light (2000 DN, shot noise) over 40 % of the frame: over a quarter of the
    # pixels stand out of the dark noise, a scene rather than a dot lattice, and its
    # grain (a local maximum every few pixels) is not hot pixels: nothing repaired.
    from fab.verify.lattice import repair_stray_spikes

    image, lattice = registered_capture
    lit = image.copy()
    lit[:, :120] += np.random.default_rng(5).poisson(2000.0, (300, 120)).astype(np.float32)
    fixed, repaired = repair_stray_spikes(lit, lattice)
    assert not repaired.any()
    assert np.array_equal(fixed, lit)


def test_pixel_noise_is_at_least_the_rounding_noise_of_the_codes():
    from fab.verify.lattice import pixel_noise

    assert pixel_noise(np.full(100, 7.0), quantum=4.0) == pytest.approx(4.0 / np.sqrt(12))
    assert pixel_noise(np.full(100, 7.0)) > 0  # float data: never a zero sigma
    noisy = np.random.default_rng(0).normal(0.0, 3.0, 10_000)
    assert pixel_noise(noisy, quantum=1.0) == pytest.approx(3.0, rel=0.05)


def test_registered_origin_is_the_lattice_point_nearest_the_image_centre(levels):
    # catches rounding the centre's lattice coordinates down: the origin up to a pitch off
    shape = (300, 300)
    zero = (np.array(shape) - 1) / 2 - 0.7 * PITCH_PX  # the centre lies 0.7 pitch down-right
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, shape=shape, centre=tuple(zero), seed=34)
    lattice, _ = register_lattice(sim["capture"] >> 4, PITCH_PX)
    # the order one step down and right lies 0.3 pitch from the centre on each axis
    assert np.allclose(lattice.origin, zero + PITCH_PX, atol=0.3)


def test_a_frame_narrower_than_4_pitches_is_refused():
    with pytest.raises(LatticeNotFound, match="image 300x40 px holds fewer than 4 dots across"):
        register_lattice(np.zeros((40, 300)), PITCH_PX)
    with pytest.raises(LatticeNotFound, match="check --pixel-pitch-um and --lattice-pitch-um"):
        register_lattice(np.zeros((40, 300)), PITCH_PX)


@pytest.mark.parametrize("scale, off", [(1.17, "+17%"), (0.83, "-17%")])
def test_dots_17_percent_off_the_nominal_pitch_are_refused(levels, scale, off):
    # within the neighbour search (0.8 to 1.18 pitches), beyond the 15 % allowed: the
    # camera pixel pitch given is wrong
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, scale=scale, shape=(300, 300), seed=1)
    with pytest.raises(LatticeNotFound, match=re.escape(f"{off} off the nominal 10.87 px")):
        register_lattice(sim["capture"], PITCH_PX)
    # a lens of another focal length: the flag that mends it is --lattice-pitch-um
    with pytest.raises(LatticeNotFound, match="give --lattice-pitch-um for a lens of another"):
        register_lattice(sim["capture"], PITCH_PX)


def test_dots_found_closer_than_photometry_needs_are_refused(levels):
    # nominally 4.6 px apart (enough), found 4.2 px apart (within 15 %, too close)
    sim = simulate_capture(levels, L, pitch_px=4.2, shape=(300, 300), seed=1)
    with pytest.raises(
        LatticeNotFound, match=re.escape("the dots are 4.2 px apart, closer than the 4.5")
    ):
        register_lattice(sim["capture"], 4.6)


@pytest.mark.parametrize(("scale", "rotation_deg"), [(0.87, 0.0), (1.12, 0.0), (1.08, 4.0)])
def test_a_plate_lighting_every_other_order_registers_off_the_nominal_pitch(scale, rotation_deg):
    # A tile of 2 x 2 copies has period N / 2: only even orders are lit, no dot has a
    # neighbour one pitch away, and the fit starts from the design's pitch. Allowed
    # to move it by 5 % at a time, it stopped between the two: the origin 4-5 px off
    # at 8-12 % magnification error, a good plate failed as other_design.
    quarter = np.random.default_rng(5).integers(0, L, (18, 18)).astype(np.uint8)
    sim = simulate_capture(
        np.tile(quarter, (2, 2)), L, pitch_px=PITCH_PX, scale=scale,
        rotation_deg=rotation_deg, shape=(600, 600), seed=2,
    )  # fmt: skip
    lattice, notes = register_lattice(sim["capture"], PITCH_PX)
    assert any("too few neighbouring dots" in n for n in notes)  # the case under test
    assert lattice.pitch_px == pytest.approx(scale * PITCH_PX, rel=1e-3)
    assert np.allclose(lattice.origin, sim["zero_order_px"], atol=0.1)


@pytest.mark.parametrize("every_other", [True, False])
def test_only_the_first_fit_of_a_pitch_not_measured_may_move_it_by_the_tolerance(
    monkeypatch, levels, every_other
):
    # Once fitted to the dots, the pitch is as good as a measured one: later fits over
    # more dots step by MAX_BASIS_STEP, so a stray dot cannot drag the lattice 20 %.
    from fab.verify import lattice as lattice_module

    steps, fit = [], lattice_module._fit_dots

    def spy(lattice, dots, weight, reach, max_step=lattice_module.MAX_BASIS_STEP):
        steps.append(max_step)
        return fit(lattice, dots, weight, reach, max_step)

    monkeypatch.setattr(lattice_module, "_fit_dots", spy)
    plate = np.tile(levels[:18, :18], (2, 2)) if every_other else levels
    sim = simulate_capture(plate, L, pitch_px=PITCH_PX, scale=1.1, shape=(600, 600), seed=2)
    register_lattice(sim["capture"], PITCH_PX)
    small, large = lattice_module.MAX_BASIS_STEP, lattice_module.PITCH_TOLERANCE
    assert steps == [large + small if every_other else small] + [small] * 3


def test_a_fit_step_larger_than_allowed_keeps_the_basis():
    # Three dots, one a quarter pitch off its site along v: their exact fit stretches v
    # by 25 %. From a measured pitch (steps of 5 % allowed) that is a stray dot: the
    # basis stays, the origin moves by the median residual (none). From the design's
    # pitch the whole tolerance is allowed, and the fit follows the dots.
    from fab.verify.lattice import MAX_BASIS_STEP, _fit_dots

    prior = Lattice(np.array([50.0, 50.0]), 10.0 * np.eye(2))
    dots = np.array([[50.0, 50.0], [60.0, 50.0], [50.0, 62.5]])
    kept = _fit_dots(prior, dots, np.ones(3), reach=3, max_step=MAX_BASIS_STEP)
    assert np.array_equal(kept.basis, prior.basis) and np.allclose(kept.origin, prior.origin)
    followed = _fit_dots(prior, dots, np.ones(3), reach=3, max_step=0.3)
    assert np.allclose(followed.basis, [[10.0, 0.0], [0.0, 12.5]])


def test_a_grating_whose_orders_lie_on_one_line_registers_along_it():
    # levels vary along x only: every order is (0, n), one lattice row; its step along
    # the row is measured, the step across it stays the nominal one
    grating = np.tile(np.random.default_rng(3).integers(0, L, N).astype(np.uint8), (N, 1))
    sim = simulate_capture(grating, L, pitch_px=PITCH_PX, rotation_deg=3.0, shape=(300, 300))
    lattice, _ = register_lattice(sim["capture"], PITCH_PX)
    assert np.allclose(lattice.origin, sim["zero_order_px"], atol=0.1)
    along = np.array(lattice.positions(0, 1)) - lattice.origin  # (row, col) of one step
    theta = np.radians(3.0)
    assert np.allclose(along, PITCH_PX * np.array([-np.sin(theta), np.cos(theta)]), atol=0.02)


@pytest.fixture(scope="module")
def empty_orders(levels):
    """A dark frame (integer codes, pedestal between two codes) and the lattice it would hold."""
    sim = simulate_capture(
        levels, L, pitch_px=PITCH_PX, centre=(300.0, 300.0), seed=41, bits=16,
        read_noise_dn=1.0, dark_level_dn=60.3,
    )  # fmt: skip
    return sim["dark"].astype(np.float32), Lattice(np.array([300.0, 300.0]), PITCH_PX * np.eye(2))


def test_empty_orders_scatter_as_their_reported_sigma(empty_orders):
    # catches a sigma without the error of the annulus background (about 30 % too small)
    image, lattice = empty_orders
    grid = measure_orders(image, lattice, quantum=1.0)
    z = grid.power[grid.valid] / grid.sigma[grid.valid]
    assert z.size > 2000  # the std of 2000 unit normals is 1 within 0.016
    assert np.std(z) == pytest.approx(1.0, abs=0.1)


def test_empty_orders_of_integer_codes_measure_no_power(empty_orders):
    # catches a median background: on integer codes it is off by up to half a DN per
    # pixel, which summed over thousands of faint orders biases the beam power
    image, lattice = empty_orders
    power = measure_orders(image, lattice, quantum=1.0).power
    power = power[np.isfinite(power)]
    assert abs(power.mean()) < 4 * power.std() / np.sqrt(power.size)


def test_saturated_pixel_outside_the_aperture_flags_no_order(empty_orders):
    # catches flagging every order whose patch (aperture and annulus) holds a clipped pixel
    image, lattice = empty_orders
    saturated = np.zeros(image.shape, bool)
    saturated[300, 305] = True  # 5 px from order (0, 0): in its annulus, off its aperture
    r, c = np.rint(lattice.positions(2, 3)).astype(int)
    saturated[r, c] = True  # on order (2, 3)
    grid = measure_orders(image, lattice, saturated, quantum=1.0)
    assert grid.aperture_radius_px < 5
    (iu,), (iv,) = np.nonzero(grid.u == 2), np.nonzero(grid.v == 3)
    assert np.array_equal(np.argwhere(grid.saturated), [[iu[0], iv[0]]])


def test_aperture_holds_99_percent_of_a_blurred_dot_plus_a_pixel(levels):
    # catches an aperture sized for 90 % of the light, which loses 1.5 % of blurred dots
    spot, blur, pitch = 0.3, 1.5, 2 * PITCH_PX
    sim = simulate_capture(
        levels, L, pitch_px=pitch, seed=35, bits=16, spot_sigma_px=spot, blur_sigma_px=blur
    )
    image = sim["capture"].astype(np.float32) - sim["dark"]
    lattice, _ = register_lattice(image, pitch)
    grid = measure_orders(image, lattice, quantum=1.0)
    # A Gaussian dot of sigma per axis (the pixels add 1/12 px^2) holds 1 - exp(-r^2 / 2 sigma^2)
    # of its light within r; the radius is searched in 0.25 px steps on a pixel grid.
    sigma = np.sqrt(spot**2 + blur**2 + 1 / 12)
    r99 = sigma * np.sqrt(2 * np.log(100))
    assert grid.aperture_radius_px == pytest.approx(r99 + 1, abs=0.5)


def test_16bit_file_with_only_three_low_bits_zero_is_read_as_stored(tmp_path):
    # catches taking it for 12-bit MSB-aligned data (four low bits zero): a negative shift crashed
    codes = np.random.default_rng(5).integers(0, 1 << 13, (20, 20)).astype(np.uint16) << 3
    codes[0, 0] = 8  # bit 3 set
    write_image(tmp_path / "cap.tif", codes)
    raw = read_raw_image(tmp_path / "cap.tif")
    assert raw.encoding == "uint16" and raw.quantum == 8.0  # 13-bit codes, 8 apart
    assert np.array_equal(raw.data, codes)


@pytest.mark.parametrize("bits", [13, 14, 15])
def test_one_clipped_pixel_of_a_msb_aligned_13_to_15_bit_capture_is_saturated(tmp_path, bits):
    # at 65535 the sensor's top code (65532 for 14 bits) went unflagged, below a plateau
    shift = 16 - bits
    codes = np.random.default_rng(bits).integers(50, 3000, (40, 40)).astype(np.uint16) << shift
    codes[7, 9] = ((1 << bits) - 1) << shift
    write_image(tmp_path / "cap.tif", codes)
    raw = read_raw_image(tmp_path / "cap.tif")
    assert raw.full_scale == 65536 - 2**shift and raw.quantum == 2**shift
    assert np.argwhere(condition_capture(raw).saturated).tolist() == [[7, 9]]


def test_16bit_file_that_reaches_4095_is_12bit_data_clipped_there(tmp_path):
    # catches "< 4095": a 12-bit capture with a clipped pixel read as 16-bit data, not saturated
    codes = np.random.default_rng(6).integers(50, 200, (40, 40)).astype(np.uint16)
    codes[20, 20] = 4095
    write_image(tmp_path / "cap.tif", codes)
    raw = read_raw_image(tmp_path / "cap.tif")
    assert raw.full_scale == 4095
    assert np.argwhere(condition_capture(raw).saturated).tolist() == [[20, 20]]


def test_dark_frame_exposure_must_match_the_capture_within_the_tolerance():
    # catches a tolerance ten times too loose: a dark 3 % longer was subtracted
    raw = RawImage(np.zeros((4, 4), np.uint16), 65535.0, 0.01, encoding="uint16")
    check_dark(raw, dataclasses.replace(raw, exposure=0.01 * (1 + EXPOSURE_RTOL / 2)), "d.tif")
    with pytest.raises(InputError, match=r"d\.tif: dark exposure"):
        check_dark(
            raw, dataclasses.replace(raw, exposure=0.01 * (1 + 1.5 * EXPOSURE_RTOL)), "d.tif"
        )


def test_a_12_bit_dark_written_msb_aligned_serves_a_12_bit_tiff_capture(tmp_path):
    # the same camera's 12-bit codes, one file written with BitsPerSample 12, the other
    # MSB-aligned in 16 bits, were refused as "other camera settings"
    import OpenImageIO as oiio

    rng = np.random.default_rng(8)
    codes = rng.integers(50, 4000, (30, 30)).astype(np.uint16)
    spec = oiio.ImageSpec(30, 30, 1, "uint16")
    spec.attribute("oiio:BitsPerSample", 12)
    out = oiio.ImageOutput.create(str(tmp_path / "cap.tif"))
    out.open(str(tmp_path / "cap.tif"), spec)
    out.write_image(np.ascontiguousarray((codes << 4)[..., None]))  # OIIO keeps the top 12
    out.close()
    dark = rng.integers(55, 66, (30, 30)).astype(np.uint16)
    write_image(tmp_path / "dark.png", dark << 4)
    capture = read_capture(tmp_path / "cap.tif", tmp_path / "dark.png")
    assert read_raw_image(tmp_path / "cap.tif").encoding == "uint12"
    np.testing.assert_allclose(capture.image, codes.astype(float) - dark, atol=1e-3)


def test_dark_frame_stored_otherwise_than_the_capture_is_refused(tmp_path):
    # catches subtracting a 16-bit LSB dark (DN) from a 12-bit MSB-aligned capture as is
    rng = np.random.default_rng(8)
    write_image(tmp_path / "cap.tif", rng.integers(50, 4000, (30, 30)).astype(np.uint16) << 4)
    write_image(tmp_path / "dark.tif", rng.integers(55, 66, (30, 30)).astype(np.uint16))
    with pytest.raises(InputError, match=r"dark\.tif: dark frame is stored as uint16 but"):
        read_capture(tmp_path / "cap.tif", tmp_path / "dark.tif")


def test_hot_pixel_ten_sigmas_above_a_2dn_dark_is_flagged():
    # catches a noise floor of 5 DN: a 2 DN dark then flagged only pixels 50 DN above it
    dark = np.rint(np.random.default_rng(9).normal(60.0, 2.0, (90, 90))).astype(np.float32)
    dark[45, 45] += 40.0  # 20 sigma
    dark[10, 10] += 12.0  # 6 sigma: noise, not hot
    assert np.argwhere(hot_pixels_from_dark(dark)).tolist() == [[45, 45]]


def test_plateau_of_exactly_the_plateau_pixels_marks_a_float_capture_clipped():
    # catches "> PLATEAU_PIXELS": a plateau of exactly that many pixels was not taken as clipped
    image = np.random.default_rng(10).normal(10.0, 1.0, (50, 50)).astype(np.float32)
    rows, cols = np.arange(PLATEAU_PIXELS) * 7 + 5, np.arange(PLATEAU_PIXELS) * 9 + 3
    image[rows, cols] = 1000.0
    raw = RawImage(image, None, None, encoding="float", quantum=0.0)
    assert np.argwhere(condition_capture(raw).saturated).tolist() == np.c_[rows, cols].tolist()
    fewer = image.copy()
    fewer[rows[0], cols[0]] = 999.0  # one pixel fewer at the maximum: a peak, not a plateau
    assert not condition_capture(dataclasses.replace(raw, data=fewer)).saturated.any()


# --- fab.verify.simulate against the physics it states ------------------------------------


def _same_phase(a, b):
    np.testing.assert_allclose(np.exp(1j * a), np.exp(1j * b), rtol=0, atol=1e-12)


def test_plate_phase_is_the_level_model_with_its_etch_faults():
    lv = np.random.default_rng(2).integers(0, L, (12, 12)).astype(np.uint8)
    _same_phase(plate_phase(lv, L), 2 * np.pi * lv / L)
    # etch and glass swapped: level l is made as L - 1 - l
    _same_phase(plate_phase(lv, L, PlateFaults(conjugate=True)), 2 * np.pi * (L - 1 - lv) / L)
    # the deep mask etches L/2 steps (pi) into levels 0 .. L/2 - 1; 15 % too deep takes
    # another 0.15 pi of glass off those pixels and leaves the others alone
    for eps in (0.15, -0.1):
        faulty = plate_phase(lv, L, PlateFaults(etch_errors=(eps, 0.0, 0.0)))
        _same_phase(faulty, 2 * np.pi * lv / L - eps * np.pi * (lv < L // 2))


@pytest.mark.parametrize("supersample", [1, 2, 3])
def test_plate_phase_overlay_moves_one_mask_up_and_right(supersample):
    # +y is up (towards row 0), +x to the right; a whole-pixel shift is the same at any
    # supersampling. Mask 1 etches 2 steps: bit 2 of the etch code L - 1 - level.
    lv = np.random.default_rng(3).integers(0, L, (12, 12)).astype(np.uint8)
    pitch = 5e-6
    faults = PlateFaults(overlay=((0.0, 0.0), (-2 * pitch, pitch), (0.0, 0.0)))  # left 2, up 1
    code = (L - 1) - lv.astype(int)
    moved = (code & ~2) | np.roll(code & 2, (-1, -2), axis=(0, 1))
    expected = np.kron(2 * np.pi * ((L - 1) - moved) / L, np.ones((supersample, supersample)))
    _same_phase(plate_phase(lv, L, faults, pitch, supersample), expected)


def test_plate_phase_needs_the_pixel_pitch_to_shift_a_mask():
    lv = np.zeros((4, 4), np.uint8)
    faults = PlateFaults(overlay=((0.0, 0.0), (0.0, 1e-6), (0.0, 0.0)))
    with pytest.raises(ValueError, match="an overlay shift needs mask_pixel_pitch"):
        plate_phase(lv, L, faults)


def _blazed():
    """Levels 0..7 along each row: a phase ramp that sends all light into order (0, +1)."""
    return np.tile(np.arange(L, dtype=np.uint8), (L, 1))


@pytest.mark.parametrize(
    "orientation, step, centre",
    [
        ("as-designed", (0, 1), (30.3, 29.6)),
        ("rot90", (-1, 0), (30.3, 29.6)),  # design right is camera up
        ("mirror-x", (0, -1), None),  # default centre: the middle of the frame
    ],
)
def test_a_single_order_lands_where_the_rotated_scaled_lattice_puts_it(orientation, step, centre):
    # Order (0, 1) of a blazed grating is the only one in the frame. Its dot is a Gaussian
    # of sigma^2 = spot^2 + blur^2 integrated over the pixels: its centroid is the lattice
    # site and its variance sigma^2 + 1/12 along each axis (to exp(-2 pi^2 sigma^2)).
    shape, pitch, scale, theta = (61, 61), 10.0, 1.1, np.radians(20.0)
    sim = simulate_capture(
        _blazed(), L, shape=shape, pitch_px=pitch, scale=scale, rotation_deg=20.0,
        orientation=orientation, centre=centre, spot_sigma_px=1.0, blur_sigma_px=1.5,
        full_well_e=1e9, read_noise_dn=0.0, dark_level_dn=0.0, bits=16,
    )  # fmt: skip
    zero = np.array(centre if centre is not None else ((shape[0] - 1) / 2, (shape[1] - 1) / 2))
    assert np.allclose(sim["zero_order_px"], zero)
    down = scale * pitch * np.array([np.cos(theta), np.sin(theta)])  # (row, col), CCW shown
    right = scale * pitch * np.array([-np.sin(theta), np.cos(theta)])
    site = zero + step[0] * down + step[1] * right
    img = sim["capture"].astype(float)
    rows, cols = np.indices(shape)
    total = img.sum()
    centroid = np.array([(img * rows).sum(), (img * cols).sum()]) / total
    assert np.allclose(centroid, site, atol=0.01)
    var = [(img * (rows - centroid[0]) ** 2).sum() / total,
           (img * (cols - centroid[1]) ** 2).sum() / total]  # fmt: skip
    assert np.allclose(var, 1.0**2 + 1.5**2 + 1 / 12, rtol=0.01)
    # exposure: the brightest pixel at peak_fraction (0.7) of full scale
    assert img.max() == pytest.approx(0.7 * 65535, rel=1e-3)


def test_a_capture_that_no_order_reaches_is_refused():
    # orders 1000 px apart, the zero order 500 px left of a 61 px frame: its neighbour
    # to the right lands at column 500, 440 px past the frame's last column
    with pytest.raises(ValueError, match="no order lands in the frame"):
        simulate_capture(_blazed(), L, shape=(61, 61), pitch_px=1000.0, centre=(30.0, -500.0))


def test_every_order_that_reaches_the_frame_is_drawn_even_past_its_far_edge():
    # Levels 0, 2, 4, 6 along each row send all light into order (0, +2), here the lattice
    # site two pitches right of a zero order on the left edge: column 199.5, the frame's
    # right edge, 199.01 px from the farthest corner. Columns 199 and 198 hold the 0..1 and
    # 1..2 sigma slices of its dot.
    from scipy.special import erf

    grating = np.tile((2 * np.arange(L) % L).astype(np.uint8), (L, 1))
    sim = simulate_capture(
        grating, L, shape=(5, 200), pitch_px=99.75, centre=(2.0, 0.0), spot_sigma_px=1.0,
        full_well_e=1e9, read_noise_dn=0.0, dark_level_dn=0.0, bits=16,
    )  # fmt: skip
    cap = sim["capture"].astype(float)
    assert cap[2, 199] == cap.max() > 0
    phi = 0.5 * (1 + erf(np.array([0.0, 1.0, 2.0]) / np.sqrt(2)))
    expected = (phi[2] - phi[1]) / (phi[1] - phi[0])
    assert cap[2, 198] / cap[2, 199] == pytest.approx(expected, rel=0.01)


def test_capture_noise_is_poisson_electrons_and_read_noise_in_dn():
    # A uniform plate: one dot. Across seeds a pixel of mean S electrons reads, in DN,
    # S / g + pedestal with variance S / g^2 + read^2 + 1/12 (g electrons per DN);
    # the dark frame reads the pedestal with read^2 + 1/12.
    flat = np.zeros((8, 8), np.uint8)
    full_well, read, pedestal = 20000.0, 3.0, 100.0
    gain = full_well / 4095
    caps, darks = [], []
    for seed in range(60):
        sim = simulate_capture(
            flat, L, shape=(15, 15), pitch_px=60.0, spot_sigma_px=2.0, full_well_e=full_well,
            read_noise_dn=read, dark_level_dn=pedestal, seed=seed,
        )  # fmt: skip
        caps.append(sim["capture"] >> 4)  # 12-bit data MSB-aligned in 16 bits
        darks.append(sim["dark"] >> 4)
    assert sim["capture"].dtype == np.uint16 and not np.any(sim["capture"] & 0xF)
    caps, darks = np.array(caps, float), np.array(darks, float)
    assert darks.mean() == pytest.approx(pedestal, abs=0.15)
    assert darks.std() == pytest.approx(np.sqrt(read**2 + 1 / 12), rel=0.05)
    lit = caps.mean(axis=0) > pedestal + 200  # the dot's core, S > 500 electrons
    assert lit.sum() >= 20
    signal = (caps.mean(axis=0)[lit] - pedestal) * gain
    expected = signal / gain**2 + read**2 + 1 / 12
    assert caps.var(axis=0, ddof=1)[lit].sum() / expected.sum() == pytest.approx(1, abs=0.1)
    # seeded: the same seed makes the same frames, another seed others
    again = simulate_capture(flat, L, shape=(15, 15), pitch_px=60.0, spot_sigma_px=2.0,
                             full_well_e=full_well, read_noise_dn=read, dark_level_dn=pedestal,
                             seed=59)  # fmt: skip
    assert np.array_equal(again["capture"] >> 4, caps[-1])
    assert np.array_equal(again["dark"] >> 4, darks[-1])
    assert not np.array_equal(caps[-1], caps[-2])


def test_hot_pixels_are_the_same_in_capture_and_dark_at_a_fifth_to_nine_tenths_of_full_scale():
    flat = np.zeros((8, 8), np.uint8)
    sim = simulate_capture(
        flat, L, shape=(40, 40), pitch_px=200.0, centre=(5.0, 5.0), hot_pixels=12,
        read_noise_dn=1.0, dark_level_dn=50.0, seed=4,
    )  # fmt: skip
    cap, dark = sim["capture"] >> 4, sim["dark"] >> 4
    hot = dark > 50 + 0.1 * 4095
    assert hot.sum() == 12
    away = hot.copy()
    away[:15, :15] = False  # off the dot
    assert away.sum() >= 8
    # the same hot electrons drawn twice: Poisson of <= 9000 e, sigma < 100 e = 41 DN each
    assert np.all(np.abs(cap[away].astype(float) - dark[away]) < 6 * np.sqrt(2) * 41)
    level = dark[hot] - 50.0
    assert np.all(level > 0.2 * 4095 - 150) and np.all(level < 0.9 * 4095 + 150)


def test_a_two_level_plate_that_fails_is_diagnosed_not_a_crash(tmp_path):
    # One mask: the overlay-and-etch fit built its classes from no other mask and raised
    # (exit 3) on every failing capture of a 2-level design; a shift of its one mask moves
    # the whole pattern, which the order powers do not see, so no overlay is fitted.
    levels = np.random.default_rng(21).integers(0, 2, (N, N)).astype(np.uint8)
    design = tmp_path / "design"
    design.mkdir()
    save_npy(design / "levels.npy", levels)
    save_npy(design / "target_psf.npy", simulate_levels(levels, 2, K)[0])
    write_json(design / "fab_manifest.json", {
        "levels": 2, "kernel_size": K, "lattice_pitch_um": PITCH_UM,
        "levels_file": "levels.npy", "target_psf_file": "target_psf.npy",
        "masks": [{"name": "M1", "etch_depth_nm": 717.6, "exposure_order": 1}],
    })  # fmt: skip
    mirrored = PlateFaults(other_levels=np.ascontiguousarray(levels[:, ::-1]))
    for name, faults, named in (
        ("deep", PlateFaults(etch_errors=(0.25,)), "deep_etch_error"),
        ("mirrored", mirrored, "mirrored"),
    ):
        sim = simulate_capture(levels, 2, pitch_px=PITCH_PX, seed=3, faults=faults)
        write_image(tmp_path / f"{name}.png", sim["capture"], exposure=0.01)
        write_image(tmp_path / f"{name}_dark.png", sim["dark"], exposure=0.01)
        out = tmp_path / f"out_{name}"
        args = [str(tmp_path / f"{name}.png"), "--dark", str(tmp_path / f"{name}_dark.png")]
        assert main(["verify", str(design), *args, "--out", str(out)]) == 1
        report = json.loads((out / "verify.json").read_text())
        assert named in report["diagnosis"]
        assert report["overlay_error_fit"] is None


def test_no_alignment_is_blamed_where_an_etch_fit_explains_the_window_better():
    # A 16-level plate's deepest etch 25 % too deep was named, and came with "mask
    # M4_1step printed 62 um off ... check that exposure's alignment": an overlay fit
    # stopped at the edge of its search (correlation 0.974, the etch fit's 0.9999).
    from fab.commands.verify import _beyond_reach_hint

    overlay = {"mask": "M4_1step", "shift_px": [-2.5, -2.5], "significance": 11.8,
               "correlation": 0.974, "chi2": 300.0}  # fmt: skip
    report = {"overlay_error_fit": overlay, "etch_error_fit": {"chi2": 900.0},
              "diagnosis": ["psf_mismatch"], "thresholds": {"correlation_min": 0.95}}  # fmt: skip
    assert "printed off the other masks by -2.50 mask pixels" in _beyond_reach_hint(report)
    assert _beyond_reach_hint({**report, "etch_error_fit": {"chi2": 120.0}}) is None
    assert _beyond_reach_hint({**report, "diagnosis": ["deep_etch_error", "psf_mismatch"]}) is None


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
