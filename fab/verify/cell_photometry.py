"""Photometry of a tight dot lattice (dots under ``ANNULUS_MIN_PITCH_PX`` apart).

A dot 3 to 4.5 px from its neighbours leaves no room for an aperture and a background
annulus around it, so each order is summed over its whole lattice cell (the pixels
nearer its site than any other's), which holds the dot's light but for its tails:

1. background: the median of the cells' corner pixels (beyond ``CORNER`` of a pitch from
   the site along both lattice axes) over the fainter half of the cells, where the
   neighbours' tails are weakest; the capture's offset (a pedestal without a dark frame,
   stray light) is taken out once for the frame;
2. each cell's sum, less its pixels' background;
3. the tails: each dot, a pixel-integrated Gaussian of the bright dots' sigma (measured
   within their cells, the pixel's 1/12 px^2 taken out) at its fitted position, puts a
   share of its light into each neighbour cell, the pixels cut as the cells are; the
   cells' sums are undone of those shares by a few fixed-point sweeps (each share is at
   most a few per cent, so they converge at once).

With every dot bright (no faint cell for the background), the powers come within 0.3 %
of the peak at 4.27 px and 3.5 % at 3.6 px (tests/fab/verify/test_cell_photometry.py).
"""

import numpy as np
from scipy.special import erf

from fab.verify.lattice import lattice_points, pixel_noise, pixel_patches
from fab.verify.photometry import OrderGrid, _remove_spikes

# A cell pixel beyond this fraction of the pitch from its site, along both lattice
# axes, is a corner pixel (the farthest from every dot).
CORNER = 0.3
# Fixed-point sweeps that undo the neighbours' tails.
TAIL_SWEEPS = 6


def measure_cells(image, lattice, saturated=None, quantum=0.0):
    """Measure every order's power as its lattice cell's light (see the module).

    Same arguments and result as ``fab.verify.photometry.measure_orders``.
    """
    x = np.asarray(image, dtype=np.float32)
    pitch = lattice.pitch_px
    outer = int(np.ceil(pitch)) + 1
    u, v, rows, cols, valid = lattice_points(lattice, x.shape, outer)
    pr, pc = rows[valid], cols[valid]
    patch = pixel_patches(x, pr, pc, outer).astype(np.float64)
    cell, corner, dist = _cell_masks(lattice, pr, pc, outer)
    raw = np.where(cell, patch, 0).sum(axis=(1, 2))
    n_cell = cell.sum(axis=(1, 2))
    faint = raw <= np.median(raw)
    corners = patch[corner & faint[:, None, None]]
    background = float(np.median(corners)) if corners.size else float(np.median(x[::4, ::4]))
    noise = pixel_noise(corners - background, quantum) if corners.size > 8 else 1e-6
    net = np.where(cell, patch - background, 0.0)
    spot = _spot_sigma(net, dist, noise)
    signal, spikes = _remove_spikes(net, net.sum(axis=(1, 2)), noise * np.sqrt(n_cell))
    power = np.full(valid.shape, np.nan)
    power[valid] = signal
    if spot is not None:
        # the dot alone, without the pixel's 1/12 px^2 (its cells already integrate it)
        sharp = float(np.sqrt(max(spot**2 - 1 / 12, 0.05**2)))
        shares = np.zeros((*valid.shape, 3, 3))
        shares[valid] = _cell_shares(lattice, pr, pc, outer, sharp)
        power = _undo_tails(power, valid, shares)
    sigma = np.full(valid.shape, np.nan)
    sigma[valid] = noise * np.sqrt(n_cell * (1 + n_cell / max(corners.size, 1)))
    sat = np.zeros(valid.shape, bool)
    if saturated is not None and np.any(saturated):
        sat[valid] = (pixel_patches(saturated, pr, pc, outer) & cell).any(axis=(1, 2))
    return OrderGrid(
        u,
        v,
        power,
        valid,
        rows,
        cols,
        sat,
        noise,
        int(np.median(n_cell)),
        sigma,
        float(pitch / 2),
        spikes,
        spot,
        pitch,
    )


def _cell_masks(lattice, rows, cols, outer):
    """Return (cell, corner, distance in px) masks of each site's patch of ``outer`` px."""
    off = np.arange(-outer, outer + 1, dtype=np.float64)
    dr = off[None, :, None] - (rows - np.rint(rows))[:, None, None]
    dc = off[None, None, :] - (cols - np.rint(cols))[:, None, None]
    inv = np.linalg.inv(lattice.basis)
    du = inv[0, 0] * dr + inv[0, 1] * dc
    dv = inv[1, 0] * dr + inv[1, 1] * dc
    # half-open so that a pixel on a boundary belongs to one cell only
    cell = (du >= -0.5) & (du < 0.5) & (dv >= -0.5) & (dv < 0.5)
    corner = cell & (np.abs(du) > CORNER) & (np.abs(dv) > CORNER)
    return cell, corner, np.hypot(dr, dc)


def _spot_sigma(net, dist, noise):
    """Return the per-axis RMS radius (px) of the bright dots' light in their cells, or
    None without 3 bright dots (the tails then stay as measured)."""
    flux = net.sum(axis=(1, 2))
    bright = np.argsort(flux)[::-1][:50]
    bright = bright[flux[bright] > 50 * noise * np.sqrt((net[bright] != 0).sum(axis=(1, 2)))]
    if bright.size < 3:
        return None
    second = (net[bright] * dist[bright] ** 2).sum(axis=(1, 2))
    return float(np.sqrt(max(np.median(second / flux[bright]), 1e-6) / 2))


def _cell_shares(lattice, rows, cols, outer, sigma):
    """Return (P, 3, 3): the share of each dot's light (a pixel-integrated Gaussian of
    ``sigma`` at its fitted position) in its own cell [1, 1] and its neighbours' cells
    [1 + du, 1 + dv], the pixels cut as the cells are (whole pixels, by their centres)."""
    off = np.arange(-outer, outer + 1, dtype=np.float64)
    fr = (rows - np.rint(rows))[:, None]
    fc = (cols - np.rint(cols))[:, None]
    s2 = np.sqrt(2) * sigma

    def profile(frac):  # light of a dot at frac in each pixel of the offsets, one axis
        return 0.5 * (erf((off + 0.5 - frac) / s2) - erf((off - 0.5 - frac) / s2))

    light = profile(fr)[:, :, None] * profile(fc)[:, None, :]
    dr = off[None, :, None] - fr[:, :, None]
    dc = off[None, None, :] - fc[:, None, :]
    inv = np.linalg.inv(lattice.basis)
    cu = np.floor(inv[0, 0] * dr + inv[0, 1] * dc + 0.5)
    cv = np.floor(inv[1, 0] * dr + inv[1, 1] * dc + 0.5)
    shares = np.zeros((rows.size, 3, 3))
    for a in (-1, 0, 1):
        for b in (-1, 0, 1):
            shares[:, a + 1, b + 1] = np.where((cu == a) & (cv == b), light, 0).sum(axis=(1, 2))
    return shares


def _undo_tails(measured, valid, shares):
    """Return the powers whose dots, each spreading ``shares`` (nu, nv, 3, 3) of its light
    over its own and its neighbours' cells, give the cells' ``measured`` sums."""
    m = np.where(valid, measured, 0.0)
    own = np.where(valid, shares[..., 1, 1], 1.0)
    p = m / own
    for _ in range(TAIL_SWEEPS):
        spread = np.zeros_like(m)
        for a in (-1, 0, 1):
            for b in (-1, 0, 1):
                if a or b:  # dot (i - a, j - b) spreads into cell (i, j)
                    spread += _shifted(p * shares[..., a + 1, b + 1], a, b)
        p = np.where(valid, (m - spread) / own, 0.0)
    return np.where(valid, p, np.nan)


def _shifted(x, a, b):
    """Return ``x`` moved by (a, b) cells (zero where it comes from outside)."""
    out = np.zeros_like(x)
    h, w = x.shape
    out[max(a, 0) : h + min(a, 0), max(b, 0) : w + min(b, 0)] = x[
        max(-a, 0) : h + min(-a, 0), max(-b, 0) : w + min(-b, 0)
    ]
    return out
