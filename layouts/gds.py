"""The GDSII library of a phase plate: one tile cell, one AREF, clipped edge tiles.

Units: user unit 1 um, database unit 1 nm (``unit=1e-6, precision=1e-9``).
Every vertex is an integer number of nanometres and every pattern vertex lies
on the mask pixel grid. Pixel (row r, col c) of the tile covers
x in [c p, (c+1) p], y in [(N-1-r) p, (N-r) p] relative to the tile origin,
so row 0 is the top edge, viewed onto the patterned surface. The tiled array
is centred on the plate: its lower-left corner is ``-(tiles * N * p // 2)`` nm.
The whole tiles are one AREF; the clear aperture around them is completed by at
most eight edge cells, the tile clipped at whole pixels (``layouts.plate_plan``),
placed where the periodic pattern continues. With several dies the plate is its
own cell, placed by one AREF in the top cell, the dicing lanes on a
documentation layer.
"""

import re
from dataclasses import dataclass, field
from datetime import datetime

import gdstk
import numpy as np

from layouts.marks import (
    DEFAULT_FEATURE_NM,
    OUTLINE_LAYER,
    MarkLayer,
    mark_rules,
    marks_and_labels,
    monitor_plan,
    plate_half_size_nm,
)
from layouts.plate_plan import (
    DEFAULT_LANE_NM,
    DICING_LANE_LAYER,
    DieLayout,
    PlatePattern,
    array_origin_nm,
    edge_pieces,
    lane_rectangles_nm,
    plan_dies,
    plan_pattern,
)
from layouts.rectangles import bitmap_rectangles, rectangle_corners_nm

# Pinned so that the same design gives a byte-identical file.
GDS_TIMESTAMP = datetime(2020, 1, 1)
LIBRARY_NAME = "DOEFAB"
GDS_UNIT = 1e-6
GDS_PRECISION = 1e-9
MAX_POLYGON_VERTICES = 8190


@dataclass(frozen=True)
class PlateLayout:
    """What was drawn: cell names, placement and per-layer statistics."""

    top_cell: str
    tile_cell: str
    pixel_pitch_nm: int
    tile_pixels: int
    tiles: tuple[int, int]
    array_origin_nm: tuple[int, int]
    polygon_counts: dict = field(default_factory=dict)  # mask name -> rectangles in the tile
    mark_layers: tuple = ()
    plate_half_nm: int = 0  # half the plate's outer size (layer 200's outer edge); 0: no marks
    mark_rules: object = None  # layouts.marks.MarkRules of the marks drawn
    pads: tuple = ()  # layouts.monitors.Pad: etch-depth monitor pads
    cd_structures: tuple = ()  # layouts.monitors.CDStructure: CD test gratings
    plate: PlatePattern | None = None  # whole tiles, edge pixels, clear aperture
    edge_cells: tuple = ()  # (cell name, layouts.plate_plan.EdgePiece) of the clipped tiles
    plate_cell: str = ""  # the cell of one plate: top_cell with one die
    dies: DieLayout | None = None
    frame_half_nm: int = 0  # half the clear-aperture frame drawn on layer 200


def cell_name(design_name, suffix):
    """Return a GDS-safe cell name (letters, digits, underscore; at most 32 characters)."""
    base = re.sub(r"[^A-Za-z0-9_]", "_", str(design_name)) or "DOE"
    return f"{base[: 32 - len(suffix) - 1]}_{suffix}"


def tile_polygons(masks, pitch_nm, window=None):
    """Return the gdstk rectangles of every mask of one tile, and their counts.

    Parameters
    ----------
    masks : list of fab.package.masks.Mask
        Bitmaps (N, N) bool, row 0 at the top.
    pitch_nm : int
        Mask pixel pitch.
    window : ((c0, c1), (r0, r1)) or None
        Draw only the pixels of these columns and rows, at their place in the tile.

    Returns
    -------
    polygons : list of gdstk.Polygon
    counts : dict
        Mask name -> number of rectangles.
    """
    polys, counts = [], {}
    for mk in masks:
        n = mk.bitmap.shape[0]
        (c0, c1), (r0, r1) = window or ((0, n), (0, n))
        rects = bitmap_rectangles(mk.bitmap[r0:r1, c0:c1]) + np.array([c0, r0, c0, r0])
        corners = rectangle_corners_nm(rects, n, pitch_nm) / 1000.0
        counts[mk.name] = len(corners)
        polys += [
            gdstk.rectangle((x0, y0), (x1, y1), layer=mk.gds_layer, datatype=mk.gds_datatype)
            for x0, y0, x1, y1 in corners.tolist()
        ]
    return polys, counts


def build_library(
    masks, pitch_nm, tiles, design_name, aperture_nm=None, marks=True, flat=False, grid_nm=1,
    feature_nm=DEFAULT_FEATURE_NM, mode="glass", dies=(1, 1), lane_nm=DEFAULT_LANE_NM,
):  # fmt: skip
    """Build the plate's GDS library.

    Parameters
    ----------
    masks : list of fab.package.masks.Mask
        All masks of the tile, each on its own GDS layer.
    pitch_nm : int
        Mask pixel pitch in nm (integer: the 1 nm grid).
    tiles : (int, int)
        Whole tiles along x (columns) and along y (rows).
    design_name : str
        Used for cell names and mask labels.
    aperture_nm : int or None
        Clear aperture (full width, nm); marks go outside it. Default: the tiled size.
    marks : bool
        Draw alignment marks, labels and the outline.
    flat : bool
        Copy every tile's polygons into the top cell instead of one AREF (for
        benchmarks only: the file grows by the number of tiles).
    grid_nm : int
        The mask writer's grid (a divisor of ``pitch_nm``): the array's origin and
        every mark and label vertex are snapped to it.
    feature_nm : int
        The design's feature size: every mark, label stroke and monitor, and every gap
        between them, is at least this wide.
    mode : str
        "fill" (clipped edge tiles complete the clear aperture), "shrink" (whole
        tiles only, the clear-aperture frame shrunk to them) or "glass" (whole tiles
        only inside the given frame, the default here; ``doefab fab`` fills); see
        :func:`layouts.plate_plan.plan_pattern`.
    dies : (int, int)
        Plates along x and y on the substrate (one AREF of the plate cell).
    lane_nm : int
        Dicing lane width between dies.

    Returns
    -------
    lib : gdstk.Library
    info : PlateLayout
    """
    pitch_nm = int(pitch_nm)
    nx, ny = (int(t) for t in tiles)
    n = masks[0].bitmap.shape[0]
    tile_um = n * pitch_nm / 1000.0
    if pitch_nm % grid_nm:
        raise ValueError(f"pitch {pitch_nm} nm is not on the {grid_nm} nm grid")
    x0, y0 = array_origin_nm((nx, ny), n, pitch_nm, grid_nm)
    half = max(nx, ny) * n * pitch_nm // 2 + 1
    design_ap = int(aperture_nm) if aperture_nm is not None else max(nx, ny) * n * pitch_nm
    plate = plan_pattern(n, pitch_nm, (nx, ny), (x0, y0), design_ap, mode)
    lib = gdstk.Library(LIBRARY_NAME, unit=GDS_UNIT, precision=GDS_PRECISION)
    several = tuple(dies) != (1, 1)
    top_name, tile_name = cell_name(design_name, "TOP"), cell_name(design_name, "TILE")
    plate_name = cell_name(design_name, "PLATE") if several else top_name
    top = lib.new_cell(plate_name)
    polys, counts = tile_polygons(masks, pitch_nm)
    tile = lib.new_cell(tile_name)
    tile.add(*polys)
    top.add(_aref(tile, (x0, y0), (nx, ny), tile_um))
    edges = _edge_cells(lib, top, masks, plate, design_name)
    if flat:
        top.flatten()  # copies every tile's polygons into the top cell (C++ side)
        for cell in [tile] + [lib[name] for name, _ in edges]:
            lib.remove(cell)
    frame_half = max(half, plate.aperture_nm // 2) if mode != "shrink" else half
    rules = mark_rules(feature_nm, grid_nm)
    marks_half = frame_half
    mark_layers, marks_info = (), {}
    if marks:
        marks_half = _marks_half(masks, frame_half, plate, design_name, rules)
        mark_layers, marks_info = _marks(top, masks, (marks_half, frame_half), design_name, rules)
    die_layout = plan_dies(dies, 2 * plate_half_size_nm(marks_half, rules), lane_nm, grid_nm)
    if several:
        mark_layers = (*mark_layers, _substrate(lib.new_cell(top_name), top, die_layout))
    info = PlateLayout(
        top_cell=top_name,
        tile_cell=tile_name,
        pixel_pitch_nm=pitch_nm,
        tile_pixels=n,
        tiles=(nx, ny),
        array_origin_nm=(x0, y0),
        polygon_counts=counts,
        mark_layers=tuple(mark_layers),
        **marks_info,
        plate=plate,
        edge_cells=tuple(edges) if not flat else (),
        plate_cell=plate_name,
        dies=die_layout,
        frame_half_nm=frame_half,
    )
    return lib, info


def _edge_cells(lib, plate_cell, masks, plate, design_name):
    """Add the clipped edge cells of ``plate`` and place them; return [(name, EdgePiece)]."""
    edges, tile_um = [], plate.tile_nm / 1000.0
    for piece in edge_pieces(plate):
        cell = lib.new_cell(cell_name(design_name, piece.suffix))
        cell.add(*tile_polygons(masks, plate.pixel_pitch_nm, (piece.columns, piece.rows))[0])
        plate_cell.add(_aref(cell, piece.origin_nm, piece.repeat, tile_um))
        edges.append((cell.name, piece))
    return edges


def _substrate(top, plate_cell, die_layout):
    """Place the plate cell on the die lattice in ``top`` with the dicing lanes; return the
    lanes' layer (a drawing layer like the outline's: the order sheet says not to write it)."""
    top.add(_aref(plate_cell, die_layout.origin_nm, die_layout.dies, die_layout.pitch_nm / 1000))
    top.add(*(_lane(r) for r in lane_rectangles_nm(die_layout)))
    return MarkLayer(DICING_LANE_LAYER, 0, "dicing lanes and substrate edge (not etched)", None)


def _marks_half(masks, frame_half, plate, design_name, rules):
    """Return the half width to draw the marks round: the frame's, or more when the
    clipped edge pixels (which reach past the frame by up to a pixel) would come
    within a feature size of a mark (a coarse pixel's can)."""
    reach = max(abs(v) for v in plate.extent_nm())
    half, f, g = frame_half, rules.feature_nm, rules.grid_nm
    for _ in range(4):
        polys, _ = marks_and_labels(masks, half, design_name, f, g, frame_half_nm=frame_half)
        gap = min(_bbox_gap(p.bounding_box(), reach) for p in polys if p.layer != OUTLINE_LAYER)
        if gap >= f:
            break
        half += -(-(f - gap) // g) * g
    return int(half)


def _bbox_gap(box, half_nm):
    """Euclidean distance (nm) from a bounding box (um) to the square |x|, |y| <= half_nm:
    at most the distance from the polygon inside the box."""
    (x0, y0), (x1, y1) = box
    dx = max(0.0, x0 * 1000 - half_nm, -half_nm - x1 * 1000)
    dy = max(0.0, y0 * 1000 - half_nm, -half_nm - y1 * 1000)
    return int(np.floor(np.hypot(dx, dy)))


def _marks(cell, masks, halves, design_name, rules):
    """Draw the marks, labels and monitors around a square of half width ``halves[0]``
    (the pattern's reach) and the clear-aperture frame of half width ``halves[1]`` into
    ``cell``; return (mark layers, the PlateLayout's marks keys)."""
    grid_nm, (half, frame_half) = rules.grid_nm, halves
    polys, layers = marks_and_labels(
        masks, half, design_name, rules.feature_nm, grid_nm, frame_half_nm=frame_half
    )
    cell.add(*(_snapped(p, grid_nm) for p in polys))
    pads, cds = monitor_plan(masks, half, rules)
    info = {
        "plate_half_nm": plate_half_size_nm(half, rules),
        "mark_rules": rules,
        "pads": pads,
        "cd_structures": cds,
    }
    return layers, info


def _aref(cell, origin_nm, repeat, spacing_um):
    """A reference to ``cell`` at ``origin_nm``, repeated (columns, rows) at ``spacing_um``."""
    cols, rows = repeat
    return gdstk.Reference(
        cell, origin=(origin_nm[0] / 1000.0, origin_nm[1] / 1000.0), columns=cols, rows=rows,
        spacing=(spacing_um, spacing_um),
    )  # fmt: skip


def _lane(rect_nm):
    """A dicing lane (or the substrate's edge) on the documentation layer."""
    x0, y0, x1, y1 = (v / 1000.0 for v in rect_nm)
    return gdstk.rectangle((x0, y0), (x1, y1), layer=DICING_LANE_LAYER, datatype=0)


def _snapped(polygon, grid_nm):
    """Return ``polygon`` (um) with its vertices on the ``grid_nm`` grid (marks are drawn
    on the 1 nm grid; a vertex moves by at most half the grid)."""
    if grid_nm == 1:
        return polygon
    points = np.round(polygon.points * 1000 / grid_nm) * grid_nm / 1000
    return gdstk.Polygon(points, layer=polygon.layer, datatype=polygon.datatype)


def write_gds(lib, path):
    """Write the library as GDSII with the pinned timestamp (byte-identical for the same design)."""
    lib.write_gds(str(path), max_points=MAX_POLYGON_VERTICES, timestamp=GDS_TIMESTAMP)


def write_oasis(gds_path, oas_path):
    """Convert a GDS file to OASIS with KLayout (same geometry, smaller file)."""
    import klayout.db as kdb

    layout = kdb.Layout()
    layout.read(str(gds_path))
    opts = kdb.SaveLayoutOptions()
    opts.format = "OASIS"
    opts.oasis_write_cell_bounding_boxes = False
    opts.oasis_write_std_properties = 0
    layout.write(str(oas_path), opts)


def max_vertices(lib):
    """Return the largest vertex count of any polygon in the library."""
    counts = [len(p.points) for c in lib.cells for p in c.polygons]
    return int(np.max(counts)) if counts else 0
