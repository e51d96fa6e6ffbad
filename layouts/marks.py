"""Alignment marks, verniers, text labels, process monitors and the plate outline.

Everything here lies outside the clear aperture and inside the plate. Every later
mask is aligned to the first (deepest) one. Per later mask j the first mask carries
a cross and two vernier combs; mask j carries the box around the cross and the
matching combs. All of it is sized to the process (:func:`mark_rules`): every bar,
gap, arm, frame and label stroke is at least the feature size ``f`` wide, measured
in any direction. The later mask's comb has bars ``w`` = f (up on the write grid)
at pitch 2w (gaps w), the reference comb pitch 2w + r with r = 2w / 50 on the grid,
so the bar pair that lines up reads the overlay error in steps of r (bar k
coincides for an offset of k r, k = -10 .. 10): r = 0.2 um for f = 5 um, 0.4 um for
f = 10 um. Marks and labels are drawn on the pattern layer of the mask they belong
to (``MARK_LAYER_OFFSET`` = 0): they are etched in that step, which is what makes
them visible to the next alignment, and each photomask is one GDS layer. Etch-depth
pads and CD test structures (:mod:`layouts.monitors`) fill the free zones beside
the aperture. The outline of the plate and of the clear aperture sits on
``OUTLINE_LAYER``, a drawing layer that is not etched.

All geometry is built in integer nanometres on the write grid and returned as gdstk
polygons in micrometres (the library's user unit). gdstk is imported where polygons
are made: design validation (``check_marks_fit``) runs on machines that only learn
PSFs, without the GDS writer.
"""

from dataclasses import dataclass

from layouts import labels as _labels
from layouts import monitors

etchable = _labels.etchable

# One named place for the mark geometry (nm); the sizes are minima, raised for a
# coarse feature size by mark_rules.
MARK_LAYER_OFFSET = 0  # marks of the mask on GDS layer L go to layer L + offset
OUTLINE_LAYER = 200  # plate edge and clear-aperture frame (documentation, not etched)
PLATE_MARGIN_NM = 1_500_000  # plate edge = aperture edge + 1.5 mm on every side (at least)
MARK_RING_NM = 750_000  # mark blocks centred 0.75 mm outside the aperture edge (at least)
# The block extent (reach down-left plus up-right) that this margin holds; the larger
# blocks of a coarse feature size widen the margin and the ring in proportion.
MARK_BLOCK_ROOM_NM = 700_000
BLOCK_STEP_NM = 600_000  # spacing of the blocks of successive masks along x (at most)
CROSS_ARM_NM = 100_000  # cross: 100 um long arms (at least)
CROSS_WIDTH_NM = 10_000  # ... 10 um wide (at least 2 f)
BOX_CLEARANCE_NM = 10_000  # box inside edge to the cross's arm ends (at least 2 f)
BOX_FRAME_NM = 20_000  # box frame width (at least 4 f)
VERNIER_BARS = 10  # bars k = -10 .. 10 -> reads +-10 resolutions
VERNIER_STEPS_PER_PITCH = 50  # resolution = later comb's pitch / 50
VERNIER_BAR_LENGTH_NM = 30_000  # at least 6 bar widths
VERNIER_CENTRE_EXTRA_NM = 10_000  # the k = 0 bars are longer (at least 2 bar widths)
VERNIER_OFFSET_NM = 200_000  # comb pairs at least 200 um from the cross (below and left)
DEFAULT_FEATURE_NM = 5_000  # the default design's feature size
LABEL_HEIGHT_NM = 150_000  # at most, unless the feature size needs taller text
LABEL_GAP_NM = 50_000  # clearance of the labels to the aperture frame and the mark blocks
OUTLINE_WIDTH_NM = 20_000
ZONE_GAP_NM = 50_000  # clearance of the monitor zones to the frames, blocks and labels


def _up(v, grid):
    """``v`` rounded up to a multiple of ``grid`` (integers)."""
    return -(-int(v) // grid) * grid


@dataclass(frozen=True)
class MarkRules:
    """The marks' dimensions for one feature size and write grid (nm, multiples of the grid).

    Attributes
    ----------
    feature_nm, grid_nm : int
        The smallest width or space drawn, and the write grid.
    bar_nm, pitch_nm, ref_pitch_nm, resolution_nm : int
        Vernier bar width, the later mask's comb pitch, the reference comb's, and the
        overlay read per bar (``ref_pitch_nm - pitch_nm``).
    bar_length_nm, centre_extra_nm : int
        Bar length and the zero bars' extra length.
    cross_arm_nm, cross_width_nm, box_inner_nm, box_outer_nm : int
        Cross (full arm length, width) and box (inside, outside widths).
    vernier_offset_nm : int
        Distance of the comb pairs' baselines from the cross.
    ring_nm, margin_nm : int
        Distance of the mark blocks' centres, and of the plate's edge, from the
        aperture's edge.
    clearance_nm : int
        Clearance between mark blocks, labels and the aperture frame (at least 2 f).
    """

    feature_nm: int
    grid_nm: int
    bar_nm: int
    pitch_nm: int
    ref_pitch_nm: int
    resolution_nm: int
    bar_length_nm: int
    centre_extra_nm: int
    cross_arm_nm: int
    cross_width_nm: int
    box_inner_nm: int
    box_outer_nm: int
    vernier_offset_nm: int
    ring_nm: int = MARK_RING_NM
    margin_nm: int = PLATE_MARGIN_NM
    clearance_nm: int = LABEL_GAP_NM

    @property
    def comb_half_span_nm(self):
        """How far the reference comb's end bars reach from its centre."""
        return VERNIER_BARS * self.ref_pitch_nm + self.bar_nm - _half(self.bar_nm, self.grid_nm)

    @property
    def reach_right_nm(self):
        """How far a block reaches up and right of its cross (the box or a comb's end bar)."""
        return max(self.box_outer_nm // 2, self.comb_half_span_nm, self.cross_arm_nm // 2)

    @property
    def reach_left_nm(self):
        """How far a block reaches down and left of its cross (the combs' bars)."""
        return self.vernier_offset_nm + self.bar_length_nm + self.centre_extra_nm

    @property
    def reading_range_nm(self):
        """The largest overlay error the vernier reads (+-)."""
        return VERNIER_BARS * self.resolution_nm


def mark_rules(feature_nm=DEFAULT_FEATURE_NM, grid_nm=1):
    """Return the :class:`MarkRules` for a feature size and write grid (nm)."""
    g = max(int(grid_nm), 1)
    f = _up(max(int(feature_nm), g), g)
    pitch = 2 * f
    resolution = max(g, round(pitch / VERNIER_STEPS_PER_PITCH / g) * g)
    bar_length = _up(max(VERNIER_BAR_LENGTH_NM, 6 * f), g)
    extra = _up(max(VERNIER_CENTRE_EXTRA_NM, 2 * f), g)
    cross_width = _up(max(CROSS_WIDTH_NM, 2 * f), g)
    cross_arm = _up(max(CROSS_ARM_NM, 10 * f), g)
    box_inner = cross_arm + 2 * _up(max(BOX_CLEARANCE_NM, 2 * f), g)
    box_outer = box_inner + 2 * _up(max(BOX_FRAME_NM, 4 * f), g)
    half_span = VERNIER_BARS * (pitch + resolution) + f - _half(f, g)
    # the x and y combs must not meet (nor the box): a clearance of LABEL_GAP_NM or 2 f
    clearance = _up(max(LABEL_GAP_NM, 2 * f), g)
    offset = max(
        VERNIER_OFFSET_NM,
        half_span + bar_length + extra + clearance,
        box_outer // 2 + bar_length + extra + clearance,
    )
    offset = _up(_up(offset, 10_000), g)
    extent = offset + bar_length + extra + max(box_outer // 2, half_span, cross_arm // 2)
    scale = max(1.0, extent / MARK_BLOCK_ROOM_NM)
    return MarkRules(
        feature_nm=f, grid_nm=g, bar_nm=f, pitch_nm=pitch, ref_pitch_nm=pitch + resolution,
        resolution_nm=resolution, bar_length_nm=bar_length, centre_extra_nm=extra,
        cross_arm_nm=cross_arm, cross_width_nm=cross_width, box_inner_nm=box_inner,
        box_outer_nm=box_outer, vernier_offset_nm=offset,
        ring_nm=_up(MARK_RING_NM * scale, g), margin_nm=_up(PLATE_MARGIN_NM * scale, g),
        clearance_nm=clearance,
    )  # fmt: skip


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


def _half(v, grid):
    """Half of ``v`` down on the grid: a shape of width v from c - half to c - half + v."""
    return v // grid // 2 * grid


def _frame(cx, cy, inner, outer, layer, grid=1):
    """A square frame (inner/outer full widths) as four rectangles (no holes, no keyholes)."""
    hi, ho = _half(inner, grid), _half(outer, grid)
    lo_i, hi_i, lo_o, hi_o = -hi, inner - hi, -ho, outer - ho
    return [
        _rect(cx + lo_o, cy + hi_i, cx + hi_o, cy + hi_o, layer),  # top
        _rect(cx + lo_o, cy + lo_o, cx + hi_o, cy + lo_i, layer),  # bottom
        _rect(cx + lo_o, cy + lo_i, cx + lo_i, cy + hi_i, layer),  # left
        _rect(cx + hi_i, cy + lo_i, cx + hi_o, cy + hi_i, layer),  # right
    ]


def _cross(cx, cy, layer, rules):
    """A plus sign as one 12-vertex polygon."""
    import gdstk

    g = rules.grid_nm
    a0, w0 = -_half(rules.cross_arm_nm, g), -_half(rules.cross_width_nm, g)
    a1, w1 = a0 + rules.cross_arm_nm, w0 + rules.cross_width_nm
    pts = [(a1, w1), (w1, w1), (w1, a1), (w0, a1), (w0, w1), (a0, w1),
           (a0, w0), (w0, w0), (w0, a0), (w1, a0), (w1, w0), (a1, w0)]  # fmt: skip
    return gdstk.Polygon([(_um(cx + x), _um(cy + y)) for x, y in pts], layer=layer, datatype=0)


def _comb(cx, cy, pitch, direction, layer, axis, rules):
    """Vernier bars at cx + k*pitch (axis "x") or cy + k*pitch (axis "y").

    Bars extend from the baseline (cx, cy) away from it: ``direction`` +1 or -1.
    """
    out = []
    w = rules.bar_nm
    half = _half(w, rules.grid_nm)
    for k in range(-VERNIER_BARS, VERNIER_BARS + 1):
        length = rules.bar_length_nm + (rules.centre_extra_nm if k == 0 else 0)
        along0, along1 = sorted((0, direction * length))
        if axis == "x":
            x = cx + k * pitch - half
            out.append(_rect(x, cy + along0, x + w, cy + along1, layer))
        else:
            y = cy + k * pitch - half
            out.append(_rect(cx + along0, y, cx + along1, y + w, layer))
    return out


def alignment_block(cx, cy, ref_layer, layer, rules=None):
    """Cross-in-box and x/y verniers aligning ``layer`` to ``ref_layer``.

    Returns
    -------
    list of gdstk.Polygon
        Cross and reference combs (pitch ``rules.ref_pitch_nm``) on ``ref_layer``;
        box and the later combs (``rules.pitch_nm``) on ``layer``.
    """
    r = rules or mark_rules()
    polys = [_cross(cx, cy, ref_layer, r)]
    polys += _frame(cx, cy, r.box_inner_nm, r.box_outer_nm, layer, r.grid_nm)
    # x vernier below the cross: reference bars point up, later-mask bars down.
    vy = cy - r.vernier_offset_nm
    polys += _comb(cx, vy, r.ref_pitch_nm, +1, ref_layer, "x", r)
    polys += _comb(cx, vy, r.pitch_nm, -1, layer, "x", r)
    # y vernier left of the cross.
    vx = cx - r.vernier_offset_nm
    polys += _comb(vx, cy, r.ref_pitch_nm, +1, ref_layer, "y", r)
    polys += _comb(vx, cy, r.pitch_nm, -1, layer, "y", r)
    return polys


def mark_layer(gds_layer):
    """Return the GDS layer of the marks and labels that go with mask layer ``gds_layer``."""
    return MARK_LAYER_OFFSET + gds_layer


def plate_half_size_nm(aperture_half_nm, rules=None):
    """Return half the plate size (nm): the aperture plus the mark margin."""
    return aperture_half_nm + (rules or mark_rules()).margin_nm


def check_marks_fit(n_masks, aperture_half_nm, feature_nm=DEFAULT_FEATURE_NM, grid_nm=1):
    """Raise ValueError when the marks, labels and monitors of ``n_masks`` masks do not fit.

    The labels are tried with their shortest text (the mask's name, e.g. "M1_shallow").
    """
    rules = mark_rules(feature_nm, grid_nm)
    a = int(aperture_half_nm)
    _block_step(a + rules.ring_nm, n_masks - 1, rules)
    _label_layout(["M1_shallow"] * n_masks, a, rules)
    _monitor_slots(n_masks, a, rules)


def _block_step(ring, blocks, rules):
    """Return the x spacing of the ``blocks`` mark blocks that run inwards from each corner.

    A block reaches ``rules.reach_left_nm`` left of its cross and
    ``rules.reach_right_nm`` right of it; the innermost blocks of the two sides must
    not meet, and neighbours keep ``rules.clearance_nm`` between them. Raises ValueError
    when the blocks of this many masks do not fit beside the aperture.
    """
    left, right = rules.reach_left_nm, rules.reach_right_nm
    innermost = left + rules.clearance_nm // 2  # the cross of the right-hand innermost block
    nominal = max(BLOCK_STEP_NM, left + right + rules.clearance_nm)
    if blocks <= 1:
        return nominal
    step = min(nominal, (ring - innermost) // (blocks - 1))
    if step < left + right + rules.clearance_nm:
        raise ValueError(
            f"the alignment marks of {blocks + 1} masks do not fit beside a "
            f"{2 * (ring - rules.ring_nm) / 1e6:g} mm aperture; make the aperture larger "
            "or use fewer levels"
        )
    return step


def _label_band(a, rules):
    """Return (x_half, top, bottom) of the label band below the clear aperture (nm).

    It runs across the plate, below the aperture frame and above the lower mark
    blocks, so that no label meets a mark whatever the aperture and mask count.
    """
    h = plate_half_size_nm(a, rules)
    block_top = a + rules.ring_nm - rules.reach_right_nm
    return (
        h - OUTLINE_WIDTH_NM - rules.clearance_nm,
        -(a + OUTLINE_WIDTH_NM + rules.clearance_nm),
        -(block_top - rules.clearance_nm),
    )


def _label_layout(texts, a, rules):
    """Return (unit, columns, rows) of the label grid: as large a font unit as fits, at most
    ``LABEL_HEIGHT_NM`` tall text unless the feature needs more, never below the feature.

    Raises ValueError when even one unit of the feature size does not fit.
    """
    g, f = rules.grid_nm, rules.feature_nm
    x_half, top, bottom = _label_band(a, rules)
    cols_px = max(_labels.label_size_units(t)[0] for t in texts)
    rows_px = _labels.label_size_units("")[1]
    cap = max(f, LABEL_HEIGHT_NM // rows_px // g * g)
    options = []
    for cols in range(1, len(texts) + 1):
        rows = -(-len(texts) // cols)
        cell_w = (2 * x_half - (cols - 1) * rules.clearance_nm) // cols
        cell_h = (top - bottom) // rows
        # rows keep a fifth of their pitch (and at least one unit) between them
        unit = min(cap, cell_w // cols_px, (4 * cell_h // 5) // rows_px, cell_h // (rows_px + 1))
        unit = unit // g * g
        options.append((unit, cols, rows))
    # fewest columns (the first exposure's label on top) unless that shrinks the text
    largest = max(unit for unit, _, _ in options)
    if largest < f:
        raise ValueError(
            f"the labels of {len(texts)} masks do not fit beside a {2 * a / 1e6:g} mm "
            f"aperture in strokes of the {f / 1000:g} um feature size; make the aperture "
            "larger or use fewer levels"
        )
    return next(o for o in options if o[0] >= max(f, 3 * largest // 4))


def _labels_polygons(masks, design_name, a, rules):
    """Each mask's label (design, mask, depth) in the label band, the first exposure on top.

    The text drops the design name, then the depth, when the full text would need
    strokes below the feature size.
    """
    texts = None
    for form in (
        lambda mk: f"{design_name} {mk.name} {mk.etch_depth * 1e9:.1f}nm",
        lambda mk: f"{mk.name} {mk.etch_depth * 1e9:.1f}nm",
        lambda mk: mk.name,
    ):
        texts = [_labels.etchable(form(mk)) for mk in masks]
        try:
            unit, cols, rows = _label_layout(texts, a, rules)
            break
        except ValueError:
            continue
    else:
        unit, cols, rows = _label_layout(texts, a, rules)  # raises, naming the problem
    g = rules.grid_nm
    x_half, top, bottom = _label_band(a, rules)
    cell_w = (2 * x_half - (cols - 1) * rules.clearance_nm) // cols
    cell_h = (top - bottom) // rows
    polys = []
    for j, (mk, text) in enumerate(zip(masks, texts, strict=True)):
        w_px, h_px = _labels.label_size_units(text)
        r, c = divmod(j, cols)
        cx = -x_half + c * (cell_w + rules.clearance_nm) + cell_w // 2
        cy = top - r * cell_h - cell_h // 2
        x0 = (cx - w_px * unit // 2) // g * g
        y0 = (cy - h_px * unit // 2) // g * g
        polys += _labels.label_polygons(text, x0, y0, unit, mark_layer(mk.gds_layer))
    return polys


def _monitor_zones(a, rules):
    """Return the free zones (x0, y0, x1, y1) for the monitors, in filling order.

    Right and left of the aperture (between the label band's top and the upper mark
    blocks), then the bands above the upper and below the lower mark blocks.
    """
    h = plate_half_size_nm(a, rules)
    ring = a + rules.ring_nm
    gap = max(ZONE_GAP_NM, 2 * rules.feature_nm)
    inner, outer = a + OUTLINE_WIDTH_NM + gap, h - OUTLINE_WIDTH_NM - gap
    low, high = -a, ring - rules.reach_left_nm - gap
    top0 = ring + rules.reach_right_nm + gap
    bottom1 = -(ring + rules.reach_left_nm + gap)
    return [
        (inner, low, outer, high),
        (-outer, low, -inner, high),
        (-outer, top0, outer, outer),
        (-outer, -outer, outer, bottom1),
    ]


def _monitor_slots(n_masks, a, rules):
    """Return the monitors' slot centres and side; ValueError when the plate has too few."""
    side, gap = monitors.slot_geometry(rules.feature_nm, rules.grid_nm)
    count = monitors.monitor_count(n_masks)
    try:
        centres = monitors.slots(_monitor_zones(a, rules), count, side, gap, rules.grid_nm)
    except ValueError as e:
        raise ValueError(
            f"the etch-depth pads and CD structures of {n_masks} masks ({e} slots of "
            f"{side / 1000:g} um) do not fit beside a {2 * a / 1e6:g} mm aperture; make "
            "the aperture larger or use fewer levels"
        ) from None
    return centres, side


def monitor_plan(masks, aperture_half_nm, rules=None):
    """Return (pads, cd_structures) of ``masks`` (see :mod:`layouts.monitors`)."""
    r = rules or mark_rules()
    a = int(aperture_half_nm)
    centres, side = _monitor_slots(len(masks), a, r)
    return monitors.monitor_plan(masks, centres, side, r.feature_nm, r.grid_nm)


def marks_and_labels(
    masks, aperture_half_nm, design_name, feature_nm=DEFAULT_FEATURE_NM, grid_nm=1,
    frame_half_nm=None,
):  # fmt: skip
    """Build every non-pattern polygon of the plate.

    Parameters
    ----------
    masks : list of fab.package.masks.Mask
        In exposure order; the first is the alignment reference.
    aperture_half_nm : int
        Half the clear aperture (>= half the tiled area), nm; nothing is drawn inside.
    design_name : str
        Design id written on every mask.
    feature_nm, grid_nm : int
        The design's feature size (the narrowest width and space drawn) and the
        write grid (every vertex lies on it).
    frame_half_nm : int or None
        Half the clear-aperture frame drawn on the outline layer, when the marks keep
        clear of a pattern reaching past it (default ``aperture_half_nm``).

    Returns
    -------
    polygons : list of gdstk.Polygon
    layers : list of MarkLayer
        The layers used, with their purpose.
    """
    rules = mark_rules(feature_nm, grid_nm)
    g = rules.grid_nm
    a = int(aperture_half_nm)
    ref_layer = mark_layer(masks[0].gds_layer)
    polys, layers = [], []
    ring = a + rules.ring_nm
    step = _block_step(ring, len(masks) - 1, rules)
    for j, mk in enumerate(masks):
        layer = mark_layer(mk.gds_layer)
        purpose = f"alignment marks, label, etch-depth pads and CD structures of {mk.name}"
        layers.append(MarkLayer(layer, 0, purpose, mk.name))
        if j > 0:
            for sx, sy in ((-1, -1), (1, -1), (-1, 1), (1, 1)):
                bx = sx * (ring - (j - 1) * step) // g * g
                polys += alignment_block(bx, sy * ring // g * g, ref_layer, layer, rules)
    polys += _labels_polygons(masks, design_name, a, rules)
    pads, cds = monitor_plan(masks, a, rules)
    polys += [
        _rect(x0, y0, x1, y1, mark_layer(layer))
        for x0, y0, x1, y1, layer in monitors.monitor_rectangles(pads, cds, g)
    ]
    h = plate_half_size_nm(a, rules)
    polys += _frame(0, 0, 2 * h - 2 * OUTLINE_WIDTH_NM, 2 * h, OUTLINE_LAYER)
    f = a if frame_half_nm is None else int(frame_half_nm)
    polys += _frame(0, 0, 2 * f, 2 * f + 2 * OUTLINE_WIDTH_NM, OUTLINE_LAYER)
    layers.append(
        MarkLayer(OUTLINE_LAYER, 0, "plate edge and clear-aperture frame (not etched)", None)
    )
    return polys, layers
