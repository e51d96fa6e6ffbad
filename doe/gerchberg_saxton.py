"""Alternating projections between the tile and its orders: the retrieval's cheap starts.

Weighted Gerchberg-Saxton (:func:`gerchberg_saxton`, also quantised onto L
levels), mixed-region amplitude freedom (:func:`mixed_region`, MRAF) and the
flat-modulus start (:func:`flat_modulus_start`): the light that does not fit the
window leaves into the orders outside it, the light sink.
"""

import numpy as np
import scipy.fft

from doe import bounds, fraunhofer

MRAF_MIX = 0.6
"""Share of the window in the projection of :func:`mixed_region` (1 would be GS)."""


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
            step = fraunhofer.level_step(n_levels)
            phase = step * np.round(phase / step)
    return phase, gains


def flat_modulus_start(target, n_pixels, rng=None, restarts=3, max_eval=200):
    """Return a tile phase (rad, (N, N)) whose band-limited field is as flat in modulus as can be.

    The field g(x) of the target's window amplitudes with the lit orders' phases
    that maximise mean |g| (:func:`doe.bounds.best_flat_field`: Wyrowski's bound
    on the efficiency of a plate forming exactly the target's shape) has the
    flattest modulus, so arg g is a start that is already both efficient and
    close to the target shape (on hard flat tops it starts more efficient than random
    phases; like theirs, its result varies with the seed).
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
