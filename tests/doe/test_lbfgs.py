"""doe.lbfgs.minimise: nlopt L-BFGS that never loses its best point."""

import numpy as np
import pytest

from doe.lbfgs import minimise


def test_a_quadratic_is_minimised():
    x, value = minimise(lambda x: (float(((x - 3.0) ** 2).sum()), 2.0 * (x - 3.0)), np.zeros(4), 50)
    np.testing.assert_allclose(x, 3.0, atol=1e-6)
    assert value == pytest.approx(0.0, abs=1e-10)


def test_a_failed_run_returns_the_best_point_seen():
    # a gradient of the wrong sign makes nlopt's line search fail: nlopt >= 2.11
    # raises its own runtime_error (not Python's RuntimeError) and drops its point
    seen = []

    def upside_down(x):
        value = float((x**2).sum())
        seen.append(value)
        return value, -2.0 * x

    x0 = np.array([1.0, 2.0])
    x, value = minimise(upside_down, x0, 100)
    assert value == min(seen)
    assert float((x**2).sum()) == value


def test_an_interrupt_in_the_objective_stops_the_minimisation():
    # nlopt turned Ctrl-C (or SIGTERM) inside the objective into an ordinary stop:
    # retrieval went on as if it had converged, and the command finished with exit 0.
    calls = []

    def fun(x):
        calls.append(1)
        if len(calls) == 5:
            raise KeyboardInterrupt
        return float(((x - 3.0) ** 4).sum()), 4 * (x - 3.0) ** 3

    with pytest.raises(KeyboardInterrupt):
        minimise(fun, np.zeros(4), max_eval=100)
    assert len(calls) <= 6


@pytest.mark.parametrize("error", [ValueError, RuntimeError, MemoryError])
def test_an_error_in_the_objective_is_raised_not_returned_as_a_result(error):
    # nlopt turned an error inside the objective into a stop, and ValueError and
    # RuntimeError were taken for nlopt's own stops: a bug (or a GPU out of memory)
    # came back as the start point, as if converged
    calls = []

    def fun(x):
        calls.append(1)
        if len(calls) == 3:
            raise error("in the objective")
        return float(((x - 3.0) ** 2).sum()), 2.0 * (x - 3.0)

    with pytest.raises(error, match="in the objective"):
        minimise(fun, np.zeros(3), 100)
    assert len(calls) == 3


def test_a_gradient_of_the_wrong_size_is_raised():
    with pytest.raises(ValueError):
        minimise(lambda x: (float((x**2).sum()), np.zeros(x.size + 1)), np.ones(3), 10)


@pytest.mark.parametrize("x0, max_eval", [(np.array([0.0, np.nan]), 10), (np.zeros(2), 0)])
def test_a_start_point_with_nan_or_no_evaluations_is_refused(x0, max_eval):
    # nlopt reads max_eval 0 as no limit; a NaN start came back as (x0, inf)
    with pytest.raises(ValueError):
        minimise(lambda x: (float((x**2).sum()), 2.0 * x), x0, max_eval)


@pytest.mark.parametrize("improves", [True, False])
def test_the_best_point_has_the_start_points_shape(improves):
    def fun(x):
        assert x.shape == (2, 2)
        return (float(((x - 1.0) ** 2).sum()), 2.0 * (x - 1.0)) if improves else (1.0, 0 * x)

    x, _ = minimise(fun, np.zeros((2, 2)), 20)
    assert x.shape == (2, 2)
