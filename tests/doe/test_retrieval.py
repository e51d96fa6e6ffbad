"""Phase retrieval end to end: quality, determinism, the finishes, refusals."""

import numpy as np
import pytest

from doe import fraunhofer, goals, refinement, retrieval, targets
from doe.gerchberg_saxton import gerchberg_saxton


def _check(q, efficiency):
    assert q["correlation"] >= 0.9999, q
    assert q["rmse"] <= 0.005, q
    assert q["efficiency"] >= efficiency, q


@pytest.mark.parametrize("name", ["compact_blob", "paper_gaussian", "asymmetric"])
def test_retrieval_quality_small_tile(name):
    target = targets.make_target(name, 11)
    res = retrieval.retrieve_phase(target, 61, 8, seed=1)
    assert res.levels.shape == (61, 61) and res.levels.dtype == np.uint8
    assert res.levels.max() < 8
    # the reported figures are the contract's, recomputed from the level map
    again = fraunhofer.quality(fraunhofer.level_phase(res.levels, 8), target)
    assert res.quality_quantised == pytest.approx(again, rel=1e-12)
    _check(res.quality_quantised, 0.85)
    _check(res.quality_continuous, 0.9)


def test_delta_targets_give_a_flat_plate_and_a_blazed_grating():
    k = 9
    on_axis = np.zeros((k, k))
    on_axis[k // 2, k // 2] = 1.0
    res = retrieval.retrieve_phase(on_axis, 41, 8, seed=0)
    assert res.quality_quantised["efficiency"] == pytest.approx(1.0, abs=1e-9)
    # off axis, up and to the right (row 2 = -y is up): the light must land there
    off = np.zeros((k, k))
    off[2, 7] = 1.0
    res = retrieval.retrieve_phase(off, 41, 8, seed=0)
    psf, eff = fraunhofer.simulate_levels(res.levels, 8, k)
    assert np.unravel_index(psf.argmax(), psf.shape) == (2, 7)
    # an 8-level blazed grating: about sinc^2(1/8) = 0.950 of the light
    assert 0.93 <= eff <= 0.97


def test_rounding_alone_is_much_worse_than_the_finish():
    # what the quantisation-aware finish buys: plain GS + rounding misses the rmse goal
    target = targets.compact_blob(11)
    phase, _ = gerchberg_saxton(target, 61, 150, np.random.default_rng(1))
    naive = fraunhofer.quality(fraunhofer.level_phase(fraunhofer.round_levels(phase, 8), 8), target)
    res = retrieval.retrieve_phase(target, 61, 8, seed=1)
    assert res.quality_quantised["rmse"] < 0.5 * naive["rmse"]


def test_retrieval_is_deterministic_for_a_seed():
    target = targets.anisotropic(7)
    one = retrieval.retrieve_phase(target, 31, 8, seed=3)
    two = retrieval.retrieve_phase(target, 31, 8, seed=3)
    other = retrieval.retrieve_phase(target, 31, 8, seed=4)
    assert one.levels.tobytes() == two.levels.tobytes()
    assert one.phase.tobytes() == two.phase.tobytes()
    assert one.levels.tobytes() != other.levels.tobytes()


def test_retrieved_continuous_phase_lies_in_one_turn():
    # catches the raw L-BFGS phase returned unwrapped (docs/retrieve.md: rad in [0, 2 pi))
    res = retrieval.retrieve_phase(targets.compact_blob(5), 17, 8, seed=0)
    assert res.phase.min() >= 0 and res.phase.max() < 2 * np.pi


def test_several_finishes_keep_the_most_efficient_design_within_the_cap():
    target = targets.asymmetric(7)
    one = retrieval.retrieve_phase(target, 31, 8, seed=5, starts=2, finishes=1)
    two = retrieval.retrieve_phase(target, 31, 8, seed=5, starts=2, finishes=2)
    again = retrieval.retrieve_phase(target, 31, 8, seed=5, starts=2, finishes=2)
    assert two.levels.tobytes() == again.levels.tobytes()
    # the first finish of both runs is the same computation; the second can only add
    assert refinement.fidelity(fraunhofer.level_phase(two.levels, 8), target) <= goals.CAP
    assert two.quality_quantised["efficiency"] >= one.quality_quantised["efficiency"] - 1e-12


def test_the_finish_with_the_best_rank_wins_and_a_tie_keeps_the_first(monkeypatch):
    # quantised_finish's rank keys, smaller first: the finish over the cap loses to any
    # within it, the most efficient within it wins, and a later finish only as good does
    # not replace it
    keys = [(1, 2.0), (0, -0.6), (0, -0.5), (0, -0.6)]
    phases = []

    def finish(phase, gains, target, n_levels, rng, cd_weights, cap, iterations, bar, no_corners):
        assert no_corners  # the default retrieval leaves no corner contact
        phases.append(phase)
        return keys[len(phases) - 1], np.full(phase.shape, len(phases) - 1, np.uint8)

    monkeypatch.setattr(retrieval, "quantised_finish", finish)
    res = retrieval.retrieve_phase(
        targets.compact_blob(5), 17, 8, starts=4, finishes=4, gs_iterations=5, lbfgs_evals=3
    )
    assert len(phases) == 4
    np.testing.assert_array_equal(res.levels, 1)
    np.testing.assert_array_equal(res.phase, np.mod(phases[1], 2 * np.pi))


def test_retrieval_refuses_bad_arguments():
    with pytest.raises(ValueError, match="exceeds"):
        retrieval.retrieve_phase(targets.compact_blob(11), 9)
    with pytest.raises(ValueError, match="odd"):
        retrieval.retrieve_phase(np.ones((4, 4)) / 16, 31)
    with pytest.raises(ValueError, match="at least 2 levels"):
        retrieval.retrieve_phase(targets.compact_blob(11), 31, n_levels=1)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["compact_blob", "dense_random"])
def test_retrieval_quality_full_tile(name):
    target = targets.make_target(name, 11)
    res = retrieval.retrieve_phase(target, 175, 8, seed=0)
    _check(res.quality_quantised, 0.85)


# efficiency floors: the acceptance's 0.85, or for three dots (whose exact-shape
# bound is 0.827 even with a continuous phase) what bench/retrieval.py measures
# (0.806-0.810 over seeds 0-3), less a little
ROBUST_FAST = {"dots_3": 0.80, "disc_r2.5": 0.85, "ring_r2": 0.85}


@pytest.mark.parametrize("name", ROBUST_FAST)
def test_robustness_targets_meet_the_fidelity_goals_at_full_size(name):
    # a sparse, a hard-edged and a ring target at the contract's N = 175
    target = targets.robustness_set(11)[name]
    res = retrieval.retrieve_phase(target, 175, 8, seed=0)
    _check(res.quality_quantised, ROBUST_FAST[name])
    # each figure within the cap: rmse <= 0.005 sqrt(CAP)
    assert res.quality_quantised["rmse"] <= 0.005 * np.sqrt(goals.CAP) + 1e-6


def test_a_flat_top_design_spends_its_fidelity_budget():
    # the smooth stand-in for the peak reads a flat top's rmse high; the exact-figure
    # climb spends what it leaves (without it: fidelity 0.54, efficiency 0.870)
    target = targets.flat_top(11)
    res = retrieval.retrieve_phase(target, 175, 8, seed=0)
    fid = refinement.fidelity(fraunhofer.level_phase(res.levels, 8), target)
    assert 0.7 <= fid <= goals.CAP
    assert res.quality_quantised["efficiency"] >= 0.875


@pytest.mark.slow
def test_every_robustness_target_meets_the_fidelity_goals_at_full_size():
    for name, target in targets.robustness_set(11).items():
        if name in ROBUST_FAST:
            continue
        res = retrieval.retrieve_phase(target, 175, 8, seed=0)
        assert res.quality_quantised["correlation"] >= 0.9999, name
        assert res.quality_quantised["rmse"] <= 0.005 * np.sqrt(goals.CAP) + 1e-6, name
        # sparse dots are bound-limited (docs/retrieve.md: 0.81-0.85 measured), all else meets 0.85
        floor = 0.80 if name.startswith("dots") else 0.85
        assert res.quality_quantised["efficiency"] >= floor, name
