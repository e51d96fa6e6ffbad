"""Phase retrieval: from a K x K target PSF to an L-level phase tile of N x N pixels.

The pipeline, all on the forward model of :mod:`doe.fraunhofer` and measured
against the goals of :mod:`doe.goals`:

1. Screening -- cheap starts (:mod:`doe.gerchberg_saxton`):
   :func:`~doe.gerchberg_saxton.flat_modulus_start` (order phases that make the
   band-limited field's modulus as flat as possible) and random weighted
   :func:`~doe.gerchberg_saxton.gerchberg_saxton`, each followed by
   :func:`~doe.gerchberg_saxton.mixed_region` (MRAF); the light that does not
   fit the window leaves into the outside orders, the light sink. The best few
   by efficiency and fidelity go on.
2. :func:`~doe.refinement.refine_constrained` (:mod:`doe.refinement`) -- nlopt
   L-BFGS on the constrained objective: maximal efficiency with the two quality
   figures (rmse, correlation, each in units of its goal) within a cap, with an
   analytic (adjoint) gradient.
3. Quantised Gerchberg-Saxton from that phase; it, and plain rounding at the
   best global offset, each start a discrete search (:mod:`doe.quantisation`).
4. :func:`~doe.quantisation.coordinate_descent` -- a direct search over the
   discrete levels on the real quantised figures; with the fidelity capped it
   climbs efficiency while both figures stay within budget. This is what closes
   the gap left by rounding.
5. Unless the design allows them, the rule-aware finish
   (:mod:`doe.rule_finish`): each descent's map loses its corner contacts
   (:mod:`doe.mask_rules`) and climbs back with moves that make none.

:func:`retrieve_phase` runs them all and reports the quality figures of
:func:`doe.fraunhofer.quality` for the continuous and the quantised design.
The loops use numpy element-wise work, small dot products and pocketfft, none
of it threaded, so a seed gives bit-identical level maps on a given machine
whatever its thread count.
"""

import time
from dataclasses import dataclass

import numpy as np

from doe import fraunhofer
from doe.gerchberg_saxton import flat_modulus_start, gerchberg_saxton, mixed_region
from doe.goals import CAP
from doe.quantisation import CD_WEIGHTS, quantised_finish
from doe.refinement import PENALTIES, fidelity, refine_constrained

SCREENS = 6
"""Cheap starts (GS + MRAF) screened for the continuous stage; see :data:`SCREEN_RATE`."""

SCREEN_RATE = 0.012
"""Efficiency that one unit of fidelity above the cap costs L-BFGS on its way to the cap.

Screened starts are ranked by efficiency - SCREEN_RATE * fidelity after MRAF
(it lies between 0.008 and 0.014 on hard flat tops; the ranking, not the value, matters).
"""

STARTS = 2
"""Best screened starts refined by L-BFGS; the most efficient within the cap is kept."""

FINISHES = 1
"""Continuous designs that are quantised, best first (more cost time and seldom win)."""

OVER_CAP_COST = 0.05
"""Efficiency that one unit of fidelity over the cap costs a refined start in the ranking."""


@dataclass(frozen=True)
class Retrieval:
    """Result of :func:`retrieve_phase`.

    Attributes
    ----------
    levels : (N, N) uint8
        Quantised tile, values 0 .. L-1 (CONVENTIONS.md: phase 2 pi l / L).
    phase : (N, N) float64
        Continuous phase (rad) before quantisation.
    n_levels : int
        Number of phase levels L.
    quality_continuous, quality_quantised : dict
        ``correlation``, ``rmse`` and ``efficiency`` of the continuous phase and
        of the level map, from :func:`doe.fraunhofer.quality`.
    seconds : float
        Wall-clock time of the retrieval.
    seed : int
        Seed of the random start.
    """

    levels: np.ndarray
    phase: np.ndarray
    n_levels: int
    quality_continuous: dict
    quality_quantised: dict
    seconds: float
    seed: int


def retrieve_phase(
    target,
    n_pixels,
    n_levels=8,
    seed=0,
    screens=SCREENS,
    starts=STARTS,
    finishes=FINISHES,
    gs_iterations=100,
    mraf_iterations=100,
    lbfgs_evals=35,
    quantised_iterations=100,
    cd_weights=CD_WEIGHTS,
    cap=CAP,
    progress=False,
    allow_corner_contacts=False,
):
    """Design an L-level phase tile whose K x K window of orders forms ``target``.

    ``screens`` cheap starts -- :func:`~doe.gerchberg_saxton.flat_modulus_start`
    and random weighted GS, each followed by mixed-region (MRAF) iterations -- are
    ranked by efficiency less :data:`SCREEN_RATE` per unit of fidelity; the best
    ``starts`` go through L-BFGS on the constrained objective (maximal efficiency
    with the fidelity within ``cap``), and the ``finishes`` most efficient
    continuous designs go on. Quantised weighted GS from each, and plain rounding
    at the best global offset, each start a coordinate descent on the level map:
    one sweep for each of the efficiency weights ``cd_weights`` in turn, with the
    fidelity capped at ``cap`` (below it only :data:`doe.goals.SLACK` of it
    counts), until the fidelity is within ``cap`` and a sweep gains less than
    :data:`doe.quantisation.MIN_GAIN` of efficiency, then sweeps on the exact
    figures bring a map over the cap within it or spend the budget left below it;
    the most efficient level map within the cap wins.

    Parameters
    ----------
    target : (K, K) array
        Target PSF, values >= 0, sum 1, K odd (CONVENTIONS.md orientation).
    n_pixels : int
        Tile size N (>= K).
    n_levels : int
        Number of phase levels L.
    seed : int
        Seed of the random starts; the same seed gives the same level map.
    screens : int
        Cheap starts: the flat-modulus start and random weighted GS, each
        followed by MRAF.
    starts : int
        Number of the best screened starts refined by L-BFGS.
    finishes : int
        Number of the best continuous designs (at most ``starts``) that go through
        the discrete stages; the best level map wins.
    gs_iterations, mraf_iterations, lbfgs_evals, quantised_iterations : int
        Effort of the stages (L-BFGS: evaluations per penalty weight).
    cd_weights : sequence of float
        Efficiency weights of the coordinate-descent sweeps, most efficient first.
    cap : float
        Fidelity (the larger of the rmse and correlation terms of
        :func:`doe.refinement.objective`, 1 = a goal just met) the design aims at.
    progress : bool
        Show a tqdm progress bar of the stages on stderr (when it is a terminal).
    allow_corner_contacts : bool
        Leave corner contacts (:mod:`doe.mask_rules`) as the search finds them;
        by default each descent's rule-aware finish leaves none in any mask.

    Returns
    -------
    Retrieval
    """
    target = _checked_target(target, n_pixels, n_levels)
    t0 = time.perf_counter()
    if target.shape[0] == 1:
        return _zero_order_plate(target, n_pixels, n_levels, seed, t0)
    starts, finishes = max(int(starts), 1), max(int(finishes), 1)
    screens, finishes = max(int(screens), starts), min(finishes, starts)
    bar = _progress_bar(progress, screens + starts + finishes * (1 + 2 * len(cd_weights)))
    rng = np.random.default_rng(seed)
    screened = _screen(target, n_pixels, screens, gs_iterations, mraf_iterations, rng, bar)
    designs = _refine(screened[:starts], target, cap, lbfgs_evals, bar)
    best = None
    for phase, gains in designs[:finishes]:
        key, levels = quantised_finish(
            phase, gains, target, n_levels, rng, cd_weights, cap, quantised_iterations, bar,
            no_corners=not allow_corner_contacts,
        )  # fmt: skip
        if best is None or key < best[0]:
            best = (key, levels, phase)
    _, levels, phase = best
    quality_cont = fraunhofer.quality(phase, target)
    bar.close()
    seconds = time.perf_counter() - t0
    quality_q = fraunhofer.quality(fraunhofer.level_phase(levels, n_levels), target)
    return Retrieval(
        levels=levels,
        phase=np.mod(phase, 2 * np.pi),
        n_levels=n_levels,
        quality_continuous=quality_cont,
        quality_quantised=quality_q,
        seconds=seconds,
        seed=seed,
    )


def _checked_target(target, n_pixels, n_levels):
    """Return ``target`` as float64 summing to 1; ValueError where the arguments cannot work."""
    target = np.asarray(target, dtype=np.float64)
    if target.ndim != 2 or target.shape[0] != target.shape[1] or target.shape[0] % 2 == 0:
        raise ValueError(f"target must be square with odd size, got shape {target.shape}")
    k = target.shape[0]
    if k > n_pixels:
        raise ValueError(f"kernel size K = {k} exceeds the tile size N = {n_pixels}")
    if n_levels < 2:
        raise ValueError(f"need at least 2 levels, got {n_levels}")
    return target / target.sum()


def _zero_order_plate(target, n_pixels, n_levels, seed, t0):
    """Return the :class:`Retrieval` of a 1 x 1 target: the zero order alone.

    An unetched (flat) plate forms it with all the light; the objective's
    correlation term is 0 / 0 on a single order.
    """
    levels = np.full((n_pixels, n_pixels), n_levels - 1, np.uint8)
    phase = fraunhofer.level_phase(levels, n_levels)
    quality = fraunhofer.quality(phase, target)
    return Retrieval(levels, phase, n_levels, quality, quality, time.perf_counter() - t0, seed)


def _screen(target, n_pixels, screens, gs_iterations, mraf_iterations, rng, bar):
    """Return the screened starts, best first: (score, index, phase, gains) each.

    Cheap starts (the flat-modulus one, then random weighted GS), each with MRAF;
    which basin the later stages end in is a lottery that the screened figures
    predict well, on flat tops and sparse dots alike.
    """
    k = target.shape[0]
    screened = []
    for i in range(screens):
        bar.set_description("Gerchberg-Saxton + MRAF")
        if i == 0:
            start, gains = flat_modulus_start(target, n_pixels, rng), np.ones_like(target)
        else:
            start, gains = gerchberg_saxton(target, n_pixels, gs_iterations, rng)
        start, gains = mixed_region(target, start, gains, mraf_iterations)
        eff = fraunhofer.window_power(start, k).sum()
        screened.append((eff - SCREEN_RATE * fidelity(start, target), i, start, gains))
        bar.update()
    screened.sort(key=lambda d: (-d[0], d[1]))
    return screened


def _refine(screened, target, cap, lbfgs_evals, bar):
    """Return the refined continuous designs, best first: (phase, gains) each.

    Ranked by efficiency, less :data:`OVER_CAP_COST` for each unit of fidelity
    over the cap.
    """
    designs = []
    for _, _, start, start_gains in screened:
        bar.set_description("L-BFGS")
        start, fid, eff = refine_constrained(start, target, cap, PENALTIES, lbfgs_evals)
        bar.update()
        designs.append(
            (eff - OVER_CAP_COST * max(fid - cap, 0.0), len(designs), start, start_gains)
        )
    designs.sort(key=lambda d: (-d[0], d[1]))
    return [(phase, gains) for _, _, phase, gains in designs]


def _progress_bar(enabled, total):
    """Return a tqdm bar on stderr, silent unless ``enabled`` and stderr is a terminal."""
    import sys

    from tqdm import tqdm

    return tqdm(total=total, disable=not (enabled and sys.stderr.isatty()), leave=False)
