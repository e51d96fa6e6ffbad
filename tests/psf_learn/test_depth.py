"""Gated-SPAD depth: gate model oracles, per-pixel fit recovery, IRF path, CLI contract."""

import json
import subprocess
import sys
import types
import warnings
from math import erf, sqrt

import numpy as np
import pytest

from doe.infra.cli import main
from doe.infra.errors import InputError
from psf_learn.cubes import read_cube, scan_gaps, write_frame_png16
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

PS = 1e-12
SHIFT = 20 * PS
T = 120  # 2.4 ns scan: room for a complete profile anywhere in [0.62, 0.82] ns


@pytest.fixture(scope="module")
def response():
    return gate_response(GateModel())


def scene(shape, amplitude, background, response, seed, margin=None):
    rng = np.random.default_rng(seed)
    return random_scene(shape, amplitude, background, SHIFT, T, response, rng, margin)


# --- the gate model ---------------------------------------------------------------------


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


# --- the fit ------------------------------------------------------------------------------


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


# --- the measured-IRF path ---------------------------------------------------------------


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


# --- files and the command line -----------------------------------------------------------


def write_scene_cube(tmp_path, response, shape=(6, 10), amplitude=80.0, background=2.0, seed=12):
    a, mu, b = scene(shape, amplitude, background, response, seed)
    a[0, 0] = 0.0
    cube = simulate_cube(a, mu, b, T, SHIFT, response, np.random.default_rng(seed + 1))
    path = tmp_path / "cube.npy"
    np.save(path, cube.astype(np.uint16))
    return path, mu


def write_frame_folder(folder, cube, names):
    folder.mkdir()
    for k, name in enumerate(names):
        write_frame_png16(folder / name, cube[..., k] / 65535.0)
    return folder


@pytest.mark.parametrize(
    "names, note",
    [
        ([f"shift_{k}.png" for k in range(12) if k != 5], "from shift_4.png to shift_6.png (1"),
        ([f"gate_{0.02 * k:g}ns.png" for k in (0, 1, 2, 5, 6, 8)],
         "by 0.02 but jump from gate_0.04ns.png to gate_0.1ns.png (3"),
        ([f"t_{k}ps.png" for k in range(-60, 60, 20)], None),  # signed, complete
        ([f"gate_{0.02 * k:g}ns.png" for k in range(9)], None),  # decimals, complete
        ([f"img_{k}.png" for k in (1003, 1017, 1052, 1060)], None),  # no common step
        ([f"cam{k % 2}_{k}.png" for k in (0, 1, 3, 4)], None),  # two numbers vary
    ],
)  # fmt: skip
def test_a_frame_missing_from_a_numbered_scan_is_noted(tmp_path, names, note):
    # Every frame is one scan step: a lost frame moved every later return by a step, and
    # a folder with one missing was accepted without a word.
    cube = np.zeros((2, 3, len(names)), np.uint16)
    folder = write_frame_folder(tmp_path / "frames", cube, names)
    gaps = scan_gaps(folder)
    if note is None:
        assert gaps == []
    else:
        assert len(gaps) == 1 and note in gaps[0]
    np.save(tmp_path / "cube.npy", cube)
    assert scan_gaps(tmp_path / "cube.npy") == []


def test_cli_depth_warns_of_a_frame_missing_from_the_scan(tmp_path, response, capsys):
    path, _ = write_scene_cube(tmp_path, response, shape=(2, 3))
    cube = np.load(path)
    names = [f"shift_{k:03d}.png" for k in range(T + 1) if k != 40]  # frame 40 lost
    folder = write_frame_folder(tmp_path / "frames", cube, names)
    assert main(["depth", str(folder), "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "depth: warning: the frame names step by 1 but jump from shift_039.png" in err
    warnings = json.loads((tmp_path / "out" / "depth.json").read_text())["warnings"]
    assert any("shift_041.png (1 frame(s) missing" in w for w in warnings)
    assert main(["transient", str(folder), "--out", str(tmp_path / "tr")]) == 0
    assert "transient: warning: the frame names step by 1" in capsys.readouterr().err
    assert json.loads((tmp_path / "tr" / "transient.json").read_text())["warnings"]


def test_cli_depth_round_trip(tmp_path, response, capsys):
    path, mu = write_scene_cube(tmp_path, response)
    out = tmp_path / "out"
    assert main(["depth", str(path), "--shift-ps", "20", "--out", str(out)]) == 0
    timing = np.load(out / "timing_ps.npy")
    depth = np.load(out / "depth_m.npy")
    valid = np.load(out / "valid.npy")
    assert timing.shape == depth.shape == valid.shape == mu.shape
    assert not valid[0, 0] and np.isnan(depth[0, 0])
    assert valid.sum() == valid.size - 1
    np.testing.assert_allclose(timing[valid], mu[valid] / PS, atol=25)
    np.testing.assert_allclose(depth[valid], SPEED_OF_LIGHT * timing[valid] * PS / 2)
    for name in ("amplitude", "background", "fit_quality"):
        assert np.load(out / f"{name}.npy").shape == mu.shape
    for name in ("intensity.png", "depth.png", "pixel_fits.png", "depth.json"):
        assert (out / name).stat().st_size > 0
    first = {p.name: p.read_bytes() for p in out.iterdir()}
    # A second run refuses to overwrite; with --force it writes identical bytes.
    assert main(["depth", str(path), "--out", str(out)]) == 2
    assert "--force" in capsys.readouterr().err
    assert main(["depth", str(path), "--out", str(out), "--force"]) == 0
    assert {p.name: p.read_bytes() for p in out.iterdir()} == first


def test_cli_depth_of_a_dark_scene_reports_no_returns(tmp_path, capsys):
    # A cube without any return once printed "timing nan .. nan ps".
    path = tmp_path / "dark.npy"
    np.save(path, np.random.default_rng(3).poisson(2.0, (4, 5, T)).astype(np.uint16))
    assert main(["depth", str(path), "--out", str(tmp_path / "out")]) == 0
    line = capsys.readouterr().out
    assert "0/20 pixels with a return, no timing" in line and "nan" not in line
    assert not np.load(tmp_path / "out" / "valid.npy").any()


def test_example_fits_show_each_pixel_once_and_a_non_return_only_if_there_is_one():
    # pixel_fits.png: brightest, median and dimmest return, then the first non-return;
    # with one or two returns some of these are the same pixel, shown once
    from psf_learn.commands.depth import _example_pixels

    def picks(valid, amplitude):
        fit = types.SimpleNamespace(valid=np.array(valid), amplitude=np.array(amplitude, float))
        return [(int(r), int(c), why) for r, c, why in _example_pixels(fit)]

    every = picks([[True, True], [True, True]], [[3, 1], [4, 2]])  # every pixel returns
    assert every == [(1, 0, "brightest"), (0, 0, "median"), (0, 1, "dimmest")]
    one = picks([[False, True], [False, False]], [[0, 7], [0, 0]])
    assert one == [(0, 1, "brightest"), (0, 0, "no return")]
    two = picks([[True, True]], [[5, 2]])  # the median of two is the brightest
    assert two == [(0, 0, "brightest"), (0, 1, "dimmest")]


def test_cli_depth_with_irf(tmp_path, response, capsys):
    path, mu = write_scene_cube(tmp_path, response)
    np.save(tmp_path / "irf.npy", response(scan_times(T, SHIFT) - 1000 * PS))
    out = tmp_path / "out"
    irf = ["--irf", str(tmp_path / "irf.npy"), "--irf-t0-ps", "1000"]
    assert main(["depth", str(path), *irf, "--out", str(out)]) == 0
    timing, valid = np.load(out / "timing_ps.npy"), np.load(out / "valid.npy")
    np.testing.assert_allclose(timing[valid], mu[valid] / PS, atol=25)
    # The IRF replaces the gate model: giving both is a usage error.
    assert main(["depth", str(path), "--irf", str(tmp_path / "irf.npy"), "--rise-ps", "30",
                 "--out", str(tmp_path / "o2")]) == 2  # fmt: skip
    for t0 in ("nan", "inf"):
        args = [*irf[:2], "--irf-t0-ps", t0, "--out", str(tmp_path / "o2")]
        assert main(["depth", str(path), *args]) == 2
        assert "--irf-t0-ps: must be a finite number" in capsys.readouterr().err
    assert not (tmp_path / "o2").exists()


def test_cli_depth_warns_when_the_profiles_do_not_follow_the_model(tmp_path, response, capsys):
    path, _ = write_scene_cube(tmp_path, response, shape=(4, 40), amplitude=300.0)
    cube = np.load(path)
    out = tmp_path / "out"
    assert main(["depth", str(path), "--out", str(out)]) == 0
    assert "warning" not in capsys.readouterr().err
    assert json.loads((out / "depth.json").read_text())["warnings"] == []
    # The same counts with the time axis first: (T, H, W) read as (H, W, T).
    wrong = tmp_path / "wrong.npy"
    np.save(wrong, np.ascontiguousarray(np.moveaxis(cube, -1, 0)))
    assert main(["depth", str(wrong), "--out", str(tmp_path / "o2")]) == 0
    err = capsys.readouterr().err
    assert "do not follow the response model" in err and "(H, W, T)" in err
    assert json.loads((tmp_path / "o2" / "depth.json").read_text())["warnings"]


def test_cli_depth_warns_when_the_irf_is_cut_high_up(tmp_path, response, capsys):
    path, _ = write_scene_cube(tmp_path, response)
    x = response.times[response.values >= 0.8]  # cut at 0.8 of the peak, at the end
    t_ref = (T - 1) * SHIFT - x[-1]
    np.save(tmp_path / "irf.npy", response(scan_times(T, SHIFT) - t_ref))
    args = ["--irf", str(tmp_path / "irf.npy"), "--irf-t0-ps", str(t_ref / PS)]
    assert main(["depth", str(path), *args, "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "IRF is cut at 0.8" in err and "end of the scan" in err
    warnings = json.loads((tmp_path / "out" / "depth.json").read_text())["warnings"]
    assert len(warnings) == 1 and "IRF" in warnings[0]
    # Cut past its peak: refused, naming the file (it passed with the same warning).
    t_ref = (T - 1) * SHIFT - response.times[np.argmax(response.values)] + 3 * SHIFT
    np.save(tmp_path / "past.npy", response(scan_times(T, SHIFT) - t_ref))
    args = ["--irf", str(tmp_path / "past.npy"), "--irf-t0-ps", str(t_ref / PS)]
    assert main(["depth", str(path), *args, "--out", str(tmp_path / "o2")]) == 2
    assert "past.npy: the IRF peaks at its last sample" in capsys.readouterr().err
    assert not (tmp_path / "o2").exists()


def bad_cubes():
    good = np.ones((4, 5, 10))
    nan = good.copy()
    nan[1, 2, 3] = np.nan
    neg = good.copy()
    neg[0, 0, 0] = -1
    return {"rank2": good[0], "rank4": good[None], "nan": nan, "negative": neg,
            "short": good[..., :3], "complex": good.astype(complex)}  # fmt: skip


@pytest.mark.parametrize("kind", sorted(bad_cubes()))
def test_bad_cubes_are_refused(tmp_path, kind):
    path = tmp_path / f"{kind}.npy"
    np.save(path, bad_cubes()[kind])
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "doe", "depth", str(path), "--out", str(out)],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and str(path) in lines[0]
    assert not out.exists()


def test_bad_flags_are_refused(tmp_path, response, capsys):
    path, _ = write_scene_cube(tmp_path, response, shape=(2, 2))
    # The last four once ended in tracebacks or were silently ignored: a 1 ms fall
    # time needs a 25 us response, a 1 ns step samples the ~312 ps response less
    # than once, 0.1 ps steps scan 12 ps of it.
    for flags in (["--shift-ps", "0"], ["--gate-width-ps", "-5"], ["--tau-ps", "10"],
                  ["--pulse", "emg"], ["--irf", str(tmp_path / "missing.npy")],
                  ["--fall-ps", "1e9"], ["--shift-ps", "1000"], ["--shift-ps", "0.1"],
                  ["--irf-t0-ps", "5"]):  # fmt: skip
        assert main(["depth", str(path), "--out", str(tmp_path / "o"), *flags]) == 2
        assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()
    for fps in ("0", "60", "1000"):  # a GIF frame of under 2 centiseconds plays as 10
        assert main(["transient", str(path), "--out", str(tmp_path / "t"), "--fps", fps]) == 2
        assert "--fps" in capsys.readouterr().err
    assert not (tmp_path / "t").exists()


@pytest.mark.parametrize(
    "fps, centiseconds", [(10, 10), (30, 3), (50, 2), (0.5, 200), (41, 3), (29, 4)]
)
def test_preview_gif_plays_at_the_nearest_rate(tmp_path, response, fps, centiseconds):
    # 41 fps: 3 cs plays 33.3, nearer than 2 cs (50); 29 fps: 4 cs (25) beats 3 cs (33.3).
    from PIL import Image

    path, _ = write_scene_cube(tmp_path, response, shape=(2, 2))
    out = tmp_path / "t"
    assert main(["transient", str(path), "--out", str(out), "--fps", str(fps)]) == 0
    with Image.open(out / "preview.gif") as gif:
        gif.seek(1)
        assert gif.info["duration"] == 10 * centiseconds
    played = json.loads((out / "transient.json").read_text())["gif_fps"]
    assert played == pytest.approx(100 / centiseconds)


def test_scan_must_sample_the_response():
    fwhm = gate_response(GateModel()).fwhm
    ok = gate_response(GateModel())
    check_scan(4, fwhm / 3, ok)
    check_scan(120, fwhm, ok)
    for n, shift in ((3, SHIFT), (120, 1.01 * fwhm), (4, fwhm / 3.1)):
        with pytest.raises(ValueError):
            check_scan(n, shift, ok)


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


@pytest.mark.parametrize(
    "name",
    ["shift_{k:03d}.png", "shift_{k}.png", "gate_{t:g}ns.png", "t_{s}ps.png", "frame-{k}.png"],
)
def test_frame_folder_is_read_as_uint16_in_name_order(tmp_path, name):
    # Unpadded numbers count as numbers: shift_2 comes before shift_10, and a gate delay
    # written as a decimal is one number: gate_0.02ns before gate_0.1ns before gate_0.12ns.
    # A delay's sign counts where the names differ by it (t_-20ps before t_0ps; they were
    # sorted 0, 20, ..., -20, -40), and a dash every name has is no sign (frame-10).
    rng = np.random.default_rng(13)
    cube = rng.integers(0, 4000, size=(5, 7, 12)).astype(np.uint16)
    folder = tmp_path / "frames"
    folder.mkdir()
    for k in range(cube.shape[-1]):
        write_frame_png16(
            folder / name.format(k=k, t=0.02 * k, s=20 * (k - 5)), cube[..., k] / 65535.0
        )
    (folder / "._shift_000.png").write_bytes(b"\x00\x05\x16\x07 macOS metadata")
    np.testing.assert_array_equal(read_cube(folder), cube.astype(np.float64))


def test_a_cube_needs_its_fewest_samples_and_no_negative_counts():
    from psf_learn.cubes import check_cube

    ones = np.ones((2, 3, 4))
    assert check_cube(ones, "c.npy").shape == (2, 3, 4)  # 4 samples fit a return
    with pytest.raises(InputError, match="T >= 4"):
        check_cube(ones[..., :3], "c.npy")
    assert check_cube(ones[..., :1], "c.npy", min_samples=1).shape == (2, 3, 1)
    with pytest.raises(InputError, match="negative counts"):  # integers too
        check_cube(-np.ones((2, 3, 4), np.int32), "c.npy")


def test_an_irf_is_read_as_one_row_and_needs_light(tmp_path):
    from psf_learn.cubes import read_irf

    irf = np.exp(-0.5 * (np.arange(20) - 8.0) ** 2)
    np.save(tmp_path / "row.npy", irf[None, :])  # saved as a (1, T) row: one response
    np.testing.assert_array_equal(read_irf(tmp_path / "row.npy"), irf)
    np.save(tmp_path / "dark.npy", np.zeros(20))
    with pytest.raises(InputError, match=r"dark\.npy.*no positive sample"):
        read_irf(tmp_path / "dark.npy")


def test_frames_are_written_rounded_to_the_nearest_16_bit_code(tmp_path):
    import OpenImageIO as oiio

    codes = np.array([[0.0, 0.4, 0.6, 1.5], [100.49, 100.51, 65534.6, 65535.0]])
    write_frame_png16(tmp_path / "f.png", codes / 65535)
    read = oiio.ImageInput.open(str(tmp_path / "f.png"))
    got = read.read_image(0, 0, 0, 1, "uint16")[..., 0]
    read.close()
    np.testing.assert_array_equal(got, [[0, 0, 1, 2], [100, 101, 65535, 65535]])


def write_frame(path, array, fmt):
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(array.shape[1], array.shape[0], array.shape[2], fmt)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(array)
    out.close()


def test_frame_folder_8bit_tiff_and_bad_folders(tmp_path):
    import OpenImageIO as oiio

    cube = np.random.default_rng(14).integers(0, 256, size=(3, 4, 5)).astype(np.uint8)
    good = tmp_path / "good"
    good.mkdir()
    for k in range(5):
        write_frame(good / f"{k}.tif", cube[..., k][:, :, None], oiio.UINT8)
    np.testing.assert_array_equal(read_cube(good), cube)
    # An RGB frame, a frame of another size, an empty folder: exit 2 naming the file.
    rgb = tmp_path / "rgb"
    rgb.mkdir()
    for k in range(4):
        write_frame(rgb / f"{k}.png", np.zeros((3, 4, 3), np.uint8), oiio.UINT8)
    sizes = tmp_path / "sizes"
    sizes.mkdir()
    for k in range(4):
        write_frame(sizes / f"{k}.png", np.zeros((3, 4 + (k == 2), 1), np.uint8), oiio.UINT8)
    # A float frame among 16-bit counts (once stacked as if both were counts).
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for k in range(4):
        frame = np.full((3, 4, 1), 0.5 if k == 3 else 2000, np.float32 if k == 3 else np.uint16)
        write_frame(mixed / f"{k}.tif", frame, oiio.FLOAT if k == 3 else oiio.UINT16)
    # A float frame with NaN or negative counts (the folder was named, not the frame).
    bad = {}
    for name, value in (("nan", np.nan), ("negative", -90.0)):
        bad[name] = tmp_path / name
        bad[name].mkdir()
        for k in range(4):
            frame = np.full((3, 4, 1), value if k == 1 else 5.0, np.float32)
            write_frame(bad[name] / f"s_{k}.tif", frame, oiio.FLOAT)
    empty = tmp_path / "empty"
    empty.mkdir()
    for folder, culprit in (
        (rgb, "0.png"),
        (sizes, "2.png"),
        (mixed, "3.tif"),
        (bad["nan"], "s_1.tif: frame contains 12 NaN"),
        (bad["negative"], "s_1.tif: frame has negative counts"),
        (empty, "empty"),
    ):
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "doe",
                "depth",
                str(folder),
                "--out",
                str(tmp_path / "o"),
            ],
            capture_output=True,
            text=True,
        )
        assert proc.returncode == 2 and culprit in proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_cli_transient(tmp_path, response):
    path, _ = write_scene_cube(tmp_path, response, shape=(4, 6))
    out = tmp_path / "out"
    assert main(["transient", str(path), "--out", str(out)]) == 0
    frames = np.load(out / "frames.npy")
    cube = np.load(path)
    np.testing.assert_array_equal(frames, np.moveaxis(cube, -1, 0))
    assert len(list((out / "frames").glob("frame_*.png"))) == T
    assert (out / "preview.gif").read_bytes()[:6] in (b"GIF89a", b"GIF87a")
    times = json.loads((out / "transient.json").read_text())["times_ps"]
    assert times == [k * 20.0 for k in range(T)] and times[5] == 100.0  # not 99.99999999999999


def test_cli_transient_shows_one_frame_and_a_tall_sensor(tmp_path):
    # Frames need no fit: one is enough. A 300 x 1 sensor enlarged to 256 px wide
    # would be 76800 px tall, more than a GIF can hold.
    from PIL import Image

    np.save(tmp_path / "one.npy", np.full((3, 2, 1), 7.0))
    assert main(["transient", str(tmp_path / "one.npy"), "--out", str(tmp_path / "a")]) == 0
    assert np.load(tmp_path / "a" / "frames.npy").shape == (1, 3, 2)
    np.save(tmp_path / "tall.npy", np.arange(600.0).reshape(300, 1, 2))
    assert main(["transient", str(tmp_path / "tall.npy"), "--out", str(tmp_path / "b")]) == 0
    with Image.open(tmp_path / "b" / "preview.gif") as gif:
        assert gif.size == (218, 300 * 218)  # the largest whole factor within 65535


def fake_sr_module():
    """A stand-in for psf_learn.sr: 4x nearest-neighbour upsampling of (..., h, w)."""

    def super_resolve(model, frames, photons=None):
        frames = np.asarray(frames, dtype=np.float64)
        return np.repeat(np.repeat(frames, 4, axis=-2), 4, axis=-1)

    return types.SimpleNamespace(super_resolve=super_resolve)


@pytest.fixture
def sr_model(tmp_path, monkeypatch):
    """A model folder for --sr, with psf_learn.sr replaced by :func:`fake_sr_module`."""
    monkeypatch.setitem(sys.modules, "psf_learn.sr", fake_sr_module())
    model = tmp_path / "model"
    model.mkdir()
    return model


def test_cli_depth_and_transient_super_resolve(tmp_path, response, sr_model):
    path, _ = write_scene_cube(tmp_path, response, shape=(3, 4))
    out = tmp_path / "out"
    assert main(["depth", str(path), "--out", str(out), "--sr", str(sr_model)]) == 0
    native = np.load(out / "timing_ps.npy")
    sr = np.load(out / "sr" / "timing_ps.npy")
    assert sr.shape == (12, 16)
    np.testing.assert_allclose(sr, np.repeat(np.repeat(native, 4, 0), 4, 1), atol=0.05)
    short = tmp_path / "short.npy"
    np.save(short, np.load(path)[..., :5])
    out2 = tmp_path / "out2"
    assert main(["transient", str(short), "--out", str(out2), "--sr", str(sr_model)]) == 0
    frames = np.load(out2 / "frames.npy")
    assert frames.shape == (5, 12, 16)
    np.testing.assert_array_equal(frames[:, ::4, ::4], np.moveaxis(np.load(short), -1, 0))


def test_a_super_resolved_cube_has_one_white_its_maximum_and_no_negative_counts(
    tmp_path, monkeypatch
):
    # One white level keeps the frames on a common scale; a network's undershoot below 0
    # is not a count. The stand-in records its white and undershoots by half of it.
    from psf_learn.commands.depth import _super_resolve_cube

    whites = []

    def super_resolve(model, frames, photons=None):
        whites.append(photons)
        return np.repeat(np.repeat(frames, 4, axis=-2), 4, axis=-1) - 0.5 * photons

    sr = types.SimpleNamespace(super_resolve=super_resolve)
    monkeypatch.setitem(sys.modules, "psf_learn.sr", sr)
    cube = np.random.default_rng(3).integers(0, 50, size=(3, 4, 6)).astype(np.float64)
    cube[1, 2, 3] = 80.0
    hr = _super_resolve_cube(tmp_path, cube)
    assert whites == [80.0]
    upsampled = np.repeat(np.repeat(cube, 4, axis=0), 4, axis=1)
    np.testing.assert_array_equal(hr, np.clip(upsampled - 40.0, 0.0, None))


def test_cli_force_leaves_no_frames_or_sr_maps_of_an_older_cube(tmp_path, response, sr_model):
    path, _ = write_scene_cube(tmp_path, response, shape=(3, 4))
    short = tmp_path / "short.npy"
    np.save(short, np.load(path)[..., :5])
    out = tmp_path / "t"
    assert main(["transient", str(path), "--out", str(out)]) == 0
    assert main(["transient", str(short), "--out", str(out), "--force"]) == 0
    assert len(list((out / "frames").glob("frame_*.png"))) == 5
    out = tmp_path / "d"
    assert main(["depth", str(path), "--out", str(out), "--sr", str(sr_model)]) == 0
    assert main(["depth", str(path), "--out", str(out), "--force"]) == 0
    assert not (out / "sr").exists()
    # a lab's own sr/ files, in a folder no run with --sr wrote, are not the run's to remove
    (out / "sr").mkdir()
    (out / "sr" / "depth.png").write_text("the lab's")
    assert main(["depth", str(path), "--out", str(out), "--force"]) == 0
    assert (out / "sr" / "depth.png").read_text() == "the lab's"


def test_depth_module_does_not_import_torch():
    code = "import sys, psf_learn.depth, psf_learn.depth_sim, psf_learn.cubes, psf_learn.commands.depth; print('torch' in sys.modules)"  # noqa: E501
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_depth_maps_show_row_0_at_the_top_and_invalid_pixels_grey(
    tmp_path, saved_figures, colour_at
):
    from psf_learn.depth_plots import save_map

    image = np.zeros((3, 5))
    image[0, 4] = 1.0  # top right, lit
    valid = np.ones((3, 5), bool)
    valid[2, 0] = False  # bottom left, no fit
    save_map(tmp_path / "map.png", image, "depth", "m", valid=valid)
    (ax,) = [a for a in saved_figures[-1].axes if a.images]

    def at(row, col):  # the centre of a cell, from the top left as displayed
        return colour_at(ax, (col + 0.5) / 5, 1 - (row + 0.5) / 3, space="axes")

    assert at(0, 4).min() > 200 and at(0, 0).max() < 60  # grey scale: white is 1, black 0
    assert np.all(np.abs(at(2, 0) - 0.6 * 255) < 3)  # "0.6" grey
    assert at(2, 4).max() < 60 and at(1, 2).max() < 60


# --- from a coverage run: paths no test took ------------------------------------------------


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


def test_example_fits_of_an_odd_count_leave_the_last_cell_blank(tmp_path, saved_figures):
    from psf_learn.depth_plots import save_pixel_fits

    profiles = np.ones((3, T))
    save_pixel_fits(tmp_path / "f.png", scan_times(T, SHIFT), profiles, [None] * 3, list("abc"))
    assert [ax.axison for ax in saved_figures[-1].axes] == [True, True, True, False]


def test_transient_refuses_frames_too_wide_for_a_gif(tmp_path, capsys):
    np.save(tmp_path / "wide.npy", np.ones((1, 65536, 1)))
    out = tmp_path / "t"
    assert main(["transient", str(tmp_path / "wide.npy"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "wide.npy: frames of 1 x 65536 pixels" in err
    assert "at most 65535 pixels a side" in err and not out.exists()


def test_sr_needs_a_model_folder(tmp_path, response, sr_model, capsys):
    path, _ = write_scene_cube(tmp_path, response, shape=(2, 2))
    gone, hint = tmp_path / "gone", "(write one with 'doefab learn')"
    for command in ("depth", "transient"):
        assert main([command, str(path), "--out", str(tmp_path / "o"), "--sr", str(gone)]) == 2
        err = capsys.readouterr().err.strip()
        assert err == f"doefab {command}: error: {gone}: no such model folder {hint}"
    assert not (tmp_path / "o").exists()


def test_a_cube_path_must_be_an_npy_file_or_a_folder_of_frames(tmp_path):
    import OpenImageIO as oiio

    with pytest.raises(InputError, match=r"gone\.npy: no such file or folder"):
        read_cube(tmp_path / "gone.npy")
    write_frame_png16(tmp_path / "frame.png", np.zeros((3, 4)))  # one frame, not the folder
    with pytest.raises(InputError, match=r"frame\.png: a cube must be a \.npy file or a folder"):
        read_cube(tmp_path / "frame.png")
    wide = tmp_path / "uint32"
    wide.mkdir()
    for k in range(4):
        write_frame(wide / f"{k}.tif", np.zeros((3, 4, 1), np.uint32), oiio.UINT32)
    with pytest.raises(InputError, match=r"0\.tif: unsupported pixel type uint"):
        read_cube(wide)


def test_an_irf_must_be_a_finite_row_of_numbers(tmp_path):
    from psf_learn.cubes import read_irf

    for name, irf, why in (
        ("mask.npy", np.ones(8, bool), "IRF must be numeric, got dtype bool"),
        (
            "table.npy",
            np.ones((3, 8)),
            r"IRF must be 1-D with at least 4 samples, got shape \(3, 8\)",
        ),
        ("short.npy", np.ones(3), "IRF must be 1-D with at least 4 samples"),
        ("inf.npy", np.array([0.0, 1.0, np.inf, 1.0]), "IRF contains NaN or infinite values"),
    ):
        np.save(tmp_path / name, irf)
        with pytest.raises(InputError, match=rf"{name.replace('.', '[.]')}: {why}"):
            read_irf(tmp_path / name)


def test_a_frame_that_cannot_be_written_raises_an_oserror_naming_it(tmp_path, monkeypatch):
    import OpenImageIO as oiio

    with pytest.raises(OSError, match=r"cannot write .*frame\.xyz: .*could not find a format"):
        write_frame_png16(tmp_path / "frame.xyz", np.zeros((2, 2)))
    # no such folder: the reason was left out ("cannot write .../frame.png: ")
    with pytest.raises(OSError, match=r"cannot write .*gone/frame\.png: Could not open file"):
        write_frame_png16(tmp_path / "gone" / "frame.png", np.zeros((2, 2)))

    class FullDisk:  # the header written, the pixels refused
        closed = False

        def open(self, path, spec):
            return True

        def write_image(self, data):
            return False

        def geterror(self):
            return "No space left on device"

        def close(self):
            FullDisk.closed = True

    monkeypatch.setattr(oiio, "ImageOutput", types.SimpleNamespace(create=lambda p: FullDisk()))
    with pytest.raises(OSError, match=r"cannot write .*full\.png: No space left on device"):
        write_frame_png16(tmp_path / "full.png", np.zeros((2, 2)))
    assert FullDisk.closed
