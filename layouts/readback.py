"""Read a written GDS back with KLayout (independent of gdstk) and rasterise the tile.

Used by ``doefab fab`` as a self-check before the package is released: the
tile cell's mask layers sampled at the pixel centres must reproduce the mask
bitmaps, every clipped edge cell must hold exactly the tile's pixels in its window
(and nothing outside it), the plate cell must place the tile and the edge cells on
the array's lattice, and with several dies the top cell must place the plate on
the die lattice.
"""

from typing import NamedTuple

import numpy as np


class Loaded(NamedTuple):
    """A GDS file read once by KLayout, for several checks."""

    layout: object
    path: str

    def __str__(self):
        return self.path


def load(gds_path):
    """Return the :class:`Loaded` file (read now unless it already is)."""
    import klayout.db as kdb

    if isinstance(gds_path, Loaded):
        return gds_path
    layout = kdb.Layout()
    layout.read(str(gds_path))
    return Loaded(layout, str(gds_path))


def _read(gds_path):
    return load(gds_path).layout


def rasterise_tile(gds_path, tile_cell, layers, tile_pixels, pitch_nm):
    """Sample each layer of the tile cell at the centres of its N x N pixels.

    Parameters
    ----------
    gds_path : path or Loaded
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

    layout = _read(gds_path)
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
    layout = _read(gds_path)
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
    plate_cell = layout_info.plate_cell or layout_info.top_cell
    try:
        layout = load(gds_path)
        rasters = rasterise_tile(layout, layout_info.tile_cell, layers, n, p)
        placements = tile_placements(layout, plate_cell, layout_info.tile_cell)
        for name, piece in layout_info.edge_cells:
            problems += _edge_problems(layout, name, piece, layers, masks, n, p)
        if layout_info.plate_cell and layout_info.plate_cell != layout_info.top_cell:
            problems += _die_problems(layout, layout_info)
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


def _edge_problems(layout, name, piece, layers, masks, n, p):
    """An edge cell must be the tile inside its window, empty outside, placed on the lattice."""
    problems = []
    (c0, c1), (r0, r1) = piece.columns, piece.rows
    for mk, got in zip(masks, rasterise_tile(layout, name, layers, n, p), strict=True):
        want = np.zeros_like(mk.bitmap)
        want[r0:r1, c0:c1] = mk.bitmap[r0:r1, c0:c1]
        bad = int(np.count_nonzero(got != want))
        if bad:
            problems.append(f"edge cell {name}, layer {mk.gds_layer}: {bad} pixels differ")
    plate = _plate_cell_name(layout, name)
    if tile_placements(layout, plate, name) != sorted(piece.placements(n * p)):
        problems.append(f"edge cell {name} is not placed where the periodic pattern continues")
    return problems


def _plate_cell_name(layout, child):
    """The name of the cell that places ``child`` (the plate cell)."""
    kl = _read(layout)
    cell = kl.cell(child)
    parents = [kl.cell(i).name for i in cell.each_parent_cell()]
    if len(parents) != 1:
        raise ValueError(f"cell {child!r} is placed by {len(parents)} cells, not by the plate")
    return parents[0]


def _die_problems(layout, info):
    """The top cell must place the plate cell on the die lattice."""
    dies = info.dies
    got = tile_placements(layout, info.top_cell, info.plate_cell)
    (nx, ny), pitch, (ox, oy) = dies.dies, dies.pitch_nm, dies.origin_nm
    want = sorted((ox + i * pitch, oy + j * pitch) for i in range(nx) for j in range(ny))
    if got != want:
        return [f"the plate is not placed on the {nx} x {ny} die lattice"]
    return []
