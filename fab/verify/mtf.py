"""Slanted-edge MTF (ISO 12233 style) of a camera or lens.

Steps: find the edge in each row (centroid of the row's derivative, Hamming
windowed about a first line fit), fit a straight line, project every pixel's
distance from the line onto the edge normal and bin it ``oversample`` times
finer than a pixel, each bin read at its samples' mean distance and resampled
onto the even grid (the edge spread function), differentiate (central
difference, whose own response sin(2 pi f d) / (2 pi f d) is divided out),
Hamming-window the line spread function about its centre (over at most twice the
reach the edge needs), Fourier transform and normalise at zero frequency.
Frequencies are in cycles per pixel along the edge normal.
"""

import numpy as np

from fab.verify.conditioning import robust_sigma

# Rows whose derivative carries less than this fraction of the typical (75th
# percentile) edge step are left out of the line fit (e.g. where the edge leaves the frame).
MIN_ROW_CONTRAST = 0.2
# The edge's step must exceed this many times the pixel noise on its two sides; a
# noise image otherwise passes for an edge anywhere.
MIN_EDGE_SNR = 5.0


# The region must reach this many 10-90 % rise widths either side of the edge: a
# Gaussian edge cut at 12 sigma (4.7 rises) reads MTF50 about 2 % high, at 7.5
# sigma 7 %, at 4 sigma 27 % (the window narrows the truncated line spread).
REACH_PER_RISE = 4.7


# This share of a float image at its extreme value, held by more pixels than any value
# between the extremes, marks a clipped side (noise spreads an unclipped side over many
# values).
PLATEAU_SHARE = 0.01


def clipped_pixels(data, full_scale=None):
    """Return (dark, bright): how many pixels of an edge image sit at a clipping level.

    Clipping flattens a side of the edge spread and overstates the MTF (an edge of
    1 px blur clipped on either side reads MTF50 tens of per cent high). Integer files
    clip at code 0 and at ``full_scale``; float files (``full_scale`` None) where their
    minimum or maximum is held by ``PLATEAU_SHARE`` of them and by more than any value
    between the two (each side on its own: one clipped on both loses neither).
    """
    data = np.asarray(data)
    lo, hi = data.min(), data.max()
    dark, bright = np.count_nonzero(data == lo), np.count_nonzero(data == hi)
    if full_scale is not None:
        return int(dark if lo <= 0 else 0), int(bright if hi >= full_scale else 0)
    values, counts = np.unique(data, return_counts=True)
    between = counts[(values > lo) & (values < hi)]
    common = max(between.max(initial=0), PLATEAU_SHARE * data.size)
    return int(dark if dark >= common else 0), int(bright if bright >= common else 0)


class EdgeNotFound(ValueError):
    """The image holds no usable straight edge."""


def slanted_edge_mtf(image, oversample=4):
    """Measure the MTF across a straight, slightly slanted edge.

    Parameters
    ----------
    image : (H, W) array
        A dark/bright edge, near vertical or near horizontal, a few degrees off
        the pixel axes.
    oversample : int
        Bins per pixel of the edge spread function.

    Returns
    -------
    dict
        "frequencies_cycles_per_pixel", "mtf" (lists, MTF 1 at 0), "mtf50_cycles_per_pixel"
        (None when the MTF stays above 0.5 over the measured frequencies),
        "edge_angle_deg" (from the pixel column axis, or the row axis for a
        horizontal edge), "edge_orientation" ("vertical"/"horizontal"), "oversample".

    Raises
    ------
    EdgeNotFound
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2 or min(img.shape) < 8:
        raise EdgeNotFound(f"need a 2-D image of at least 8x8 pixels, got shape {img.shape}")
    vertical = np.abs(np.diff(img, axis=1)).mean() >= np.abs(np.diff(img, axis=0)).mean()
    if not vertical:
        img = img.T
    slope, offset, use, polarity = _fit_edge(img)
    dist, half, keep = _edge_region(img, slope, offset, use)
    esf = _edge_spread(img, dist, keep, slope, oversample)
    rise = _rise_px(esf * polarity, oversample)
    freq, mtf = _mtf_of_edge_spread(esf, polarity, rise, oversample)
    return {
        "frequencies_cycles_per_pixel": freq.tolist(),
        "mtf": mtf.tolist(),
        "mtf50_cycles_per_pixel": _crossing(freq, mtf, 0.5),
        "edge_angle_deg": float(np.degrees(np.arctan(slope))),
        "edge_orientation": "vertical" if vertical else "horizontal",
        "oversample": int(oversample),
        "rows_used": int(use.sum()),
        "edge_rise_px": rise,
        "edge_reach_px": half,
        # A profile cut within ~12 blur widths (sigmas) of the edge reads high; see
        # REACH_PER_RISE.
        "region_too_small": bool(half < REACH_PER_RISE * rise),
    }


def _fit_edge(img):
    """Return the edge line col = offset + slope * row of a near-vertical edge, the rows
    that show it and the edge's polarity (+1 dark to bright left to right, -1 back)."""
    h, w = img.shape
    deriv = np.diff(img, axis=1)
    _check_single_edge(deriv)
    polarity = np.sign(deriv.sum())
    if polarity == 0:
        raise EdgeNotFound("the image is flat: no edge")
    deriv *= polarity
    x_mid = np.arange(w - 1) + 0.5
    rows = np.arange(h, dtype=float)
    slope, offset, use = _fit_line(rows, *_centroids(deriv, x_mid, None))
    for _ in range(3):  # window each row's derivative about the fitted edge, refit
        guess = offset + slope * rows
        slope, offset, use = _fit_line(rows, *_centroids(deriv, x_mid, guess, max(8.0, w / 4)))
    return slope, offset, use, polarity


def _edge_region(img, slope, offset, use):
    """Return every pixel's distance from the edge along its normal, the reach of the
    region either side of it (px) and the pixels within that reach on the rows used.

    Raises EdgeNotFound when the edge runs within 4 px of the border or its step does
    not stand ``MIN_EDGE_SNR`` times out of the noise.
    """
    h, w = img.shape
    rows = np.arange(h, dtype=float)
    cos = 1 / np.hypot(1, slope)
    dist = (np.arange(w)[None, :] - (offset + slope * rows)[:, None]) * cos
    half = float(np.min(np.abs(dist[use][:, [0, -1]])))
    if half < 4:
        raise EdgeNotFound("the edge runs too close to the image border")
    keep = (np.abs(dist) < half) & use[:, None]
    dark, bright = img[keep & (dist < -half / 2)], img[keep & (dist > half / 2)]
    step = abs(float(bright.mean() - dark.mean()))
    noise = 0.5 * (robust_sigma(dark) + robust_sigma(bright))
    if not step > MIN_EDGE_SNR * noise:
        raise EdgeNotFound(
            f"no edge stands out of the noise: step {step:.3g} against a pixel noise "
            f"of {noise:.3g} (at least {MIN_EDGE_SNR:g} times needed)"
        )
    return dist, half, keep


def _edge_spread(img, dist, keep, slope, oversample):
    """Return the edge spread function: the ``keep`` pixels binned by their distance from
    the edge, ``oversample`` bins a pixel, resampled onto the even grid."""
    bins = np.floor(dist[keep] * oversample).astype(np.int64)
    lo = bins.min()
    n_bins = bins.max() - lo + 1
    counts = np.bincount(bins - lo, minlength=n_bins)
    sums = np.bincount(bins - lo, weights=img[keep], minlength=n_bins)
    filled = counts > 0
    if filled.sum() < 0.8 * n_bins:
        raise EdgeNotFound(
            f"the edge, {np.degrees(np.arctan(abs(slope))):.1f} deg off the pixel axis, fills "
            f"{filled.mean():.0%} of the {oversample}x oversampled bins; tilt it 2-10 deg off "
            "the pixel axis (not near 45 deg) and include more rows"
        )
    x = np.arange(n_bins)
    # Each bin's value is placed at its samples' mean position: an edge whose slope is
    # a simple fraction (1/10, 1/4) puts its samples at a few fixed places in each bin,
    # which read at the bins' centres would jitter the profile.
    where = np.bincount(bins - lo, weights=dist[keep] * oversample - lo - 0.5, minlength=n_bins)
    return np.interp(x, where[filled] / counts[filled], sums[filled] / counts[filled])


def _mtf_of_edge_spread(esf, polarity, rise, oversample):
    """Return (frequencies in cycles per pixel, MTF) of an edge spread function whose
    10-90 % rise is ``rise`` px: its derivative, windowed, Fourier transformed."""
    n_bins = esf.size
    x = np.arange(n_bins)
    lsf = np.zeros(n_bins)
    lsf[1:-1] = 0.5 * (esf[2:] - esf[:-2]) * polarity
    peak = int(
        np.round(np.sum(x * np.clip(lsf, 0, None)) / max(np.clip(lsf, 0, None).sum(), 1e-30))
    )
    # The window spans the whole region up to twice the reach it needs: beyond that the
    # line spread holds only noise, which would roughen the MTF of a wide region.
    span = min(n_bins, 2 * int(np.ceil(oversample * max(8.0, 2 * REACH_PER_RISE * rise))) + 1)
    window = np.zeros(n_bins)
    start = n_bins // 2 - span // 2
    window[start : start + span] = np.hamming(span)
    lsf = np.roll(lsf, n_bins // 2 - peak) * window
    spectrum = np.abs(np.fft.rfft(lsf))
    if spectrum[0] <= 0:
        raise EdgeNotFound("the edge has no contrast")
    freq = np.fft.rfftfreq(n_bins, d=1.0 / oversample)
    arg = 2 * np.pi * freq / oversample
    correction = np.ones_like(freq)
    ok = arg < np.pi / 2
    correction[ok] = np.sinc(arg[ok] / np.pi)  # sin(arg) / arg
    mtf = spectrum / spectrum[0]
    mtf[ok] /= correction[ok]
    mtf[~ok] = np.nan
    keep_f = freq <= min(oversample / 4, 2.0)
    return freq[keep_f], mtf[keep_f]


def _check_single_edge(deriv):
    """Refuse a region with two opposite edges (a bar, or a chart's whole square).

    Averaged over the rows, noise leaves the derivative; two edges leave a lobe of
    each sign, and a fit to both measures neither. A lobe counts when it stands
    ``MIN_EDGE_SNR`` times out of the noise of a mean over the rows.
    """
    profile = deriv.mean(axis=0)
    noise = robust_sigma(deriv) / np.sqrt(deriv.shape[0])
    weaker = min(profile.max(), -profile.min())
    if weaker > 0.3 * np.abs(profile).max() and weaker > MIN_EDGE_SNR * noise:
        raise EdgeNotFound(
            "the region holds edges of both signs (both sides of a bar or square): "
            "crop it to one edge"
        )


def _centroids(deriv, x_mid, guess, width=None):
    """Return each row's derivative centroid and sum (Hamming-windowed about ``guess``).

    The derivative keeps its sign, as ISO 12233 has it: clipped at zero, the noise
    would become weight everywhere in the window, pulling every centroid to the
    window's centre and the fitted edge towards the pixel axis.
    """
    d = deriv
    if guess is not None:
        t = (x_mid[None, :] - guess[:, None]) / width
        d = d * np.where(np.abs(t) <= 0.5, 0.54 + 0.46 * np.cos(2 * np.pi * t), 0.0)
    total = d.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (d @ x_mid) / total, total


def _fit_line(rows, centres, contrast):
    """Fit the edge line through the rows that show it (their step is the contrast)."""
    typical = np.percentile(contrast, 75)
    use = np.isfinite(centres) & (contrast > MIN_ROW_CONTRAST * typical)
    if use.sum() < 4:
        raise EdgeNotFound("fewer than 4 rows show the edge")
    slope, offset = np.polyfit(rows[use], centres[use], 1)
    return float(slope), float(offset), use


def _rise_px(esf, oversample):
    """Return the 10-90 % rise of a rising edge spread function, in pixels.

    Counted as the bins between 10 and 90 % of the step between its outer tenths,
    which noise in single bins barely moves.
    """
    tenth = max(1, len(esf) // 10)
    low, high = np.median(esf[:tenth]), np.median(esf[-tenth:])
    level = (esf - low) / (high - low)
    return float(np.count_nonzero((level > 0.1) & (level < 0.9)) / oversample)


def _crossing(freq, mtf, level):
    """Return the first frequency where the MTF falls to ``level`` (linear interpolation).

    None when the MTF stays above ``level`` wherever it is measured (finite), as it
    does for an edge sharper than the pixel grid resolves.
    """
    finite = np.isfinite(mtf)
    freq, mtf = freq[finite], mtf[finite]
    below = np.nonzero(mtf < level)[0]
    if below.size == 0:
        return None
    i = int(below[0])
    if i == 0:
        return 0.0
    f0, f1, m0, m1 = freq[i - 1], freq[i], mtf[i - 1], mtf[i]
    return float(f0 + (m0 - level) * (f1 - f0) / (m0 - m1))
