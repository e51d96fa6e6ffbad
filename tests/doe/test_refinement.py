"""The continuous stage: objective, adjoint gradients, constrained L-BFGS refinement."""

import numpy as np
import pytest

from doe import fraunhofer, goals, refinement, targets
from doe.gerchberg_saxton import gerchberg_saxton, mixed_region


def assert_gradient_matches_finite_differences(fun, phase):
    """Check fun(phase) -> (value, grad) against central differences at a few pixels."""
    _, grad = fun(phase)
    h = 1e-6
    for r, c in [(0, 0), (4, 9), (12, 3), (7, 7)]:
        up, down = phase.copy(), phase.copy()
        up[r, c] += h
        down[r, c] -= h
        fd = (fun(up)[0] - fun(down)[0]) / (2 * h)
        assert grad[r, c] == pytest.approx(fd, rel=1e-5, abs=1e-7 * np.abs(grad).max())


@pytest.mark.parametrize("name", ["compact_blob", "near_delta", "flat_top", "sparse_dots"])
def test_objective_gradient_matches_finite_differences(name):
    rng = np.random.default_rng(7)
    target = targets.make_target(name, 5)
    phase = rng.uniform(0, 2 * np.pi, (13, 13))
    assert_gradient_matches_finite_differences(
        lambda p: refinement.objective(p, target, weight=3.0), phase
    )


@pytest.mark.parametrize("cap", [0.0, 1e9])
@pytest.mark.parametrize("name", ["compact_blob", "flat_top", "sparse_dots"])
def test_constrained_objective_gradient_matches_finite_differences(name, cap):
    # cap 0: the penalty is active; cap 1e9: only -efficiency is left
    rng = np.random.default_rng(11)
    target = targets.make_target(name, 5)
    phase = rng.uniform(0, 2 * np.pi, (13, 13))
    assert_gradient_matches_finite_differences(
        lambda p: refinement.constrained_objective(p, target, cap=cap, mu=0.3), phase
    )


def test_constrained_objective_is_efficiency_within_the_cap_and_penalised_above():
    rng = np.random.default_rng(12)
    target = targets.asymmetric(5)
    phase = rng.uniform(0, 2 * np.pi, (15, 15))
    eff = fraunhofer.window_power(phase, 5).sum()
    fid = float(
        goals.goal_values(
            fraunhofer.window_power(phase, 5), goals.Goal.of(target), 0.0, mode="smooth"
        )
    )
    inside, _ = refinement.constrained_objective(phase, target, cap=2 * fid, mu=5.0)
    assert inside == pytest.approx(-eff, rel=1e-12)
    # each term above the cap is penalised by its own excess
    (f_rmse, _), (f_corr, _) = goals.fidelity_parts(
        fraunhofer.window_power(phase, 5), goals.Goal.of(target)
    )
    assert max(f_rmse, f_corr) == pytest.approx(fid, rel=1e-12)
    cap = min(f_rmse, f_corr) / 2
    above, _ = refinement.constrained_objective(phase, target, cap=cap, mu=5.0)
    expect = -eff + 5.0 * ((f_rmse - cap) ** 2 + (f_corr - cap) ** 2)
    assert above == pytest.approx(expect, rel=1e-10)


def test_constrained_refinement_reaches_the_cap_and_gains_efficiency():
    target = targets.flat_top(7)
    rng = np.random.default_rng(14)
    start, gains = gerchberg_saxton(target, 41, 60, rng)
    start, _ = mixed_region(target, start, gains, 60)
    goal = goals.Goal.of(target)
    before = float(goals.goal_values(fraunhofer.window_power(start, 7), goal, 0.0, mode="smooth"))
    phase, fid, eff = refinement.refine_constrained(start, target, 0.5, (0.1, 1.0, 10.0), 60)
    assert before > 0.5  # the start misses the cap ...
    assert fid <= 0.55  # ... the refinement walks onto it
    assert eff == pytest.approx(fraunhofer.window_power(phase, 7).sum(), rel=1e-12)
    assert eff > 0.7
