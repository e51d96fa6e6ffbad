"""The markers of a large tile array, and of the clipped edge tiles round it, counted
from four small plates of the same tile.

Every marker of a check depends on the geometry near it, or, for a polygon edge that
runs through whole rows or columns of tiles, on that row or column. In an array of
nx x ny copies of one tile the markers are then those inside a tile (nx ny times),
across each vertical or horizontal seam, at the array's edges and corners, and along
whole rows or columns, so a count is ``a + b nx + c ny + d nx ny`` once the array is
large enough for its edges not to meet (3 tiles; a marker reaches at most into the
next tile, the feature size being below a tile). A filled plate adds clipped edge
tiles round the array: a strip along each side, one copy per tile of the array
(the strip's cell repeated nx or ny times), and one piece at each corner. They keep
the count of that form: the strips are periodic along the array like its rows and
columns. The four plates of 3 x 3, 3 x 4, 4 x 3 and 4 x 4 whole tiles, with the same
edge pieces on the same lattice, fix a, b, c, d. A merged array whose pixels touch
through corner contacts is one polygon across the plate, on which KLayout's width and
notch checks run flat whatever the hierarchy: 16 counted tiles instead of 256 bound
that cost.
"""

from dataclasses import dataclass

MIN_TILES = 6  # both ways: smaller arrays are checked whole
SIZES = ((3, 3), (4, 3), (3, 4), (4, 4))  # (na, nb) of the arrays counted


@dataclass(frozen=True)
class PlateArray:
    """The top cell's tile array and the edge pieces placed on its lattice.

    Attributes
    ----------
    cell_index : int
        The tile cell (a leaf).
    origin : (int, int)
        The array's first placement (database units).
    step : (int, int)
        The tile pitch along x and y.
    na, nb : int
        Whole tiles along x and along y.
    edges : tuple of (int, (int, int), (int, int))
        Each edge piece's cell index, its first placement's lattice index (i, j) and
        its repeat (ri, rj): outside the array on an axis (i < 0 or i >= na, ri = 1)
        or along it (i = 0, ri = na).
    """

    cell_index: int
    origin: tuple[int, int]
    step: tuple[int, int]
    na: int
    nb: int
    edges: tuple


def _grid(ci):
    """Return ((repeats along x, along y), (step x, step y)) of an axis-aligned instance
    (steps None where it is not repeated), or None for a rotated, mirrored, magnified or
    skewed one (the plate's never are)."""
    if ci.is_complex() or ci.trans.rot != 0 or ci.trans.is_mirror():
        return None
    if not ci.is_regular_array():
        return (1, 1), (None, None)
    a, b = ci.a, ci.b
    if a.y == 0 and b.x == 0:
        (rx, sx), (ry, sy) = (ci.na, a.x), (ci.nb, b.y)
    elif a.x == 0 and b.y == 0:  # gdstk writes the rows' step first
        (rx, sx), (ry, sy) = (ci.nb, b.x), (ci.na, a.y)
    else:
        return None
    return (rx, ry), (sx if rx > 1 else None, sy if ry > 1 else None)


def single_array(layout, top):
    """Return the :class:`PlateArray` of the top cell: one regular array of a leaf cell,
    at least :data:`MIN_TILES` both ways, and leaf edge pieces on its lattice beside
    or along it; None when the top cell holds anything else."""
    insts = [inst.cell_inst for inst in top.each_inst()]
    if any(layout.cell(ci.cell_index).child_cells() for ci in insts):
        return None
    grids = [_grid(ci) for ci in insts]
    if any(g is None for g in grids):
        return None
    big = [k for k, g in enumerate(grids) if min(g[0]) >= MIN_TILES]
    if len(big) != 1:
        return None
    ci, ((na, nb), (sx, sy)) = insts[big[0]], grids[big[0]]
    if sx <= 0 or sy <= 0:
        return None
    origin = (ci.trans.disp.x, ci.trans.disp.y)
    edges = []
    for k, (e, ((ri, rj), (ex, ey))) in enumerate(zip(insts, grids, strict=True)):
        if k == big[0]:
            continue
        dx, dy = e.trans.disp.x - origin[0], e.trans.disp.y - origin[1]
        if dx % sx or dy % sy or ex not in (None, sx) or ey not in (None, sy):
            return None
        i, j = dx // sx, dy // sy
        for m, r, n in ((i, ri, na), (j, rj, nb)):
            if not (r == 1 and (m < 0 or m >= n)) and (m, r) != (0, n):
                return None  # overlapping the array: not an edge piece
        edges.append((e.cell_index, (i, j), (ri, rj)))
    return PlateArray(ci.cell_index, origin, (sx, sy), na, nb, tuple(edges))


def _remap(k, r, n, s):
    """A lattice index and repeat on an axis of n whole tiles, moved to one of s."""
    if r == n and k == 0:
        return 0, s
    return (k, r) if k < 0 else (k - n + s, r)


def small_arrays(layout, plate, layer, dss=None):
    """Return [(layout, region)] of the plate's ``layer`` with the arrays of :data:`SIZES`
    (same origin and pitch; the edge pieces moved with the array's far sides; each
    layout must outlive its region). The regions are flat: small plates check fast
    flat, and a flat run is what the counts must equal."""
    import klayout.db as kdb

    (x0, y0), (sx, sy) = plate.origin, plate.step
    source_layer = layout.find_layer(layer, 0)
    out = []
    for na, nb in SIZES:
        sub = kdb.Layout()
        sub.dbu = layout.dbu
        li = sub.layer(layer, 0)
        top = sub.create_cell("TOP")
        placed = [(plate.cell_index, (0, 0), (na, nb))]
        for cell_index, (i, j), (ri, rj) in plate.edges:
            (i2, ri2), (j2, rj2) = _remap(i, ri, plate.na, na), _remap(j, rj, plate.nb, nb)
            placed.append((cell_index, (i2, j2), (ri2, rj2)))
        cells = {}
        for cell_index, (i, j), (ri, rj) in placed:
            if cell_index not in cells:
                cell = sub.create_cell(f"C{len(cells)}")
                cell.shapes(li).insert(layout.cell(cell_index).shapes(source_layer))
                cells[cell_index] = cell.cell_index()
            trans = kdb.Trans(kdb.Vector(x0 + i * sx, y0 + j * sy))
            a, b = kdb.Vector(sx, 0), kdb.Vector(0, sy)
            top.insert(kdb.CellInstArray(cells[cell_index], trans, a, b, ri, rj))
        out.append((sub, kdb.Region(top.begin_shapes_rec(li))))
    return out


def extrapolate(counts, na, nb):
    """Return the count of an na x nb array from those of :data:`SIZES` (same order)."""
    c33, c43, c34, c44 = counts
    return (
        c33
        + (na - 3) * (c43 - c33)
        + (nb - 3) * (c34 - c33)
        + (na - 3) * (nb - 3) * (c44 - c43 - c34 + c33)
    )
