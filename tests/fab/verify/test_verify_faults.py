"""Faulty plates diagnosed end to end: etch depths, overlays, both, and what verify says of them."""

import json
import re
from pathlib import Path

import numpy as np
import pytest
from verify_helpers import CAMERA_UM, PITCH_PX, PITCH_UM, K, L, N, make_design_dir, run_verify

from doe.fraunhofer import simulate_levels
from doe.infra.cli import main
from doe.infra.files import save_npy, write_json
from fab.plate.model import PlateFaults, plate_far_field, plate_phase
from fab.verify.analysis import analyse, resolve_thresholds
from fab.verify.capture import RawImage, write_image
from fab.verify.conditioning import condition_capture
from fab.verify.diagnosis import etched_off
from fab.verify.etch_fit import fit_etch_errors
from fab.verify.lattice import register_lattice
from fab.verify.photometry import measure_orders
from fab.verify.simulate import simulate_capture

# A lab's acceptance tighter than the defaults: a 2 um overlay error fails it.
STRICT_ACCEPTANCE = dict(
    correlation_min=0.99, rmse_max=0.02, efficiency_min=0.5, zero_order_max=0.05
)


def _grid(sim):
    raw = RawImage(sim["capture"] >> 4, 4095.0, None)
    cap = condition_capture(raw, RawImage(sim["dark"] >> 4, 4095.0, None))
    lattice, _ = register_lattice(cap.image, PITCH_PX)
    return measure_orders(cap.image, lattice, cap.saturated)


def test_deep_etch_error_fails_on_zero_order_with_implied_error(tmp_path, levels):
    code, report, sim = run_verify(
        tmp_path, levels, dict(seed=5, faults=PlateFaults(etch_errors=(0.15, 0.0, 0.0)))
    )
    assert code == 1 and report["pass"] is False
    assert "zero_order_excess" in report["diagnosis"]
    assert report["zero_order"] == pytest.approx(float(sim["order_power"](0, 0)), rel=0.1)
    assert report["implied_deep_etch_error"] == pytest.approx(0.15, abs=0.02)
    assert report["implied_deep_etch_error_nm"] == pytest.approx(0.15 * 717.6, abs=15)


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
                 "--out", str(out), "--pixel-pitch-um", str(CAMERA_UM)])  # fmt: skip
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
    # the report and the figure quote the fit's own shift (1.49 or 1.51: within its sigma)
    dy, dx = (f"{v:+.2f}" for v in fit["shift_px"])
    html = (out / "verify_report.html").read_text()
    assert re.search(rf"{name} by y {re.escape(dy)}, x {re.escape(dx)} mask pixels "
                     r"\(\+7\.\d\d um, -2\.\d\d um\); correlation 0\.99\d\d with that "
                     r"plate \(frame [01]\.\d\d\d\)", html)  # fmt: skip
    assert fit["frame_correlation"] > 0.99
    title, from_design, from_fitted = fitted_plate_panels(saved_figures)
    assert title == f"fitted plate: {name} shifted y {dy}, x {dx} mask px"
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
    from fab.verify.fault_fits import overlay_and_etch_fit_record
    from fab.verify.overlay import fit_overlay_error

    overlay = fit_overlay_error(window, sigma, levels, L)
    etch = fit_etch_errors(window, sigma, levels, L)
    result = {
        "overlay_error_fit": {**overlay, "significance": overlay["chi2_drop"]},
        "etch_error_fit": {"masks": etch["masks"], "errors": list(etch["eps"]),
                           "significance": etch["chi2_drop"], "chi2": etch["chi2"]},
    }  # fmt: skip
    measured = np.clip(window, 0, None) / np.clip(window, 0, None).sum()
    both = overlay_and_etch_fit_record(result, measured, (window, sigma), lambda p: 1.0, levels, L)
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
    # a nearly point-symmetric design, whose mirror fits the window almost as well: the
    # default run's levels.npy before the pixel was kept at least the feature size
    # (N = 175; tests/data/default_levels.npy is today's, N = 174, whose mirror is far)
    return np.load(Path(__file__).parents[2] / "data" / "point_symmetric_levels.npy")


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


@pytest.fixture(scope="module")
def designed_with_corner_contacts():
    """``designed`` as retrieved before corner contacts were repaired: a valid plate whose
    M2 diagonal overlay mimics the conjugate (no diagonal overlay of the corner-free map
    brings the conjugate within 100 of the bare design)."""
    from doe.retrieval import retrieve_phase
    from doe.targets import make_target

    target = make_target("asymmetric", K)
    return retrieve_phase(target, N, L, seed=0, allow_corner_contacts=True).levels


def test_a_diagonal_overlay_does_not_leave_the_zero_order_ambiguous(
    tmp_path, designed_with_corner_contacts
):
    # M2 one mask pixel off in y and in x left the conjugate within 3 of the bare design
    faults = PlateFaults(overlay=((0.0, 0.0), (5e-6, 5e-6), (0.0, 0.0)))
    code, report, _ = verify_faulty_plate(
        tmp_path, designed_with_corner_contacts, faults, 11, supersample=4, pixel_pitch_nm=4990
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
    # the fit's own shift is said (2.24 +- 0.04 px on the blob: 11.18 um, not 11.23)
    said = f"mask {fit['mask']} printed off the other masks by {fit['shift_um'][0]:+.2f} um in y"
    assert said in err and abs(fit["shift_um"][0] - truth * 4.99) < 0.05 * 4.99
    assert "beyond the 2 mask pixels" in err


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
        args += ["--pixel-pitch-um", str(CAMERA_UM)]  # a 2-level plate's sparse dots
        assert main(["verify", str(design), *args, "--out", str(out)]) == 1
        report = json.loads((out / "verify.json").read_text())
        assert named in report["diagnosis"]
        assert report["overlay_error_fit"] is None


def test_no_alignment_is_blamed_where_an_etch_fit_explains_the_window_better():
    # A 16-level plate's deepest etch 25 % too deep was named, and came with "mask
    # M4_1step printed 62 um off ... check that exposure's alignment": an overlay fit
    # stopped at the edge of its search (correlation 0.974, the etch fit's 0.9999).
    from fab.verify.hints import beyond_reach_hint

    overlay = {"mask": "M4_1step", "shift_px": [-2.5, -2.5], "significance": 11.8,
               "correlation": 0.974, "chi2": 300.0}  # fmt: skip
    report = {"overlay_error_fit": overlay, "etch_error_fit": {"chi2": 900.0},
              "diagnosis": ["psf_mismatch"], "thresholds": {"correlation_min": 0.95}}  # fmt: skip
    assert "printed off the other masks by -2.50 mask pixels" in beyond_reach_hint(report)
    assert beyond_reach_hint({**report, "etch_error_fit": {"chi2": 120.0}}) is None
    assert beyond_reach_hint({**report, "diagnosis": ["deep_etch_error", "psf_mismatch"]}) is None
