"""Alignment marks, verniers, text labels and the plate outline (outside the aperture).

Every later mask is aligned to the first (deepest) one. Per later mask j the
first mask carries a cross and two vernier combs (pitch 10 um); mask j carries
the box around the cross and the matching combs at pitch 9.8 um, so the bar
pair that lines up reads the overlay error in 0.2 um steps (bar k coincides
for an offset of k * 0.2 um, k = -10 .. 10). Marks and labels are drawn on the
pattern layer of the mask they belong to (``MARK_LAYER_OFFSET`` = 0): they are
etched in that step, which is what makes them visible to the next alignment,
each photomask is one GDS layer with nothing to merge, and a mask that etches
no pixel of the tile still has its layer in the file. The outline of the plate
and of the clear aperture sits on ``OUTLINE_LAYER``, a drawing layer that is not
etched.

All geometry is built in integer nanometres and returned as gdstk polygons in
micrometres (the library's user unit), so every vertex lies on the 1 nm grid.
gdstk is imported where polygons are made: design validation (``check_marks_fit``)
runs on machines that only learn PSFs, without the GDS writer.
"""

import unicodedata
from dataclasses import dataclass

import numpy as np

# One named place for the mark geometry (nm).
MARK_LAYER_OFFSET = 0  # marks of the mask on GDS layer L go to layer L + offset
OUTLINE_LAYER = 200  # plate edge and clear-aperture frame (documentation, not etched)
PLATE_MARGIN_NM = 1_500_000  # plate edge = aperture edge + 1.5 mm on every side
MARK_RING_NM = 750_000  # mark blocks centred 0.75 mm outside the aperture edge
BLOCK_STEP_NM = 600_000  # spacing of the blocks of successive masks along x (at most)
CROSS_ARM_NM = 100_000  # cross: 100 um long arms
CROSS_WIDTH_NM = 10_000  # ... 10 um wide
BOX_INNER_NM = 120_000  # box: 120 um inside (10 um clearance to the cross arms)
BOX_OUTER_NM = 160_000  # ... 160 um outside
VERNIER_PITCH_REF_NM = 10_000  # first mask's comb
VERNIER_PITCH_NM = 9_800  # later mask's comb: 0.2 um reading resolution
VERNIER_BARS = 10  # bars k = -10 .. 10 -> reads +-2 um
VERNIER_BAR_WIDTH_NM = 4_000
VERNIER_BAR_LENGTH_NM = 30_000
VERNIER_CENTRE_EXTRA_NM = 10_000  # the k = 0 bars are longer, to find the scale's zero
VERNIER_OFFSET_NM = 250_000  # comb pairs 250 um from the cross (below it and left of it)
LABEL_HEIGHT_NM = 150_000  # at most; smaller when many masks share the label band
LABEL_GAP_NM = 50_000  # clearance of the labels to the aperture frame and the mark blocks
OUTLINE_WIDTH_NM = 20_000
LABEL_BIAS = 0.013  # glyph outline grown by this many text heights (joins corner touches)


@dataclass(frozen=True)
class MarkLayer:
    """A non-pattern GDS layer and what it is for."""

    gds_layer: int
    gds_datatype: int
    purpose: str
    merge_with_mask: str | None


def _um(v):
    return v / 1000.0


def _rect(x0, y0, x1, y1, layer):
    """An axis-aligned rectangle from integer-nm corners."""
    import gdstk

    return gdstk.rectangle((_um(x0), _um(y0)), (_um(x1), _um(y1)), layer=layer, datatype=0)


def _frame(cx, cy, inner, outer, layer):
    """A square frame (inner/outer full widths) as four rectangles (no holes, no keyholes)."""
    hi, ho = inner // 2, outer // 2
    return [
        _rect(cx - ho, cy + hi, cx + ho, cy + ho, layer),  # top
        _rect(cx - ho, cy - ho, cx + ho, cy - hi, layer),  # bottom
        _rect(cx - ho, cy - hi, cx - hi, cy + hi, layer),  # left
        _rect(cx + hi, cy - hi, cx + ho, cy + hi, layer),  # right
    ]


def _cross(cx, cy, layer):
    """A plus sign as one 12-vertex polygon."""
    import gdstk

    a, w = CROSS_ARM_NM // 2, CROSS_WIDTH_NM // 2
    pts = [(a, w), (w, w), (w, a), (-w, a), (-w, w), (-a, w),
           (-a, -w), (-w, -w), (-w, -a), (w, -a), (w, -w), (a, -w)]  # fmt: skip
    return gdstk.Polygon([(_um(cx + x), _um(cy + y)) for x, y in pts], layer=layer, datatype=0)


def _comb(cx, cy, pitch, direction, layer, axis):
    """Vernier bars at cx + k*pitch (axis "x") or cy + k*pitch (axis "y").

    Bars extend from the baseline (cx, cy) away from it: ``direction`` +1 or -1.
    """
    out = []
    for k in range(-VERNIER_BARS, VERNIER_BARS + 1):
        length = VERNIER_BAR_LENGTH_NM + (VERNIER_CENTRE_EXTRA_NM if k == 0 else 0)
        half = VERNIER_BAR_WIDTH_NM // 2
        along0, along1 = sorted((0, direction * length))
        if axis == "x":
            x = cx + k * pitch
            out.append(_rect(x - half, cy + along0, x + half, cy + along1, layer))
        else:
            y = cy + k * pitch
            out.append(_rect(cx + along0, y - half, cx + along1, y + half, layer))
    return out


def alignment_block(cx, cy, ref_layer, layer):
    """Cross-in-box and x/y verniers aligning ``layer`` to ``ref_layer``.

    Returns
    -------
    list of gdstk.Polygon
        Cross and reference combs on ``ref_layer``; box and 9.8 um combs on ``layer``.
    """
    polys = [_cross(cx, cy, ref_layer), *_frame(cx, cy, BOX_INNER_NM, BOX_OUTER_NM, layer)]
    # x vernier below the cross: reference bars point up, later-mask bars down.
    vy = cy - VERNIER_OFFSET_NM
    polys += _comb(cx, vy, VERNIER_PITCH_REF_NM, +1, ref_layer, "x")
    polys += _comb(cx, vy, VERNIER_PITCH_NM, -1, layer, "x")
    # y vernier left of the cross.
    vx = cx - VERNIER_OFFSET_NM
    polys += _comb(vx, cy, VERNIER_PITCH_REF_NM, +1, ref_layer, "y")
    polys += _comb(vx, cy, VERNIER_PITCH_NM, -1, layer, "y")
    return polys


def mark_layer(gds_layer):
    """Return the GDS layer of the marks and labels that go with mask layer ``gds_layer``."""
    return MARK_LAYER_OFFSET + gds_layer


def plate_half_size_nm(aperture_half_nm):
    """Return half the plate size (nm): the aperture plus the mark margin."""
    return aperture_half_nm + PLATE_MARGIN_NM


# How far a block reaches up and right of its cross: the box, or the x vernier's end bar.
_BLOCK_REACH = max(
    BOX_OUTER_NM // 2, VERNIER_BARS * VERNIER_PITCH_REF_NM + VERNIER_BAR_WIDTH_NM // 2
)


def check_marks_fit(n_masks, aperture_half_nm):
    """Raise ValueError when the alignment marks of ``n_masks`` masks do not fit the plate."""
    _block_step(int(aperture_half_nm) + MARK_RING_NM, n_masks - 1)


def _block_step(ring, blocks):
    """Return the x spacing of the ``blocks`` mark blocks that run inwards from each corner.

    A block reaches ``VERNIER_OFFSET_NM`` + bar length left of its cross and its x
    vernier's end bar right of it; the innermost blocks of the two sides must not
    meet, and neighbours keep ``LABEL_GAP_NM`` between them. Raises ValueError when the
    blocks of this many masks do not fit beside the aperture.
    """
    left = VERNIER_OFFSET_NM + VERNIER_BAR_LENGTH_NM + VERNIER_CENTRE_EXTRA_NM
    right = _BLOCK_REACH
    innermost = left + LABEL_GAP_NM // 2  # the cross of the right-hand innermost block
    if blocks <= 1:
        return BLOCK_STEP_NM
    step = min(BLOCK_STEP_NM, (ring - innermost) // (blocks - 1))
    if step < left + right + LABEL_GAP_NM:
        raise ValueError(
            f"the alignment marks of {blocks + 1} masks do not fit beside a "
            f"{2 * (ring - MARK_RING_NM) / 1e6:g} mm aperture; make the aperture larger "
            "or use fewer levels"
        )
    return step


def _label(text, row, rows, a, h, layer):
    """Return ``text`` as polygons centred on row ``row`` of ``rows`` in the label band.

    The band runs below the clear aperture, above the lower mark blocks, across the
    plate, so that no label meets a mark whatever the aperture and mask count; the
    text shrinks to fit its row and the plate's width. Vertices are snapped to 1 nm.
    """
    import gdstk

    block_top = a + MARK_RING_NM - _BLOCK_REACH
    top, bottom = -(a + OUTLINE_WIDTH_NM + LABEL_GAP_NM), -(block_top - LABEL_GAP_NM)
    pitch = (top - bottom) / rows
    probe = gdstk.text(text, 1.0, (0, 0))  # size 1: glyph extents per unit height
    (x0, y0), (x1, y1) = _bbox(probe)
    width_room = 2 * (h - OUTLINE_WIDTH_NM - LABEL_GAP_NM)
    size = min(LABEL_HEIGHT_NM, 0.8 * pitch / (y1 - y0), width_room / (x1 - x0))
    cx, cy = -size * (x0 + x1) / 2, top - (row + 0.5) * pitch - size * (y0 + y1) / 2
    # The font draws diagonals ("0", "&") as squares meeting only at a corner: a
    # zero-width neck that mask DRC flags and a writer may or may not bridge. A small
    # bias joins them (neck 2.8 x bias) and keeps the one-unit gaps (1/16 - 2 x bias).
    glyphs = gdstk.offset(
        [gdstk.Polygon(p.points * size + (cx, cy)) for p in probe],
        LABEL_BIAS * size, join="miter", use_union=True,
    )  # fmt: skip
    return [gdstk.Polygon(np.round(p.points) / 1000, layer=layer, datatype=0) for p in glyphs]


def etchable(text):
    """Return ``text`` in the printable ASCII that gdstk's font draws.

    gdstk drops every other character without a word ("µ-plate" etched as "-plate"):
    accents go (é -> e), micro signs become u, anything else becomes "?".
    """
    text = unicodedata.normalize("NFKD", text.replace("µ", "u").replace("μ", "u"))
    text = "".join(c for c in text if not unicodedata.combining(c))
    return "".join(c if " " <= c <= "~" else "?" for c in text)


def _bbox(polys):
    """Return ((xmin, ymin), (xmax, ymax)) of polygons."""
    pts = np.concatenate([p.points for p in polys])
    return tuple(pts.min(axis=0)), tuple(pts.max(axis=0))


def marks_and_labels(masks, aperture_half_nm, design_name):
    """Build every non-pattern polygon of the plate.

    Parameters
    ----------
    masks : list of fab.package.masks.Mask
        In exposure order; the first is the alignment reference.
    aperture_half_nm : int
        Half the clear aperture (>= half the tiled area), nm; nothing is drawn inside.
    design_name : str
        Design id written on every mask.

    Returns
    -------
    polygons : list of gdstk.Polygon
    layers : list of MarkLayer
        The layers used, with their purpose.
    """
    a = int(aperture_half_nm)
    ref = masks[0]
    ref_layer = mark_layer(ref.gds_layer)
    polys, layers = [], []
    ring = a + MARK_RING_NM
    step = _block_step(ring, len(masks) - 1)
    for j, mk in enumerate(masks):
        layer = mark_layer(mk.gds_layer)
        layers.append(MarkLayer(layer, 0, f"alignment marks and label of {mk.name}", mk.name))
        if j > 0:
            for sx, sy in ((-1, -1), (1, -1), (-1, 1), (1, 1)):
                bx = sx * (ring - (j - 1) * step)
                polys += alignment_block(bx, sy * ring, ref_layer, layer)
    h = plate_half_size_nm(a)
    for j, mk in enumerate(masks):
        text = etchable(f"{design_name} {mk.name} {mk.etch_depth * 1e9:.1f}nm")
        polys += _label(text, j, len(masks), a, h, mark_layer(mk.gds_layer))
    polys += _frame(0, 0, 2 * h - 2 * OUTLINE_WIDTH_NM, 2 * h, OUTLINE_LAYER)
    polys += _frame(0, 0, 2 * a, 2 * a + 2 * OUTLINE_WIDTH_NM, OUTLINE_LAYER)
    layers.append(
        MarkLayer(OUTLINE_LAYER, 0, "plate edge and clear-aperture frame (not etched)", None)
    )
    return polys, layers
