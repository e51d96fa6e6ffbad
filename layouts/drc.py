"""Design-rule checks of a plate's masks with KLayout (``klayout.db``), as a mask shop runs them.

Each mask layer (GDS layer L, datatype 0, pattern and marks together; the outline
layer is documentation and is not checked) is merged and checked for:

- ``width``: interior widths below the minimum (Euclidean metrics: two pixels that
  touch only at a corner are a width of 0 through that corner);
- ``space``: clearances below the minimum, between polygons and inside one (KLayout's
  space check includes notches; corner contacts are a space of 0 too);
- ``notch``: the part of ``space`` inside one polygon, listed on its own as decks do;
- ``area``: polygons smaller than the minimum area;
- ``off_grid``: vertices off the mask writer's grid.

The tile array is checked hierarchically (a ``DeepShapeStore``: the tile cell with
its neighbours in the array as context) and the marks in the top cell flat; the two
lie far apart (else the whole layer is checked flat), so the counts add up to those
of a flat run on the whole plate: every marker is counted at each of its placements.
An array of at least 6 x 6 tiles, with the clipped edge tiles that fill the clear
aperture round it, is counted from four such plates of 3 or 4 whole tiles a side
(:mod:`layouts.drc_periodic`), exactly: the tests compare with flat runs. The same
rules as a KLayout DRC script are written by :mod:`layouts.drc_deck`, the markers by
:mod:`layouts.drc_rdb`.
"""

from dataclasses import dataclass
from itertools import islice

from layouts.drc_periodic import extrapolate, single_array, small_arrays

RULES = ("width", "space", "notch", "area", "off_grid")
EXAMPLES = 3  # marker locations given per layer and rule
_DISTANCE = ("width", "space", "notch")  # the checks giving edge pairs with a distance


@dataclass(frozen=True)
class DrcRules:
    """The design rules of a plate (integer nanometres, the GDS database unit).

    Attributes
    ----------
    layers : tuple of int
        The GDS layers checked (datatype 0), one per mask.
    min_width_nm, min_space_nm : int
        Minimum width and space (Euclidean).
    min_area_nm2 : int
        Minimum polygon area.
    grid_nm : int
        The mask writer's grid every vertex must lie on.
    """

    layers: tuple[int, ...]
    min_width_nm: int
    min_space_nm: int
    min_area_nm2: int
    grid_nm: int

    def limits(self):
        """Return {rule: limit as text} for reports."""
        return {
            "width": f">= {self.min_width_nm / 1000:g} um (Euclidean)",
            "space": f">= {self.min_space_nm / 1000:g} um (Euclidean)",
            "notch": f">= {self.min_space_nm / 1000:g} um (Euclidean)",
            "area": f">= {self.min_area_nm2 / 1e6:g} um^2",
            "off_grid": f"vertices on the {self.grid_nm} nm grid",
        }


def plate_rules(layers, feature_nm, grid_nm):
    """Return the rules of a process printing ``feature_nm`` on a ``grid_nm`` grid:
    width and space at the feature size, area at its square."""
    f = int(feature_nm)
    return DrcRules(tuple(int(x) for x in layers), f, f, f * f, int(grid_nm))


@dataclass(frozen=True)
class RuleCount:
    """The markers of one rule on one layer.

    Attributes
    ----------
    layer : int
    rule : str
        One of :data:`RULES`.
    count : int
        Markers on the flattened plate (edge pairs; polygons for ``area``).
    at_corners : int
        Of ``count``, the edge pairs of zero distance: pixels touching only at a corner.
    examples_um : tuple of (float, float)
        Centres of the first few markers (um, GDS coordinates).
    """

    layer: int
    rule: str
    count: int
    at_corners: int
    examples_um: tuple[tuple[float, float], ...]


@dataclass(frozen=True, eq=False)
class DrcResult:
    """What :func:`check_plate` found.

    Attributes
    ----------
    rules : DrcRules
    counts : tuple of RuleCount
        One per layer and rule, layers ascending, rules in :data:`RULES` order.
    corner_contacts : dict
        Layer -> number of points where pixels touch only at a corner.
    top_cell : str
    markers : dict
        (layer, rule) -> tuple of klayout.db EdgePairs or Region (for the marker
        database): the tile array's markers (of its 3 x 3 tiles at the origin for a
        large array) and the marks', or the whole layer's.
    store : tuple
        The ``DeepShapeStore`` and small layouts that hold the hierarchical markers:
        they live as long as it does.
    """

    rules: DrcRules
    counts: tuple[RuleCount, ...]
    corner_contacts: dict
    top_cell: str
    markers: dict
    store: object

    @property
    def total(self):
        """Every marker of every layer and rule."""
        return sum(c.count for c in self.counts)

    def beyond_corners(self):
        """Markers that are not corner contacts (what a process accepting them still refuses)."""
        return sum(c.count - c.at_corners for c in self.counts)


def check_plate(gds_path, rules):
    """Run the design-rule checks on every layer of ``rules`` in the GDS's top cell.

    Parameters
    ----------
    gds_path : path
        A GDS (or OASIS) file with one top cell and a 1 nm database unit.
    rules : DrcRules

    Returns
    -------
    DrcResult
    """
    import klayout.db as kdb

    layout = kdb.Layout()
    layout.read(str(gds_path))
    if abs(layout.dbu - 0.001) > 1e-12:
        raise ValueError(f"{gds_path}: DBU is {layout.dbu} um, not 0.001")
    top = layout.top_cell()
    dss = kdb.DeepShapeStore()
    reach = max(rules.min_width_nm, rules.min_space_nm) + 1
    array = single_array(layout, top)
    counts, corners, markers, keep = [], {}, {}, []
    for layer in rules.layers:
        parts = _layer_parts(layout, top, layer, dss, reach)
        if array is not None and len(parts) == 2:  # the tile array counted from small ones
            small = small_arrays(layout, array, layer, dss)
            keep += small
            tallies = [_tally(_layer_markers(region, rules)) for _, region in small[1:]]
            # the markers shown are those of the 3 x 3 tiles at the array's origin
            found = [_layer_markers(small[0][1], rules), _layer_markers(parts[1], rules)]
            tallies.insert(0, _tally(found[0]))
            tally = {
                rule: [extrapolate([t[rule][i] for t in tallies], array.na, array.nb)
                       for i in range(3)]
                for rule in RULES
            }  # fmt: skip
            tally = _add(tally, _tally(found[1]))
        else:
            found = [_layer_markers(part, rules) for part in parts]
            tally = {rule: [0, 0, 0] for rule in RULES}
            for f in found:
                tally = _add(tally, _tally(f))
        for rule in RULES:
            marks = tuple(f[rule] for f in found)
            count, at_corners, touch = tally[rule]
            counts.append(RuleCount(layer, rule, count, at_corners, _examples(marks)))
            markers[(layer, rule)] = marks
            if rule == "width":  # a corner contact is a width of 0 (and a space of 0) at a point
                corners[layer] = touch
    return DrcResult(rules, tuple(counts), corners, top.name, markers, (dss, keep))


def _tally(found):
    """Return {rule: [markers, at corner contacts, corner-contact points]} of
    :func:`_layer_markers`'s result."""
    out = {}
    for rule, marks in found.items():
        zero = marks.with_distance(0, 1, False) if rule in _DISTANCE else None
        out[rule] = [
            marks.count(),
            zero.count() if zero is not None else 0,
            _touch_points(zero) if zero is not None and rule == "width" else 0,
        ]
    return out


def _add(a, b):
    return {rule: [x + y for x, y in zip(a[rule], b[rule], strict=True)] for rule in a}


def _layer_parts(layout, top, layer, dss, reach):
    """Return the layer's shapes as regions checked apart: the tile array (hierarchically
    when it is one array of a leaf cell) and the top cell's own shapes (the marks) flat,
    or the whole layer flat when a mark lies within ``reach`` of the array (then the two
    interact).

    The marks are few and flat; checked hierarchically their polygons are cut where
    KLayout splits the top cell, which changes how many edge pairs a flat run reports.
    """
    import klayout.db as kdb

    li = layout.find_layer(layer, 0)
    if li is None:
        return (kdb.Region(),)
    below = top.begin_shapes_rec(li)
    below.min_depth = 1  # the shapes of the cells placed in the top cell: the tile array
    # KLayout's hierarchical space check counts other edge pairs than a flat run where
    # cells other than one array's tiles abut (the clipped edge tiles, the dies' plate
    # cell): the array checked hierarchically only when it is all the top cell places
    insts = list(top.each_inst())
    pure = len(insts) == 1 and not layout.cell(insts[0].cell_index).child_cells()
    array = kdb.Region(below, dss) if pure else kdb.Region(below)
    marks = kdb.Region(top.shapes(li))
    near = kdb.Region(array.bbox().enlarged(reach, reach))
    if not array.is_empty() and not marks.interacting(near).is_empty():
        return (kdb.Region(top.begin_shapes_rec(li)),)
    return (array, marks)


def _layer_markers(region, rules):
    """Return {rule: markers} of one merged mask layer."""
    import klayout.db as kdb

    euclid = kdb.Metrics.Euclidian
    return {
        "width": region.width_check(rules.min_width_nm, False, euclid),
        "space": region.space_check(rules.min_space_nm, False, euclid),
        "notch": region.notch_check(rules.min_space_nm, False, euclid),
        "area": region.with_area(0, rules.min_area_nm2, False),
        "off_grid": region.grid_check(rules.grid_nm, rules.grid_nm),
    }


def _touch_points(pairs):
    """Return how many points the zero-distance width pairs of one layer meet at.

    At a corner contact the two pixels' horizontal edges meet end to end (one pair)
    and so do their vertical edges (another): counting the horizontal pairs counts
    the points, without walking the markers in Python.
    """
    return pairs.with_angle(0.0, False).count()


def _examples(parts):
    """Distinct centres (um) of the first :data:`EXAMPLES` markers, in KLayout's
    (deterministic) order; a corner contact's two edge pairs share one centre."""
    out = []
    for m in islice((m for part in parts for m in part.each()), 20 * EXAMPLES):
        c = m.bbox().center()
        if (c.x / 1000, c.y / 1000) not in out:
            out.append((c.x / 1000, c.y / 1000))
        if len(out) == EXAMPLES:
            break
    return tuple(out)
