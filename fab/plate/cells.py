"""A mask pixel cut by the fabricated plate's mask edges, and the Fourier weight of each part.

Every mask edge of the fabricated plate lies at a pixel boundary of that mask's own
(shifted) grid, moved by the CD bias. Along one axis, the offsets {shift, shift +- bias}
of all masks cut every pixel [0, 1) into the same intervals, and on each interval every
mask shows one pixel of its bitmap (or the OR / AND of two neighbours, where a bias
moves its edge across). ``fab.plate.model`` builds the plate from these cells; this
module holds their geometry, in pixels, along array axes (rows, columns).
"""

import itertools
import math

import numpy as np


def pixel_shifts(dx, dy, pixel_pitch):
    """Return the (row, column) shifts in pixels of an overlay (dx, dy) in metres.

    The one place the plate's axes meet the array's: columns follow +x, rows grow
    towards -y (row 0 is the top edge, CONVENTIONS.md), so +y moves a pattern towards
    row 0.
    """
    return -np.asarray(dy, dtype=float) / pixel_pitch, np.asarray(dx, dtype=float) / pixel_pitch


def axis_cells(shifts, bias, supersample):
    """Cut a pixel [0, 1) at every mask's edges; return (start, end, offsets per mask).

    ``shifts`` are the masks' shifts in pixels along one array axis, ``bias`` the CD
    bias in pixels. ``offsets[i]`` lists the pixel offsets q whose bitmap value reaches
    this interval for mask i: the mask value at pixel c is the OR (bias > 0) or AND
    (bias < 0) of bitmap[c + q] over q.
    """
    cuts = {0.0}
    for s in shifts:
        for e in (s, s + bias, s - bias):
            cuts.add(_frac(e, supersample))
    cuts = [*sorted(cuts), 1.0]
    cells = []
    for a, b in itertools.pairwise(cuts):
        if b - a <= 1e-12:
            continue
        mid = 0.5 * (a + b)
        offsets = []
        for s in shifts:
            w = mid - s
            q = math.floor(w)
            f = w - q
            near = [q]
            if f < abs(bias):
                near.append(q - 1)
            if f > 1 - abs(bias):
                near.append(q + 1)
            offsets.append(tuple(near))
        cells.append((a, b, offsets))
    return cells


def _frac(x, supersample):
    f = x - math.floor(x)
    if supersample is not None:
        f = round(f * supersample) / supersample
    return 0.0 if f >= 1.0 - 1e-12 or f < 1e-12 else f


def reduce_rolls(bitmap, offsets, axis, bias):
    """Return OR (bias >= 0) / AND (bias < 0) over q of bitmap[c + q] along ``axis``."""
    out = np.roll(bitmap, -offsets[0], axis=axis)
    for q in offsets[1:]:
        rolled = np.roll(bitmap, -q, axis=axis)
        out = out | rolled if bias >= 0 else out & rolled
    return out


def interval_weight(orders, a, b, n, supersample):
    """Return g(m) of the pixel interval [a, b) (pixel units) for each order m.

    Continuous (``supersample`` None): the integral of exp(-2 pi i m t / N) over the
    interval; ``a`` and ``b`` may then be arrays of one shape S, giving S + (len(orders),).
    Sampled: the sum over the interval's sub-samples s of exp(-2 pi i m s / (N S)) / S.
    """
    if supersample is None:
        m = orders.astype(float)
        a, b = np.asarray(a, dtype=float)[..., None], np.asarray(b, dtype=float)[..., None]
        safe = np.where(m == 0, 1.0, m)
        w = (np.exp(-2j * np.pi * m * b / n) - np.exp(-2j * np.pi * m * a / n)) / (
            -2j * np.pi * safe / n
        )
        return np.where(m == 0, b - a, w)
    s = np.arange(round(a * supersample), round(b * supersample))
    return np.exp(-2j * np.pi * np.outer(orders, s) / (n * supersample)).sum(axis=1) / supersample


def bias_pixels(cd_bias, pixel_pitch, supersample):
    """Return a CD bias in pixels as a model samples it (rounded to its sub-samples)."""
    bias = cd_bias / pixel_pitch
    if supersample is not None:
        bias = round(bias * supersample) / supersample
    return bias


def below_half_pixel(bias):
    """Whether a bias (pixels) is below half a pixel, and not half a pixel in rounding.

    The pitch is grid steps x 1e-9 m, so 0.25 um over a 500 nm pitch is 0.4999999999999999.
    """
    return abs(bias) < 0.5 - 1e-9
