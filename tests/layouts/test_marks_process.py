"""Marks to the process, read back from the GDS with KLayout (independent of gdstk):
Euclidean width/space at the feature size, etch-depth pads on the right layers, CD gratings."""

import klayout.db as kdb
import numpy as np
import pytest

from fab.package.masks import masks_from_levels
from layouts import marks as mk_marks
from layouts.gds import build_library, write_gds

STEP = 179.4e-9
NAME = "sun2020 &0/%"  # glyphs whose font squares meet only at a corner
# (levels, aperture mm, feature nm, grid nm, pixel pitch nm): the default design, the
# default at 10 um, a 4-level 12.7 mm design on a 10 nm grid, a 16-level 6 mm one.
DESIGNS = [
    (8, 14.0, 5_000, 1, 4_990),
    (8, 14.0, 10_000, 1, 9_990),
    (4, 12.7, 10_000, 10, 9_990),
    (16, 6.0, 7_500, 5, 7_495),
]


def written(tmp_path, n_levels, aperture_mm, feature_nm, grid_nm, pitch_nm):
    """Write a plate of a tiny 6 x 6 tile; return (layout, top cell, masks, PlateLayout)."""
    levels = np.random.default_rng(1).integers(0, n_levels, (6, 6))
    masks = masks_from_levels(levels, n_levels, STEP)
    aperture = round(aperture_mm * 1e6)
    lib, info = build_library(
        masks, pitch_nm, (2, 2), NAME, aperture, grid_nm=grid_nm, feature_nm=feature_nm
    )
    path = tmp_path / "plate.gds"
    write_gds(lib, path)
    layout = kdb.Layout()
    layout.read(str(path))
    return layout, layout.cell(info.top_cell), masks, info


def marks_region(layout, top, layer, aperture_half):
    """The layer's shapes outside the clear aperture (the tile lies inside it), merged."""
    region = kdb.Region(top.begin_shapes_rec(layout.layer(layer, 0)))
    clear = kdb.Region(kdb.Box(-aperture_half, -aperture_half, aperture_half, aperture_half))
    assert (region - clear).count() > 0
    return (region - clear).merged()


@pytest.mark.parametrize("design", [*DESIGNS, (8, 14.0, 60_000, 1, 59_990)])  # + coarse
def test_marks_pass_a_euclidean_width_and_space_check_at_the_feature_size(tmp_path, design):
    _, aperture_mm, feature_nm, grid_nm, _ = design
    layout, top, masks, info = written(tmp_path, *design)
    a = round(aperture_mm * 1e6) // 2
    for mk in masks:
        region = marks_region(layout, top, mk.gds_layer, a)
        width = region.width_check(feature_nm, False, kdb.Metrics.Euclidian)
        space = region.space_check(feature_nm, False, kdb.Metrics.Euclidian)
        assert width.count() == 0 and space.count() == 0, (mk.name, width.count(), space.count())
        # the check bites: one grid step more and the narrowest marks are flagged
        too_wide = region.width_check(feature_nm + grid_nm, False, kdb.Metrics.Euclidian)
        assert too_wide.count() > 0
        # every vertex on the write grid
        for poly in region.each():
            assert all(p.x % grid_nm == 0 and p.y % grid_nm == 0 for p in poly.each_point_hull())
    # the vernier reads in steps of 2 f / 50 (0.2 um at 5 um, 0.4 um at 10 um)
    assert info.mark_rules.resolution_nm == pytest.approx(2 * feature_nm / 50, abs=grid_nm)


@pytest.mark.parametrize("design", [DESIGNS[0], DESIGNS[2], DESIGNS[3]])
def test_etch_depth_pads_are_etched_by_the_masks_of_their_code(tmp_path, design):
    n_levels, aperture_mm, feature_nm, _, _ = design
    layout, top, masks, info = written(tmp_path, *design)
    a = round(aperture_mm * 1e6) // 2
    h = info.plate_half_nm
    regions = {mk.gds_layer: marks_region(layout, top, mk.gds_layer, a) for mk in masks}
    steps = {mk.gds_layer: mk.steps for mk in masks}
    outline = kdb.Region(top.begin_shapes_rec(layout.layer(mk_marks.OUTLINE_LAYER, 0)))
    assert outline.bbox() == kdb.Box(-h, -h, h, h)  # the plate's outer edge
    codes = []
    for pad in info.pads:
        x, y = pad.centre_nm
        s = pad.size_nm
        assert s >= 200_000
        box = kdb.Box(x - s // 2, y - s // 2, x - s // 2 + s, y - s // 2 + s)
        assert max(abs(box.left), abs(box.right), abs(box.bottom), abs(box.top)) <= h
        assert not box.overlaps(kdb.Box(-a, -a, a, a)), "a pad inside the clear aperture"
        near = kdb.Region(box.enlarged(feature_nm, feature_nm))
        covering = []
        for layer, region in regions.items():
            there = region & near
            if there.is_empty():
                continue
            # a whole clear square of the pad's size, nothing else within a feature size
            assert (there ^ kdb.Region(box)).is_empty(), (pad.code, layer)
            covering.append(layer)
        assert tuple(covering) == pad.layers
        codes.append(sum(steps[layer] for layer in covering))  # steps etched at the pad
    # every etch and every combination: the depths of levels L-2 .. 0
    assert sorted(codes) == list(range(1, n_levels))


@pytest.mark.parametrize("design", [DESIGNS[0], DESIGNS[2]])
def test_cd_gratings_measure_one_to_two_feature_sizes_in_the_gds(tmp_path, design):
    _, aperture_mm, feature_nm, grid_nm, _ = design
    layout, top, masks, info = written(tmp_path, *design)
    a = round(aperture_mm * 1e6) // 2
    regions = {mk.gds_layer: marks_region(layout, top, mk.gds_layer, a) for mk in masks}
    found = {}
    for cd in info.cd_structures:
        x, y = cd.centre_nm
        half = cd.length_nm // 2 + feature_nm
        lines = regions[cd.layer] & kdb.Region(kdb.Box(x - half, y - half, x + half, y + half))
        boxes = sorted((p.bbox() for p in lines.each()), key=lambda b: (b.left, b.bottom))
        vertical = cd.orientation == "vertical"
        widths = [b.width() if vertical else b.height() for b in boxes]
        starts = sorted(b.left if vertical else b.bottom for b in boxes)
        assert len(boxes) == cd.lines and len(set(widths)) == 1
        assert np.all(np.diff(starts) == 2 * widths[0])  # spaces as wide as the lines
        found.setdefault(cd.layer, set()).add((widths[0], cd.orientation))
    for mk in masks:  # 1x, 1.5x, 2x the feature size, up on the grid, both orientations
        expected = {-(-feature_nm * k // grid_nm) * grid_nm for k in (1, 1.5, 2)}
        assert {w for w, _ in found[mk.gds_layer]} == {int(w) for w in expected}
        assert len(found[mk.gds_layer]) == 6


def test_a_plate_too_small_for_the_monitors_is_refused():
    # 32 levels: 31 pads and 30 gratings beside a 1 mm aperture
    with pytest.raises(ValueError, match="do not fit beside a 1 mm aperture"):
        mk_marks.check_marks_fit(5, 500_000, 5_000)
    mk_marks.check_marks_fit(3, 500_000, 5_000)  # 8 levels fit there
