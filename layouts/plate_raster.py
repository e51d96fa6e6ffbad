"""The whole plate as written, read back with KLayout: its level map over the clear aperture.

Every mask layer of the plate cell (AREF, clipped edge cells and all, flattened by
KLayout's recursive shape iterator) is sampled at the centres of the mask pixel grid
that the whole-tile array sits on; the level of a pixel follows from the masks that
etch it (level = L - 1 - etched steps, ``fab.package.masks``). Comparing it with the
tile repeated without end gives the fraction of the clear aperture that carries the
design's periodic pattern: plain glass matches it only where the tile happens to be
unetched.
"""

import numpy as np

from layouts.readback import load


def plate_levels(gds_path, cell, masks, n_levels, pitch_nm, origin_nm, columns, rows):
    """Return the levels written at the pixel centres of a window of the array's grid.

    Parameters
    ----------
    gds_path : path or layouts.readback.Loaded
    cell : str
        The plate cell.
    masks : list of fab.package.masks.Mask
        Their layers and etch steps.
    n_levels : int
    pitch_nm : int
    origin_nm : (int, int)
        The array origin x0 and its top edge (y of the array's row 0 top), nm.
    columns, rows : (int, int)
        Pixel columns c0 <= c < c1 (from x0) and rows r0 <= r < r1 (downwards from the top).

    Returns
    -------
    (r1 - r0, c1 - c0) uint8, row 0 at the top.
    """
    import klayout.db as kdb

    layout = load(gds_path).layout
    top = layout.cell(cell)
    if top is None:
        raise ValueError(f"no cell {cell!r}")
    p = int(pitch_nm)
    (c0, c1), (r0, r1) = columns, rows
    w, h = c1 - c0, r1 - r0
    x0, ytop = origin_nm
    # the raster's lower-left pixel is the window's bottom row, first column
    corner = kdb.Point(x0 + c0 * p + p // 2 - 1, ytop - r1 * p + p // 2 - 1)
    etched = np.zeros((h, w), dtype=np.int64)
    for mk in masks:
        li = layout.find_layer(mk.gds_layer, mk.gds_datatype)
        if li is None:
            continue
        region = kdb.Region(top.begin_shapes_rec(li))
        area = np.array(region.rasterize(corner, kdb.Vector(p, p), kdb.Vector(2, 2), w, h))
        etched += np.flipud(area > 0) * mk.steps
    return (n_levels - 1 - etched).astype(np.uint8)


def aperture_match(gds_path, cell, masks, levels, plate, window_nm=None):
    """Return (fraction, written, periodic): how much of the clear aperture carries the
    tile's periodic pattern, and the two level maps compared.

    The pixel centres inside the clear aperture (``plate.aperture_nm`` wide, centred on
    0, or ``window_nm`` wide) are compared; ``plate`` is a
    :class:`layouts.plate_plan.PlatePattern`.
    """
    n, p = plate.tile_pixels, plate.pixel_pitch_nm
    x0, y0 = plate.array_origin_nm
    ytop = y0 + plate.tiles[1] * plate.tile_nm
    a = (window_nm or plate.aperture_nm) / 2
    # pixel c's centre x0 + (c + 1/2) p inside (-a, a); pixel r's centre ytop - (r + 1/2) p
    c0, c1 = int(np.ceil((-a - x0) / p - 0.5)), int(np.floor((a - x0) / p - 0.5)) + 1
    r0, r1 = int(np.ceil((ytop - a) / p - 0.5)), int(np.floor((ytop + a) / p - 0.5)) + 1
    n_levels = 2 ** len(masks)
    written = plate_levels(gds_path, cell, masks, n_levels, p, (x0, ytop), (c0, c1), (r0, r1))
    periodic = np.asarray(levels)[np.ix_(np.arange(r0, r1) % n, np.arange(c0, c1) % n)]
    return float(np.mean(written == periodic)), written, periodic
