"""Process monitors outside the clear aperture: etch-depth pads and CD test structures.

Etch-depth pads: one clear (etched) square per etch code c = 1 .. 2**m - 1, drawn on
every mask whose step count is a bit of c (the masks of ``fab.package.masks``: mask j
etches ``steps`` = 2**(m-1-j) level steps). After all etches the pad's floor lies
c level steps below the unetched top, the depth of level L-1-c, so a stylus
profilometer run from the surrounding glass across each pad reads every single
etch and every combination that makes a level.

CD structures: per mask, gratings of equal lines and spaces (a line = a drawn,
etched stripe) at 1x, 1.5x and 2x the mark feature size, one with vertical lines
and one with horizontal lines per width, for measuring the printed line width
in both directions.

Every item sits in its own square slot; the slots fill free zones of the plate
(given by :mod:`layouts.marks`) in order, and a plate without room for them all is
refused. Coordinates are integer nanometres on the write grid.
"""

from dataclasses import dataclass

PAD_NM = 250_000  # pad side: at least the 200 um a stylus scan needs, with a margin
SLOT_GAP_NM = 50_000  # at least this clearance between slots (and more for coarse features)
CD_FACTORS = ((1, 1), (3, 2), (2, 1))  # line width = feature x num / den
CD_LINES = 5  # lines per grating


@dataclass(frozen=True)
class Pad:
    """An etch-depth monitor pad.

    Attributes
    ----------
    code : int
        Level steps etched at the pad (the sum of its masks' steps).
    centre_nm : tuple of int
        (x, y) of the pad's centre.
    size_nm : int
        Side of the square.
    layers : tuple of int
        GDS layers (masks) that etch it.
    """

    code: int
    centre_nm: tuple[int, int]
    size_nm: int
    layers: tuple[int, ...]


@dataclass(frozen=True)
class CDStructure:
    """A grating of equal lines and spaces on one mask.

    Attributes
    ----------
    layer : int
        GDS layer (mask).
    width_nm : int
        Line width = space width.
    lines : int
        Number of drawn (etched) lines.
    orientation : str
        "vertical" (lines along y, width measured along x) or "horizontal".
    centre_nm : tuple of int
        (x, y) of the grating's centre.
    length_nm : int
        Length of each line.
    """

    layer: int
    width_nm: int
    lines: int
    orientation: str
    centre_nm: tuple[int, int]
    length_nm: int


def cd_widths_nm(feature_nm, grid_nm):
    """Return the CD structures' line widths: 1x, 1.5x and 2x the feature, up on the grid."""
    return tuple(-(-feature_nm * num // (den * grid_nm)) * grid_nm for num, den in CD_FACTORS)


def slot_geometry(feature_nm, grid_nm):
    """Return (slot side, gap between slots) in nm for this feature size."""
    span = (2 * CD_LINES - 1) * max(cd_widths_nm(feature_nm, grid_nm))
    side = max(PAD_NM, span)
    gap = max(SLOT_GAP_NM, 2 * feature_nm)
    return _up(side, grid_nm), _up(gap, grid_nm)


def _up(v, grid):
    return -(-int(v) // grid) * grid


def monitor_count(n_masks):
    """Return the number of slots the monitors of ``n_masks`` masks take."""
    return (2**n_masks - 1) + n_masks * 2 * len(CD_FACTORS)


def slots(zones, count, side, gap, grid_nm):
    """Return ``count`` slot centres (nm, on the grid) filling ``zones`` in order.

    Each zone (x0, y0, x1, y1) is filled row by row from its top-left; slots keep
    ``gap`` between each other and stay inside the zone. Raises ValueError when the
    zones hold fewer than ``count`` slots.
    """
    out = []
    step = side + gap
    for x0, y0, x1, y1 in zones:
        cols, rows = (x1 - x0 + gap) // step, (y1 - y0 + gap) // step
        if cols < 1 or rows < 1:
            continue
        for r in range(rows):
            for c in range(cols):
                left = _up(x0 + c * step, grid_nm)
                top = (y1 - r * step) // grid_nm * grid_nm
                if left + side > x1 or top - side < y0:
                    continue
                half = side // grid_nm // 2 * grid_nm
                out.append((left + half, top - half))
    if len(out) < count:
        raise ValueError(f"room for {len(out)} of {count}")
    return out[:count]


def monitor_plan(masks, centres, side, feature_nm, grid_nm):
    """Return (pads, cd_structures) placed on the slot ``centres`` (pads first).

    Parameters
    ----------
    masks : list
        Objects with ``gds_layer`` and ``steps`` (fab.package.masks.Mask).
    centres : list of (int, int)
        At least :func:`monitor_count` slot centres.
    side : int
        Slot side (nm): the pads' size.
    """
    m = len(masks)
    pads = []
    for code in range(1, 2**m):
        layers = tuple(mk.gds_layer for mk in masks if code & mk.steps)
        pads.append(Pad(code, centres[code - 1], side, layers))
    cds, k = [], 2**m - 1
    half_side = side // grid_nm // 2 * grid_nm
    for mk in masks:
        for w in cd_widths_nm(feature_nm, grid_nm):
            for orientation in ("vertical", "horizontal"):
                cds.append(
                    CDStructure(mk.gds_layer, w, CD_LINES, orientation, centres[k], 2 * half_side)
                )
                k += 1
    return tuple(pads), tuple(cds)


def monitor_rectangles(pads, cds, grid_nm=1):
    """Return the monitors as (x0, y0, x1, y1, layer) rectangles in nm (on the grid)."""
    out = []
    for pad in pads:
        cx, cy = pad.centre_nm
        h0 = pad.size_nm // grid_nm // 2 * grid_nm
        for layer in pad.layers:
            out.append((cx - h0, cy - h0, cx - h0 + pad.size_nm, cy - h0 + pad.size_nm, layer))
    for cd in cds:
        cx, cy = cd.centre_nm
        w, n, half = cd.width_nm, cd.lines, cd.length_nm // 2
        start = -((2 * n - 1) * (w // grid_nm) // 2) * grid_nm
        for i in range(n):
            a = start + 2 * i * w
            if cd.orientation == "vertical":
                out.append((cx + a, cy - half, cx + a + w, cy + half, cd.layer))
            else:
                out.append((cx - half, cy + a, cx + half, cy + a + w, cd.layer))
    return out
