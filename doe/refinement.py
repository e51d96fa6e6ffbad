"""The continuous stage of the retrieval: its objective, adjoint gradient and L-BFGS refinement.

:func:`refine_constrained` runs nlopt L-BFGS (:func:`doe.lbfgs.minimise`) on
:func:`constrained_objective`: maximal window efficiency with each fidelity
term of :mod:`doe.goals` within a cap, its gradient the adjoint of the window
DFT. :func:`objective` is the unconstrained trade-off of fidelity against
efficiency. The window helpers here (:func:`window_matrix`, :func:`window_fft`)
serve the discrete stage (:mod:`doe.quantisation`) too.
"""

import numpy as np
import scipy.fft

from doe import fraunhofer
from doe.goals import CAP, Goal, cap_penalty, fidelity_parts, goal_values
from doe.lbfgs import minimise

DEFAULT_WEIGHT = 30.0
"""Weight of the efficiency term against the fidelity terms in :func:`objective`.

The fidelity terms are 1 where the rmse or the correlation reaches its goal, so
30 trades one percent of efficiency against 0.3 of that budget.
"""

PENALTIES = (0.1, 1.0)
"""Penalty weights of :func:`refine_constrained`, one L-BFGS run each."""


# --------------------------------------------------------------------------- window
def window_matrix(n, k):
    """Return the (K, N) partial DFT that maps a tile axis to the K window orders.

    ``A @ exp(1j * phase) @ A.T / N**2`` equals the K x K window of
    :func:`doe.fraunhofer.order_amplitudes` (row i holds order i - K//2).
    """
    orders = np.arange(k) - k // 2
    return np.exp(-2j * np.pi * np.outer(orders, np.arange(n)) / n)


def window_fft(field, idx):
    """Return the K x K window of orders of a unit-amplitude field (FFT, no BLAS threads)."""
    return scipy.fft.fft2(field)[np.ix_(idx, idx)] / field.size


def _back_fft(g, idx, n):
    """Return sum_mn g[m, n] exp(-2 pi i (m r + n c) / N) for every pixel (r, c), (N, N)."""
    full = np.zeros((n, n), dtype=np.complex128)
    full[np.ix_(idx, idx)] = g
    return scipy.fft.fft2(full)


# --------------------------------------------------------------------------- objective
def _fidelity_terms(power, goal, weight):
    """Return (J, dJ/dP) for one (K, K) window power P (see :func:`objective`)."""
    parts = fidelity_parts(power, goal)
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
    goal : Goal or None
        Cached target constants.

    Returns
    -------
    value : float
    grad : (N, N) float64
        dJ/dphase, rad^-1.
    """
    field, w, idx = _window_of(phase, target.shape[0])
    goal = Goal.of(target) if goal is None else goal
    value, grad_p = _fidelity_terms(np.abs(w) ** 2, goal, weight)
    return value, _phase_gradient(field, w, idx, grad_p)


def _window_of(phase, k):
    """Return (tile field, K x K window of orders, window indices) of a phase."""
    phase = np.asarray(phase, dtype=np.float64)
    idx = fraunhofer.window_indices(phase.shape[0], k)
    field = np.exp(1j * phase)
    return field, window_fft(field, idx), idx


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
    return float(goal_values(power, Goal.of(target), 0.0))


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
    goal : Goal or None
        Cached target constants.

    Returns
    -------
    value : float
    grad : (N, N) float64
        dJ/dphase, rad^-1.
    """
    cap = CAP if cap is None else cap
    field, w, idx = _window_of(phase, target.shape[0])
    goal = Goal.of(target) if goal is None else goal
    power = w.real**2 + w.imag**2
    penalty, d_penalty = cap_penalty(power, goal, cap, mu)
    return float(-power.sum() + penalty), _phase_gradient(field, w, idx, d_penalty - 1.0)


def refine_constrained(phase, target, cap=None, mus=PENALTIES, max_eval=35):
    """Return (phase, fidelity, efficiency) after L-BFGS on :func:`constrained_objective`.

    One L-BFGS run of ``max_eval`` evaluations for each penalty weight in ``mus``
    (increasing), each from the previous one's best point; the returned figures
    are the smooth fidelity and the efficiency of the final phase.
    """
    shape = phase.shape
    goal = Goal.of(target)
    x = np.asarray(phase, float).ravel()
    for mu in mus:

        def fun(v, mu=mu):
            return constrained_objective(v.reshape(shape), target, cap, mu, goal)

        x, _ = minimise(fun, x, max_eval)
    power = fraunhofer.window_power(x.reshape(shape), target.shape[0])
    fid = float(goal_values(power, goal, 0.0, mode="smooth"))
    return x.reshape(shape), fid, float(power.sum())
