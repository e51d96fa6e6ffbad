"""Bounds on the efficiency of a phase-only tile that forms a target PSF, estimated from below.

Let the window orders u carry w_u = c sqrt(t_u) e^{i theta_u} on the lit orders of
the target t (sum 1) and nothing on its dark ones: exactly the target's shape,
efficiency |c|^2. With g(x) = sum_u sqrt(t_u) e^{i theta_u} e^{2 pi i u.x / N}
(the band-limited field of the lit orders, unit mean power), Parseval gives
c = mean_x(plate(x) conj g(x)), so for a plate of unit modulus

    efficiency <= max over theta of (mean_x |g(x)|)^2

(Wyrowski's bound), reached only where |g| is constant. A plate of L levels can
only match arg g to the nearest level, so

    efficiency <= max over theta of (mean_x |g(x)| cos d(x))^2,

d the distance of arg g to the nearest level (the global phase is part of
theta). Both maxima are found by L-BFGS from random phases, so the figures
returned are estimates from below of the true bounds. A design within the
fidelity goals need not have exactly the target's shape: a faint, nearly
uniform background in the dark orders counts as window power, which lets a
design pass the exact-shape bound by a few percent (docs/retrieve.md);
:func:`within_goals` bounds every design within the goals.
"""

import numpy as np
import scipy.fft

from doe import fraunhofer
from doe.goals import RMSE_GOAL, Goal, cap_penalty, goal_values
from doe.lbfgs import minimise


def best_flat_field(target, n_pixels, n_levels=None, rng=None, restarts=16, max_eval=200):
    """Return (bound, g) maximising the exact-shape efficiency bound over the lit orders' phases.

    Parameters
    ----------
    target : (K, K) array
        Target PSF, >= 0, sum 1.
    n_pixels : int
        Tile size N.
    n_levels : int or None
        L for the bound of an L-level plate; None for a continuous phase.
    rng : numpy Generator
        Draws the random starting phases (default seed 0).

    Returns
    -------
    bound : float
        The efficiency bound (mean |g| cos d)^2 at the best phases found.
    g : (N, N) complex128
        The band-limited field there; its argument is a flat-modulus start.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    k = target.shape[0]
    sel = np.ix_(*[fraunhofer.window_indices(n_pixels, k)] * 2)
    lit = target > 0
    amp = np.sqrt(target[lit])

    def field(theta):
        win = np.zeros((k, k), dtype=np.complex128)
        win[lit] = amp * np.exp(1j * theta)
        return _band_field(win, sel, n_pixels), win[lit]

    def objective(step):
        def fun(theta):
            # mean Re(g conj q) with q the unit-modulus plate that best matches g (arg g,
            # or its nearest level); d/dtheta_u = Re(i w_u conj(Q_u)), Q the window of q
            g, w = field(theta)
            q = _best_plate(g, step)
            matched = np.abs(g) if step is None else np.real(g * np.conj(q))
            h = scipy.fft.fft2(q)[sel][lit] / n_pixels**2
            return -float(np.mean(matched)), -np.real(1j * w * np.conj(h))

        return fun

    starts = [rng.uniform(-np.pi, np.pi, int(lit.sum())) for _ in range(restarts)]
    runs = [minimise(objective(None), x0, max_eval) for x0 in starts]
    theta, value = min(runs, key=lambda run: run[1])
    if n_levels is not None:
        # the levelled objective is piecewise smooth with many local maxima: start
        # from the continuous optimum under a sweep of global phases (over which its
        # mean keeps sinc(1 / L) of mean |g|) as well as from the random phases
        step = 2 * np.pi / n_levels
        starts += [theta + offset for offset in np.arange(8) * step / 8]
        runs = [minimise(objective(step), x0, max_eval) for x0 in starts]
        theta, value = min(runs, key=lambda run: run[1])
    return value**2, field(theta)[0]


def with_background(target, rmse):
    """Return the target with a uniform background in its dark orders that costs ``rmse``.

    The background is ``rmse * sqrt(K^2 / dark orders)`` of the peak, so the rmse
    of CONVENTIONS.md between the two (both normalised by their peaks) is ``rmse``;
    the result sums to 1.
    """
    dark = target == 0
    if not dark.any():
        return target / target.sum()
    level = rmse * np.sqrt(target.size / dark.sum()) * target.max()
    padded = target + level * dark
    return padded / padded.sum()


def efficiency_bound(target, n_pixels, n_levels=None, rng=None, restarts=16, max_eval=200):
    """Return the exact-shape efficiency bound of a continuous (None) or L-level tile.

    The best of ``restarts`` random starts: the maximum has many local peaks on
    flat-topped targets, where more starts find a higher one; on sparse dots a few
    starts already find it.
    """
    return best_flat_field(target, n_pixels, n_levels, rng, restarts, max_eval)[0]


def within_goals(target, n_pixels, n_levels=None, cap=1.0, max_eval=150, mus=(10, 100, 1e3, 1e4)):
    """Return (bound, window) maximising the efficiency bound over window patterns within the goals.

    A design need not form exactly the target: any window field w whose power
    P = |w|^2 / |w|^2.sum() meets the fidelity goals will do. The bound above,
    (mean_x Re(g conj q))^2 / |w|^2 with g the band-limited field of w and q its
    nearest unit-modulus (or L-level) value, is maximised here over every order's
    amplitude *and* phase, subject to each fidelity term of
    :func:`doe.goals.fidelity_parts` staying within ``cap`` (1 = the goals
    just met). Penalty method (the penalty of
    :func:`doe.refinement.constrained_objective`, weights ``mus``) with L-BFGS, started from the
    target plus the uniform background that spends the rmse of ``cap``
    (:func:`with_background`, a better start than random ones); the exact shape's
    own bound (:func:`best_flat_field`) is the floor. Only points whose exact
    figures (CONVENTIONS.md) are within ``cap`` count, so the result is an
    estimate from below of the true maximum, like the others.

    Returns
    -------
    bound : float
        The best efficiency bound found within the goals.
    window : (K, K) complex128
        Its window field, unit norm.
    """
    k = target.shape[0]
    sel = np.ix_(*[fraunhofer.window_indices(n_pixels, k)] * 2)
    goal = Goal.of(target)
    step = None if n_levels is None else 2 * np.pi / n_levels
    best = {"bound": 0.0, "w": None}

    def fun(x, mu):
        w = x[: k * k].reshape(k, k) + 1j * x[k * k :].reshape(k, k)
        g = _band_field(w, sel, n_pixels)
        q = _best_plate(g, step)
        big_q = scipy.fft.fft2(q)[sel] / n_pixels**2  # d mean Re(g conj q) / d w (re + i im)
        s = float((w.real**2 + w.imag**2).sum())
        m = float(np.real(np.vdot(big_q, w)))
        b = m / np.sqrt(s)
        power = (w.real**2 + w.imag**2) / s
        penalty, d_p = cap_penalty(power, goal, cap, mu)
        # chain rule through P = |w|^2 / s (complex gradient: d/d re + i d/d im)
        grad = 2.0 * w * (d_p - (d_p * power).sum()) / s
        grad -= 2.0 * b * (big_q / np.sqrt(s) - m * w / s**1.5)
        bound = b * b
        # only patterns whose exact figures (CONVENTIONS.md) are within the cap count
        if bound > best["bound"] and goal_values(power, goal, 0.0) <= cap:
            best["bound"], best["w"] = bound, w / np.sqrt(s)
        return -bound + penalty, np.concatenate([grad.real.ravel(), grad.imag.ravel()])

    def start(psf):
        w = scipy.fft.fft2(best_flat_field(psf, n_pixels, n_levels)[1])[sel] / n_pixels**2
        return np.concatenate([w.real.ravel(), w.imag.ravel()])

    fun(start(target), mus[0])  # the exact shape is within the goals: never report less
    x = start(with_background(target, RMSE_GOAL * np.sqrt(cap)))
    for mu in mus:
        x, _ = minimise(lambda v, mu=mu: fun(v, mu), x, max_eval)
    return best["bound"], best["w"]


def _band_field(window, sel, n_pixels):
    """Return the (N, N) field whose only orders are the K x K ``window`` (at ``sel``)."""
    spec = np.zeros((n_pixels, n_pixels), dtype=np.complex128)
    spec[sel] = window
    return scipy.fft.ifft2(spec) * n_pixels**2


def _best_plate(g, step):
    """Return the unit-modulus plate that best matches g: arg g, or its nearest level (``step``)."""
    if step is None:
        return g / np.maximum(np.abs(g), 1e-300)
    return np.exp(1j * step * np.round(np.angle(g) / step))
