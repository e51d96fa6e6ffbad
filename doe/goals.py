"""The quality goals of a design and the fidelity figures measured against them.

A design meets its goals when the quantised plate's PSF has a Pearson
correlation of at least :data:`CORRELATION_GOAL` with the target and a
peak-normalised rmse of at most :data:`RMSE_GOAL` (CONVENTIONS.md). The
retrieval (:mod:`doe.retrieval` and its stages) and the efficiency bounds
(:mod:`doe.bounds`) measure a window of orders against these goals through
:class:`Goal` and the fidelity figures here; the fabrication package and the run
summary quote them.

The fidelity of a window power P is the larger of (rmse / RMSE_GOAL)^2 and
(1 - correlation) / (1 - CORRELATION_GOAL): at most 1 means both goals are met.
"""

from dataclasses import dataclass

import numpy as np

from doe import fraunhofer
from doe.figures import value_and_limit

RMSE_GOAL = 0.005
"""Peak-normalised rmse the fidelity term is measured against (the acceptance bound)."""

CORRELATION_GOAL = 0.9999
"""Pearson correlation the fidelity term is measured against (the acceptance bound)."""

CAP = 0.81
"""Fidelity (see :func:`doe.refinement.fidelity`) the design aims at: each quality figure
within 81 % of its goal's error budget (rmse <= 0.0045 and 1 - correlation <= 8.1e-5)."""

SLACK = 0.1
"""Weight of the fidelity below a cap in :func:`goal_values` (the coordinate descent's)."""


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


@dataclass(frozen=True)
class Goal:
    """The target's constants that the fidelity figures need (see :func:`goal_values`).

    Build one with :meth:`Goal.of`; it is computed once per target and passed to
    every evaluation.
    """

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
        """Return the :class:`Goal` of a (K, K) target PSF that sums to 1."""
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


def goal_values(power, goal, weight, cap=0.0, mode="exact"):
    """Return J for window powers ``power`` (..., K, K), broadcasting over leading axes.

    J = fidelity - weight * E, the fidelity being the larger of (rmse / RMSE_GOAL)^2
    and (1 - correlation) / (1 - CORRELATION_GOAL); ``mode`` "exact" normalises the
    rmse by the simulated peak as CONVENTIONS.md does, "smooth" by the mean over
    the target's peak orders (the stand-in of :func:`doe.refinement.objective`).

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


def window_value(window, goal, weight, cap=0.0, mode="exact"):
    """Return :func:`goal_values` of one complex (K, K) window, lean (the greedy inner loop)."""
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


def fidelity_parts(power, goal):
    """Return the two fidelity terms of one (K, K) window power P, each with its dP.

    ((rmse / RMSE_GOAL)^2, d/dP), ((1 - corr) / (1 - CORRELATION_GOAL), d/dP), the
    rmse normalised by the smooth stand-in for the peak (see
    :func:`doe.refinement.objective`).
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


def cap_penalty(power, goal, cap, mu):
    """Return (mu * sum of each fidelity term's squared excess over ``cap``, its dP).

    The penalty of :func:`doe.refinement.constrained_objective` and
    :func:`doe.bounds.within_goals`.
    """
    (f_r, d_r), (f_c, d_c) = fidelity_parts(power, goal)
    e_r, e_c = max(f_r - cap, 0.0), max(f_c - cap, 0.0)
    return mu * (e_r * e_r + e_c * e_c), 2.0 * mu * (e_r * d_r + e_c * d_c)
