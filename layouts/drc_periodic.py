"""The markers of a large tile array counted from four small arrays of the same tile.

Every marker of a check depends on the geometry near it, or, for a polygon edge that
runs through whole rows or columns of tiles, on that row or column. In an array of
nx x ny copies of one tile the markers are then those inside a tile (nx ny times),
across each vertical or horizontal seam, at the array's edges and corners, and along
whole rows or columns, so a count is ``a + b nx + c ny + d nx ny`` once the array is
large enough for its edges not to meet (3 tiles; a marker reaches at most into the
next tile, the feature size being below a tile). The four arrays 3 x 3, 3 x 4, 4 x 3
and 4 x 4 fix a, b, c, d. A merged array whose pixels touch through corner contacts
is one polygon across the plate, on which KLayout's width and notch checks run flat
whatever the hierarchy: 16 counted tiles instead of 256 bound that cost.
"""

MIN_TILES = 6  # both ways: smaller arrays are checked whole
SIZES = ((3, 3), (4, 3), (3, 4), (4, 4))  # (na, nb) of the arrays counted


def single_array(layout, top):
    """Return the top cell's one regular array instance of a leaf cell, at least
    :data:`MIN_TILES` both ways, or None when the top cell holds anything else."""
    insts = list(top.each_inst())
    if len(insts) != 1:
        return None
    ci = insts[0].cell_inst
    if not ci.is_regular_array() or min(ci.na, ci.nb) < MIN_TILES:
        return None
    if layout.cell(ci.cell_index).child_cells():
        return None
    return ci


def small_arrays(layout, ci, layer, dss):
    """Return [(layout, region)] of the tile's ``layer`` in the arrays of :data:`SIZES`
    (same origin and pitch as ``ci``; each layout must outlive its region)."""
    import klayout.db as kdb

    source = layout.cell(ci.cell_index).shapes(layout.find_layer(layer, 0))
    out = []
    for na, nb in SIZES:
        sub = kdb.Layout()
        sub.dbu = layout.dbu
        li = sub.layer(layer, 0)
        tile = sub.create_cell("TILE")
        tile.shapes(li).insert(source)
        top = sub.create_cell("TOP")
        top.insert(kdb.CellInstArray(tile.cell_index(), ci.trans, ci.a, ci.b, na, nb))
        out.append((sub, kdb.Region(top.begin_shapes_rec(li), dss)))
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
