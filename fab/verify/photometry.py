"""Aperture photometry of every order of a registered dot lattice.

Each lattice point in the frame gets a disc aperture about its fitted position and a
background from an annulus around it (``measure_orders``); single-pixel spikes (hot
pixels, cosmic rays) are taken out of the apertures' sums.
"""

from dataclasses import dataclass

import numpy as np

from fab.verify.lattice import (
    DETECT_SIGMAS,
    SPIKE_FRACTION,
    lattice_points,
    pixel_noise,
    pixel_patches,
)

# Aperture photometry radii as fractions of the pitch: dot aperture, background annulus.
APERTURE_RADIUS = 0.30
ANNULUS = (0.38, 0.50)
# The most of its light a focused dot puts in one pixel (0.3 px sigma, centred), and how
# many sigmas of the aperture's noise the rest of a hot pixel's aperture must lie below
# what such a dot leaves around its peak.
DOT_PEAK_FRACTION = 0.82
SPIKE_SIGMAS = 4.0
# Below this pitch (px) the dot aperture (>= 1.5 px) overlaps its background annulus:
# such lattices are measured cell by cell (``fab.verify.cell_photometry``).
ANNULUS_MIN_PITCH_PX = 4.5


@dataclass(frozen=True)
class OrderGrid:
    """Aperture photometry of every lattice point in the frame.

    Attributes
    ----------
    u, v : (nu,) and (nv,) int arrays
        Lattice coordinates of the grid's rows and columns.
    power : (nu, nv) float array
        Background-subtracted dot signal in DN (NaN where not measured).
    valid : (nu, nv) bool array
        The dot's aperture and background annulus lie inside the frame.
    rows, cols : (nu, nv) float arrays
        Dot positions in pixels.
    saturated : (nu, nv) bool array
        The aperture holds a saturated pixel.
    noise_px : float
        Robust per-pixel noise (DN) of the background annuli.
    aperture_pixels : int
        Pixels in one aperture (median).
    sigma : (nu, nv) float array
        1-sigma uncertainty of ``power`` from the background noise (DN).
    aperture_radius_px : float
        Radius of the photometry apertures.
    spike_orders : int
        Apertures whose light was a single hot pixel (removed from their power).
    spot_sigma_px : float or None
        RMS radius per axis of the bright dots' light within the background
        annulus (pixels; None without bright dots); it saturates near 1.7 px
        for blurred dots, which then spill into their neighbours' apertures.
    pitch_px : float
        The lattice pitch the grid was measured on.
    """

    u: np.ndarray
    v: np.ndarray
    power: np.ndarray
    valid: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    saturated: np.ndarray
    noise_px: float
    aperture_pixels: int
    sigma: np.ndarray
    aperture_radius_px: float
    spike_orders: int = 0
    spot_sigma_px: float | None = None
    pitch_px: float = 0.0


def measure_orders(image, lattice, saturated=None, quantum=0.0):
    """Measure every dot's power by aperture photometry with a local background.

    Each dot's aperture is a disc about its fitted position, just wide enough to
    hold 99 % of the light of the bright dots (plus a pixel for other sub-pixel
    phases; at least 2 px, at most ``APERTURE_RADIUS`` pitches), since a wider one only adds
    noise to the thousands of faint orders. Its background is a sigma-clipped
    mean over an annulus (``ANNULUS`` pitches) around it, which shrugs off stray
    hot pixels; the clipped mean rather than the median because the median of
    integer data is biased by up to half a DN, which summed over thousands of
    faint orders would bias the total power.

    Parameters
    ----------
    image : (H, W) float array
        Capture in DN.
    lattice : Lattice
    saturated : (H, W) bool array or None
        Saturated pixels of the raw capture.
    quantum : float
        Step between the capture's codes in DN; 0 for float data.

    Returns
    -------
    OrderGrid
    """
    x = np.asarray(image, dtype=np.float32)
    pitch = lattice.pitch_px
    outer = int(np.ceil(ANNULUS[1] * pitch))
    u, v, rows, cols, valid = lattice_points(lattice, x.shape, outer)
    off = np.arange(-outer, outer + 1)
    dist0 = np.hypot(off[:, None], off[None, :])
    annulus = (dist0 >= ANNULUS[0] * pitch) & (dist0 <= ANNULUS[1] * pitch)
    pr, pc = rows[valid], cols[valid]
    patch = pixel_patches(x, pr, pc, outer)
    ring = patch[:, annulus].astype(np.float64)
    median = np.median(ring, axis=1)
    noise = pixel_noise((ring - median[:, None])[:: max(1, ring.shape[0] // 2000)], quantum)
    near = np.abs(ring - median[:, None]) <= max(4 * noise, 1.0)
    n_ring = np.maximum(near.sum(axis=1), 1)
    background = (ring * near).sum(axis=1) / n_ring
    fr = (pr - np.rint(pr)).astype(np.float32)[:, None, None]
    fc = (pc - np.rint(pc)).astype(np.float32)[:, None, None]
    offf = off.astype(np.float32)
    dist = np.sqrt((offf[None, :, None] - fr) ** 2 + (offf[None, None, :] - fc) ** 2)
    net = patch - background[:, None, None].astype(np.float32)
    radius = _aperture_radius(net, dist, noise, max(APERTURE_RADIUS * pitch, 1.5))
    spot = _spot_sigma(net, dist, noise, ANNULUS[0] * pitch)
    aperture = dist <= radius
    n_ap = aperture.sum(axis=(1, 2))
    inap = np.where(aperture, net, 0).astype(np.float64)
    signal = inap.sum(axis=(1, 2))
    sigma_k = noise * np.sqrt(n_ap * (1 + n_ap / n_ring))
    signal, spikes = _remove_spikes(inap, signal, sigma_k)
    power = np.full(valid.shape, np.nan)
    power[valid] = signal
    sigma = np.full(valid.shape, np.nan)
    sigma[valid] = sigma_k
    sat = np.zeros(valid.shape, bool)
    if saturated is not None and np.any(saturated):
        sat_patch = pixel_patches(saturated, pr, pc, outer)
        sat[valid] = (sat_patch & aperture).any(axis=(1, 2))
    return OrderGrid(
        u,
        v,
        power,
        valid,
        rows,
        cols,
        sat,
        noise,
        int(np.median(n_ap)),
        sigma,
        float(radius),
        spikes,
        spot,
        pitch,
    )


def _remove_spikes(inap, signal, sigma):
    """Take single-pixel spikes (hot pixels) out of the aperture sums.

    A focused dot puts at most ~82 % of its light into one pixel (a spot of
    0.3 px sigma centred on it); an aperture with more than ``SPIKE_FRACTION``
    of a significant signal in one pixel holds a hot pixel (or a cosmic ray),
    whose excess over the median of its 8 neighbours is removed, where the rest
    of the aperture is also ``SPIKE_SIGMAS`` of its noise below the least a dot of
    that peak leaves around it: a faint dot centred on a pixel, the share of its
    neighbours hidden in the noise, keeps its light.

    Returns
    -------
    (signal, count)
    """
    p = inap.shape[0]
    flat = inap.reshape(p, -1)
    peak_idx = np.argmax(flat, axis=1)
    peak = flat[np.arange(p), peak_idx]
    rest = signal - peak
    below_a_dot = rest < peak * (1 - DOT_PEAK_FRACTION) / DOT_PEAK_FRACTION - SPIKE_SIGMAS * sigma
    spike = (signal > DETECT_SIGMAS * sigma) & (peak > SPIKE_FRACTION * signal) & below_a_dot
    if not spike.any():
        return signal, 0
    side = inap.shape[1]
    r, c = np.divmod(peak_idx[spike], side)
    padded = np.pad(inap[spike], ((0, 0), (1, 1), (1, 1)))
    off = np.array([(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc])
    k = np.arange(r.size)[:, None]
    neigh = padded[k, r[:, None] + 1 + off[None, :, 0], c[:, None] + 1 + off[None, :, 1]]
    out = signal.copy()
    out[spike] -= peak[spike] - np.median(neigh, axis=1)
    return out, int(spike.sum())


def _spot_sigma(net, dist, noise, r_max):
    """Return the per-axis RMS radius (px) of the bright dots' light within ``r_max``."""
    inside = dist <= r_max
    flux = np.where(inside, net, 0).sum(axis=(1, 2))
    bright = np.argsort(flux)[::-1][:50]
    bright = bright[flux[bright] > 50 * noise * np.sqrt(inside[bright].sum(axis=(1, 2)))]
    if bright.size < 3:
        return None
    second = np.where(inside[bright], net[bright] * dist[bright] ** 2, 0).sum(axis=(1, 2))
    return float(np.sqrt(max(np.median(second / flux[bright]), 0) / 2))


def _aperture_radius(net, dist, noise, r_max):
    """Return the radius (px) holding 99 % of the bright dots' light, plus 1 px, in [2, r_max].

    The margin covers dots whose sub-pixel phase spreads their light differently
    from the bright dots' (a compact PSF has only a handful of bright dots).
    """
    inside = dist <= r_max
    flux = np.where(inside, net, 0).sum(axis=(1, 2))
    bright = np.argsort(flux)[::-1][:50]
    bright = bright[flux[bright] > 50 * noise * np.sqrt(inside[bright].sum(axis=(1, 2)))]
    if bright.size < 3:
        return float(r_max)
    for r in np.arange(1.0, r_max + 0.25, 0.25):
        held = np.where(dist[bright] <= r, net[bright], 0).sum(axis=(1, 2)) / flux[bright]
        if np.median(held) >= 0.99:
            return float(min(max(r + 1.0, 2.0), r_max))
    return float(r_max)
