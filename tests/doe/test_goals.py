"""The quality goals and the fidelity figures measured against them."""

import numpy as np
import pytest

from doe import fraunhofer, goals, refinement, targets
from doe.gerchberg_saxton import gerchberg_saxton


def test_fidelity_terms_measure_the_quality_goals():
    # the fidelity is the larger of (rmse / goal)^2 and (1 - corr) / (1 - goal), and the
    # smooth stand-in equals it when the simulated peak sits where the target's does
    rng = np.random.default_rng(8)
    target = targets.compact_blob(7)
    phase = gerchberg_saxton(target, 31, 30, rng)[0]
    q = fraunhofer.quality(phase, target)
    terms = (
        (q["rmse"] / goals.RMSE_GOAL) ** 2,
        (1 - q["correlation"]) / (1 - goals.CORRELATION_GOAL),
    )
    assert min(terms) > 0.3 * max(terms)  # both terms matter here
    expect = max(terms)
    assert refinement.fidelity(phase, target) == pytest.approx(expect, rel=1e-6)
    # the batched evaluation of coordinate descent agrees with the objective's stand-in
    power = fraunhofer.window_power(phase, 7)
    goal = goals.Goal.of(target)
    batch = goals.goal_values(np.stack([power, power]), goal, 2.0, mode="smooth")
    one = refinement._fidelity_terms(power, goal, 2.0)[0]
    np.testing.assert_allclose(batch, [one, one], rtol=1e-12)
    assert one == pytest.approx(refinement.objective(phase, target, 2.0)[0], rel=1e-12)


@pytest.mark.parametrize("mode", ["exact", "smooth"])
@pytest.mark.parametrize("cap", [0.0, 0.6, 1e6])
def test_lean_single_window_value_matches_the_batched_one(mode, cap):
    rng = np.random.default_rng(11)
    for name in ("flat_top", "sparse_dots", "anisotropic"):
        target = targets.make_target(name, 7)
        goal = goals.Goal.of(target)
        w = (rng.normal(size=(7, 7)) + 1j * rng.normal(size=(7, 7))) * np.sqrt(target) + 1e-3
        batched = float(goals.goal_values(np.abs(w) ** 2, goal, 30.0, cap, mode))
        assert goals.window_value(w, goal, 30.0, cap, mode) == pytest.approx(batched, rel=1e-12)


def test_fidelity_within_one_exactly_when_both_goals_are_met():
    # the acceptance asks for each figure on its own: rmse <= 0.005 and corr >= 0.9999
    rng = np.random.default_rng(15)
    target = targets.random_dots(7, seed=0, count=5)  # a few dots on a dark ground
    goal = goals.Goal.of(target)
    seen = set()
    for scale in np.geomspace(1e-4, 3e-2, 60):
        noise = rng.uniform(0, 1, (7, 7))
        power = 0.8 * (target + scale * noise * target.max())
        psf = power / power.sum()
        met = (
            fraunhofer.rmse(psf, target) <= goals.RMSE_GOAL
            and fraunhofer.correlation(psf, target) >= goals.CORRELATION_GOAL
        )
        assert (float(goals.goal_values(power, goal, 0.0)) <= 1.0) == met
        seen.add(met)
    assert seen == {True, False}


def test_exact_fidelity_uses_the_simulated_peak_on_flat_tops():
    # a plateau whose simulated values differ: the rmse normalises by the highest
    target = np.zeros((5, 5))
    target[1:4, 1:4] = 1 / 9
    power = target * np.linspace(0.9, 1.1, 25).reshape(5, 5)
    psf = power / power.sum()
    rmse = fraunhofer.rmse(psf, target)
    goal = goals.Goal.of(target)
    corr = fraunhofer.correlation(psf, target)
    expect = max((rmse / goals.RMSE_GOAL) ** 2, (1 - corr) / (1 - goals.CORRELATION_GOAL))
    assert float(goals.goal_values(power, goal, 0.0)) == pytest.approx(expect, rel=1e-9)
    # the smooth stand-in (mean over the plateau) reads lower here
    assert float(goals.goal_values(power, goal, 0.0, mode="smooth")) < expect


def test_fidelity_cap_counts_only_slack_below_the_cap():
    target = targets.compact_blob(5)
    goal = goals.Goal.of(target)
    power = 0.9 * target * (1 + 0.001 * np.arange(25).reshape(5, 5) / 25)
    fid = float(goals.goal_values(power, goal, 0.0))
    eff = power.sum()
    assert fid < 0.5
    capped = float(goals.goal_values(power, goal, 3.0, cap=0.5))
    assert capped == pytest.approx(0.5 + goals.SLACK * fid - 3.0 * eff, rel=1e-12)
    above = float(goals.goal_values(power, goal, 3.0, cap=fid / 2))
    assert above == pytest.approx(fid + goals.SLACK * fid / 2 - 3.0 * eff, rel=1e-12)


def test_missed_goals_at_and_beyond_each_bound():
    met = {"correlation": 0.9999, "rmse": 0.005, "efficiency": 0.5}
    assert goals.missed_goals(met) == []
    assert goals.missed_goals({**met, "correlation": None}) == []
    assert goals.missed_goals({**met, "correlation": float("nan")}) == []
    low = {**met, "correlation": 0.99989}
    assert goals.missed_goals(low) == ["correlation 0.999890 < 0.9999"]
    assert goals.missed_goals({**met, "rmse": 0.00501}) == ["rmse 0.00501 > 0.005"]
    assert len(goals.missed_goals({**met, "rmse": float("nan")})) == 1


def test_a_missed_goal_is_never_shown_rounded_onto_the_goal():
    # 0.99989996 was shown as "correlation 0.999900 < 0.9999"
    met = {"correlation": 0.9999, "rmse": 0.005, "efficiency": 0.5}
    missed = goals.missed_goals({"correlation": 0.99989996, "rmse": 0.0050004})
    assert missed == ["correlation 0.99989996 < 0.9999", "rmse 0.0050004 > 0.005"]
    assert goals.missed_goals({**met, "rmse": float("nan")}) == ["rmse nan > 0.005"]
