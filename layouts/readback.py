"""Read a written GDS back with KLayout (independent of gdstk) and rasterise the tile.

Used by ``doefab fab`` as a self-check before the package is released: the
tile cell's mask layers sampled at the pixel centres must reproduce the mask
bitmaps, and the top cell must place the tile on the expected lattice.
"""

import numpy as np


def rasterise_tile(gds_path, tile_cell, layers, tile_pixels, pitch_nm):
    """Sample each layer of the tile cell at the centres of its N x N pixels.

    Parameters
    ----------
    gds_path : path
    tile_cell : str
    layers : list of (layer, datatype)
    tile_pixels : int
        N.
    pitch_nm : int
        Pixel pitch (the file's DBU must be 1 nm).

    Returns
    -------
    list of (N, N) bool arrays
        True where a centre is covered; row 0 is the top edge (largest y).
    """
    import klayout.db as kdb

    layout = kdb.Layout()
    layout.read(str(gds_path))
    if abs(layout.dbu - 0.001) > 1e-12:
        raise ValueError(f"{gds_path}: DBU is {layout.dbu} um, not 0.001")
    cell = layout.cell(tile_cell)
    if cell is None:
        raise ValueError(f"{gds_path}: no cell {tile_cell!r}")
    p, n = int(pitch_nm), int(tile_pixels)
    out = []
    for layer, datatype in layers:
        li = layout.find_layer(layer, datatype)
        if li is None:
            out.append(np.zeros((n, n), dtype=bool))
            continue
        region = kdb.Region(cell.begin_shapes_rec(li))
        # A 2 x 2 nm probe at each pixel centre: > 0 means the centre is covered.
        origin = kdb.Point(p // 2 - 1, p // 2 - 1)
        area = np.array(region.rasterize(origin, kdb.Vector(p, p), kdb.Vector(2, 2), n, n))
        out.append(np.flipud(area > 0))  # raster rows run upwards, bitmap rows downwards
    return out


def tile_placements(gds_path, top_cell, tile_cell):
    """Return the sorted (x, y) nm displacements of every placement of the tile in the top cell."""
    import klayout.db as kdb

    layout = kdb.Layout()
    layout.read(str(gds_path))
    top, tile = layout.cell(top_cell), layout.cell(tile_cell)
    if top is None or tile is None:
        raise ValueError(f"{gds_path}: missing cell {top_cell!r} or {tile_cell!r}")
    disp = []
    for inst in top.each_inst():
        if inst.cell_index != tile.cell_index():
            continue
        for t in inst.cell_inst.each_cplx_trans():
            if t.is_mirror() or t.is_mag() or t.angle != 0:
                raise ValueError(f"{gds_path}: tile placed with rotation, mirror or magnification")
            disp.append((int(t.disp.x), int(t.disp.y)))
    return sorted(disp)


def check_written_gds(gds_path, layout_info, masks):
    """Return a list of problems (empty when the GDS reproduces the masks and the lattice)."""
    problems = []
    layers = [(mk.gds_layer, mk.gds_datatype) for mk in masks]
    n, p = layout_info.tile_pixels, layout_info.pixel_pitch_nm
    try:
        rasters = rasterise_tile(gds_path, layout_info.tile_cell, layers, n, p)
        placements = tile_placements(gds_path, layout_info.top_cell, layout_info.tile_cell)
    except ValueError as e:  # another DBU, a missing cell, a mirrored tile: a failed check
        return [str(e)]
    for mk, got in zip(masks, rasters, strict=True):
        bad = int(np.count_nonzero(got != mk.bitmap))
        if bad:
            problems.append(f"layer {mk.gds_layer} ({mk.name}): {bad} pixels differ from the mask")
    nx, ny = layout_info.tiles
    x0, y0 = layout_info.array_origin_nm
    want = sorted((x0 + i * n * p, y0 + j * n * p) for i in range(nx) for j in range(ny))
    if placements != want:
        problems.append(f"the tile is not placed on the {nx} x {ny} lattice at {x0, y0} nm")
    return problems
