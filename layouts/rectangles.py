"""Bitmap -> non-overlapping rectangles (row runs merged vertically, vectorised).

Rectangles never touch only at a corner in a way that joins them into one
polygon (each is its own 4-vertex boundary), so the mask shop's fracturing and
KLayout's raster both see exactly the bitmap.
"""

import numpy as np


def row_runs(bitmap):
    """Return the horizontal runs of True pixels of every row.

    Parameters
    ----------
    bitmap : (H, W) bool array

    Returns
    -------
    (R, 3) int64 array
        Rows of (row, c0, c1) with columns c0 <= c < c1 set, ordered by row then c0.
    """
    b = np.asarray(bitmap, dtype=bool)
    h, w = b.shape
    padded = np.zeros((h, w + 2), dtype=np.int8)
    padded[:, 1:-1] = b
    d = np.diff(padded, axis=1)  # +1 where a run starts, -1 one past its end
    r0, c0 = np.nonzero(d == 1)
    _, c1 = np.nonzero(d == -1)  # same row-major order, one end per start
    return np.stack([r0, c0, c1], axis=1).astype(np.int64)


def bitmap_rectangles(bitmap):
    """Cover the True pixels of a bitmap exactly with disjoint rectangles.

    Runs of True pixels along each row become rectangles; identical runs
    (same c0, c1) in consecutive rows merge into one taller rectangle.

    Parameters
    ----------
    bitmap : (H, W) bool array
        Row 0 is the top edge.

    Returns
    -------
    (M, 4) int64 array
        Rows of (c0, r0, c1, r1): pixel columns c0 <= c < c1 and rows
        r0 <= r < r1 are covered. Deterministic order (by c0, c1, r0).
    """
    runs = row_runs(bitmap)
    if len(runs) == 0:
        return np.zeros((0, 4), dtype=np.int64)
    order = np.lexsort((runs[:, 0], runs[:, 2], runs[:, 1]))  # by c0, then c1, then row
    r, c0, c1 = runs[order].T
    same_cols = (c0[1:] == c0[:-1]) & (c1[1:] == c1[:-1])
    starts = np.ones(len(r), dtype=bool)
    starts[1:] = ~(same_cols & (r[1:] == r[:-1] + 1))
    first = np.flatnonzero(starts)
    last = np.append(first[1:], len(r)) - 1
    rects = np.stack([c0[first], r[first], c1[first], r[last] + 1], axis=1)
    return rects


def rectangles_to_bitmap(rects, shape):
    """Paint rectangles (c0, r0, c1, r1) into a bool bitmap (the inverse, for tests)."""
    out = np.zeros(shape, dtype=bool)
    for c0, r0, c1, r1 in np.asarray(rects, dtype=np.int64).reshape(-1, 4):
        out[r0:r1, c0:c1] = True
    return out


def rectangle_corners_nm(rects, n_rows, pitch_nm):
    """Return rectangle corners in layout coordinates (integer nm, y up).

    Pixel (row r, col c) covers x in [c p, (c+1) p], y in [(N-1-r) p, (N-r) p].

    Parameters
    ----------
    rects : (M, 4) int array of (c0, r0, c1, r1)
    n_rows : int
        N, the number of rows of the bitmap.
    pitch_nm : int
        Pixel pitch in nm.

    Returns
    -------
    (M, 4) int64 array
        Rows of (x0, y0, x1, y1) in nm with x0 < x1, y0 < y1.
    """
    rects = np.asarray(rects, dtype=np.int64).reshape(-1, 4)
    p = int(pitch_nm)
    c0, r0, c1, r1 = rects.T
    return np.stack([c0 * p, (n_rows - r1) * p, c1 * p, (n_rows - r0) * p], axis=1)
