"""Gated-SPAD depth: gate response oracles, per-pixel fit recovery, the measured-IRF path."""

import subprocess
import sys
import warnings
from math import erf, sqrt

import numpy as np
import pytest
from depth_helpers import PS, SHIFT, T, scene

from psf_learn.depth import (
    FWHM_PER_SIGMA,
    SPEED_OF_LIGHT,
    GateModel,
    Response,
    check_scan,
    expected_counts,
    fit_profiles,
    gate_response,
    response_from_irf,
    scan_times,
)
from psf_learn.depth_sim import random_scene, simulate_cube


@pytest.fixture(scope="module")
def response():
    return gate_response(GateModel())


# --- the gate model -------------------------------------------------------------------


def test_rectangular_gate_is_a_difference_of_error_functions():
    # No RC distortion: a gate open on [x, x + w] after the light's arrival catches
    # the share of a Gaussian (sigma sqrt(s_pulse^2 + s_band^2)) arriving in it.
    model = GateModel(width=200 * PS, rise=0.0, fall=0.0, band_sigma=100 * PS, pulse_fwhm=80 * PS)
    h = gate_response(model)
    s = np.hypot(80 * PS / FWHM_PER_SIGMA, 100 * PS)

    def oracle(x):
        return 0.5 * (erf((x + 200 * PS) / (sqrt(2) * s)) - erf(x / (sqrt(2) * s)))

    x = np.linspace(-700, 500, 49) * PS
    expected = np.array([oracle(v) for v in x]) / oracle(-100 * PS)
    np.testing.assert_allclose(h(x), expected, atol=2e-4)
    assert h.peak_time == pytest.approx(-100 * PS, abs=1.5 * PS)


def test_rc_gate_follows_rise_and_fall_constants():
    # A near-delta pulse and no band limit leave the RC gate itself, reversed: the
    # gate opening x = -t before the light sees it t after opening, Pi(t).
    model = GateModel(rise=40 * PS, fall=60 * PS, band_sigma=0.0, pulse_fwhm=1 * PS)
    h = gate_response(model)
    plateau = 1 - np.exp(-200 / 40)
    for t_ps in (20, 50, 100, 150):
        assert h(-t_ps * PS) == pytest.approx((1 - np.exp(-t_ps / 40)) / plateau, abs=2e-3)
    for t_ps in (230, 260, 320):
        assert h(-t_ps * PS) == pytest.approx(np.exp(-(t_ps - 200) / 60), abs=2e-3)
    assert h(20 * PS) < 1e-6  # a gate opening after the light sees none of it


def test_a_point_gate_reproduces_the_pulse_and_its_fwhm():
    # Catches the pulse sigma taken as FWHM / sqrt(2 ln 2) instead of FWHM / 2.355.
    model = GateModel(width=1 * PS, rise=0.0, fall=0.0, band_sigma=0.0, pulse_fwhm=300 * PS)
    assert gate_response(model).fwhm == pytest.approx(300 * PS, abs=2 * PS)


def test_an_unblurred_rectangular_gate_has_its_width_as_fwhm():
    # Catches a FWHM taken as the count of samples above half (one step too long).
    for width in (137 * PS, 200 * PS):
        model = GateModel(width=width, rise=0.0, fall=0.0, band_sigma=0.0, pulse_fwhm=1e-14)
        assert gate_response(model).fwhm == pytest.approx(width, abs=0.5 * PS)


def test_response_interpolates_linearly_between_its_samples():
    # Catches the table index rounded instead of floored (a backward extrapolation).
    r = Response(start=10.0, step=2.0, values=np.array([0.0, 1.0, 4.0, 9.0]))
    x = np.array([11.0, 13.2, 14.5, 16.0, 7.0, 30.0])
    np.testing.assert_allclose(r(x), [0.5, 1.0 + 0.6 * 3, 4.0 + 0.25 * 5, 9.0, 0.0, 0.0])


def test_emg_pulse_delays_the_centroid_by_tau():
    # The mean of a convolution is the sum of the means: the exponential tail adds tau.
    gauss = gate_response(GateModel())
    emg = gate_response(GateModel(pulse="emg", tau=50 * PS))

    def centroid(r):
        return np.sum(r.times * r.values) / np.sum(r.values)

    assert centroid(emg) - centroid(gauss) == pytest.approx(50 * PS, abs=0.05 * PS)


def test_profile_is_the_gate_scanned_across_the_pulse_brute_force():
    """Sample k counts the pulse arriving at mu through the gate opened at t_k = k * shift:
    integral A G(t - mu) Pi(t - t_k) dt + b, summed here on a 0.1 ps grid from the
    gate as docs/depth.md states it; the fit must return mu itself."""
    model = GateModel(rise=40 * PS, fall=60 * PS, band_sigma=0.0, pulse_fwhm=80 * PS)
    mu, amplitude, background = 700 * PS, 400.0, 2.0
    dt = 0.1 * PS
    t = np.arange(-2000, 4000, 0.1) * PS  # absolute time
    sigma = model.pulse_fwhm / FWHM_PER_SIGMA
    pulse = np.exp(-0.5 * ((t - mu) / sigma) ** 2)

    def gate(tau):  # sensitivity tau after the gate opened
        inside = (tau >= 0) & (tau <= model.width)
        end = 1 - np.exp(-model.width / model.rise)
        after = end * np.exp(-np.clip(tau - model.width, 0, None) / model.fall)
        return np.where(inside, 1 - np.exp(-np.clip(tau, 0, None) / model.rise), 0.0) + np.where(
            tau > model.width, after, 0.0
        )

    times = scan_times(T, SHIFT)
    counts = np.array([np.sum(pulse * gate(t - tk)) * dt for tk in times])
    expected = amplitude * counts / counts.max() + background
    response = gate_response(model)
    model_counts = expected_counts(response, times, amplitude, mu, background)
    np.testing.assert_allclose(model_counts, expected, atol=0.01 * amplitude)
    # the profile drops to the background as the gate opens after the light
    assert expected[times > mu + 200 * PS].max() < background + 1e-3 * amplitude
    cube = np.random.default_rng(0).poisson(np.tile(expected, (200, 1))).astype(float)
    fit = fit_profiles(cube, SHIFT, response)
    assert fit.valid.all()
    assert np.mean(fit.timing) == pytest.approx(mu, abs=2 * PS)


def test_expected_counts_convention(response):
    # counts(t_k) = A h(t_k - mu) + b with t_k = k * shift: the profile peaks at mu + t_peak.
    mu = 700 * PS
    m = expected_counts(response, scan_times(T, SHIFT), 50.0, mu, 3.0)
    t_peak = scan_times(T, SHIFT)[np.argmax(m)]
    assert abs(t_peak - (mu + response.peak_time)) <= SHIFT / 2
    assert m.max() == pytest.approx(53.0, rel=0.01)
    assert m.min() == pytest.approx(3.0, abs=1e-6)


def test_gate_model_limits():
    # A pulse far shorter than the 1 ps grid is a single sample (once 0 * inf = NaN).
    delta = gate_response(GateModel(pulse_fwhm=1e-300))
    short = gate_response(GateModel(pulse_fwhm=1e-14))
    assert np.all(np.isfinite(delta.values)) and delta.start == pytest.approx(short.start)
    np.testing.assert_allclose(delta.values, short.values, atol=1e-12)
    with pytest.raises(ValueError, match="span"):
        gate_response(GateModel(fall=1e-3))


@pytest.mark.parametrize(
    "params, why",
    [
        ({"width": 0.0}, "width must be > 0"),
        ({"pulse_fwhm": -1 * PS}, "pulse_fwhm must be > 0"),
        ({"rise": -1 * PS}, "rise must be >= 0"),
        ({"tau": np.nan}, "tau must be >= 0"),
        ({"pulse": "lorentz"}, "pulse must be 'gaussian' or 'emg'"),
        ({"pulse": "emg"}, "an 'emg' pulse needs tau > 0"),
    ],
)
def test_a_gate_model_the_response_cannot_be_built_from_is_refused(params, why):
    # The command line checks its flags first; these guard the Python API.
    with pytest.raises(ValueError, match=why):
        GateModel(**params)


def test_scan_must_sample_the_response():
    fwhm = gate_response(GateModel()).fwhm
    ok = gate_response(GateModel())
    check_scan(4, fwhm / 3, ok)
    check_scan(120, fwhm, ok)
    for n, shift in ((3, SHIFT), (120, 1.01 * fwhm), (4, fwhm / 3.1)):
        with pytest.raises(ValueError):
            check_scan(n, shift, ok)


# --- the fit --------------------------------------------------------------------------


def test_noiseless_profiles_are_recovered_exactly(response):
    rng = np.random.default_rng(1)
    a, mu, _ = scene((8, 8), 1.0, 0.0, response, seed=2)
    a = rng.uniform(5, 500, size=a.shape)
    b = rng.uniform(0, 20, size=a.shape)
    fit = fit_profiles(simulate_cube(a, mu, b, T, SHIFT, response), SHIFT, response)
    assert fit.valid.all()
    np.testing.assert_allclose(fit.timing, mu, atol=0.01 * PS)
    np.testing.assert_allclose(fit.amplitude, a, rtol=1e-4)
    np.testing.assert_allclose(fit.background, b, atol=1e-3)
    np.testing.assert_allclose(fit.depth, SPEED_OF_LIGHT * mu / 2, atol=1e-5)


def cramer_rao_timing(response, a, mu, b):
    """Per-pixel Cramer-Rao bound on the std of mu (s) for Poisson counts."""
    t = scan_times(T, SHIFT)
    h, dh = response(t[None, :] - mu.reshape(-1, 1), derivative=True)
    m = a.reshape(-1, 1) * h + b.reshape(-1, 1)
    jac = np.stack([h, -a.reshape(-1, 1) * dh, np.ones_like(h)], axis=-1)
    fisher = np.einsum("pt,ptk,ptl->pkl", 1 / m, jac, jac)
    return np.sqrt(np.linalg.inv(fisher)[:, 1, 1])


@pytest.mark.parametrize(("amplitude", "background"), [(200.0, 5.0), (10.0, 2.0)])
def test_noisy_timing_reaches_the_cramer_rao_bound(response, amplitude, background):
    a, mu, b = scene((32, 32), amplitude, background, response, seed=3)
    cube = simulate_cube(a, mu, b, T, SHIFT, response, np.random.default_rng(4))
    fit = fit_profiles(cube, SHIFT, response)
    assert fit.valid.all()
    err = fit.timing - mu
    crb = np.sqrt(np.mean(cramer_rao_timing(response, a.ravel(), mu.ravel(), b.ravel()) ** 2))
    rmse = np.sqrt(np.mean(err**2))
    assert rmse < 1.2 * crb  # an efficient estimator: within 20 % of the bound
    assert abs(np.mean(err)) < 4 * crb / np.sqrt(err.size)  # and unbiased
    argmax = scan_times(T, SHIFT)[np.argmax(cube, axis=-1)] - response.peak_time
    assert rmse <= 0.5 * np.sqrt(np.mean((argmax - mu) ** 2))


def test_fit_is_scale_equivariant(response):
    # The Poisson stationarity condition is homogeneous: scaling counts scales A, b only.
    a, mu, b = scene((4, 8), 40.0, 4.0, response, seed=5)
    cube = simulate_cube(a, mu, b, T, SHIFT, response, np.random.default_rng(6))
    f1 = fit_profiles(cube, SHIFT, response)
    f2 = fit_profiles(cube * 7.0, SHIFT, response)
    np.testing.assert_allclose(f2.timing, f1.timing, atol=0.05 * PS)
    np.testing.assert_allclose(f2.amplitude, 7 * f1.amplitude, rtol=1e-3)


def test_emg_pulse_fit(response):
    emg = gate_response(GateModel(pulse="emg", tau=60 * PS))
    # The pulse's tail and the gate's fall reach out on both sides: profiles cut
    # below 1e-3 of their peak (noise-free data: the fit still has them exactly).
    a, mu, b = scene((4, 4), 300.0, 2.0, emg, seed=7, margin=800 * PS)
    fit = fit_profiles(simulate_cube(a, mu, b, T, SHIFT, emg), SHIFT, emg)
    np.testing.assert_allclose(fit.timing, mu, atol=0.01 * PS)
    # The Gaussian-pulse model misreads the same data: the pulse shape matters.
    wrong = fit_profiles(simulate_cube(a, mu, b, T, SHIFT, emg), SHIFT, response)
    assert np.mean(wrong.timing - mu) > 20 * PS


def test_a_return_the_scan_cannot_place_has_no_timing(response):
    # Light arriving after the scan ends shows only the rising flank of its profile
    # (the gate's fall): significant, but the fit runs into the end of its range.
    times = scan_times(T, SHIFT)
    late, inside = T * SHIFT + 600 * PS, T * SHIFT - 700 * PS
    m = np.stack([expected_counts(response, times, 5000.0, mu, 2.0) for mu in (late, inside)])
    cube = np.random.default_rng(3).poisson(np.repeat(m, 50, axis=0)).astype(float)
    fit = fit_profiles(cube, SHIFT, response)
    assert fit.significance[:50].min() > 100  # light there is
    assert not fit.valid[:50].any() and np.isnan(fit.timing[:50]).all()
    assert fit.valid[50:].all()
    assert np.median(fit.timing[50:]) == pytest.approx(inside, abs=2 * PS)


def test_a_bright_pixel_leaves_the_fits_of_the_others_alone(response):
    a, mu, b = scene((4, 8), 20.0, 0.05, response, seed=14)
    cube = simulate_cube(a, mu, b, T, SHIFT, response, np.random.default_rng(15))
    alone = fit_profiles(cube, SHIFT, response)
    bright = cube.astype(float)
    bright[0, 0] *= 1e8
    beside = fit_profiles(bright, SHIFT, response)
    np.testing.assert_allclose(beside.significance[1:], alone.significance[1:], rtol=1e-9)
    np.testing.assert_allclose(beside.timing[1:], alone.timing[1:], rtol=1e-9)


def test_background_only_pixels_are_no_return(response):
    a, mu, b = scene((16, 16), 30.0, 3.0, response, seed=8)
    a[:8] = 0.0  # the top half sees no return at all
    cube = simulate_cube(a, mu, b, T, SHIFT, response, np.random.default_rng(9))
    fit = fit_profiles(cube, SHIFT, response)
    assert not fit.valid[:8].any()
    assert np.isnan(fit.timing[:8]).all() and np.isnan(fit.depth[:8]).all()
    assert (fit.amplitude[:8] == 0).all()
    np.testing.assert_allclose(fit.background[:8], cube[:8].mean(axis=-1))
    # Their fit quality is the Poisson deviance per dof of that constant background.
    y, m = cube[:8].astype(float), cube[:8].mean(axis=-1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        dev = 2 * np.sum(np.where(y > 0, y * np.log(y / m), 0.0) - (y - m), axis=-1)
    np.testing.assert_allclose(fit.fit_quality[:8], dev / (T - 1), rtol=1e-6)
    assert fit.valid[8:].all()
    assert np.isfinite(fit.depth[8:]).all()


def test_pure_background_false_returns_are_rare(response):
    rng = np.random.default_rng(10)
    fits = [fit_profiles(rng.poisson(b, size=(500, T)), SHIFT, response) for b in (0.3, 5, 80)]
    false = sum(int(f.valid.sum()) for f in fits)
    assert false <= 3  # about 1e-4 per pixel at the default threshold; 1500 pixels


def test_all_zero_pixels_are_no_return(response):
    fit = fit_profiles(np.zeros((2, 3, T)), SHIFT, response)
    assert not fit.valid.any() and np.isnan(fit.timing).all()


@pytest.mark.parametrize("side", [-1, 1])
def test_a_profile_peaking_just_outside_the_scan_is_still_timed(response, side):
    # Catches a mu range without its half-FWHM margin beyond the scan (docs/depth.md).
    times = scan_times(T, SHIFT)
    end = times[-1] if side > 0 else times[0]
    mu = end - response.peak_time + side * 60 * PS  # peak 60 ps past an end: FWHM/2 is 156
    fit = fit_profiles(expected_counts(response, times, 1000.0, mu, 2.0)[None], SHIFT, response)
    assert fit.valid.all()
    np.testing.assert_allclose(fit.timing, mu, atol=0.1 * PS)


def test_the_grid_search_alone_starts_close_to_the_truth(response):
    # Catches a wrong sign of the parabola refinement or of the intercept b = mean - A mean(h),
    # and a grid block that drops its left neighbour (arrivals every 5 ps span all blocks).
    mu = np.linspace(500, 1900, 281) * PS
    times = scan_times(T, SHIFT)
    cube = expected_counts(response, times, np.full(mu.size, 300.0), mu, np.full(mu.size, 10.0))
    fit = fit_profiles(cube, SHIFT, response, max_iter=0)  # no likelihood iterations
    assert fit.valid.all()
    # The grid spacing is ~12.5 ps; the vertex of the parabola lands well within a step.
    np.testing.assert_allclose(fit.timing, mu, atol=1 * PS)
    np.testing.assert_allclose(fit.amplitude, 300.0, rtol=0.01)
    np.testing.assert_allclose(fit.background, 10.0, atol=0.1)


def test_fit_quality_of_a_return_is_its_model_deviance_per_dof(response):
    # Catches the returns' deviance divided by T - 1 instead of T - 3 (three fitted parameters).
    a, mu, b = scene((4, 4), 80.0, 4.0, response, seed=22)
    cube = simulate_cube(a, mu, b, T, SHIFT, response, np.random.default_rng(23))
    fit = fit_profiles(cube, SHIFT, response)
    assert fit.valid.all()
    m = expected_counts(response, scan_times(T, SHIFT), fit.amplitude, fit.timing, fit.background)
    y = cube.astype(float)
    with np.errstate(divide="ignore", invalid="ignore"):
        dev = 2 * np.sum(np.where(y > 0, y * np.log(y / m), 0.0) - (y - m), axis=-1)
    np.testing.assert_allclose(fit.fit_quality, dev / (T - 3), rtol=1e-6)


def test_the_fit_is_at_least_as_likely_as_the_truth(response):
    # Catches Levenberg-Marquardt damping that grows on accepted steps (stalls before the maximum).
    rng = np.random.default_rng(45)
    mu = rng.uniform(700, 1700, 500) * PS
    truth = expected_counts(response, scan_times(T, SHIFT), 3.0, mu, 0.1)
    cube = rng.poisson(truth).astype(float)
    fit = fit_profiles(cube, SHIFT, response)

    def log_likelihood_ratio(m):  # 2 (log L(m) - log L(constant mean)), Poisson
        mean = cube.mean(axis=1, keepdims=True)
        with np.errstate(divide="ignore", invalid="ignore"):
            return 2 * np.sum(np.where(cube > 0, cube * np.log(m / mean), 0.0) - (m - mean), axis=1)

    # The maximum-likelihood estimate is never less likely than the true parameters.
    assert (fit.significance >= log_likelihood_ratio(truth) - 1e-6).all()


def test_a_pixel_that_reaches_the_threshold_exactly_is_a_return(response):
    # Catches "significance > threshold" where the contract is "reaches" (>=).
    a, mu, b = scene((1, 3), 5.0, 2.0, response, seed=25)
    cube = simulate_cube(a, mu, b, T, SHIFT, response, np.random.default_rng(26))
    s = fit_profiles(cube, SHIFT, response, threshold=0.0).significance
    assert (s > 0).all()
    for k, level in enumerate(s.ravel()):
        assert fit_profiles(cube, SHIFT, response, threshold=level).valid.ravel()[k]


def test_a_cube_without_pixels_is_refused(response):
    with pytest.raises(ValueError, match="the cube has no pixels"):
        fit_profiles(np.zeros((0, 3, T)), SHIFT, response)


def test_the_fit_shows_its_chunks_on_a_terminal(response, monkeypatch):
    import io

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    a, mu, b = scene((3, 4), 100.0, 3.0, response, seed=5)
    cube = simulate_cube(a, mu, b, T, SHIFT, response)
    shown = Terminal()
    monkeypatch.setattr(sys, "stderr", shown)
    whole = fit_profiles(cube, SHIFT, response, progress=True)
    assert shown.getvalue() == ""  # one chunk: no bar
    chunked = fit_profiles(cube, SHIFT, response, chunk=5, progress=True)
    assert "fit" in shown.getvalue() and "3/3" in shown.getvalue()  # 12 pixels, 5 a chunk
    np.testing.assert_array_equal(chunked.timing, whole.timing)


def test_a_random_scene_needs_room_for_a_complete_profile(response):
    # 10 samples scan 180 ps, less than the ~330 ps the response spans; a margin of
    # half the scan leaves no arrival time between the margins
    with pytest.raises(ValueError, match="too short for a complete profile"):
        random_scene((2, 2), 100.0, 3.0, SHIFT, 10, response)
    with pytest.raises(ValueError, match="too short for a complete profile"):
        random_scene((2, 2), 100.0, 3.0, SHIFT, T, response, margin=(T - 1) * SHIFT / 2)


def test_depth_module_does_not_import_torch():
    code = "import sys, psf_learn.depth, psf_learn.depth_response, psf_learn.depth_sim, psf_learn.depth_scan, psf_learn.depth_options, psf_learn.cubes, psf_learn.commands.depth; print('torch' in sys.modules)"  # noqa: E501
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


# --- the measured-IRF path ------------------------------------------------------------


@pytest.mark.parametrize("edge", ["early", "late"])
def test_irf_cut_by_the_scan_is_extended_and_serves_every_arrival(response, edge):
    # A reference whose profile is cut by the scan half-way down its early edge
    # (the gate's fall) or its late edge (the blurred RC rise as the gate opens
    # after the light): the extension must still serve every arrival.
    x = response.times[response.values >= 0.5]
    t_ref = -x[0] if edge == "early" else (T - 1) * SHIFT - x[-1]
    irf = response(scan_times(T, SHIFT) - t_ref)
    assert irf[0 if edge == "early" else -1] == pytest.approx(0.5, abs=0.02)
    from_irf = response_from_irf(irf, SHIFT, t_ref=t_ref)
    t = np.linspace(-1000, 500, 151) * PS
    np.testing.assert_allclose(from_irf(t), response(t), atol=0.01)
    a, mu, b = scene((8, 8), 100.0, 3.0, response, seed=11)
    fit = fit_profiles(simulate_cube(a, mu, b, T, SHIFT, response), SHIFT, from_irf)
    assert fit.valid.all()
    np.testing.assert_allclose(fit.timing, mu, atol=2 * PS)


def test_negative_irf_noise_is_clipped_to_zero(response):
    # Catches an IRF whose negative (background-subtracted) noise reaches the spline.
    rng = np.random.default_rng(27)
    irf = response(scan_times(T, SHIFT) - 1200 * PS) + rng.normal(0, 0.01, T)
    assert (irf < 0).any()
    noisy, clipped = response_from_irf(irf, SHIFT), response_from_irf(np.clip(irf, 0, None), SHIFT)
    assert noisy.start == clipped.start
    np.testing.assert_array_equal(noisy.values, clipped.values)


def test_an_irf_is_refused_unless_a_finite_profile_with_light(response):
    for irf, why in (
        (np.ones((2, 5)), "1-D with at least 4 samples"),
        (np.ones(3), "1-D with at least 4 samples"),
        (np.array([0.0, 1.0, np.inf, 1.0]), "NaN or infinite"),
        (-np.ones(6), "all zero"),  # background-subtracted noise alone
        # The peak outside the scan: h's scale and timing origin unknown (110-300 ps off)
        (np.array([1.0, 0.8, 0.5, 0.2, 0.1]), "peaks at its first sample"),
        (np.array([0.1, 0.5, 0.9, 1.0]), "peaks at its last sample"),
    ):
        with pytest.raises(ValueError, match=why):
            response_from_irf(irf, SHIFT)


def test_an_irf_tail_of_two_decays_is_extended_along_its_last_slope():
    # Two decay constants make log h convex where the scan cuts it: a parabola through
    # the edge's samples would turn upwards, so h goes on along the straight line (in
    # log h) through the last two samples, h(t_end + d) = h(t_end) exp(-s d) with
    # s = ln(y[-2] / y[-1]) / shift. The early edge rises from 0 into the scan (its peak
    # inside it): no extension.
    n = np.arange(30)
    irf = np.concatenate([[0.0, 0.5], 0.5 * np.exp(-n / 3) + 0.5 * np.exp(-n / 12)])
    h = response_from_irf(irf, SHIFT)
    t_end, slope = 31 * SHIFT, np.log(irf[-2] / irf[-1]) / SHIFT
    d = np.array([20.0, 100.0, 500.0]) * PS
    np.testing.assert_allclose(h(t_end + d) / h(t_end), np.exp(-slope * d), rtol=1e-3)
    assert h.start == 0.0


def test_an_irf_tail_with_zeros_among_its_last_samples_is_extended_through_the_others():
    # Background-subtracted noise clips tail samples to 0: of the last four only two
    # are positive, too few for the parabola; h goes on along the straight line (in
    # log h) through those two, 2 shifts apart: h(t_end + d) = h(t_end) 2^(-d / 2 shift).
    # (A parabola through two points is underdetermined: numpy warns, RankWarning.)
    irf = np.array([0.0, 0.1, 0.5, 1.0, 0.5, 0.1, 0.0, 0.04, 0.0, 0.02])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        h = response_from_irf(irf, SHIFT)
    t_end = 9 * SHIFT
    d = np.array([20.0, 100.0, 500.0]) * PS
    np.testing.assert_allclose(h(t_end + d) / h(t_end), 2.0 ** (-d / (2 * SHIFT)), rtol=1e-3)
    assert h.start == 0.0  # the early edge starts at 0: no extension


def test_irf_reference_time_shifts_the_response(response):
    irf = response(scan_times(T, SHIFT) - 500 * PS)  # reference target at 500 ps
    from_irf = response_from_irf(irf, SHIFT, t_ref=500 * PS)
    assert from_irf.peak_time == pytest.approx(response.peak_time, abs=2 * PS)
