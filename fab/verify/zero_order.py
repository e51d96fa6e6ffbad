"""Where the zero order sits in a measured order grid, and the whole beam's power.

The design's far field is matched to the measured order powers at every integer
offset (``offset_chi2``, three FFT cross-correlations): the zero order is often not
the brightest dot. The orders that carry signal then give the beam's power
(``beam_power``) and how well the measured and model powers correlate
(``frame_score``).
"""

import numpy as np

from doe.fraunhofer import correlation, pixel_envelope, window_indices

# An order carries signal when measured this many sigma above the noise (one false
# detection in ~3 million orders), or predicted by the design above PREDICTED_SIGMAS.
SIGNAL_SIGMAS = 5.0
PREDICTED_SIGMAS = 3.0


def model_powers(period_power, m0, n0, shape):
    """Return the model's order powers on a grid whose element [m0, n0] is the zero order."""
    n = period_power.shape[0]
    m = np.arange(shape[0]) - m0
    k = np.arange(shape[1]) - n0
    env = pixel_envelope(m, n)[:, None] * pixel_envelope(k, n)[None, :]
    return period_power[np.ix_(m % n, k % n)] * env


def _scale(meas, model, detected, valid):
    """Return DN per unit beam power: least squares of the model on the detected orders.

    (The sum over every order in the frame would carry the noise of thousands of
    empty apertures.)
    """
    if detected.any():
        den = float((model[detected] ** 2).sum())
        if den > 0:
            return max(float((model[detected] * meas[detected]).sum()) / den, 0.0)
    return max(float(meas[valid].sum()), 0.0) / max(float(model[valid].sum()), 1e-30)


def _pearson(a, b):
    a, b = a - a.mean(), b - b.mean()
    den = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / den) if den > 0 else 0.0


def _model_table(period_power, shape):
    """Return the model's order powers for order offsets -(nu-1)..nu-1 by -(nv-1)..nv-1.

    Element [i, j] is order (i - nu + 1, j - nv + 1), pixel envelope included.
    """
    n = period_power.shape[0]
    m = np.arange(-(shape[0] - 1), shape[0])
    k = np.arange(-(shape[1] - 1), shape[1])
    env = pixel_envelope(m, n)[:, None] * pixel_envelope(k, n)[None, :]
    return period_power[np.ix_(m % n, k % n)] * env


def _correlate(table, grid):
    """Return C[m0, n0] = sum_uv grid[u, v] table[u - m0 + nu - 1, v - n0 + nv - 1] (FFT)."""
    from scipy.signal import fftconvolve

    return fftconvolve(table, grid[::-1, ::-1], mode="valid")[::-1, ::-1]


def offset_chi2(measured, valid, sigma, period_power):
    """Return the chi-square of the far-field model with its zero order at every grid element.

    For a zero order at [m0, n0] the model of order [u, v] is the tile's far
    field at (u - m0, v - n0) with the pixel envelope, times a free scale
    (weighted least squares, >= 0); the chi-square sums over EVERY valid order
    in the frame, each weighted by its noise, so that the weak orders outside
    the K x K window count as much as their signal warrants: they tell a
    design from its point reflection when the window alone cannot (a PSF
    nearly symmetric about a point half an order off the axis). The candidate
    zero order itself is left out (a deep-etch depth error changes it most).
    Orders with no light add the same (their noise) to every candidate.
    Three FFT cross-correlations give all offsets at once.

    Parameters
    ----------
    measured, valid, sigma : (nu, nv) arrays
        Dot powers in the design frame, which are measured, their 1-sigma noise.
    period_power : (N, N) float array
        Order powers of the tile, FFT index order.

    Returns
    -------
    (nu, nv) float array
        Chi-square per candidate zero order (inf where the candidate is not valid).
    """
    wts = np.where(valid, 1.0 / np.where(valid, sigma, 1.0) ** 2, 0.0)
    meas = np.where(valid, measured, 0.0)
    table = _model_table(period_power, measured.shape)
    zero = float(period_power[0, 0])
    a = float((wts * meas**2).sum()) - wts * meas**2
    b = _correlate(table, wts * meas) - wts * meas * zero
    d = _correlate(table**2, wts) - wts * zero**2
    with np.errstate(divide="ignore", invalid="ignore"):
        chi2 = a - np.where((b > 0) & (d > 0), b**2 / d, 0.0)
    return np.where(valid, chi2, np.inf)


def frame_score(meas, valid, sigma, period_power, m0, n0, half):
    """Pearson correlation of measured and model powers over the orders with signal.

    The orders of the (2 half + 1)^2 window and those that carry signal
    (measured above ``SIGNAL_SIGMAS`` sigma, or predicted so by the design)
    count, the candidate zero order does not; the pixel envelope is divided
    out, so that two unrelated plates do not correlate through it.

    Returns
    -------
    (score, outside_score, outside_orders)
        The correlation (NaN when the design predicts no order but the zero
        order above the noise: nothing to correlate, a flat plate); that over
        the orders with signal outside the window alone (NaN when fewer than
        3) and their count.
    """
    shape = meas.shape
    sig = np.where(valid, sigma, np.inf)
    detected = valid & (meas > SIGNAL_SIGMAS * sig)
    model = model_powers(period_power, m0, n0, shape)
    scale = _scale(meas, model, detected, valid)
    predicted = valid & (model * scale > PREDICTED_SIGMAS * sig)
    predicted[m0, n0] = False
    use = detected | predicted
    # The window always counts: its dark orders are as telling as its bright ones.
    win = (slice(max(m0 - half, 0), m0 + half + 1), slice(max(n0 - half, 0), n0 + half + 1))
    use[win] |= valid[win]
    use[m0, n0] = False
    if use.sum() < 3:
        return 0.0, float("nan"), 0
    if not predicted.any():
        return float("nan"), float("nan"), 0
    env = np.maximum(model_powers(np.ones_like(period_power), m0, n0, shape)[use], 0.0025)
    r = _pearson(meas[use] / env, model[use] / env)
    out = use.copy()
    out[win] = False
    r_out = _pearson(meas[out], model[out]) if out.sum() >= 3 else float("nan")
    return r, r_out, int(out.sum())


def locate_zero_order(measured, valid, sigma, period_power, half=5):
    """Find where the zero order sits in a measured grid by matching the design's far field.

    The zero order is the candidate with the least chi-square over all the
    visible orders (``offset_chi2``); the runner-up offset is returned too, so
    that an ambiguous match can be reported rather than passed.

    Parameters
    ----------
    measured : (nu, nv) float array
        Dot powers in the design frame (anything where not ``valid``).
    valid : (nu, nv) bool array
    sigma : (nu, nv) float array
        1-sigma noise of ``measured``.
    period_power : (N, N) float array
        Order powers of the tile, FFT index order.
    half : int
        K // 2.

    Returns
    -------
    dict
        "m0", "n0" (grid indices of the zero order), "chi2" there, "runner_up"
        ((m, n) of the next best offset), "runner_up_chi2", "score" (Pearson
        correlation there, see ``frame_score``), "outside_score",
        "outside_orders".
    """
    if not valid.any():
        raise ValueError("no valid dot where the zero order could sit")
    chi2 = offset_chi2(measured, valid, sigma, period_power)
    order = np.argsort(chi2, axis=None)
    m0, n0 = (int(i) for i in np.unravel_index(order[0], chi2.shape))
    second = np.unravel_index(order[1], chi2.shape) if order.size > 1 else (m0, n0)
    meas = np.where(valid, measured, 0.0)
    score, out_score, out_orders = frame_score(meas, valid, sigma, period_power, m0, n0, half)
    return {
        "m0": m0,
        "n0": n0,
        "chi2": float(chi2[m0, n0]),
        "runner_up": (int(second[0]), int(second[1])),
        "runner_up_chi2": float(chi2[second]),
        "score": score,
        "outside_score": out_score,
        "outside_orders": out_orders,
    }


def beam_power(meas, sigma, valid, model, window):
    """Estimate the whole beam's power (DN) from the orders that carry signal.

    Summing every order in the frame adds the noise of thousands of empty
    apertures; instead the orders of the window, those measured above
    ``SIGNAL_SIGMAS`` sigma and those the design puts above it are summed, and
    divided by the design's share of the beam in those orders (the design's
    far field sums to 1 over all orders).

    The same orders give the on-camera power outside the window: the share of
    their light outside it (the empty apertures would add only noise).

    Returns
    -------
    dict
        "power" (DN), "signal" (DN in the orders used), "signal_var", "model_share",
        "orders" (count).
    """
    detected = valid & (meas > SIGNAL_SIGMAS * sigma)
    scale = _scale(meas, model, detected, valid)
    use = detected | (valid & (model * scale > PREDICTED_SIGMAS * sigma))
    use[window] = True
    signal = float(meas[use].sum())
    share = float(model[use].sum())
    return {
        "power": signal / share,
        "signal": signal,
        "signal_var": float((sigma[use] ** 2).sum()),
        "model_share": share,
        "orders": int(use.sum()),
    }


def search_summary(searches, valid, rows, cols, period, design_psf, transforms):
    """Return the JSON-ready evidence of the zero-order search.

    The chi-squares are compared after dividing by the reduced chi-square of
    the best hypothesis when it exceeds 1 (a plate with fabrication errors
    fits no model to the noise; its misfit must not pass for evidence).
    "delta_chi2" > 0 means the transform explains the capture better than
    the design; "runner_up_margin" is how much worse the design fits with its
    zero order at the next best place. "transform_psf_correlation" is how
    well each transform of the design's PSF matches the design's PSF: near 1
    when telling them apart does not matter. ``transforms`` maps each
    hypothesis's name to the function that transforms the design's order powers so.
    """
    dof = max(int(valid.sum()) - 2, 1)
    best = min(s["chi2"] for s in searches.values())
    inflation = max(1.0, best / dof)
    d = searches["design"]
    k = design_psf.shape[0]
    idx = window_indices(period.shape[0], k)
    psf_corr = {}
    for name, transform in transforms.items():
        window = transform(period)[np.ix_(idx, idx)]
        psf_corr[name] = correlation(window / window.sum(), design_psf)
    r, c = d["runner_up"]
    return {
        "chi2": {name: s["chi2"] for name, s in searches.items()},
        "dof": dof,
        "inflation": inflation,
        "delta_chi2": {
            name: (d["chi2"] - s["chi2"]) / inflation
            for name, s in searches.items()
            if name != "design"
        },
        "runner_up_margin": (d["runner_up_chi2"] - d["chi2"]) / inflation,
        "runner_up_px": [float(rows[r, c]), float(cols[r, c])],
        "transform_psf_correlation": psf_corr,
    }
