"""Scan direction (gate, laser, auto) and the per-pixel timing precision of the depth fit."""

import json

import numpy as np
import pytest
from depth_helpers import PS, SHIFT, T, scene

from doe.infra.cli import main
from psf_learn.depth import GateModel, fit_profiles, gate_response, scan_times
from psf_learn.depth_scan import MIN_LOG_LIKELIHOOD_DIFFERENCE, choose_scan, scan_responses
from psf_learn.depth_sim import simulate_cube

LEVELS = {"high": (1000.0, 10.0), "medium": (100.0, 5.0), "low": (10.0, 2.0)}


@pytest.fixture(scope="module")
def responses():
    return scan_responses()


def scene_cube(responses, scan, shape=(6, 10), amplitude=80.0, background=2.0, seed=12):
    a, mu, b = scene(shape, amplitude, background, responses[scan], seed)
    cube = simulate_cube(a, mu, b, T, SHIFT, responses[scan], np.random.default_rng(seed + 1))
    return cube, mu


# --- the laser direction's response ---------------------------------------------------


def test_the_laser_response_mirrors_the_gate_one_for_a_symmetric_pulse(responses):
    x = np.arange(-800, 800) * PS
    np.testing.assert_allclose(responses["laser"](x), responses["gate"](-x), atol=1e-12)
    assert responses["laser"].peak_time == pytest.approx(145 * PS, abs=0.5 * PS)


def test_the_laser_response_is_the_pulse_convolved_with_the_gate():
    # A point pulse and no band limit: G * Pi is the gate itself, rising at 0 with the RC
    # rise and falling after the width (the gate direction's h is it mirrored).
    model = GateModel(band_sigma=0.0, pulse_fwhm=0.01 * PS, rise=40 * PS, fall=60 * PS)
    h = gate_response(model, scan="laser")
    t = np.array([-20, 20, 100, 199, 260]) * PS
    gate = np.array([0, -np.expm1(-0.5), -np.expm1(-2.5), -np.expm1(-199 / 40), 0])
    gate[-1] = -np.expm1(-5) * np.exp(-1)
    np.testing.assert_allclose(h(t) * h.values.max(), gate / gate.max(), atol=2e-3)
    with pytest.raises(ValueError, match="scan must be one of"):
        gate_response(model, scan="up")


# --- choosing the direction -----------------------------------------------------------


@pytest.mark.parametrize("scan", ["gate", "laser"])
@pytest.mark.parametrize("level", sorted(LEVELS))
def test_auto_keeps_the_direction_the_cube_was_scanned_in(responses, scan, level):
    amplitude, background = LEVELS[level]
    cube, mu = scene_cube(responses, scan, (8, 16), amplitude, background, seed=21)
    choice = choose_scan(cube, SHIFT, responses)
    assert choice.scan == scan and not choice.ambiguous
    assert choice.difference >= MIN_LOG_LIKELIHOOD_DIFFERENCE
    # The kept fit is exactly the fit with the true direction's response.
    fit = fit_profiles(cube, SHIFT, responses[scan])
    np.testing.assert_array_equal(choice.fit.timing, fit.timing)
    np.testing.assert_array_equal(choice.fit.timing_sigma, fit.timing_sigma)
    assert np.nanmax(np.abs(choice.fit.timing - mu)) < 100 * PS
    other = choice.fits["laser" if scan == "gate" else "gate"]
    assert abs(np.nanmedian(other.timing - mu) - (-300 if scan == "gate" else 300) * PS) < 20 * PS


def test_a_symmetric_response_cannot_tell_the_directions_apart():
    # No RC edges: the gate is a blurred rectangle, the same in either direction.
    model = GateModel(rise=0.0, fall=0.0)
    responses = scan_responses(model)
    a, mu, b = scene((4, 8), 300.0, 5.0, responses["gate"], seed=3)
    cube = simulate_cube(a, mu, b, T, SHIFT, responses["gate"], np.random.default_rng(4))
    choice = choose_scan(cube, SHIFT, responses)
    assert choice.returns == 32 and choice.ambiguous
    assert choice.difference < 1e-3


def test_a_few_dim_returns_do_not_tell_the_directions_apart(responses):
    # About 0.2 of log-likelihood per pixel at A 10, b 2: 4 pixels are not enough.
    cube, _ = scene_cube(responses, "laser", (2, 2), 10.0, 2.0, seed=21)
    choice = choose_scan(cube, SHIFT, responses)
    assert choice.returns == 4 and choice.ambiguous


def test_a_dark_cube_has_no_direction_to_choose(responses):
    cube = np.random.default_rng(3).poisson(2.0, (4, 5, T))
    choice = choose_scan(cube, SHIFT, responses)
    assert choice.returns == 0 and choice.difference == 0.0 and not choice.ambiguous
    assert choice.scan == "gate"


# --- the commands ---------------------------------------------------------------------


def save(tmp_path, cube, name="cube.npy"):
    path = tmp_path / name
    np.save(path, cube.astype(np.uint16))
    return path


def test_cli_depth_auto_fits_a_laser_cube_and_says_so(tmp_path, responses, capsys):
    cube, mu = scene_cube(responses, "laser")
    path, out = save(tmp_path, cube), tmp_path / "out"
    assert main(["depth", str(path), "--shift-ps", "20", "--out", str(out)]) == 0
    note = capsys.readouterr().out.splitlines()[0]
    assert note.startswith("depth: scan direction laser (auto): log-likelihood ")
    assert note.endswith(" above the gate direction's")
    np.testing.assert_allclose(np.load(out / "timing_ps.npy"), mu / PS, atol=25)
    record = json.loads((out / "depth.json").read_text())
    assert record["scan"]["direction"] == "laser" and record["scan"]["chosen_by"] == "auto"
    ll = record["scan"]["log_likelihood"]
    assert record["scan"]["log_likelihood_difference"] == pytest.approx(ll["laser"] - ll["gate"])
    assert "Pi(x - t)" in record["timing_convention"]
    # The same cube read as gate-scanned is fitted as today, ~300 ps late.
    assert main(["depth", str(path), "--scan", "gate", "--out", str(tmp_path / "g")]) == 0
    late = np.load(tmp_path / "g" / "timing_ps.npy") - mu / PS
    assert 280 < np.median(late) < 320


def test_cli_depth_scan_gate_writes_the_gate_model_fit(tmp_path, responses, capsys):
    cube, _ = scene_cube(responses, "gate")
    path = save(tmp_path, cube)
    assert main(["depth", str(path), "--scan", "gate", "--out", str(tmp_path / "g")]) == 0
    assert "scan direction" not in capsys.readouterr().out
    assert main(["depth", str(path), "--out", str(tmp_path / "a")]) == 0
    fit = fit_profiles(cube.astype(np.float64), SHIFT, gate_response(GateModel()))
    expected = {"timing_ps": fit.timing / PS, "depth_m": fit.depth, "amplitude": fit.amplitude,
                "background": fit.background, "fit_quality": fit.fit_quality,
                "significance": fit.significance, "valid": fit.valid}  # fmt: skip
    for name, value in expected.items():
        np.testing.assert_array_equal(np.load(tmp_path / "g" / f"{name}.npy"), value)
    # auto picks gate for a gate cube and writes the same files, depth.json aside.
    for name in [*expected, "timing_sigma_ps", "depth_sigma_m"]:
        auto, given = (np.load(tmp_path / d / f"{name}.npy") for d in "ag")
        np.testing.assert_array_equal(auto, given)
    for name in ("intensity.png", "depth.png", "pixel_fits.png"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "g" / name).read_bytes()
    scan = json.loads((tmp_path / "g" / "depth.json").read_text())["scan"]
    assert scan == {"direction": "gate", "chosen_by": "--scan"}


def test_cli_depth_refuses_to_guess_between_two_like_directions(tmp_path, capsys):
    responses = scan_responses(GateModel(rise=0.0, fall=0.0))
    a, mu, b = scene((3, 4), 300.0, 5.0, responses["gate"], seed=3)
    cube = simulate_cube(a, mu, b, T, SHIFT, responses["gate"], np.random.default_rng(4))
    path, out = save(tmp_path, cube), tmp_path / "out"
    gate = ["--rise-ps", "0", "--fall-ps", "0"]
    assert main(["depth", str(path), *gate, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not told apart" in err
    assert "give --scan gate or --scan laser" in err and not out.exists()
    assert main(["depth", str(path), *gate, "--scan", "laser", "--out", str(out)]) == 0


def test_cli_depth_with_irf_takes_its_direction(tmp_path, responses, capsys):
    cube, mu = scene_cube(responses, "laser")
    path = save(tmp_path, cube)
    np.save(tmp_path / "irf.npy", responses["laser"](scan_times(T, SHIFT) - 1000 * PS))
    irf = ["--irf", str(tmp_path / "irf.npy"), "--irf-t0-ps", "1000"]
    out = tmp_path / "out"
    assert main(["depth", str(path), *irf, "--out", str(out)]) == 0
    assert "scan direction fixed by the IRF" in capsys.readouterr().out
    timing, valid = np.load(out / "timing_ps.npy"), np.load(out / "valid.npy")
    np.testing.assert_allclose(timing[valid], mu[valid] / PS, atol=25)
    assert json.loads((out / "depth.json").read_text())["scan"]["chosen_by"] == "irf"
    assert main(["depth", str(path), *irf, "--scan", "gate", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "--scan: a measured IRF, taken in the same scan, fixes the direction" in err


def test_cli_transient_labels_its_frames_with_the_direction(tmp_path, responses, capsys):
    cube, _ = scene_cube(responses, "laser", shape=(3, 4))
    path = save(tmp_path, cube)
    assert main(["transient", str(path), "--out", str(tmp_path / "a")]) == 0
    assert "scan direction laser (auto)" in capsys.readouterr().out
    record = json.loads((tmp_path / "a" / "transient.json").read_text())
    assert record["scan"]["direction"] == "laser"
    assert record["frame_arrival_ps"][:2] == [-145.0, -125.0]  # t_k less h's peak time
    assert main(["transient", str(path), "--scan", "gate", "--out", str(tmp_path / "g")]) == 0
    record = json.loads((tmp_path / "g" / "transient.json").read_text())
    assert record["scan"] == {"direction": "gate", "chosen_by": "--scan"}
    assert record["frame_arrival_ps"][:2] == [145.0, 165.0]
    np.save(tmp_path / "one.npy", np.full((3, 2, 1), 7.0))
    assert main(["transient", str(tmp_path / "one.npy"), "--out", str(tmp_path / "o")]) == 0
    assert "scan direction not determined" in capsys.readouterr().out
    record = json.loads((tmp_path / "o" / "transient.json").read_text())
    assert record["scan"]["direction"] is None and record["frame_arrival_ps"] is None


# --- precision ------------------------------------------------------------------------


@pytest.mark.parametrize("scan", ["gate", "laser"])
@pytest.mark.parametrize("level", ["medium", "low"])
def test_quoted_timing_sigma_matches_the_spread_over_repeated_cubes(responses, scan, level):
    amplitude, background = LEVELS[level]
    a, mu, b = scene((4, 8), amplitude, background, responses[scan], seed=5)
    repeats = [np.broadcast_to(v, (200, 4, 8)) for v in (a, mu, b)]
    cubes = simulate_cube(*repeats, T, SHIFT, responses[scan], np.random.default_rng(6))
    fit = fit_profiles(cubes, SHIFT, responses[scan])  # 200 cubes of 4 x 8 pixels at once
    assert fit.valid.all()
    spread = np.std(fit.timing, axis=0)
    quoted = np.sqrt(np.mean(fit.timing_sigma**2, axis=0))
    assert np.all(np.abs(quoted / spread - 1) < 0.2)  # each pixel within 20 %
    assert abs(np.sqrt(np.mean(quoted**2) / np.mean(spread**2)) - 1) < 0.05
    np.testing.assert_allclose(fit.depth_sigma, 299_792_458.0 * fit.timing_sigma / 2)


def test_cli_depth_writes_the_precision_of_every_return(tmp_path, responses):
    cube, _ = scene_cube(responses, "gate")
    cube[0, 0] = 2  # no return
    path, out = save(tmp_path, cube), tmp_path / "out"
    assert main(["depth", str(path), "--out", str(out)]) == 0
    sigma, depth_sigma = np.load(out / "timing_sigma_ps.npy"), np.load(out / "depth_sigma_m.npy")
    valid = np.load(out / "valid.npy")
    assert np.isnan(sigma[0, 0]) and np.isnan(depth_sigma[0, 0]) and not valid[0, 0]
    assert np.all((sigma[valid] > 1) & (sigma[valid] < 20))  # A 80, b 2: about 4-5 ps
    np.testing.assert_allclose(depth_sigma, 299_792_458.0 * sigma * PS / 2)
    native = json.loads((out / "depth.json").read_text())["native"]
    assert native["timing_sigma_ps_median"] == pytest.approx(np.median(sigma[valid]))
    assert native["depth_sigma_m_p90"] == pytest.approx(np.percentile(depth_sigma[valid], 90))


def test_the_depth_figure_has_a_precision_panel(tmp_path, saved_figures):
    from psf_learn.depth_plots import save_depth_maps

    valid = np.ones((3, 5), bool)
    valid[2, 0] = False
    save_depth_maps(tmp_path / "d.png", np.ones((3, 5)), np.full((3, 5), 2e-3), valid)
    axes = [a for a in saved_figures[-1].axes if a.images]
    assert [a.get_title() for a in axes][1] == "precision: 1-sigma of the depth"
    labels = [a.get_ylabel() for a in saved_figures[-1].axes if not a.images]
    assert labels == ["depth (m)", "depth sigma (mm)"]
    assert axes[1].images[0].get_array().max() == pytest.approx(2.0)  # drawn in mm


# --- acceptance: default flags against a least-squares fit that knows the model -----


def least_squares_timing(cube, response, a, mu, b):
    """Per-pixel scipy least-squares fit of the true model, started at the truth (s)."""
    from scipy.optimize import least_squares

    t = scan_times(cube.shape[-1], SHIFT) / PS
    out, starts = [], np.stack([a.ravel(), mu.ravel() / PS, b.ravel()], axis=-1)
    for y, x0 in zip(cube.reshape(-1, cube.shape[-1]), starts, strict=True):

        def residual(p, y=y):
            return p[0] * response((t - p[1]) * PS) + p[2] - y

        scale = [max(x0[0], 1.0), 10.0, max(x0[2], 1.0)]
        out.append(
            least_squares(residual, x0, x_scale=scale, bounds=([0, -np.inf, 0], np.inf)).x[1]
        )
    return np.array(out).reshape(mu.shape) * PS


@pytest.mark.parametrize("scan", ["gate", "laser"])
def test_default_flags_time_either_direction_as_well_as_a_fit_that_knows_it(responses, scan):
    # Issue 47's acceptance on 8 x 16 cubes (bench/depth.py: 32 x 64 x 200): the
    # default (auto) timing RMSE, bias included, within 1.1 x the reference's.
    for level, (amplitude, background) in LEVELS.items():
        a, mu, b = scene((8, 16), amplitude, background, responses[scan], seed=31)
        cube = simulate_cube(a, mu, b, T, SHIFT, responses[scan], np.random.default_rng(32))
        choice = choose_scan(cube, SHIFT, responses)
        assert choice.scan == scan and choice.fit.valid.all(), level
        rmse = np.sqrt(np.mean((choice.fit.timing - mu) ** 2))
        reference = least_squares_timing(cube, responses[scan], a, mu, b)
        assert rmse <= 1.1 * np.sqrt(np.mean((reference - mu) ** 2)), level


def test_a_laser_scan_is_calibrated_and_checked_in_its_direction(tmp_path, responses, capsys):
    # depth-calibrate tells the direction as depth does and records a laser scan's;
    # a cube fitted in the other direction than its calibration is refused.
    from psf_learn.depth_sim import random_gate_skew, random_scene, simulate_skewed_cube

    laser, n, rng = responses["laser"], 200, np.random.default_rng(41)
    delay = random_gate_skew((4, 8), 150 * PS, rng)
    flat = np.full((4, 8), 2 * 0.15 / 299_792_458.0)
    cube = simulate_skewed_cube(1000.0, flat, 10.0, delay, n, SHIFT, laser, rng)
    np.save(tmp_path / "flat.npy", cube.astype(np.uint16))
    a, mu, b = random_scene((4, 8), 100.0, 5.0, SHIFT, n, laser, rng, 700 * PS)
    np.save(tmp_path / "scene.npy", simulate_skewed_cube(a, mu, b, delay, n, SHIFT, laser, rng))
    cal = tmp_path / "cal"
    args = [str(tmp_path / "flat.npy"), "--distance-m", "0.15", "--out", str(cal)]
    assert main(["depth-calibrate", *args]) == 0
    assert "depth-calibrate: scan direction laser (auto)" in capsys.readouterr().out
    assert json.loads((cal / "calibration.json").read_text())["gate"]["scan"] == "laser"
    scene = [str(tmp_path / "scene.npy"), "--calibration", str(cal)]
    assert main(["depth", *scene, "--out", str(tmp_path / "o")]) == 0
    timing = np.load(tmp_path / "o" / "timing_ps.npy")
    assert np.sqrt(np.mean((timing - mu / PS) ** 2)) < 10  # the skew alone: 150 ps
    assert main(["depth", *scene, "--scan", "gate", "--out", str(tmp_path / "g")]) == 2
    assert "gate scan None against laser" in capsys.readouterr().err
