"""Repair of hot pixels once the dot lattice is known: off the dots, and those that clipped.

A pixel flagged hot (by the dark frame, or as a single-pixel spike where there is none)
is replaced by the median of its neighbours only away from every dot's core: on a dot
the median of its neighbours would not hold the dot's light.
"""

import numpy as np

from fab.verify.conditioning import repair_pixels
from fab.verify.lattice import DETECT_SIGMAS, pixel_noise

# A dot's light lies within this many pixels of its lattice point (a focused spot is
# ~0.7 px wide); sharp spikes farther out are hot pixels.
SPOT_CORE = 1.5


def repair_stray_spikes(image, lattice, quantum=0.0):
    """Repair single-pixel spikes (hot pixels) away from every dot's centre.

    Without a dark frame a hot pixel looks like a compact dot; but a dot's light
    lies within ``SPOT_CORE`` pixels of its lattice point, so a pixel standing
    ``DETECT_SIGMAS`` sigma above the median of its 3 x 3 neighbourhood, and
    highest in it, farther from every lattice point is not light from the plate.
    It is replaced by the median of its neighbours. Pixels on the frame's rim
    are left alone: the wing of a dot centred just outside the frame is the
    highest of the neighbours that can be seen.

    Returns
    -------
    (image, repaired)
        A repaired copy (float32) and the (H, W) bool map of the pixels repaired.
    """
    x = np.asarray(image, dtype=np.float32)
    noise = pixel_noise(x[::4, ::4], quantum)
    floor = float(np.median(x[::4, ::4]))
    inner = np.zeros(x.shape, bool)
    inner[1:-1, 1:-1] = True
    rows, cols = np.nonzero((x > floor + DETECT_SIGMAS * noise) & inner)
    spikes = np.zeros(x.shape, bool)
    if 0 < rows.size <= 0.25 * x.size:  # more: a bright scene, not a dot lattice
        off = np.arange(-1, 2)
        block = x[
            rows[:, None, None] + off[None, :, None], cols[:, None, None] + off[None, None, :]
        ]
        block = block.reshape(rows.size, 9)
        # A spike is the highest pixel of its 3 x 3 block: the wing of a blurred
        # dot also stands above its neighbours' median, but falls away from the dot.
        spike = (x[rows, cols] - np.median(block, axis=1) > DETECT_SIGMAS * noise) & (
            x[rows, cols] >= block.max(axis=1)
        )
        spikes[rows[spike], cols[spike]] = True
    repaired = away_from_dots(spikes, lattice)
    return repair_pixels(x, repaired), repaired


def repair_hot_pixels(image, hot, saturated, lattice):
    """Repair a dark frame's hot pixels off the dots, and those that clipped.

    On a dot, a hot pixel less its dark still holds the dot's light (the median
    of its neighbours would not): unless it clipped, it is kept.

    Returns
    -------
    (image, repaired)
        A repaired copy (float32) and the (H, W) bool map of the pixels repaired.
    """
    repaired = away_from_dots(hot, lattice) | (hot & saturated)
    return repair_pixels(image, repaired), repaired


def away_from_dots(flagged, lattice):
    """Return the (H, W) bool map of the ``flagged`` pixels outside every dot's core.

    Outside: farther than ``SPOT_CORE`` pixels from every lattice point.
    """
    rows, cols = np.nonzero(flagged)
    u, v = lattice.coordinates(rows, cols)
    pr, pc = lattice.positions(np.round(u), np.round(v))
    far = np.hypot(rows - pr, cols - pc) > SPOT_CORE
    out = np.zeros(np.shape(flagged), bool)
    out[rows[far], cols[far]] = True
    return out
