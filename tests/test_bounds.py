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
