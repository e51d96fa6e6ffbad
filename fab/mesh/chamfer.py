"""Pinched corners of a level map and the chamfer that keeps the relief a manifold.

At a grid corner where the two cells of one diagonal both stand higher than the two
cells of the other (min of the high pair > max of the low pair), the two high cells
touch along a vertical segment only: the solid is pinched there. A mesh can be a
2-manifold by vertex index (two vertices at one position), but STL stores no indices
and every reader merges vertices by position, which turns the segment back into an
edge of four faces. No mesh with identical positions avoids that, so the modelled
solid differs from the pixel relief by a chamfer far below any fabrication scale:

- the lower of the two high cells (on a tie, the one in the first quadrant of
  NE, NW, SW, SE) loses the triangular prism of legs ``CHAMFER_LEG`` pixel pitches at
  that corner, from the top of the higher low cell (``z_lo``) up to its own top;
- each pinch removes (leg p)^2 / 2 * (its top - z_lo), see :func:`chamfer_volume`.

The leg (p / 1000: 4.99 nm at a 4.99 um pitch) is ~500 x trimesh's merge tolerance
(1e-8 mm), > 2 float32 spacings at 16 mm, and small enough that every pixel top keeps
its area to 5e-7 px per pinch.
"""

import numpy as np

# Chamfer leg in pixel pitches; its inverse is an integer so that the polygons of
# the surface triangulate with exact integer predicates.
CHAMFER_DENOM = 1000
CHAMFER_LEG = 1 / CHAMFER_DENOM
CHAMFER_NOTE = (
    "at each pinched corner (two diagonal pixels above the other two) the lower high "
    "pixel loses a right prism of legs leg_nm from the higher low pixel's top to its "
    "own: -leg^2/2 * that height per corner; analytic_volume_mm3 = pixel sum - volume_mm3"
)


def chamfer_quadrant(q):
    """Return the quadrant (0 NE, 1 NW, 2 SW, 3 SE) chamfered at a corner, or None.

    ``q`` holds the levels of the four cells around the corner in that order.
    """
    for d in (0, 1):
        high = min(q[d], q[d + 2])
        if high > max(q[d + 1], q[(d + 3) % 4]):
            return d if q[d] <= q[d + 2] else d + 2
    return None


def pinched_corners(levels):
    """Return the pinched interior corners of a level map (row 0 at the top).

    Returns
    -------
    rc : ndarray of int64, shape (P, 2)
        (row, column) of the cell up-left of each pinched corner.
    top : ndarray of int64, shape (P,)
        Level of the chamfered cell, min of the high pair: where the chamfer ends.
    low : ndarray of int64, shape (P,)
        max of the low pair: where the chamfer starts (z_lo).
    """
    lev = np.asarray(levels, np.int64)
    a, b, c, d = lev[:-1, :-1], lev[:-1, 1:], lev[1:, :-1], lev[1:, 1:]
    top = np.where(np.minimum(a, d) > np.maximum(b, c), np.minimum(a, d), np.minimum(b, c))
    low = np.where(np.minimum(a, d) > np.maximum(b, c), np.maximum(b, c), np.maximum(a, d))
    pinched = top > low  # at most one diagonal pair can stand above the other
    return np.argwhere(pinched), top[pinched], low[pinched]


def pinch_depths(levels):
    """Return each pinched corner's chamfer height in level steps, shape (P,)."""
    _, top, low = pinched_corners(levels)
    return top - low


def tiled_pinch_count(levels, tiles):
    """Return the pinched corners of ``tiles`` x ``tiles`` copies of ``levels``.

    Counted from the tile and its seams (no tiled map is built): inside each tile,
    on the vertical and horizontal seams, and at the seam crossings.
    """
    lev = np.asarray(levels, np.int64)
    c = int(tiles)
    inside = len(pinch_depths(lev))
    vertical = len(pinch_depths(np.stack([lev[:, -1], lev[:, 0]], axis=1)))
    horizontal = len(pinch_depths(np.stack([lev[-1], lev[0]], axis=0)))
    crossing = len(pinch_depths([[lev[-1, -1], lev[-1, 0]], [lev[0, -1], lev[0, 0]]]))
    return c * c * inside + c * (c - 1) * (vertical + horizontal) + (c - 1) ** 2 * crossing


def chamfer_volume(levels, step, pitch, leg=CHAMFER_LEG):
    """Return the volume the chamfers remove from a level map's relief (units of step * pitch^2).

    Each pinched corner removes a right prism of legs ``leg * pitch`` and height
    (its chamfer height in levels) * step.
    """
    return float(pinch_depths(levels).sum()) * step * (leg * pitch) ** 2 / 2


# Edge d (0 north, 1 west, 2 south, 3 east) points this way from a corner; quadrant d
# (0 NE, 1 NW, 2 SW, 3 SE) lies this way.
_EDGE_DIR = ((0, 1), (-1, 0), (0, -1), (1, 0))
_QUADRANT_DIR = ((1, 1), (-1, 1), (-1, -1), (1, -1))


def cut_chamfer(cg, i, j, dc, q, z_lo, cells, edge_keys, leg, edge_end):
    """Cut the prism of legs ``leg`` off cell ``dc`` at corner (i, j), from z_lo to its top.

    Adds two vertices on each of the cell's two edges at the corner (at z_lo and at
    its top), appends them to the two walls' chains (which get a notch), replaces
    the cell's top corner by the two top ones, puts the z_lo one into the top of a
    neighbour at z_lo, and adds the chamfer face and the up-facing triangle at z_lo.
    """
    grid, top_vid = cg.grid, cg.top_vid  # the builder's corner grid (relief._CornerGrid)
    z_top = q[dc]
    d_in, d_out = dc, (dc - 1) % 4  # the cell's boundary arrives along d_in, leaves along d_out
    off = {}
    for d in (d_in, d_out):
        x, y = i + leg * _EDGE_DIR[d][0], j + leg * _EDGE_DIR[d][1]
        off[d] = (len(grid), len(grid) + 1)
        grid += [(x, y, z_lo), (x, y, z_top)]
        chains = cg.walls.setdefault(edge_keys[d], ([], []))
        chains[edge_end[d]].extend([(z_lo, 1, off[d][0]), (z_top, 1, off[d][1])])
        cg.notched.add(edge_keys[d])
    r, c = cells[dc]
    apex = int(top_vid[r, c, dc])  # the corner at z_lo, counted as the cell's top by qc
    cg.tops[r, c, dc] = [off[d_in][1], off[d_out][1]]
    for dq, shared in (((dc + 1) % 4, d_in), ((dc - 1) % 4, d_out)):
        if q[dq] == z_lo:  # that neighbour's top holds the edge corner -> chamfer at z_lo
            rq, cq = cells[dq]
            corner = int(top_vid[rq, cq, dq])
            leaves = shared == (dq - 1) % 4
            cg.tops[rq, cq, dq] = [corner, off[shared][0]] if leaves else [off[shared][0], corner]
    cg.faces.append(([off[d_in][0], apex, off[d_out][0]], (0, 0, 1)))
    sx, sy = _QUADRANT_DIR[dc]
    face = [off[d_out][1], off[d_in][1], off[d_in][0], off[d_out][0]]
    cg.faces.append((face, (-sx, -sy, 0)))
    cg.chamfers += 1


def ear_clip(ids, points):
    """Triangulate a simple polygon, collinear vertices allowed.

    Parameters
    ----------
    ids : list of int
        Vertex ids in loop order.
    points : list of (int, int)
        Their 2-D coordinates in the polygon's plane, exact integers.

    Returns
    -------
    list of (int, int, int)
        Triangles with the loop's orientation, none degenerate, no vertex of the
        polygon inside or on the boundary of a triangle it does not belong to.
    """
    pts = [tuple(p) for p in points]
    area2 = sum(pts[m - 1][0] * pts[m][1] - pts[m][0] * pts[m - 1][1] for m in range(len(pts)))
    sign = 1 if area2 > 0 else -1
    idx = list(range(len(pts)))
    out = []
    while len(idx) > 3:
        n = len(idx)
        for t in range(n):
            p, c, nx = idx[t - 1], idx[t], idx[(t + 1) % n]
            if _orient(pts[p], pts[c], pts[nx]) * sign <= 0:
                continue
            if any(
                _in_closed_triangle(pts[m], pts[p], pts[c], pts[nx], sign)
                for m in idx
                if m not in (p, c, nx)
            ):
                continue
            out.append((ids[p], ids[c], ids[nx]))
            del idx[t]
            break
        else:
            raise ValueError(f"polygon {ids} has no ear: not simple")
    p, c, nx = idx
    if _orient(pts[p], pts[c], pts[nx]) * sign <= 0:
        raise ValueError(f"polygon {ids} leaves a degenerate triangle")
    out.append((ids[p], ids[c], ids[nx]))
    return out


def _orient(a, b, c):
    """Return twice the signed area of triangle abc (> 0: counter-clockwise)."""
    return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])


def _in_closed_triangle(m, a, b, c, sign):
    """Whether ``m`` lies in triangle abc (oriented by ``sign``) or on its boundary."""
    return (
        _orient(a, b, m) * sign >= 0
        and _orient(b, c, m) * sign >= 0
        and _orient(c, a, m) * sign >= 0
    )
