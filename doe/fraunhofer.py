"""Fraunhofer model of a periodic phase tile: the one forward model of CONVENTIONS.md.

A tile of N x N pixels repeated across the aperture puts light only into the
diffraction orders of its period; order (m, n) carries |FFT(tile)|^2 / N^4 of the
power. The K x K window of orders around the zero order is the PSF on the
sensor's sub-pixel grid.
"""

import numpy as np


def level_phase(levels, n_levels):
    """Return the phase (rad) of a level map: level l delays 2 pi l / L."""
    return 2 * np.pi * np.asarray(levels, dtype=np.float64) / n_levels


def level_step(n_levels):
    """Return the phase step between two levels, 2 pi / L (rad)."""
    return 2 * np.pi / n_levels


def round_levels(phase, n_levels):
    """Return the nearest level (uint8 (N, N)) to each phase (rad), modulo 2 pi.

    The inverse of :func:`level_phase` on the levels themselves.
    """
    q = np.round(np.asarray(phase) * n_levels / (2 * np.pi)).astype(np.int64) % n_levels
    return q.astype(np.uint8)


def order_amplitudes(phase):
    """Return the complex amplitudes of all N x N orders of a tile, total power 1.

    Parameters
    ----------
    phase : (N, N) array
        Phase of each mask pixel in radians.
    """
    phase = np.asarray(phase, dtype=np.float64)
    return np.fft.fft2(np.exp(1j * phase)) / phase.size


def window_indices(n, k):
    """Return the FFT indices of the K window orders (window index i holds order i - K//2)."""
    return (np.arange(k) - k // 2) % n


def window_power(phase, k):
    """Return the power (fraction of the incident light) in each order of the K x K window.

    Element [K//2, K//2] is the zero order; rows grow downwards (-y), columns to +x.
    """
    amp = order_amplitudes(phase)
    idx = window_indices(phase.shape[0], k)
    return np.abs(amp[np.ix_(idx, idx)]) ** 2


def simulate_psf(phase, k):
    """Return (psf, efficiency): the normalised K x K PSF and the power in the window."""
    window = window_power(phase, k)
    efficiency = float(window.sum())
    return window / efficiency, efficiency


def simulate_levels(levels, n_levels, k):
    """Return (psf, efficiency) of a quantised level map (the contract's definition)."""
    return simulate_psf(level_phase(levels, n_levels), k)


def correlation(psf, target):
    """Return the Pearson correlation of two PSFs, flattened.

    NaN where either is uniform (a flat top filling the window): Pearson's
    correlation is then undefined, and the rmse alone measures the fit.
    """
    a, b = np.ravel(psf).astype(float), np.ravel(target).astype(float)
    a, b = a - a.mean(), b - b.mean()
    norm_a, norm_b = np.sqrt(np.dot(a, a)), np.sqrt(np.dot(b, b))
    # a spread of rounding errors is no variation
    if norm_a <= 1e-12 * np.abs(psf).max() or norm_b <= 1e-12 * np.abs(target).max():
        return float("nan")
    return float(np.dot(a, b) / (norm_a * norm_b))


def rmse(psf, target):
    """Return the RMS difference of the two PSFs, each normalised to its peak."""
    psf, target = np.asarray(psf, float), np.asarray(target, float)
    return float(np.sqrt(np.mean((psf / psf.max() - target / target.max()) ** 2)))


def quality(phase, target):
    """Return a dict of correlation, rmse and efficiency of ``phase`` against ``target``."""
    psf, eff = simulate_psf(phase, target.shape[0])
    return {"correlation": correlation(psf, target), "rmse": rmse(psf, target), "efficiency": eff}


def pixel_envelope(orders, n):
    """Return sinc^2(m / N): the power envelope of square mask pixels at order m."""
    return np.sinc(np.asarray(orders) / n) ** 2


def plate_quality(phase, target):
    """Return :func:`quality` as a plate of square pixels gives it.

    The contract's window powers are those of point-like pixels; square ones
    dim order (m, n) by sinc^2(m/N) sinc^2(n/N), under 0.6 % in an 11-order
    window at N = 175, which a flat top filling the window still feels in its rmse.
    """
    k = target.shape[0]
    env = pixel_envelope(np.arange(k) - k // 2, phase.shape[0])
    window = window_power(phase, k) * np.outer(env, env)
    psf = window / window.sum()
    return {
        "correlation": correlation(psf, target),
        "rmse": rmse(psf, target),
        "efficiency": float(window.sum()),
    }


def dot_lattice_image(phase, shape, order_pitch_px, centre=None, spot_sigma_px=0.8):
    """Render the dot lattice that the tiled plate forms on a detector.

    Every diffraction order (m, n) that lands on the detector becomes a Gaussian
    spot at ``centre + (n, m) * order_pitch_px`` (x right, y down), weighted by its
    power: the tile's periodic DFT power times the envelope of its square pixels,
    sinc^2(m / N) sinc^2(n / N) (all orders together carry the whole beam). This
    is the picture a camera or the SPAD sees before sampling; the spot width
    stands in for the aperture's diffraction-limited spot.

    Parameters
    ----------
    phase : (N, N) array
        Tile phase (rad).
    shape : (H, W)
        Image size in detector pixels.
    order_pitch_px : float
        Spacing of the orders in detector pixels (lambda f / tile size / pixel pitch).
    centre : (row, col) or None
        Detector position of the zero order; default the image centre.
    spot_sigma_px : float
        Standard deviation of each spot, in detector pixels.
    """
    h, w = shape
    n = phase.shape[0]
    power = np.abs(order_amplitudes(phase)) ** 2
    cy, cx = centre if centre is not None else ((h - 1) / 2, (w - 1) / 2)
    reach = 4 * spot_sigma_px

    def orders_on(length, c):  # the orders whose spots reach [0, length)
        lo = np.ceil((-reach - c) / order_pitch_px)
        hi = np.floor((length + reach - c) / order_pitch_px)
        return np.arange(lo, hi + 1).astype(int)

    m, k = orders_on(h, cy), orders_on(w, cx)
    y = np.arange(h)[:, None]
    x = np.arange(w)[:, None]
    # Separable: image = sum_mk P[m, k] gy_m(y) gx_k(x) = Gy P Gx^T
    gy = np.exp(-0.5 * ((y - (cy + m * order_pitch_px)[None, :]) / spot_sigma_px) ** 2)
    gx = np.exp(-0.5 * ((x - (cx + k * order_pitch_px)[None, :]) / spot_sigma_px) ** 2)
    envelope = np.outer(pixel_envelope(m, n), pixel_envelope(k, n))
    sub = power[np.ix_(m % n, k % n)] * envelope
    return gy @ sub @ gx.T / (2 * np.pi * spot_sigma_px**2)
