"""Exact-shape efficiency bounds against their analytic values."""

import numpy as np
import pytest

from doe import bounds, fraunhofer

K, N = 11, 175


def _orders(*cells):
    """Return a K x K target with equal power in the given (row, col) orders."""
    target = np.zeros((K, K))
    for r, c in cells:
        target[K // 2 + r, K // 2 + c] = 1.0
    return target / target.sum()


@pytest.mark.parametrize("n_levels", [2, 4, 8])
def test_one_tilted_order_is_bounded_by_the_staircase_blazed_grating(n_levels):
    # one order off the axis: g is a pure tilt, |g| = 1, so a continuous plate can
    # reach 1; L levels can only follow the tilt in steps: sinc^2(1 / L)
    target = _orders((0, 1))
    assert bounds.efficiency_bound(target, N) == pytest.approx(1.0, abs=1e-12)
    expected = np.sinc(1 / n_levels) ** 2
    assert bounds.efficiency_bound(target, N, n_levels) == pytest.approx(expected, rel=1e-4)


def test_the_zero_order_alone_is_reached_by_any_level_count():
    assert bounds.efficiency_bound(_orders((0, 0)), N, 8) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("n_levels", [None, 2, 8])
def test_two_equal_orders_are_bounded_by_eight_over_pi_squared(n_levels):
    # g = sqrt(2) cos(2 pi x / N + const): mean |g| = 2 sqrt(2) / pi, and a 0 / pi
    # grating follows arg g exactly, so every even L reaches the same bound
    target = _orders((0, -1), (0, 1))
    bound = bounds.efficiency_bound(target, N, n_levels)
    assert bound == pytest.approx(8 / np.pi**2, rel=1e-4)


def test_levels_cost_at_most_the_staircase_factor():
    # rounding arg g to L levels at a uniformly random global phase keeps
    # sinc(1 / L) of mean |g| on average, so the best global phase keeps at least that
    target = _orders((0, -2), (1, 1), (-2, 0))
    continuous = bounds.efficiency_bound(target, N)
    eight = bounds.efficiency_bound(target, N, 8)
    assert np.sinc(1 / 8) ** 2 * continuous <= eight < continuous < 1


def test_a_uniform_background_costs_exactly_its_rmse_and_no_correlation():
    target = _orders((0, -2), (1, 1), (-2, 0))
    padded = bounds.with_background(target, 0.004)
    assert padded.sum() == pytest.approx(1.0)
    assert fraunhofer.rmse(padded, target) == pytest.approx(0.004, rel=1e-9)
    assert fraunhofer.correlation(padded, target) == pytest.approx(1.0, abs=1e-12)


def test_a_target_without_dark_orders_gets_no_background():
    target = np.arange(1.0, K * K + 1).reshape(K, K)
    np.testing.assert_allclose(bounds.with_background(target, 0.004), target / target.sum())


def _bound_of_window(window, n_levels):
    """(mean_x |g| cos d)^2 / |w|^2 of a window field, computed afresh (d: distance to a level)."""
    spec = np.zeros((N, N), dtype=np.complex128)
    idx = fraunhofer.window_indices(N, K)
    spec[np.ix_(idx, idx)] = window
    g = np.fft.ifft2(spec) * N * N
    step = 2 * np.pi / n_levels
    d = np.angle(g) - step * np.round(np.angle(g) / step)
    return (np.mean(np.abs(g) * np.cos(d)) / np.linalg.norm(window)) ** 2


def test_a_single_order_within_the_goals_is_still_bounded_by_one():
    # Cauchy-Schwarz: mean |g| <= sqrt(mean |g|^2) = |w|, whatever the background
    bound, _ = bounds.within_goals(_orders((0, 1)), N, None, cap=1.0)
    assert 0.999 <= bound <= 1.0 + 1e-12


def test_a_pattern_within_the_goals_passes_the_uniform_background_and_meets_them():
    target = _orders((0, -2), (1, 1), (-2, 0))
    cap = 0.81
    rmse = 0.005 * np.sqrt(cap)
    background = bounds.efficiency_bound(bounds.with_background(target, rmse), N, 8)
    bound, window = bounds.within_goals(target, N, 8, cap=cap)
    assert bound >= background - 1e-3
    assert bound < bounds.efficiency_bound(target, N) + 0.2  # finite, near the physics
    # the window it reports is a pattern within the goals, and its bound is the one reported
    power = np.abs(window) ** 2 / (np.abs(window) ** 2).sum()
    assert fraunhofer.rmse(power, target) <= rmse * (1 + 1e-9)
    assert 1 - fraunhofer.correlation(power, target) <= cap * 1e-4 * (1 + 1e-9)
    assert _bound_of_window(window, 8) == pytest.approx(bound, rel=1e-9)


def test_the_bound_is_never_below_a_plate_that_forms_the_target_exactly():
    # a binary 4 x 4 plate forms this PSF exactly at efficiency 7/8 (found by brute
    # force over all 2^16 plates); from 3 random starts the bound read 0.772
    target = np.array([[1, 0, 5], [1, 0, 1], [5, 0, 1]]) / 14
    levels = np.array([[0, 0, 1, 1], [1, 0, 0, 1], [1, 1, 0, 0], [1, 1, 0, 0]], np.uint8)
    psf, efficiency = fraunhofer.simulate_levels(levels, 2, 3)
    assert efficiency == pytest.approx(7 / 8) and np.allclose(psf, target)
    assert bounds.efficiency_bound(target, 4, 2) >= efficiency - 1e-9
