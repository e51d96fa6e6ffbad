"""Phase retrieval: from a K x K target PSF to an L-level phase tile of N x N pixels.

The pipeline, all on the forward model of :mod:`doe.fraunhofer`:

1. Screening -- cheap starts: :func:`flat_modulus_start` (order phases that make
   the band-limited field's modulus as flat as possible) and random weighted
   :func:`gerchberg_saxton`, each followed by :func:`mixed_region` (MRAF); the
   light that does not fit the window leaves into the outside orders, the
   light sink. The best few by efficiency and fidelity go on.
2. :func:`refine_constrained` -- nlopt L-BFGS on :func:`constrained_objective`:
   maximal efficiency with the two quality figures (rmse, correlation, each in
   units of its goal) within a cap, with an analytic (adjoint) gradient.
3. :func:`gerchberg_saxton` with ``n_levels`` -- quantised GS from that phase;
   it, and plain rounding at the best global offset, each start a discrete search.
4. :func:`coordinate_descent` -- a direct search over the discrete levels on the
   real quantised figures; with the fidelity capped it climbs efficiency while
   both figures stay within budget. This is what closes the gap left by rounding.

:func:`retrieve_phase` runs all four and reports the quality figures of
:func:`doe.fraunhofer.quality` for the continuous and the quantised design.
The loops use numpy element-wise work, small dot products and pocketfft, none
of it threaded, so a seed gives bit-identical level maps on a given machine
whatever its thread count.
"""

import time
from dataclasses import dataclass

import numpy as np
import scipy.fft

from doe import bounds, fraunhofer
from doe.figures import value_and_limit
from doe.lbfgs import minimise

DEFAULT_WEIGHT = 30.0
"""Weight of the efficiency term against the fidelity terms in :func:`objective`.

The fidelity terms are 1 where the rmse or the correlation reaches its goal, so
30 trades one percent of efficiency against 0.3 of that budget.
"""

CD_WEIGHTS = (100.0, 60.0, 40.0, 30.0, 20.0, 15.0, 10.0, 5.0, 2.0)
"""Efficiency weights of the coordinate-descent sweeps, most efficient first."""

CAP = 0.81
"""Fidelity (see :func:`fidelity`) the design aims at: each quality figure within
81 % of its goal's error budget (rmse <= 0.0045 and 1 - correlation <= 8.1e-5)."""

SLACK = 0.1
"""Weight of the fidelity below :data:`CAP` in the coordinate descent's objective."""

MIN_GAIN = 0.002
"""Efficiency gain below which a coordinate-descent sweep within :data:`CAP` ends the finish."""


MRAF_MIX = 0.6
"""Share of the window in the projection of :func:`mixed_region` (1 would be GS)."""

PENALTIES = (0.1, 1.0)
"""Penalty weights of :func:`refine_constrained`, one L-BFGS run each."""

SCREENS = 6
"""Cheap starts (GS + MRAF) screened for the continuous stage; see :data:`SCREEN_RATE`."""

SCREEN_RATE = 0.012
"""Efficiency that one unit of fidelity above the cap costs L-BFGS on its way to the cap.

Screened starts are ranked by efficiency - SCREEN_RATE * fidelity after MRAF
(0.008-0.014 measured on hard flat tops; the ranking, not the value, matters).
"""

STARTS = 2
"""Best screened starts refined by L-BFGS; the most efficient within the cap is kept."""

FINISHES = 1
"""Continuous designs that are quantised, best first (more cost time and seldom win)."""

POLISH_SWEEPS = 6
"""Most exact-figure coordinate-descent sweeps that bring the fidelity within the cap."""

CLIMB_SWEEPS = 3
"""Most exact-figure coordinate-descent sweeps that spend fidelity left below the cap."""

CLIMB_WEIGHT = 10.0
"""Efficiency weight of those sweeps (30 overshoots the cap more often; measured on flat tops)."""


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


# --------------------------------------------------------------------------- window
def window_matrix(n, k):
    """Return the (K, N) partial DFT that maps a tile axis to the K window orders.

    ``A @ exp(1j * phase) @ A.T / N**2`` equals the K x K window of
    :func:`doe.fraunhofer.order_amplitudes` (row i holds order i - K//2).
    """
    orders = np.arange(k) - k // 2
    return np.exp(-2j * np.pi * np.outer(orders, np.arange(n)) / n)


def _window_fft(field, idx):
    """Return the K x K window of orders of a unit-amplitude field (FFT, no BLAS threads)."""
    return scipy.fft.fft2(field)[np.ix_(idx, idx)] / field.size


def _back_fft(g, idx, n):
    """Return sum_mn g[m, n] exp(-2 pi i (m r + n c) / N) for every pixel (r, c), (N, N)."""
    full = np.zeros((n, n), dtype=np.complex128)
    full[np.ix_(idx, idx)] = g
    return scipy.fft.fft2(full)


# --------------------------------------------------------------------------- objective
RMSE_GOAL = 0.005
"""Peak-normalised rmse the fidelity term is measured against (the acceptance bound)."""

CORRELATION_GOAL = 0.9999
"""Pearson correlation the fidelity term is measured against (the acceptance bound)."""


def missed_goals(quality):
    """Return the quality goals a design misses, one phrase each; empty when it meets them.

    ``quality`` is a dict of :func:`doe.fraunhofer.quality`. A uniform target has
    no correlation (NaN, or None as read back from JSON); its rmse alone decides.
    """
    missed = []
    corr, rmse = quality["correlation"], quality["rmse"]
    if corr is not None and not np.isnan(corr) and not corr >= CORRELATION_GOAL:
        shown = value_and_limit(corr, CORRELATION_GOAL, 6, "f")[0]
        missed.append(f"correlation {shown} < {CORRELATION_GOAL}")
    if not rmse <= RMSE_GOAL:  # NaN too
        missed.append(f"rmse {value_and_limit(rmse, RMSE_GOAL, 5, 'f')[0]} > {RMSE_GOAL}")
    return missed


@dataclass(frozen=True)
class _Goal:
    """The target's constants that the fidelity terms need (see :func:`objective`)."""

    target: np.ndarray  # (K, K), sum 1
    scaled: np.ndarray  # target / max(target)
    centred: np.ndarray  # target - mean, (K, K)
    norm: float  # |target - mean|
    peak: np.ndarray  # (K, K) bool, where the target has its maximum
    c_rmse: float  # 1 / (K * RMSE_GOAL)^2
    c_corr: float  # 1 / (1 - CORRELATION_GOAL)
    flat_centred: np.ndarray  # centred.ravel()
    flat_scaled: np.ndarray  # scaled.ravel()
    flat_peak: np.ndarray  # peak.ravel() / number of peak orders

    @classmethod
    def of(cls, target):
        centred = target - target.mean()
        tmax = float(target.max())
        norm = float(np.sqrt((centred**2).sum()))
        # a uniform target has no correlation to speak of (Pearson's is undefined):
        # the rmse term alone then measures the fit
        flat = norm <= 1e-12 * tmax
        peak = target >= tmax * (1 - 1e-12)
        return cls(
            target=target,
            scaled=target / tmax,
            centred=centred,
            norm=1.0 if flat else norm,
            peak=peak,
            c_rmse=1.0 / (target.shape[0] * RMSE_GOAL) ** 2,
            c_corr=0.0 if flat else 1.0 / (1.0 - CORRELATION_GOAL),
            flat_centred=centred.ravel(),
            flat_scaled=(target / tmax).ravel(),
            flat_peak=peak.ravel() / peak.sum(),
        )


def goals_missed(levels, n_levels, target, simulated_psf):
    """Return the goals a plate of ``levels`` misses, in the contract's model (its
    ``simulated_psf``) and as a plate of square pixels, whose sinc^2 envelope the
    contract leaves out: two lists of :func:`missed_goals` phrases, empty where met."""
    contract = {
        "correlation": fraunhofer.correlation(simulated_psf, target),
        "rmse": fraunhofer.rmse(simulated_psf, target),
    }
    plate = fraunhofer.plate_quality(fraunhofer.level_phase(levels, n_levels), target)
    return missed_goals(contract), missed_goals(plate)


def _values(power, goal, weight, cap=0.0, mode="exact"):
    """Return J for window powers ``power`` (..., K, K), broadcasting over leading axes.

    J = fidelity - weight * E, the fidelity being the larger of (rmse / RMSE_GOAL)^2
    and (1 - correlation) / (1 - CORRELATION_GOAL); ``mode`` "exact" normalises the
    rmse by the simulated peak as CONVENTIONS.md does, "smooth" by the mean over
    the target's peak orders (the stand-in of :func:`objective`).

    With ``cap`` > 0 a fidelity F below ``cap`` counts as ``cap`` + :data:`SLACK` * F:
    the efficiency is then maximised subject to the fidelity staying within
    ``cap``, and fidelity is not given away for a negligible gain.
    """
    axes = (-2, -1)
    eff = power.sum(axis=axes)
    centred = power - eff[..., None, None] / goal.target.size
    corr = (centred * goal.centred).sum(axis=axes) / (
        np.sqrt((centred * centred).sum(axis=axes)) * goal.norm
    )
    if mode == "exact":
        p0 = power.max(axis=axes)  # the rmse normalises by the simulated peak
    else:
        p0 = (power * goal.peak).sum(axis=axes) / goal.peak.sum()
    u = power / p0[..., None, None] - goal.scaled
    fid = np.maximum(goal.c_corr * (1.0 - corr), goal.c_rmse * (u * u).sum(axis=axes))
    if cap > 0:
        fid = np.maximum(fid, cap) + SLACK * np.minimum(fid, cap)
    return fid - weight * eff


def _value_one(window, goal, weight, cap=0.0, mode="exact"):
    """Return :func:`_values` of one complex (K, K) window, lean (the greedy inner loop)."""
    p = window.real.ravel() ** 2 + window.imag.ravel() ** 2
    eff = p.sum()
    pc = p - eff / p.size
    corr = np.dot(pc, goal.flat_centred) / (np.sqrt(np.dot(pc, pc)) * goal.norm)
    p0 = p.max() if mode == "exact" else np.dot(p, goal.flat_peak)
    u = p / p0 - goal.flat_scaled
    fid = max(goal.c_rmse * np.dot(u, u), goal.c_corr * (1.0 - corr))
    if cap > 0:
        fid = max(fid, cap) + SLACK * min(fid, cap)
    return float(fid - weight * eff)


def _fidelity_parts(power, goal):
    """Return the two fidelity terms of one (K, K) window power P, each with its dP.

    ((rmse / RMSE_GOAL)^2, d/dP), ((1 - corr) / (1 - CORRELATION_GOAL), d/dP), the
    rmse normalised by the smooth stand-in for the peak (see :func:`objective`).
    """
    centred = power - power.mean()
    cnorm = np.sqrt((centred**2).sum())
    corr = (centred * goal.centred).sum() / (cnorm * goal.norm)
    # A smooth stand-in for the rmse's peak normalisation: the mean over the orders
    # where the target peaks (equal to the simulated peak once the fit is good);
    # the exact max would make the objective non-smooth on flat-topped targets.
    npeak = goal.peak.sum()
    p0 = (power * goal.peak).sum() / npeak
    u = power / p0 - goal.scaled
    d_rmse = 2.0 * goal.c_rmse * (u / p0 - goal.peak * ((u * power).sum() / p0**2 / npeak))
    # d corr / dP: the mean removal drops out because both centred arrays sum to 0
    d_corr = goal.centred / (cnorm * goal.norm) - corr * centred / cnorm**2
    return (
        (float(goal.c_rmse * (u**2).sum()), d_rmse),
        (float(goal.c_corr * (1.0 - corr)), -goal.c_corr * d_corr),
    )


def _fidelity_terms(power, goal, weight):
    """Return (J, dJ/dP) for one (K, K) window power P (see :func:`objective`)."""
    parts = _fidelity_parts(power, goal)
    fid, d_fid = max(parts, key=lambda part: part[0])  # the gradient of the larger term
    return fid - weight * float(power.sum()), d_fid - weight


def objective(phase, target, weight=DEFAULT_WEIGHT, goal=None):
    """Return (J, dJ/dphase) of the retrieval objective.

    J = max(sum((P / p0 - t / max(t))^2) / (K * RMSE_GOAL)^2,
            (1 - corr(P, t)) / (1 - CORRELATION_GOAL)) - weight * E,

    where P is the window power of ``phase`` (fraction of the incident light per
    order), E = sum(P) the efficiency, t the target, corr Pearson's correlation
    and p0 the mean of P over the orders where t peaks. The two fidelity terms
    are the squared rmse and the correlation deficit of CONVENTIONS.md, each in
    units of its goal (1 = goal just met; :func:`fidelity` gives the exact
    figure, normalised by the simulated peak). The larger counts: the goals are
    met when each is, so neither needs to leave budget to the other. The
    gradient (of the larger term where they differ) is the adjoint of the
    window DFT.

    Parameters
    ----------
    phase : (N, N) array
        Tile phase, rad.
    target : (K, K) array
        Target PSF, sum 1.
    weight : float
        Efficiency weight (see :data:`DEFAULT_WEIGHT`).
    goal : _Goal or None
        Cached target constants.

    Returns
    -------
    value : float
    grad : (N, N) float64
        dJ/dphase, rad^-1.
    """
    field, w, idx = _window_of(phase, target.shape[0])
    goal = _Goal.of(target) if goal is None else goal
    value, grad_p = _fidelity_terms(np.abs(w) ** 2, goal, weight)
    return value, _phase_gradient(field, w, idx, grad_p)


def _window_of(phase, k):
    """Return (tile field, K x K window of orders, window indices) of a phase."""
    phase = np.asarray(phase, dtype=np.float64)
    idx = fraunhofer.window_indices(phase.shape[0], k)
    field = np.exp(1j * phase)
    return field, _window_fft(field, idx), idx


def _phase_gradient(field, w, idx, d_power):
    """Return dJ/dphase (N, N) from dJ/d(window power) by the adjoint of the window DFT."""
    back = _back_fft(d_power * np.conj(w), idx, field.shape[0])
    return -2.0 / field.size * np.imag(field * back)


def fidelity(phase, target):
    """Return the larger of (rmse / RMSE_GOAL)^2 and (1 - correlation) / (1 - CORRELATION_GOAL).

    The exact figures of :func:`doe.fraunhofer.quality`: at most 1 means both
    quality goals are met.
    """
    power = fraunhofer.window_power(phase, target.shape[0])
    return float(_values(power, _Goal.of(target), 0.0))


def constrained_objective(phase, target, cap=None, mu=1.0, goal=None):
    """Return (J, dJ/dphase) of the constrained retrieval objective.

    J = -E + mu * (max(F_rmse - cap, 0)^2 + max(F_corr - cap, 0)^2), with E the
    window efficiency and F_rmse, F_corr the two smooth fidelity terms of
    :func:`objective`: a penalty form of "maximise the efficiency subject to
    each term <= cap" (smooth where the larger of the two is not). Raising ``mu``
    between L-BFGS runs (:func:`refine_constrained`) walks the design onto the
    constraint.

    Parameters
    ----------
    phase : (N, N) array
        Tile phase, rad.
    target : (K, K) array
        Target PSF, sum 1.
    cap : float or None
        Fidelity budget (1 = both goals just met); default :data:`CAP`.
    mu : float
        Penalty weight.
    goal : _Goal or None
        Cached target constants.

    Returns
    -------
    value : float
    grad : (N, N) float64
        dJ/dphase, rad^-1.
    """
    cap = CAP if cap is None else cap
    field, w, idx = _window_of(phase, target.shape[0])
    goal = _Goal.of(target) if goal is None else goal
    power = w.real**2 + w.imag**2
    penalty, d_penalty = _cap_penalty(power, goal, cap, mu)
    return float(-power.sum() + penalty), _phase_gradient(field, w, idx, d_penalty - 1.0)


def _cap_penalty(power, goal, cap, mu):
    """Return (mu * sum of each fidelity term's squared excess over ``cap``, its dP).

    The penalty of :func:`constrained_objective` and :func:`doe.bounds.within_goals`.
    """
    (f_r, d_r), (f_c, d_c) = _fidelity_parts(power, goal)
    e_r, e_c = max(f_r - cap, 0.0), max(f_c - cap, 0.0)
    return mu * (e_r * e_r + e_c * e_c), 2.0 * mu * (e_r * d_r + e_c * d_c)


# --------------------------------------------------------------------------- GS
def gerchberg_saxton(
    target, n_pixels, iterations=150, rng=None, phase=None, weighted=True, n_levels=None, gains=None
):
    """Return (phase, gains): a tile phase (rad, (N, N)) by (weighted) Gerchberg-Saxton.

    Order plane: the K x K window gets the amplitude gains * sqrt(target) with the
    current phases; every other order is set to zero. Tile plane: only the phase
    is kept (phase-only plate), which scatters the light that does not fit the
    window into the orders outside it -- the light sink. Zeroing the outside
    orders in the projection is what pulls light into the window; leaving them
    untouched and rescaling the window to its own power keeps the efficiency of
    the random start (about K^2 / N^2).

    Parameters
    ----------
    target : (K, K) array
        Target PSF, sum 1.
    n_pixels : int
        Tile size N.
    iterations : int
        Number of iterations.
    rng : numpy.random.Generator or None
        Source of the random start phase (ignored when ``phase`` is given).
    phase : (N, N) array or None
        Start phase, rad.
    weighted : bool
        Weighted GS: each window order's gain is multiplied every iteration by
        sqrt(target / simulated PSF), which evens out the orders' errors.
    n_levels : int or None
        If given, the tile-plane projection rounds the phase to these levels
        (quantised GS); the returned phase then lies on the levels.
    gains : (K, K) array or None
        Start gains (e.g. from a previous call), default 1.
    """
    k = target.shape[0]
    if phase is None:
        rng = np.random.default_rng(0) if rng is None else rng
        phase = rng.uniform(-np.pi, np.pi, (n_pixels, n_pixels))
    idx = fraunhofer.window_indices(n_pixels, k)
    sel = np.ix_(idx, idx)
    amp = np.sqrt(target)
    lit = target > 0
    gains = np.ones_like(target) if gains is None else np.array(gains, dtype=np.float64)
    phase = np.asarray(phase, dtype=np.float64)
    for _ in range(iterations):
        win = scipy.fft.fft2(np.exp(1j * phase))[sel]
        if weighted:
            power = np.abs(win) ** 2
            power = power / power.sum()
            gains[lit] *= np.sqrt(target[lit] / np.maximum(power[lit], 1e-300))
            gains /= np.sqrt((gains[lit] ** 2 * target[lit]).sum())
        spec = np.zeros((n_pixels, n_pixels), dtype=np.complex128)
        spec[sel] = gains * amp * np.exp(1j * np.angle(win))
        phase = np.angle(scipy.fft.ifft2(spec))
        if n_levels is not None:
            phase = level_step(n_levels) * np.round(phase / level_step(n_levels))
    return phase, gains


def flat_modulus_start(target, n_pixels, rng=None, restarts=3, max_eval=200):
    """Return a tile phase (rad, (N, N)) whose band-limited field is as flat in modulus as can be.

    The field g(x) of the target's window amplitudes with the lit orders' phases
    that maximise mean |g| (:func:`doe.bounds.best_flat_field`: Wyrowski's bound
    on the efficiency of a plate forming exactly the target's shape) has the
    flattest modulus, so arg g is a start that is already both efficient and
    close to the target shape (on a hard 5 x 5 square it beat two random starts
    by 3.5 % of efficiency; like theirs, its result varies with the seed).
    """
    return np.angle(bounds.best_flat_field(target, n_pixels, None, rng, restarts, max_eval)[1])


def mixed_region(target, phase, gains, iterations=100, mix=MRAF_MIX):
    """Return (phase, gains) after weighted mixed-region amplitude-freedom iterations.

    Like :func:`gerchberg_saxton`, but the order-plane projection keeps
    ``1 - mix`` of the field outside the window (the MRAF algorithm) and scales
    the window to ``mix`` times its own current amplitude. Where GS forces every
    outside order to zero -- the phase-only plate can never do that, so GS
    converges to a design with a large in-window error -- the kept outside field
    leaves the phase the freedom to put the window's shape right; the start of
    the constrained refinement is then both efficient and close to the target.

    Parameters
    ----------
    target : (K, K) array
        Target PSF, sum 1.
    phase : (N, N) array
        Start phase, rad.
    gains : (K, K) array
        Start gains of the weighted GS (see :func:`gerchberg_saxton`).
    iterations : int
        Number of iterations.
    mix : float
        Share of the window in the projection, 0 < mix <= 1.
    """
    n, k = phase.shape[0], target.shape[0]
    idx = fraunhofer.window_indices(n, k)
    sel = np.ix_(idx, idx)
    amp = np.sqrt(target)
    lit = target > 0
    gains = np.array(gains, dtype=np.float64)
    phase = np.asarray(phase, dtype=np.float64)
    for _ in range(iterations):
        spec = scipy.fft.fft2(np.exp(1j * phase)) / phase.size
        win = spec[sel]
        power = win.real**2 + win.imag**2
        eff = power.sum()
        gains[lit] *= np.sqrt(target[lit] * eff / np.maximum(power[lit], 1e-300))
        gains /= np.sqrt((gains[lit] ** 2 * target[lit]).sum())
        spec *= 1.0 - mix
        spec[sel] = mix * np.sqrt(eff) * gains * amp * np.exp(1j * np.angle(win))
        phase = np.angle(scipy.fft.ifft2(spec))
    return phase, gains


def level_step(n_levels):
    """Return the phase step between two levels, 2 pi / L (rad)."""
    return 2 * np.pi / n_levels


def refine_constrained(phase, target, cap=None, mus=PENALTIES, max_eval=35):
    """Return (phase, fidelity, efficiency) after L-BFGS on :func:`constrained_objective`.

    One L-BFGS run of ``max_eval`` evaluations for each penalty weight in ``mus``
    (increasing), each from the previous one's best point; the returned figures
    are the smooth fidelity and the efficiency of the final phase.
    """
    shape = phase.shape
    goal = _Goal.of(target)
    x = np.asarray(phase, float).ravel()
    for mu in mus:

        def fun(v, mu=mu):
            return constrained_objective(v.reshape(shape), target, cap, mu, goal)

        x, _ = minimise(fun, x, max_eval)
    power = fraunhofer.window_power(x.reshape(shape), target.shape[0])
    fid = float(_values(power, goal, 0.0, mode="smooth"))
    return x.reshape(shape), fid, float(power.sum())


def round_levels(phase, n_levels):
    """Return the nearest level (uint8 (N, N)) to each phase (rad), modulo 2 pi."""
    q = np.round(np.asarray(phase) * n_levels / (2 * np.pi)).astype(np.int64) % n_levels
    return q.astype(np.uint8)


# --------------------------------------------------------------------------- discrete
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
        Efficiency weight of :func:`objective`.
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
        Fidelity cap (see :func:`_values`): 0 minimises fidelity - weight * E,
        > 0 maximises the efficiency within a fidelity of ``cap``.
    mode : {"exact", "smooth"}
        Peak normalisation of the rmse term: the simulated peak (the exact
        figure) or the mean over the target's peak orders (smoother, so the
        greedy search progresses faster on flat-topped targets).

    Returns
    -------
    levels : (N, N) uint8
    """
    rng = np.random.default_rng(0) if rng is None else rng
    q = np.asarray(levels).astype(np.int64)
    n, k = q.shape[0], target.shape[0]
    goal = _Goal.of(target)
    a = window_matrix(n, k)
    phasors = np.exp(1j * level_step(n_levels) * np.arange(n_levels))
    w = _window_fft(phasors[q], fraunhofer.window_indices(n, k))
    value = _value_one(w, goal, weight, cap, mode)
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
            vals = _values(trial.real**2 + trial.imag**2, goal, weight, cap, mode)
            best = np.argmin(vals, axis=1)
            gain = vals[np.arange(pix.size), best] - value
            ranked = np.argsort(gain, kind="stable")
            ranked = ranked[gain[ranked] < 0]
            for i in ranked:
                new_w = w + delta[i, best[i]] * basis[i]
                new_value = _value_one(new_w, goal, weight, cap, mode)
                if new_value < value:
                    w, value = new_w, new_value
                    q[r[i], c[i]] = cand[i, best[i]]
                    changed += 1
        if changed == 0:
            break
    return q.astype(np.uint8)


# --------------------------------------------------------------------------- entry point
def _progress_bar(enabled, total):
    """Return a tqdm bar on stderr, silent unless ``enabled`` and stderr is a terminal."""
    import sys

    from tqdm import tqdm

    return tqdm(total=total, disable=not (enabled and sys.stderr.isatty()), leave=False)


def _finish(phase, gains, target, n_levels, rng, cd_weights, cap, quantised_iterations, bar):
    """Return (:func:`_rank` key, levels): the discrete stages of :func:`retrieve_phase`.

    Two descents, one from quantised GS and one from the best plain rounding: which
    of them ends higher is a lottery (on 7 hard flat tops x 2 seeds the second won
    13 times, by 0.0004-0.012 of efficiency), so both run and the better is kept.
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
    goal = _Goal.of(target)
    roundings = [round_levels(phase + j / 8 * level_step(n_levels), n_levels) for j in range(8)]
    scores = [
        float(
            _values(
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
        levels, eff, fid = _descend(start, target, goal, n_levels, rng, cd_weights, cap, bar)
        ranked.append((_rank(eff, fid, cap), len(ranked), levels))
    key, _, levels = min(ranked, key=lambda r: r[:2])
    return key, levels


def _rank(eff, fid, cap):
    """Sort key of a level map: within the cap the most efficient first, else the most faithful."""
    return (0, -eff) if fid <= cap else (1, fid)


def _descend(levels, target, goal, n_levels, rng, cd_weights, cap, bar):
    """Return (levels, efficiency, exact fidelity) after the descent sweeps of :func:`_finish`."""

    def figures(levels):
        """(efficiency, exact fidelity) of a level map."""
        power = fraunhofer.window_power(fraunhofer.level_phase(levels, n_levels), target.shape[0])
        return float(power.sum()), float(_values(power, goal, 0.0))

    def sweep(levels, weight, mode):
        return coordinate_descent(
            levels, target, n_levels, weight, sweeps=1, rng=rng, cap=cap, mode=mode
        )

    eff, fid = figures(levels)
    bar.set_description("coordinate descent")
    for w in cd_weights:
        bar.update()
        levels = sweep(levels, w, "smooth")
        new_eff, fid = figures(levels)
        gain, eff = new_eff - eff, new_eff
        if fid <= cap and gain < MIN_GAIN:
            break
    # The smooth stand-in for the peak normalisation can disagree with the exact
    # rmse on flat-topped targets, either way: the last sweeps use the exact figures.
    for _ in range(POLISH_SWEEPS):
        if fid <= cap:
            break
        # over the cap: polish, sweep by sweep, still weighing efficiency (with
        # weight 0 the slack below the cap would trade efficiency for needless fidelity)
        levels = sweep(levels, cd_weights[-1], "exact")
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
):
    """Design an L-level phase tile whose K x K window of orders forms ``target``.

    ``screens`` cheap starts -- :func:`flat_modulus_start` and random weighted GS,
    each followed by mixed-region (MRAF) iterations -- are ranked by efficiency less
    :data:`SCREEN_RATE` per unit of fidelity; the best ``starts`` go through L-BFGS
    on the constrained objective (maximal efficiency with the fidelity within
    ``cap``), and the ``finishes`` most efficient continuous designs go on.
    Quantised weighted GS from each, and plain rounding at the best global offset,
    each start a coordinate descent on the level map: one sweep for each of the
    efficiency weights ``cd_weights`` in turn, with the fidelity capped at ``cap``
    (below it only :data:`SLACK` of it counts), until the fidelity is within
    ``cap`` and a sweep gains less than :data:`MIN_GAIN` of efficiency, then
    sweeps on the exact figures bring a map over the cap within it or spend the
    budget left below it; the most efficient level map within the cap wins.

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
        Cheap starts: the flat-modulus start (:func:`flat_modulus_start`) and
        random weighted GS, each followed by MRAF.
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
        :func:`objective`, 1 = a goal just met) the design aims at.
    progress : bool
        Show a tqdm progress bar of the stages on stderr (when it is a terminal).

    Returns
    -------
    Retrieval
    """
    target = np.asarray(target, dtype=np.float64)
    if target.ndim != 2 or target.shape[0] != target.shape[1] or target.shape[0] % 2 == 0:
        raise ValueError(f"target must be square with odd size, got shape {target.shape}")
    k = target.shape[0]
    if k > n_pixels:
        raise ValueError(f"kernel size K = {k} exceeds the tile size N = {n_pixels}")
    if n_levels < 2:
        raise ValueError(f"need at least 2 levels, got {n_levels}")
    target = target / target.sum()
    t0 = time.perf_counter()
    if k == 1:
        # the zero order alone, which an unetched (flat) plate forms with all the
        # light; the objective's correlation term is 0 / 0 on a single order
        levels = np.full((n_pixels, n_pixels), n_levels - 1, np.uint8)
        phase = fraunhofer.level_phase(levels, n_levels)
        quality = fraunhofer.quality(phase, target)
        return Retrieval(levels, phase, n_levels, quality, quality, time.perf_counter() - t0, seed)
    starts, finishes = max(int(starts), 1), max(int(finishes), 1)
    screens, finishes = max(int(screens), starts), min(finishes, starts)
    bar = _progress_bar(progress, screens + starts + finishes * (1 + 2 * len(cd_weights)))
    rng = np.random.default_rng(seed)
    # Screening: cheap starts (the flat-modulus one, then random weighted GS), each
    # with MRAF; which basin the later stages end in is a lottery that the
    # screened figures predict well (measured on flat tops and sparse dots).
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
    designs = []
    for _, _, start, start_gains in screened[:starts]:
        bar.set_description("L-BFGS")
        start, fid, eff = refine_constrained(start, target, cap, PENALTIES, lbfgs_evals)
        bar.update()
        # efficiency, less 0.05 for each unit of fidelity over the cap
        designs.append((eff - 0.05 * max(fid - cap, 0.0), len(designs), start, start_gains))
    designs.sort(key=lambda d: (-d[0], d[1]))
    best = None
    for _, _, phase, gains in designs[:finishes]:
        key, levels = _finish(
            phase, gains, target, n_levels, rng, cd_weights, cap, quantised_iterations, bar
        )
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
