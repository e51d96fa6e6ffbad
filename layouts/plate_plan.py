"""Where a plate's pattern lies: whole tiles, the clipped edge tiles, the dies on a substrate.

The pattern of a plate is the infinite periodic continuation of the tile restricted
to the clear aperture, clipped at whole mask pixels. Pixel columns and rows are
counted from the whole-tile array: column c covers x in [x0 + c p, x0 + (c+1) p]
(x0 the array's left edge) and row r covers y in [top - (r+1) p, top - r p] (top the
array's upper edge, rows grow downwards as in a level map), for every integer c and
r, so column c shows tile column c mod N. The clip keeps every pixel that overlaps
the aperture (:func:`edge_pixels`): the pattern covers the whole clear aperture and
reaches past its edge by less than one pixel. No pixel is cut, so no feature is
narrower than a pixel.

All lengths are integer nanometres.
"""

from dataclasses import dataclass

DICING_LANE_LAYER = 201  # dicing lanes and the substrate outline (documentation, not etched)
DEFAULT_LANE_NM = 200_000  # dicing lane width between dies


def array_origin_nm(tiles, tile_pixels, pitch_nm, grid_nm=1):
    """Return the lower-left corner (nm, integers) of a tiles[0] x tiles[1] array centred
    on 0, on the ``grid_nm`` grid (an odd number of odd-sized tiles would put it half a
    pitch off, and every vertex of a 5 nm design off its grid)."""
    nx, ny = tiles
    size = int(tile_pixels) * int(pitch_nm)
    return (-(nx * size // 2 // grid_nm * grid_nm), -(ny * size // 2 // grid_nm * grid_nm))


@dataclass(frozen=True)
class PlatePattern:
    """The pattern of one plate.

    Attributes
    ----------
    tile_pixels : int
        N.
    pixel_pitch_nm : int
        p.
    tiles : (int, int)
        Whole tiles along x and y (the AREF).
    array_origin_nm : (int, int)
        Lower-left corner of the whole-tile array.
    edge_pixels : (int, int, int, int)
        Pixel columns left and right of the array, pixel rows below and above it,
        that continue the periodic pattern to the clear aperture (all 0 with whole
        tiles only).
    aperture_nm : int
        Full width of the clear-aperture frame drawn (layer 200): the design's
        aperture, or the whole-tile array when the frame shrinks to the pattern.
    design_aperture_nm : int
        The design's clear aperture (``aperture_mm``).
    """

    tile_pixels: int
    pixel_pitch_nm: int
    tiles: tuple[int, int]
    array_origin_nm: tuple[int, int]
    edge_pixels: tuple[int, int, int, int]
    aperture_nm: int
    design_aperture_nm: int

    @property
    def tile_nm(self):
        return self.tile_pixels * self.pixel_pitch_nm

    def pixel_span(self):
        """Return ((c0, c1), (r0, r1)): the pattern's columns c0 <= c < c1 and rows r0 <= r < r1."""
        (nx, ny), n = self.tiles, self.tile_pixels
        left, right, bottom, top = self.edge_pixels
        return (-left, nx * n + right), (-top, ny * n + bottom)

    def extent_nm(self):
        """Return (x0, y0, x1, y1): the rectangle the pattern covers."""
        (c0, c1), (r0, r1) = self.pixel_span()
        p, (x0, y0) = self.pixel_pitch_nm, self.array_origin_nm
        top = y0 + self.tiles[1] * self.tile_nm
        return (x0 + c0 * p, top - r1 * p, x0 + c1 * p, top - r0 * p)

    def patterned_fraction(self):
        """Return the fraction of the clear-aperture frame's area that the pattern covers."""
        a = self.aperture_nm / 2
        x0, y0, x1, y1 = self.extent_nm()
        w = max(0.0, min(x1, a) - max(x0, -a))
        h = max(0.0, min(y1, a) - max(y0, -a))
        return w * h / float(self.aperture_nm) ** 2

    def aperture_light_kept(self):
        """Return the fraction of the design aperture's area (its light) the frame passes."""
        return min(1.0, (self.aperture_nm / self.design_aperture_nm) ** 2)

    def as_dict(self):
        """The manifest's ``plate`` record (JSON-ready)."""
        return {
            "tiles": list(self.tiles),
            "array_origin_nm": list(self.array_origin_nm),
            "edge_pixels": dict(
                zip(("left", "right", "bottom", "top"), self.edge_pixels, strict=True)
            ),
            "pattern_extent_nm": list(self.extent_nm()),
            "clear_aperture_nm": self.aperture_nm,
            "design_aperture_nm": self.design_aperture_nm,
            "patterned_fraction": self.patterned_fraction(),
            "aperture_light_kept": self.aperture_light_kept(),
        }


def edge_pixels(array_lo_nm, array_hi_nm, half_aperture_nm, pitch_nm):
    """Return (below, above): whole pixels of the periodic pattern outside [lo, hi] that
    overlap (-a, a), on each side (a pixel that only touches the edge is left out)."""
    p, a = int(pitch_nm), half_aperture_nm
    below = max(0, -(-(array_lo_nm + a) // p))  # pixels whose right edge lies above -a
    above = max(0, -(-(a - array_hi_nm) // p))
    return below, above


def plan_pattern(tile_pixels, pitch_nm, tiles, origin_nm, design_aperture_nm, mode="fill"):
    """Return the :class:`PlatePattern` of a plate.

    ``mode``: "fill" completes the clear aperture with clipped edge tiles; "shrink"
    places whole tiles only and shrinks the clear-aperture frame to them; "glass"
    places whole tiles only and keeps the design's frame (plain glass around them).
    """
    n, p = int(tile_pixels), int(pitch_nm)
    nx, ny = (int(t) for t in tiles)
    x0, y0 = (int(v) for v in origin_nm)
    tile = n * p
    design_ap = int(design_aperture_nm)
    aperture = design_ap
    edges = (0, 0, 0, 0)
    if mode == "fill":
        a = design_ap // 2
        left, right = edge_pixels(x0, x0 + nx * tile, a, p)
        bottom, top = edge_pixels(y0, y0 + ny * tile, a, p)
        if max(left, right, bottom, top) > n:
            raise ValueError(
                f"{nx} x {ny} whole tiles leave more than a tile of the {design_ap / 1e6:g} mm "
                "aperture on one side; place more whole tiles"
            )
        edges = (left, right, bottom, top)
    elif mode == "shrink":
        aperture = min(design_ap, max(nx, ny) * tile)
    elif mode != "glass":
        raise ValueError(f"unknown plate mode {mode!r}")
    return PlatePattern(n, p, (nx, ny), (x0, y0), edges, aperture, design_ap)


@dataclass(frozen=True)
class DieLayout:
    """Plates (dies) on a substrate, with dicing lanes between them.

    Attributes
    ----------
    dies : (int, int)
        Dies along x and y (one AREF of the plate cell).
    lane_nm : int
        Dicing lane width; half a lane runs round the substrate's edge.
    plate_nm : int
        One plate's outer size (square).
    pitch_nm : int
        Die pitch: plate plus lane.
    origin_nm : (int, int)
        Centre of the lower-left die (the AREF's origin, the plate cell being centred).
    """

    dies: tuple[int, int]
    lane_nm: int
    plate_nm: int
    pitch_nm: int
    origin_nm: tuple[int, int]

    @property
    def substrate_nm(self):
        """(width, height) of the substrate: the dies at their pitch."""
        return (self.dies[0] * self.pitch_nm, self.dies[1] * self.pitch_nm)

    def as_dict(self):
        """The manifest's ``dies`` record (JSON-ready; the order sheet reads it)."""
        return {
            "nx": self.dies[0],
            "ny": self.dies[1],
            "pitch_nm": [self.pitch_nm, self.pitch_nm],
            "lane_nm": self.lane_nm,
            "plate_size_nm": [self.plate_nm, self.plate_nm],
            "substrate_size_nm": list(self.substrate_nm),
            "dicing_lane_layer": DICING_LANE_LAYER,
        }


def plan_dies(dies, plate_nm, lane_nm=DEFAULT_LANE_NM, grid_nm=1):
    """Return the :class:`DieLayout` of ``dies`` (nx, ny) plates of ``plate_nm`` each."""
    nx, ny = (int(d) for d in dies)
    lane = int(lane_nm)
    if nx < 1 or ny < 1:
        raise ValueError(f"dies must be at least 1 x 1, got {nx} x {ny}")
    if lane < 0:
        raise ValueError(f"the dicing lane must be >= 0 um, got {lane / 1000:g}")
    pitch = -(-(int(plate_nm) + lane) // grid_nm) * grid_nm
    origin = tuple(-((d - 1) * pitch // 2 // grid_nm * grid_nm) for d in (nx, ny))
    return DieLayout((nx, ny), lane, int(plate_nm), pitch, origin)


def lane_rectangles_nm(die_layout):
    """Return the dicing lanes and the substrate outline as (x0, y0, x1, y1) nm rectangles.

    Lanes run between neighbouring dies (full lane width) and round the edge (half a
    lane), so that every die sits in a cell of one pitch.
    """
    (nx, ny), pitch, lane = die_layout.dies, die_layout.pitch_nm, die_layout.lane_nm
    ox, oy = die_layout.origin_nm
    left, bottom = ox - pitch // 2, oy - pitch // 2
    right, top = left + nx * pitch, bottom + ny * pitch
    half = lane // 2
    rects = []
    for i in range(nx + 1):
        x = left + i * pitch
        rects.append((max(left, x - half), bottom, min(right, x + half), top))
    for j in range(ny + 1):
        y = bottom + j * pitch
        rects.append((left, max(bottom, y - half), right, min(top, y + half)))
    return [r for r in rects if r[0] < r[2] and r[1] < r[3]]


@dataclass(frozen=True)
class EdgePiece:
    """A clipped edge tile: one cell holding the tile's pixels in a window, placed where
    the periodic pattern continues past the whole-tile array.

    The cell's polygons keep the tile's coordinates (pixel (r, c) at the same place as
    in the tile cell), so a placement's origin is the origin of the virtual tile it
    clips, on the array's lattice.

    Attributes
    ----------
    suffix : str
        Cell name suffix, E_<x><y> with x in L, W, R (left strip, whole width, right
        strip) and y in B, W, T.
    columns, rows : (int, int)
        Tile columns c0 <= c < c1 and rows r0 <= r < r1 kept (row 0 at the top).
    origin_nm : (int, int)
        Origin of the first placement.
    repeat : (int, int)
        Placements along x and y at the tile pitch (an AREF when either exceeds 1).
    """

    suffix: str
    columns: tuple[int, int]
    rows: tuple[int, int]
    origin_nm: tuple[int, int]
    repeat: tuple[int, int]

    def placements(self, tile_nm):
        """Every placement's origin (nm)."""
        (x, y), (cx, cy) = self.origin_nm, self.repeat
        return [(x + i * tile_nm, y + j * tile_nm) for i in range(cx) for j in range(cy)]


def edge_pieces(plate):
    """Return the :class:`EdgePiece` s of a plate (at most 8 cells; none with whole tiles only)."""
    n, t = plate.tile_pixels, plate.tile_nm
    (nx, ny), (x0, y0) = plate.tiles, plate.array_origin_nm
    left, right, bottom, top = plate.edge_pixels
    # (name, tile window, index of the first virtual tile, count) along each axis
    xs = [("L", (n - left, n), -1, 1), ("W", (0, n), 0, nx), ("R", (0, right), nx, 1)]
    ys = [("T", (n - top, n), -1, 1), ("W", (0, n), 0, ny), ("B", (0, bottom), ny, 1)]
    pieces = []
    for yname, rows, jy, cy in ys:
        for xname, cols, ix, cx in xs:
            if xname == yname == "W" or cols[0] >= cols[1] or rows[0] >= rows[1]:
                continue
            # virtual tile jy, counted downwards from the array's top tile
            origin = (x0 + ix * t, y0 + (ny - 1 - jy - (cy - 1)) * t)
            pieces.append(EdgePiece(f"E_{xname}{yname}", cols, rows, origin, (cx, cy)))
    return pieces
