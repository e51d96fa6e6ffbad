"""The forward model of CONVENTIONS.md: power, analytic efficiencies, orientation and sign."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from doe import fraunhofer
from doe.refinement import window_matrix


def test_parseval_all_orders_carry_unit_power():
    rng = np.random.default_rng(1)
    for n in (7, 32, 45):
        amp = fraunhofer.order_amplitudes(rng.uniform(-10, 10, (n, n)))
        assert (np.abs(amp) ** 2).sum() == pytest.approx(1.0, abs=1e-12)


def test_window_power_matches_contract_formula(window_from_contract):
    rng = np.random.default_rng(2)
    levels = rng.integers(0, 8, (23, 23)).astype(np.uint8)
    got = fraunhofer.window_power(fraunhofer.level_phase(levels, 8), 7)
    np.testing.assert_allclose(got, window_from_contract(levels, 8, 7), rtol=0, atol=1e-15)
    psf, eff = fraunhofer.simulate_levels(levels, 8, 7)
    assert eff == pytest.approx(got.sum(), rel=1e-14)
    assert psf.sum() == pytest.approx(1.0, abs=1e-14)


def test_partial_dft_equals_fft_window():
    rng = np.random.default_rng(3)
    n, k = 29, 9
    phase = rng.uniform(0, 2 * np.pi, (n, n))
    a = window_matrix(n, k)
    w = a @ np.exp(1j * phase) @ a.T / n**2
    idx = fraunhofer.window_indices(n, k)
    np.testing.assert_allclose(w, fraunhofer.order_amplitudes(phase)[np.ix_(idx, idx)], atol=1e-13)


def _staircase(n_levels, steps_width):
    """Levels growing by one every ``steps_width`` columns: L equal steps across the tile."""
    n = n_levels * steps_width
    row = np.arange(n) // steps_width
    return np.tile(row, (n, 1)).astype(np.uint8)


@pytest.mark.parametrize("n_levels", [2, 4, 8, 16])
def test_staircase_grating_first_order_is_sinc_squared(n_levels):
    width = 4096 // n_levels  # fine sampling: the discrete sum converges to sinc^2 as 1/N^2
    levels = _staircase(n_levels, width)[:1]  # one row suffices: the tile is 1-D
    field = np.exp(2j * np.pi * levels[0] / n_levels)
    first = abs(np.fft.fft(field)[1] / field.size) ** 2
    assert first == pytest.approx(np.sinc(1 / n_levels) ** 2, rel=1e-5)


@pytest.mark.parametrize("n_levels", [4, 8, 16])  # L = 2 is symmetric: +1 and -1 tie
def test_staircase_tile_exact_sampled_efficiency_and_orientation(n_levels):
    width = 5
    levels = _staircase(n_levels, width)
    n = levels.shape[0]
    k = 5
    window = fraunhofer.window_power(fraunhofer.level_phase(levels, n_levels), k)
    # exact sampled staircase: |(L/N) sin(pi/L) / sin(pi/N)|^2 -> sinc^2(1/L)
    exact = ((n_levels / n) * np.sin(np.pi / n_levels) / np.sin(np.pi / n)) ** 2
    # levels grow towards +x (column index): the light goes to column K//2 + 1, row K//2
    assert window[k // 2, k // 2 + 1] == pytest.approx(exact, rel=1e-12)
    # ... which exceeds sinc^2 by the sampling factor ((pi/N) / sin(pi/N))^2 ~ 1 + (pi/N)^2/3
    sampling = (np.pi / n) ** 2 / 3
    assert window[k // 2, k // 2 + 1] == pytest.approx(
        np.sinc(1 / n_levels) ** 2, rel=1.05 * sampling
    )
    assert window.argmax() == np.ravel_multi_index((k // 2, k // 2 + 1), window.shape)
    # the same ramp down the rows (towards -y) goes to row K//2 + 1
    window_t = fraunhofer.window_power(fraunhofer.level_phase(levels.T, n_levels), k)
    assert window_t.argmax() == np.ravel_multi_index((k // 2 + 1, k // 2), window.shape)
    # a falling ramp (levels decreasing with x) goes to -x
    flipped = fraunhofer.window_power(fraunhofer.level_phase(levels[:, ::-1], n_levels), k)
    assert flipped.argmax() == np.ravel_multi_index((k // 2, k // 2 - 1), window.shape)


def test_conjugated_plate_gives_point_reflected_psf():
    rng = np.random.default_rng(4)
    n_levels, k = 8, 9
    levels = rng.integers(0, n_levels, (31, 31)).astype(np.uint8)
    conj = ((n_levels - levels.astype(int)) % n_levels).astype(np.uint8)
    psf, eff = fraunhofer.simulate_levels(levels, n_levels, k)
    psf_c, eff_c = fraunhofer.simulate_levels(conj, n_levels, k)
    np.testing.assert_allclose(psf_c, psf[::-1, ::-1], atol=1e-14)
    assert eff_c == pytest.approx(eff, rel=1e-12)
    assert not np.allclose(psf, psf[::-1, ::-1], atol=1e-6)  # the test can tell them apart


def test_flat_plate_sends_everything_to_the_axis():
    psf, eff = fraunhofer.simulate_levels(np.full((15, 15), 3, np.uint8), 8, 5)
    assert eff == pytest.approx(1.0, abs=1e-14)
    assert psf[2, 2] == pytest.approx(1.0, abs=1e-14)


def test_quality_figures_are_the_contract_definitions(window_from_contract):
    rng = np.random.default_rng(5)
    phase = rng.uniform(0, 2 * np.pi, (25, 25))
    target = rng.uniform(0, 1, (5, 5))
    target /= target.sum()
    q = fraunhofer.quality(phase, target)
    window = window_from_contract(phase * 8 / (2 * np.pi), 8, 5)
    sim = window / window.sum()
    assert q["efficiency"] == pytest.approx(window.sum(), rel=1e-12)
    assert q["correlation"] == pytest.approx(np.corrcoef(sim.ravel(), target.ravel())[0, 1])
    ref = np.sqrt(np.mean((sim / sim.max() - target / target.max()) ** 2))
    assert q["rmse"] == pytest.approx(ref, rel=1e-12)


def test_correlation_with_a_uniform_target_is_undefined_not_noise():
    rng = np.random.default_rng(1)
    psf = rng.uniform(0, 1, (11, 11))
    # 1/121 does not sum exactly: the mean leaves rounding residues, not variation
    assert np.isnan(fraunhofer.correlation(psf, np.full((11, 11), 1 / 121)))
    assert np.isnan(fraunhofer.correlation(np.full((5, 5), 0.3), psf[:5, :5]))
    assert fraunhofer.correlation(psf, 2 * psf + 1) == pytest.approx(1.0, abs=1e-14)
    assert fraunhofer.correlation(psf, -psf) == pytest.approx(-1.0, abs=1e-14)
    # scale-free both ways: tiny values still vary, huge uniform ones still do not
    assert fraunhofer.correlation(1e-14 * psf, psf) == pytest.approx(1.0, abs=1e-14)
    assert np.isnan(fraunhofer.correlation(psf, np.full((11, 11), 1e6 / 121)))


def test_dot_lattice_image_has_every_order_with_the_pixel_envelope():
    # Order (m, n) of a tiled plate of square pixels carries |DFT[m mod N, n mod N]|^2
    # sinc^2(m/N) sinc^2(n/N); the image once held one period of orders, unweighted.
    from doe.fraunhofer import dot_lattice_image

    n, pitch = 8, 12.0
    phase = np.random.default_rng(3).uniform(0, 2 * np.pi, (n, n))
    centre = (200.3, 190.7)
    img = dot_lattice_image(phase, (400, 400), pitch, centre=centre, spot_sigma_px=0.8)
    dft = np.abs(np.fft.fft2(np.exp(1j * phase))) ** 2 / n**4
    yy, xx = np.mgrid[:400, :400]
    for m, k in ((0, 0), (3, -2), (5, -9), (-12, 14)):  # within, and beyond, one period
        r, c = centre[0] + m * pitch, centre[1] + k * pitch
        spot = img[np.hypot(yy - r, xx - c) < 4].sum()
        expected = dft[m % n, k % n] * (np.sinc(m / n) * np.sinc(k / n)) ** 2
        assert spot == pytest.approx(expected, rel=1e-4, abs=1e-12), (m, k)


def test_dot_lattice_spots_are_centred_and_reach_in_from_outside():
    from doe.fraunhofer import dot_lattice_image

    flat = np.zeros((4, 4))  # all light in the zero order
    # default centre: the middle of the image, here pixel (2, 3) of 5 x 7
    img = dot_lattice_image(flat, (5, 7), 10.0, spot_sigma_px=0.8)
    assert np.unravel_index(np.argmax(img), img.shape) == (2, 3)
    np.testing.assert_allclose(img, img[::-1, ::-1], rtol=1e-12)
    # a spot 2 sigma above the top edge still lights it: exp(-2) / (2 pi sigma^2)
    img = dot_lattice_image(flat, (5, 7), 10.0, centre=(-1.6, 3.0), spot_sigma_px=0.8)
    assert img[0, 3] == pytest.approx(np.exp(-2) / (2 * np.pi * 0.8**2), rel=1e-12)


def test_plate_quality_is_that_of_a_finely_sampled_plate_of_square_pixels():
    # each mask pixel drawn as 64 x 64 samples: the window orders of that FFT
    n, k, levels, s = 9, 5, 8, 64
    rng = np.random.default_rng(3)
    phase = fraunhofer.level_phase(rng.integers(0, levels, (n, n)), levels)
    target = rng.uniform(size=(k, k))
    target /= target.sum()
    fine = np.kron(np.exp(1j * phase), np.ones((s, s)))
    idx = (np.arange(k) - k // 2) % (n * s)
    window = np.abs(np.fft.fft2(fine)[np.ix_(idx, idx)] / fine.size) ** 2
    psf = window / window.sum()
    plate = fraunhofer.plate_quality(phase, target)
    assert plate["efficiency"] == pytest.approx(window.sum(), rel=1e-4)
    assert plate["correlation"] == pytest.approx(fraunhofer.correlation(psf, target), rel=1e-4)
    assert plate["rmse"] == pytest.approx(fraunhofer.rmse(psf, target), rel=1e-4)
    # and not the contract's point-like pixels, whose figures differ by more than that
    assert fraunhofer.quality(phase, target)["efficiency"] > window.sum() * (1 + 1e-2)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([2, 4, 8, 16]))
def test_rounding_levels_is_idempotent(seed, n_levels):
    phase = np.random.default_rng(seed).uniform(-20, 20, (6, 6))
    levels = fraunhofer.round_levels(phase, n_levels)
    assert levels.dtype == np.uint8 and levels.max() < n_levels
    again = fraunhofer.round_levels(fraunhofer.level_phase(levels, n_levels), n_levels)
    np.testing.assert_array_equal(again, levels)
    # the nearest level: the wrapped phase error is at most half a step
    err = np.angle(np.exp(1j * (phase - fraunhofer.level_phase(levels, n_levels))))
    assert np.abs(err).max() <= np.pi / n_levels + 1e-9
