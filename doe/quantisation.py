"""The discrete stage of the retrieval: from a continuous phase to the best L-level map.

Quantised Gerchberg-Saxton from the continuous phase, and plain rounding at the
best global offset, each start a :func:`coordinate_descent` on the level map:
a direct search over the discrete levels on the real quantised figures. With
the fidelity capped it climbs efficiency while both figures stay within budget;
this is what closes the gap left by rounding. :func:`quantised_finish` runs
both and keeps the better level map; by default each descent ends without
corner contacts (:mod:`doe.rule_finish`).
"""

import numpy as np

from doe import fraunhofer
from doe.fraunhofer import level_step, round_levels
from doe.gerchberg_saxton import gerchberg_saxton
from doe.goals import Goal, goal_values, window_value
from doe.mask_rules import contacts_at, pixel_is_clean
from doe.refinement import DEFAULT_WEIGHT, window_fft, window_matrix
from doe.rule_finish import repair_corners

CD_WEIGHTS = (100.0, 60.0, 40.0, 30.0, 20.0, 15.0, 10.0, 5.0, 2.0)
"""Efficiency weights of the coordinate-descent sweeps, most efficient first."""

MIN_GAIN = 0.002
"""Efficiency gain below which a coordinate-descent sweep within the cap ends the finish."""

POLISH_SWEEPS = 6
"""Most exact-figure coordinate-descent sweeps that bring the fidelity within the cap."""

CLIMB_SWEEPS = 3
"""Most exact-figure coordinate-descent sweeps that spend fidelity left below the cap."""

CLIMB_WEIGHT = 10.0
"""Efficiency weight of those sweeps (a larger one, such as 30, overshoots the cap on flat tops)."""


def coordinate_descent(
    levels,
    target,
    n_levels,
    weight=DEFAULT_WEIGHT,
    sweeps=1,
    chunk=512,
    rng=None,
    shifts=(1, -1),
    cap=0.0,
    mode="exact",
    no_corners=False,
):
    """Return a level map improved by greedy single-pixel level changes.

    Changing pixel (r, c) from level a to b adds (e^{2 pi i b/L} - e^{2 pi i a/L})
    A[:, r] A[:, c]^T / N^2 to the window (A = :func:`window_matrix`), so every
    candidate costs O(K^2). Pixels are visited in chunks (random order); each
    chunk's L - 1 candidates per pixel are scored together against the current
    window, then the improving ones are applied in order of predicted gain, each
    re-checked against the window updated by the moves before it.

    Parameters
    ----------
    levels : (N, N) uint8
        Start level map.
    target : (K, K) array
        Target PSF, sum 1.
    n_levels : int
        Number of levels L.
    weight : float
        Efficiency weight of :func:`doe.refinement.objective`.
    sweeps : int
        Maximum passes over all pixels (stops early when a pass changes nothing).
    chunk : int
        Pixels scored together.
    rng : numpy.random.Generator or None
        Source of the visiting order.
    shifts : sequence of int or None
        Level changes tried per pixel (modulo L); None tries all L - 1. One level
        up or down finds almost every improving move at a third of the cost.
    cap : float
        Fidelity cap (see :func:`doe.goals.goal_values`): 0 minimises fidelity - weight * E,
        > 0 maximises the efficiency within a fidelity of ``cap``.
    mode : {"exact", "smooth"}
        Peak normalisation of the rmse term: the simulated peak (the exact
        figure) or the mean over the target's peak orders (smoother, so the
        greedy search progresses faster on flat-topped targets).
    no_corners : bool
        Make no move that leaves the moved pixel in a corner contact
        (:mod:`doe.mask_rules`, periodic): a map without one keeps none.

    Returns
    -------
    levels : (N, N) uint8
    """
    rng = np.random.default_rng(0) if rng is None else rng
    q = np.asarray(levels).astype(np.int64)
    n, k = q.shape[0], target.shape[0]
    goal = Goal.of(target)
    a = window_matrix(n, k)
    phasors = np.exp(1j * level_step(n_levels) * np.arange(n_levels))
    w = window_fft(phasors[q], fraunhofer.window_indices(n, k))
    value = window_value(w, goal, weight, cap, mode)
    shifts = np.arange(1, n_levels) if shifts is None else np.asarray(shifts) % n_levels
    for _ in range(sweeps):
        changed = 0
        order = rng.permutation(n * n)
        for start in range(0, order.size, chunk):
            pix = order[start : start + chunk]
            r, c = pix // n, pix % n
            cur = q[r, c]
            cand = (cur[:, None] + shifts[None, :]) % n_levels  # (B, L-1)
            delta = (phasors[cand] - phasors[cur][:, None]) / (n * n)  # (B, L-1)
            basis = a[:, r].T[:, :, None] * a[:, c].T[:, None, :]  # (B, K, K)
            trial = w + delta[:, :, None, None] * basis[:, None]  # (B, L-1, K, K)
            vals = goal_values(trial.real**2 + trial.imag**2, goal, weight, cap, mode)
            if no_corners:
                made = contacts_at(q, r, c, cand, n_levels).any(axis=-1)
                vals = np.where(made, np.inf, vals)
            best = np.argmin(vals, axis=1)
            gain = vals[np.arange(pix.size), best] - value
            ranked = np.argsort(gain, kind="stable")
            ranked = ranked[gain[ranked] < 0]
            for i in ranked:
                if no_corners and not pixel_is_clean(q, r[i], c[i], cand[i, best[i]], n_levels):
                    continue  # a move before it in this chunk changed a neighbour
                new_w = w + delta[i, best[i]] * basis[i]
                new_value = window_value(new_w, goal, weight, cap, mode)
                if new_value < value:
                    w, value = new_w, new_value
                    q[r[i], c[i]] = cand[i, best[i]]
                    changed += 1
        if changed == 0:
            break
    return q.astype(np.uint8)


def quantised_finish(
    phase,
    gains,
    target,
    n_levels,
    rng,
    cd_weights,
    cap,
    quantised_iterations,
    bar,
    no_corners=False,
):
    """Return (rank, levels): the discrete stages of :func:`doe.retrieval.retrieve_phase`.

    Two descents, one from quantised GS and one from the best plain rounding: which
    of them ends higher is a lottery (on hard flat tops mostly the second, by up to
    about 0.01 of efficiency, but not always), so both run and the better is kept.

    Parameters
    ----------
    phase, gains : (N, N) and (K, K) arrays
        The continuous design (rad) and its weighted-GS gains.
    target : (K, K) array
        Target PSF, sum 1.
    n_levels : int
        Number of levels L.
    rng : numpy.random.Generator
        Source of the descents' visiting orders.
    cd_weights : sequence of float
        Efficiency weights of the descent sweeps, most efficient first.
    cap : float
        Fidelity the level map aims at.
    quantised_iterations : int
        Iterations of the quantised GS.
    bar : tqdm
        Progress bar the stages advance.
    no_corners : bool
        Leave no corner contact in any mask (:mod:`doe.mask_rules`, periodic):
        each descent ends with :func:`doe.rule_finish.repair_corners` and sweeps
        that make none.

    Returns
    -------
    rank : tuple
        Sort key, smaller is better: (0, -efficiency) within ``cap``, else (1, fidelity).
    levels : (N, N) uint8
    """
    n_pixels, k = phase.shape[0], target.shape[0]
    bar.set_description("quantised GS")
    soft, _ = gerchberg_saxton(
        target, n_pixels, quantised_iterations, phase=phase, n_levels=n_levels, gains=gains
    )
    bar.update()
    # Quantised GS usually starts the discrete search best, but it can collapse a
    # nearly flat phase (near-delta targets) into a 0/pi grating; rounding with the
    # best global offset is the other start.
    goal = Goal.of(target)
    roundings = [round_levels(phase + j / 8 * level_step(n_levels), n_levels) for j in range(8)]
    scores = [
        float(
            goal_values(
                fraunhofer.window_power(fraunhofer.level_phase(s, n_levels), k),
                goal,
                cd_weights[0],
                cap,
                "smooth",
            )
        )
        for s in roundings
    ]
    ranked = []
    for start in (round_levels(soft, n_levels), roundings[int(np.argmin(scores))]):
        levels, eff, fid = _descend(
            start, target, goal, n_levels, rng, cd_weights, cap, bar, no_corners
        )
        ranked.append((_rank(eff, fid, cap), len(ranked), levels))
    key, _, levels = min(ranked, key=lambda r: r[:2])
    return key, levels


def _rank(eff, fid, cap):
    """Sort key of a level map: within the cap the most efficient first, else the most faithful."""
    return (0, -eff) if fid <= cap else (1, fid)


def _descend(levels, target, goal, n_levels, rng, cd_weights, cap, bar, no_corners=False):
    """Return (levels, efficiency, exact fidelity) after :func:`quantised_finish`'s sweeps.

    With ``no_corners`` the level map the sweeps end on has its corner contacts
    repaired (:func:`doe.rule_finish.repair_corners`), and where there were any
    the exact-figure sweeps run again with moves that make none.
    """

    def figures(levels):
        """(efficiency, exact fidelity) of a level map."""
        power = fraunhofer.window_power(fraunhofer.level_phase(levels, n_levels), target.shape[0])
        return float(power.sum()), float(goal_values(power, goal, 0.0))

    def sweep(levels, weight, mode, rules=False):
        return coordinate_descent(
            levels, target, n_levels, weight, sweeps=1, rng=rng, cap=cap, mode=mode,
            no_corners=rules,
        )  # fmt: skip

    eff, fid = figures(levels)
    bar.set_description("coordinate descent")
    for w in cd_weights:
        bar.update()
        levels = sweep(levels, w, "smooth")
        new_eff, fid = figures(levels)
        gain, eff = new_eff - eff, new_eff
        if fid <= cap and gain < MIN_GAIN:
            break
    levels, eff, fid = _settle(levels, eff, fid, sweep, figures, cap, cd_weights[-1])
    if no_corners:
        bar.set_description("corner contacts")
        repaired = repair_corners(levels, target, goal, n_levels, CLIMB_WEIGHT, cap)
        if np.array_equal(repaired, levels):
            return levels, eff, fid  # none to repair: the map is final as it is
        eff, fid = figures(repaired)
        rules = lambda lv, w, mode: sweep(lv, w, mode, rules=True)  # noqa: E731
        levels, eff, fid = _settle(repaired, eff, fid, rules, figures, cap, cd_weights[-1])
    return levels, eff, fid


def _settle(levels, eff, fid, sweep, figures, cap, polish_weight):
    """Return (levels, efficiency, fidelity) after the exact-figure sweeps of :func:`_descend`."""
    # The smooth stand-in for the peak normalisation can disagree with the exact
    # rmse on flat-topped targets, either way: the last sweeps use the exact figures.
    for _ in range(POLISH_SWEEPS):
        if fid <= cap:
            break
        # over the cap: polish, sweep by sweep, still weighing efficiency (with
        # weight 0 the slack below the cap would trade efficiency for needless fidelity)
        levels = sweep(levels, polish_weight, "exact")
        eff, fid = figures(levels)
    for _ in range(CLIMB_SWEEPS if fid <= cap else 0):
        # within the cap: climb into the budget the stand-in left unused (it reads
        # flat tops' rmse high); a sweep that ends over the cap is not kept
        trial = sweep(levels, CLIMB_WEIGHT, "exact")
        trial_eff, trial_fid = figures(trial)
        if trial_fid > cap or trial_eff <= eff:
            break
        levels, fid, gain, eff = trial, trial_fid, trial_eff - eff, trial_eff
        if gain < MIN_GAIN:
            break
    return levels, eff, fid
