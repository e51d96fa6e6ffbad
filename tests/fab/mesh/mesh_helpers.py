"""Closed forms the mesh tests compare with: pinched corners and the exact volume."""

import numpy as np


def pinches(levels):
    """Return (top, low) of every pinched corner, found by a plain loop over the corners.

    A corner is pinched when both cells of one diagonal stand higher than both of the
    other; the chamfer then runs from the higher low cell (low) to the lower high
    cell's top (top).
    """
    lev = np.asarray(levels, np.int64).tolist()
    out = []
    for r in range(len(lev) - 1):
        for c in range(len(lev[0]) - 1):
            a, b, cc, d = lev[r][c], lev[r][c + 1], lev[r + 1][c], lev[r + 1][c + 1]
            for high, low in (((a, d), (b, cc)), ((b, cc), (a, d))):
                if min(high) > max(low):
                    out.append((min(high), max(low)))
    return out


def exact_volume_mm3(levels, n_levels, step, pitch, thickness, leg=1e-3, dtype=np.float64):
    """Return the exact volume (mm^3) of the chamfered relief a mesh file holds.

    The pixel relief on the grid lines and level tops as the file stores them
    (``dtype``: float32 for STL and GLB, rounded like the writers round the
    float64 millimetres), minus (leg p)^2 / 2 * (top - low) per pinched corner.
    """
    lev = np.asarray(levels, np.int64)
    rows, cols = lev.shape
    xs = (np.arange(cols + 1) * pitch * 1e3).astype(dtype).astype(np.float64)
    ys = (np.arange(rows + 1) * pitch * 1e3).astype(dtype).astype(np.float64)
    tops_mm = (thickness - (n_levels - 1 - np.arange(n_levels)) * step) * 1e3
    tops = tops_mm.astype(dtype).astype(np.float64)
    widths = np.diff(xs)[None, :]
    heights = np.diff(ys)[::-1][:, None]  # row 0 covers the largest y
    pixel_sum = float((widths * heights * tops[lev]).sum())
    leg_mm = leg * pitch * 1e3
    chamfers = sum((tops_mm[t] - tops_mm[lo]) * leg_mm**2 / 2 for t, lo in pinches(lev))
    return pixel_sum - chamfers
