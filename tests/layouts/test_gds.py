"""GDS: golden geometry (KLayout XOR against an independent reference), orientation, AREF,
grid, byte-identical files, marks outside the aperture, layer images read back with OIIO."""

import dataclasses
import itertools
import re
import string
import tempfile
from pathlib import Path

import gdstk
import klayout.db as kdb
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from fab.package.layer_images import plate_preview, read_image, tile_image, write_image
from fab.package.masks import masks_from_levels
from layouts import marks as mk_marks
from layouts.gds import (
    array_origin_nm,
    build_library,
    cell_name,
    max_vertices,
    write_gds,
    write_oasis,
)
from layouts.readback import check_written_gds

L = 8
STEP = 179.4e-9
PITCH = 4990  # nm


def random_levels(n, seed=0):
    return np.random.default_rng(seed).integers(0, L, (n, n)).astype(np.uint8)


def write_plate(tmp_path, levels, tiles=(3, 2), name="plate.gds", **kw):
    masks = masks_from_levels(levels, L, STEP)
    lib, info = build_library(masks, PITCH, tiles, "test design", **kw)
    path = tmp_path / name
    write_gds(lib, path)
    return path, masks, info


def read_layout(path):
    layout = kdb.Layout()
    layout.read(str(path))
    return layout


def reference_region(bitmap, tiles, origin, p=PITCH):
    """The tiled mask built pixel by pixel with KLayout boxes (independent of gdstk/rectangles)."""
    n = bitmap.shape[0]
    region = kdb.Region()
    for r, c in np.argwhere(bitmap).tolist():
        for i in range(tiles[0]):
            for j in range(tiles[1]):
                x = origin[0] + (i * n + c) * p
                y = origin[1] + (j * n + n - 1 - r) * p  # row 0 = top edge of each tile
                region.insert(kdb.Box(x, y, x + p, y + p))
    return region.merged()


def flat_layer(layout, cell_name, layer):
    li = layout.find_layer(layer, 0)
    assert li is not None, f"layer {layer} missing"
    return kdb.Region(layout.cell(cell_name).begin_shapes_rec(li)).merged()


def test_golden_xor_against_independent_reference(tmp_path):
    levels = random_levels(12, seed=3)
    tiles = (3, 2)  # unequal so that a swapped x/y shows up
    path, masks, info = write_plate(tmp_path, levels, tiles)
    layout = read_layout(path)
    origin = array_origin_nm(tiles, 12, PITCH)
    assert info.array_origin_nm == origin == (-(3 * 12 * PITCH) // 2, -(2 * 12 * PITCH) // 2)
    # marks and labels share the mask layers but lie outside the tiled area
    array = kdb.Region(
        kdb.Box(
            origin[0],
            origin[1],
            origin[0] + tiles[0] * 12 * PITCH,
            origin[1] + tiles[1] * 12 * PITCH,
        )
    )
    for mk in masks:
        got = flat_layer(layout, info.top_cell, mk.gds_layer) & array
        want = reference_region(mk.bitmap, tiles, origin)
        diff = got ^ want
        if not diff.is_empty():  # leave a debug layout next to the test output
            dbg = kdb.Layout()
            dbg.dbu = 0.001
            top = dbg.create_cell("DEBUG")
            top.shapes(dbg.layer(1, 0)).insert(diff)
            dbg.write(str(tmp_path / f"xor_{mk.name}.gds"))
        assert diff.is_empty(), f"{mk.name}: XOR area {diff.area()} nm^2"


def test_array_origin_of_an_odd_sized_array_rounds_towards_zero():
    # -(tiles * N * p // 2): 3 * 5 * 4991 nm = 74865 nm -> -37432, the spare nm at +x/+y
    assert array_origin_nm((3, 1), 5, 4991) == (-37432, -12477)
    # on a 5 nm grid: 3 * 5 * 4995 = 74925 -> 37462 -> 37460 (it was -37462, off the grid)
    assert array_origin_nm((3, 1), 5, 4995, grid_nm=5) == (-37460, -12485)


def test_a_coarse_grid_puts_every_vertex_of_the_plate_on_it():
    # 19 tiles of 35 pixels of 20265 nm (532 nm on a 5 nm grid): the array's origin was
    # half a pitch off the grid, and so was every placed vertex; marks and labels too.
    grid, pitch = 5, 4995
    masks = masks_from_levels(random_levels(7, seed=5), L, STEP)
    lib, info = build_library(masks, pitch, (3, 3), "grid test", aperture_nm=400_000, grid_nm=grid)
    assert all(v % grid == 0 for v in info.array_origin_nm)
    top = next(c for c in lib.cells if c.name == info.top_cell).copy("flat").flatten()
    points = np.concatenate([p.points for p in top.polygons]) * 1000  # nm
    assert points.shape[0] > 1000  # tiles, marks and labels
    np.testing.assert_array_equal(np.round(points) % grid, 0)
    with pytest.raises(ValueError, match="not on the 5 nm grid"):
        build_library(masks, 4991, (1, 1), "t", grid_nm=grid)


def test_flat_library_draws_the_tiles_polygons_in_the_top_cell(tmp_path):
    levels = random_levels(7, seed=11)
    tiles = (3, 2)
    path, masks, info = write_plate(tmp_path, levels, tiles, marks=False, flat=True)
    layout = read_layout(path)
    assert list(layout.cell(info.top_cell).each_inst()) == []  # no reference left
    assert layout.cell(info.tile_cell) is None
    for mk in masks:
        want = reference_region(mk.bitmap, tiles, info.array_origin_nm)
        assert (flat_layer(layout, info.top_cell, mk.gds_layer) ^ want).is_empty(), mk.name


def test_each_mask_is_drawn_on_its_own_layer_and_datatype(tmp_path):
    masks = masks_from_levels(random_levels(6, seed=10), L, STEP)
    masks = [
        dataclasses.replace(mk, gds_datatype=d) for mk, d in zip(masks, (0, 3, 7), strict=True)
    ]
    lib, info = build_library(masks, PITCH, (1, 1), "t", marks=False)
    path = tmp_path / "dt.gds"
    write_gds(lib, path)
    layout = read_layout(path)
    for mk in masks:
        li = layout.find_layer(mk.gds_layer, mk.gds_datatype)
        assert li is not None, (mk.gds_layer, mk.gds_datatype)
        got = kdb.Region(layout.cell(info.tile_cell).begin_shapes_rec(li)).merged()
        assert (got ^ reference_region(mk.bitmap, (1, 1), (0, 0))).is_empty(), mk.name
    assert check_written_gds(path, info, masks) == []


def test_cell_names_are_gds_safe_and_at_most_32_characters():
    for name in ("x" * 50, "µ-plate été 2020", ""):
        top, tile = cell_name(name, "TOP"), cell_name(name, "TILE")
        assert len(top) <= 32 and len(tile) <= 32 and top != tile
        assert re.fullmatch(r"[A-Za-z0-9_]+", top + tile)


def test_max_vertices_is_the_largest_polygon_of_the_library():
    masks = masks_from_levels(random_levels(6, seed=12), L, STEP)
    bare, _ = build_library(masks, PITCH, (2, 2), "t", marks=False)
    assert max_vertices(bare) == 4  # rectangles only
    marked, _ = build_library(masks, PITCH, (2, 2), "t")
    assert max_vertices(marked) >= 12  # the alignment cross is one 12-vertex polygon


def test_single_pixel_at_row0_col0_lands_top_left(tmp_path):
    levels = np.full((10, 10), L - 1, np.uint8)
    levels[0, 0] = L - 2  # etched by the shallow mask only
    path, masks, info = write_plate(tmp_path, levels, tiles=(1, 1), marks=False)
    layout = read_layout(path)
    tile = layout.cell(info.tile_cell)
    shapes = {
        m.name: [s.bbox() for s in tile.shapes(layout.find_layer(m.gds_layer, 0)).each()]
        for m in masks
        if layout.find_layer(m.gds_layer, 0) is not None
    }
    assert shapes.get("M1_deep", []) == [] and shapes.get("M2_mid", []) == []
    (box,) = shapes["M3_shallow"]
    # x in [0, p], y in [(N-1) p, N p]: the top-left pixel, viewed onto the patterned surface.
    assert (box.left, box.bottom, box.right, box.top) == (0, 9 * PITCH, PITCH, 10 * PITCH)


def test_tile_is_one_cell_placed_by_one_aref(tmp_path):
    levels = random_levels(9, seed=1)
    path, masks, info = write_plate(tmp_path, levels, tiles=(4, 3))
    layout = read_layout(path)
    assert abs(layout.dbu - 0.001) < 1e-12
    top = layout.cell(info.top_cell)
    insts = list(top.each_inst())
    assert len(insts) == 1
    inst = insts[0]
    assert layout.cell(inst.cell_index).name == info.tile_cell
    assert inst.is_regular_array()
    lattice = {(inst.na, inst.a.x, inst.a.y), (inst.nb, inst.b.x, inst.b.y)}
    assert lattice == {(4, 9 * PITCH, 0), (3, 0, 9 * PITCH)}  # 4 columns along x, 3 rows along y
    assert (inst.trans.disp.x, inst.trans.disp.y) == info.array_origin_nm
    assert check_written_gds(path, info, masks) == []


def test_pattern_vertices_on_pixel_grid_and_rectangles_only(tmp_path):
    levels = random_levels(15, seed=2)
    path, masks, info = write_plate(tmp_path, levels, tiles=(2, 2))
    layout = read_layout(path)
    tile = layout.cell(info.tile_cell)
    for mk in masks:
        li = layout.find_layer(mk.gds_layer, 0)
        area = 0
        for s in tile.shapes(li).each():
            poly = s.polygon
            pts = [(pt.x, pt.y) for pt in poly.each_point_hull()]
            assert len(pts) == 4 and poly.is_box()
            assert all(x % PITCH == 0 and y % PITCH == 0 for x, y in pts)
            area += poly.area()
        assert area == mk.bitmap.sum() * PITCH**2  # no overlaps, no gaps


def test_gds_bytes_identical_for_a_fixed_design(tmp_path):
    levels = random_levels(11, seed=4)
    a, *_ = write_plate(tmp_path, levels, name="a.gds")
    b, *_ = write_plate(tmp_path, levels, name="b.gds")
    assert a.read_bytes() == b.read_bytes()
    c, *_ = write_plate(tmp_path, random_levels(11, seed=5), name="c.gds")
    assert a.read_bytes() != c.read_bytes()


def test_library_units_are_um_and_nm():
    levels = random_levels(5)
    masks = masks_from_levels(levels, L, STEP)
    built, _ = build_library(masks, PITCH, (1, 1), "u")
    assert built.unit == 1e-6 and built.precision == 1e-9


def test_marks_labels_outline_outside_the_aperture(tmp_path):
    levels = random_levels(10, seed=6)
    tiles = (4, 4)
    aperture = 14_000_000  # a tiny tiled area inside the preset's aperture
    path, masks, info = write_plate(tmp_path, levels, tiles, aperture_nm=aperture)
    layout = read_layout(path)
    top = layout.cell(info.top_cell)
    x0, y0 = info.array_origin_nm
    tiled = kdb.Region(kdb.Box(x0, y0, -x0, -y0))
    a = aperture // 2
    clear = kdb.Region(kdb.Box(-a, -a, a, a))
    h = mk_marks.plate_half_size_nm(a)
    plate = kdb.Box(-h, -h, h, h)
    pattern_layers = {mk.gds_layer for mk in masks}
    extra = [layout.get_info(li) for li in layout.layer_indexes()]
    extra = [i.layer for i in extra if i.layer not in pattern_layers]
    assert extra == [mk_marks.OUTLINE_LAYER]  # marks and labels live on the mask layers
    outline = flat_layer(layout, info.top_cell, mk_marks.OUTLINE_LAYER)
    assert (outline & clear).is_empty(), "the outline draws inside the aperture"
    for mk in masks:
        # Every mask carries marks and a label; all of it outside the clear aperture,
        # inside the plate; within the tiled area a mask layer holds only its pattern.
        marks = flat_layer(layout, info.top_cell, mk.gds_layer) - tiled
        assert not marks.is_empty(), f"mask {mk.name} has no marks"
        assert (marks & clear).is_empty(), f"layer {mk.gds_layer} draws inside the aperture"
        assert (plate & marks.bbox()) == marks.bbox(), f"layer {mk.gds_layer} leaves the plate"
    assert top.bbox().width() == 2 * mk_marks.plate_half_size_nm(aperture // 2)


@pytest.mark.parametrize(
    ("n_levels", "aperture_mm"), [(8, 14.0), (8, 3.3), (8, 0.9), (16, 0.9), (64, 3.3), (128, 14.0)]
)
def test_marks_and_labels_of_different_masks_never_overlap_and_stay_on_the_plate(
    n_levels, aperture_mm
):
    # Labels sat at a fixed x beside marks that move with the aperture: below ~3.9 mm
    # they were etched over the marks of the next masks, and from 5 masks on they ran
    # off the plate. Marks of two masks may touch (vernier combs abut), never overlap,
    # but where an etch-depth pad is etched by both masks (its code has both bits).
    import gdstk

    masks = masks_from_levels(random_levels(6, seed=3) % n_levels, n_levels, STEP)
    a = round(aperture_mm * 1e6) // 2
    polys, _ = mk_marks.marks_and_labels(masks, a, "sun2020")
    pads, _ = mk_marks.monitor_plan(masks, a)
    by_layer = {}
    for p in polys:
        by_layer.setdefault(p.layer, []).append(p)
    layers = sorted(set(by_layer) - {mk_marks.OUTLINE_LAYER})
    assert len(layers) == len(masks)
    for i, first in enumerate(layers):
        for second in layers[i + 1 :]:
            common = gdstk.boolean(by_layer[first], by_layer[second], "and")
            shared = [p for p in pads if first in p.layers and second in p.layers]
            expected = sum((p.size_nm / 1000) ** 2 for p in shared)
            assert sum(q.area() for q in common) == pytest.approx(expected), (first, second)
    points = np.concatenate([p.points for p in polys]) * 1000  # nm
    assert np.abs(points).max() <= mk_marks.plate_half_size_nm(a)
    assert np.abs(points - np.round(points)).max() < 1e-6  # on the 1 nm grid
    labels = [p for p in polys if p.layer != mk_marks.OUTLINE_LAYER and p.points[:, 1].max() < 0]
    assert all(np.abs(p.points).max() * 1000 > a for p in labels)


def test_labels_etch_names_outside_ascii_legibly():
    # gdstk's font draws printable ASCII only: "µ-plate" was etched as "-plate".
    masks = masks_from_levels(random_levels(6, seed=3), 8, STEP)

    def label_points(name):
        polys, _ = mk_marks.marks_and_labels(masks, 7_000_000, name)
        return [p.points.tolist() for p in polys]

    assert label_points("µ-plate_été") == label_points("u-plate_ete")
    assert label_points("设计") == label_points("??")


@pytest.mark.parametrize("name", ["sun2020", string.punctuation, string.ascii_letters + "0123"])
def test_labels_hold_no_zero_width_neck_or_gap(name):
    # gdstk's font draws the slash of "0" and parts of "&" as squares that meet only at
    # a corner: a zero-width neck that mask DRC flags (8 on each layer of sun2020's).
    masks = masks_from_levels(random_levels(6, seed=3), 8, STEP)
    polys, _ = mk_marks.marks_and_labels(masks, 7_000_000, name)
    for layer in {p.layer for p in polys}:
        region = kdb.Region()
        for p in (p for p in polys if p.layer == layer):
            points = np.round(p.points * 1000).astype(int).tolist()
            region.insert(kdb.Polygon([kdb.Point(x, y) for x, y in points]))
        region.merge()
        assert region.width_check(1).is_empty(), (name, layer)
        assert region.space_check(1).is_empty(), (name, layer)


def test_marks_of_too_many_masks_for_the_aperture_are_refused():
    masks = masks_from_levels(random_levels(6, seed=3) % 64, 64, STEP)
    with pytest.raises(ValueError, match="6 masks do not fit beside a 2 mm aperture"):
        mk_marks.marks_and_labels(masks, 1_000_000, "sun2020")


@pytest.mark.parametrize(("feature_nm", "resolution_um"), [(5_000, 0.2), (10_000, 0.4)])
def test_vernier_reads_the_overlay_in_steps_of_its_resolution(feature_nm, resolution_um):
    rules = mk_marks.mark_rules(feature_nm)
    polys = mk_marks.alignment_block(0, 0, ref_layer=1, layer=2, rules=rules)
    w, below = feature_nm / 1000, rules.box_outer_nm / 2000

    def bars(layer, axis):
        """(centre, length) of the bars of the x vernier (below the cross) or the y one."""
        out = []
        for p in polys:
            (x0, y0), (x1, y1) = p.bounding_box()
            if p.layer == layer and axis == "x" and y1 < -below and abs((x1 - x0) - w) < 1e-9:
                out.append((round((x0 + x1) / 2, 6), y1 - y0))
            if p.layer == layer and axis == "y" and x1 < -below and abs((y1 - y0) - w) < 1e-9:
                out.append((round((y0 + y1) / 2, 6), x1 - x0))
        return np.array(sorted(out))

    pitch = 2 * w  # bars and gaps of the later comb both the feature size
    for axis in ("x", "y"):  # x vernier below the cross, y vernier left of it: same reading
        (ref, ref_len), (moving, moving_len) = bars(1, axis).T, bars(2, axis).T
        assert len(ref) == len(moving) == 2 * mk_marks.VERNIER_BARS + 1
        assert np.allclose(np.diff(moving), pitch)
        assert np.allclose(np.diff(ref), pitch + resolution_um)
        assert np.diff(ref).min() - w >= w  # the reference comb's gaps too
        # an overlay error of k resolutions lines up bar k of the two scales
        for k in (-4, 3):
            shift = k * resolution_um
            i = np.argmin(np.abs(moving + shift - ref[:, None]).min(axis=0))
            assert np.isclose(moving[i] + shift, ref[i]) and i - mk_marks.VERNIER_BARS == k
        # the longer zero bars, which find the scale's zero, lie on the cross's axis
        assert ref[np.argmax(ref_len)] == 0 and moving[np.argmax(moving_len)] == 0
    # cross on the reference mask, box on the later one
    (cross,) = [p for p in polys if len(p.points) == 12]
    arm, width = rules.cross_arm_nm / 1000, rules.cross_width_nm / 1000
    assert cross.layer == 1 and width >= w
    assert np.allclose(cross.bounding_box(), ((-arm / 2, -arm / 2), (arm / 2, arm / 2)))
    assert cross.area() == pytest.approx(2 * arm * width - width**2)


def test_every_mask_carries_its_own_label_in_exposure_order():
    masks = masks_from_levels(random_levels(6, seed=3), L, STEP)
    a = 7_000_000
    polys, _ = mk_marks.marks_and_labels(masks, a, "sun2020")
    # the label band: below the aperture, above the lower mark blocks, which reach at most
    # 104.5 um (the x vernier's end bar: 10 x 10.2 um + 2.5 um) above their crosses at
    # y = -(a + 0.75 mm)
    low = -(a + mk_marks.MARK_RING_NM) + 104_500
    centres = []
    for mk in masks:
        ys = [
            p.points[:, 1] * 1000
            for p in polys
            if p.layer == mk.gds_layer
            and low < p.points[:, 1].min() * 1000
            and p.points[:, 1].max() * 1000 < -a
        ]
        assert ys, f"no label on layer {mk.gds_layer} ({mk.name})"
        centres.append(np.concatenate(ys).mean())
    assert centres == sorted(centres, reverse=True)  # the first exposure's label on top


@pytest.mark.parametrize("aperture_mm", [2.0, 2.4, 2.8, 14.0])
def test_mark_blocks_of_successive_masks_keep_the_label_gap_or_are_refused(aperture_mm):
    masks = masks_from_levels(random_levels(6, seed=3) % 64, 64, STEP)
    a = round(aperture_mm * 1e6) // 2
    try:
        polys, _ = mk_marks.marks_and_labels(masks, a, "t")
    except ValueError:
        return  # too many masks for this aperture: refused
    ring = a + mk_marks.MARK_RING_NM
    extents = []  # x extent of each later mask's own part of its lower-left block
    for mk in masks[1:]:
        pts = np.concatenate([p.points for p in polys if p.layer == mk.gds_layer]) * 1000
        # below the labels, above the monitors of the band under the blocks
        reach = mk_marks.mark_rules().reach_left_nm
        block = pts[(pts[:, 0] < 0) & (pts[:, 1] < -ring + 110_000) & (pts[:, 1] >= -ring - reach)]
        extents.append((block[:, 0].min(), block[:, 0].max()))
    extents.sort()
    gaps = [lo - hi for (_, hi), (lo, _) in itertools.pairwise(extents)]
    assert min(gaps) >= mk_marks.LABEL_GAP_NM


def test_oasis_reads_back_as_the_same_masks(tmp_path):
    levels = random_levels(13, seed=7)
    path, masks, info = write_plate(tmp_path, levels, tiles=(2, 3))
    oas = tmp_path / "plate.oas"
    write_oasis(path, oas)
    assert check_written_gds(oas, info, masks) == []


def test_readback_detects_a_mirrored_layer(tmp_path):
    levels = random_levels(8, seed=8)
    masks = masks_from_levels(levels, L, STEP)
    lib, info = build_library(masks, PITCH, (2, 2), "t")
    path = tmp_path / "ok.gds"
    write_gds(lib, path)
    flipped = [masks[0], masks[1], masks_from_levels(levels[::-1], L, STEP)[2]]
    problems = check_written_gds(path, info, flipped)
    assert len(problems) == 1 and "M3_shallow" in problems[0]


def test_readback_detects_a_single_wrong_pixel(tmp_path):
    levels = random_levels(8, seed=8)
    path, masks, info = write_plate(tmp_path, levels, (2, 2), marks=False)
    bitmap = masks[1].bitmap.copy()
    bitmap[2, 5] = not bitmap[2, 5]
    wrong = [masks[0], dataclasses.replace(masks[1], bitmap=bitmap), masks[2]]
    problems = check_written_gds(path, info, wrong)
    assert len(problems) == 1 and "M2_mid" in problems[0] and ": 1 pixels differ" in problems[0]


def tampered_plate(tmp_path, tiles, tamper):
    """Write the seed-8 plate's library after ``tamper(library, top cell)``.

    Returns the file, the layout info and the masks it was built from.
    """
    masks = masks_from_levels(random_levels(8, seed=8), L, STEP)
    lib, info = build_library(masks, PITCH, tiles, "t", marks=False)
    (top,) = [c for c in lib.cells if c.name == info.top_cell]
    tamper(lib, top)
    path = tmp_path / "tampered.gds"
    write_gds(lib, path)
    return path, info, masks


def test_readback_refuses_a_mirrored_tile_placement(tmp_path):
    # same displacements as the lattice, but every tile etched upside down
    def mirror(lib, top):
        top.references[0].x_reflection = True

    path, info, masks = tampered_plate(tmp_path, (2, 2), mirror)
    (problem,) = check_written_gds(path, info, masks)
    assert "mirror" in problem and str(path) in problem


def test_readback_refuses_a_database_unit_other_than_1_nm(tmp_path):
    def finer_unit(lib, top):
        lib.precision = 1e-10  # 0.1 nm database unit: every coordinate read 10 times too large

    path, info, masks = tampered_plate(tmp_path, (1, 1), finer_unit)
    (problem,) = check_written_gds(path, info, masks)
    assert "DBU" in problem and str(path) in problem


def test_readback_refuses_a_tile_off_its_lattice(tmp_path):
    def shift(lib, top):
        x, y = top.references[0].origin
        top.references[0].origin = (x + 8 * PITCH, y)  # one tile to the right, onto its neighbour

    path, info, masks = tampered_plate(tmp_path, (2, 2), shift)
    (problem,) = check_written_gds(path, info, masks)
    assert problem == f"the tile is not placed on the 2 x 2 lattice at {info.array_origin_nm} nm"


def test_readback_counts_only_placements_of_the_tile(tmp_path):
    def add_logo(lib, top):
        logo = lib.new_cell("LOGO")
        logo.add(gdstk.rectangle((0, 0), (1000, 1000), layer=99))
        top.add(gdstk.Reference(logo, (10**6, 0)))  # another cell placed beside the array

    path, info, masks = tampered_plate(tmp_path, (2, 2), add_logo)
    assert check_written_gds(path, info, masks) == []


@pytest.mark.parametrize("cell", ["top_cell", "tile_cell"])
def test_readback_names_a_missing_cell(tmp_path, cell):
    path, masks, info = write_plate(tmp_path, random_levels(8, seed=8), (2, 2), marks=False)
    (problem,) = check_written_gds(path, dataclasses.replace(info, **{cell: "NOPE"}), masks)
    assert problem.startswith(f"{path}: ") and "cell 'NOPE'" in problem


def test_tile_image_round_trips_through_openimageio(tmp_path):
    bitmap = np.zeros((7, 9), bool)
    bitmap[0, 0] = True  # top-left pixel etched
    bitmap[6, 3] = True
    path = tmp_path / "m.tif"
    write_image(path, tile_image(bitmap))
    back = read_image(path)
    assert back.shape == (7, 9) and back.dtype == np.uint8
    assert back[0, 0] == 255 and back[6, 3] == 255 and back.sum() == 2 * 255
    first = path.read_bytes()
    write_image(path, tile_image(bitmap))
    assert path.read_bytes() == first  # pinned DateTime


def test_a_2d_image_is_written_as_one_grey_channel(tmp_path):
    img = np.arange(6 * 5, dtype=np.uint8).reshape(6, 5) * 8  # no two pixels alike
    write_image(tmp_path / "g.png", img)
    assert np.array_equal(read_image(tmp_path / "g.png"), img)


@pytest.mark.parametrize("name", ["nowhere/m.tif", "m.not-an-image-format"])
def test_an_image_that_cannot_be_written_raises_naming_the_file(tmp_path, name):
    with pytest.raises(OSError, match=re.escape(str(tmp_path / name))):
        write_image(tmp_path / name, tile_image(np.ones((3, 3), bool)))
    assert not (tmp_path / name).exists()


def test_plate_preview_refuses_an_array_larger_than_the_plate():
    with pytest.raises(ValueError, match="does not fit inside the plate"):
        plate_preview(np.ones((10, 10), bool), (4, 4), PITCH, 50_000, 40_000, max_px=60)


@pytest.mark.parametrize("plate_half", [2_000_000, 12_000_000])  # 1 and 5 mask px per preview px
def test_layer_images_record_their_pixel_size(tmp_path, plate_half):
    # read by Pillow, not the writer's library: a viewer shows the mask at true scale
    from PIL import Image

    from fab.package.layer_images import write_layer_images

    masks = masks_from_levels(random_levels(10, seed=4), L, STEP)
    names = write_layer_images(tmp_path, masks, (4, 4), PITCH, plate_half, 1_000_000)
    for name in names:
        with Image.open(tmp_path / name) as im:
            pixel_nm = 25.4e6 / im.info["dpi"][0]
            assert im.info["dpi"][0] == pytest.approx(im.info["dpi"][1])
            width = im.width
        if name.endswith(".tif"):
            assert pixel_nm == pytest.approx(PITCH, rel=1e-6) and width == 10
        else:  # the preview spans the plate, in whole mask pixels per preview pixel
            assert pixel_nm == pytest.approx(round(pixel_nm / PITCH) * PITCH, rel=1e-5)
            assert width * pixel_nm == pytest.approx(2 * plate_half, abs=pixel_nm)


def test_plate_preview_places_the_tiles_and_the_outline(tmp_path):
    bitmap = np.ones((10, 10), bool)
    img = plate_preview(
        bitmap, (4, 4), PITCH, plate_half_nm=150_000, aperture_half_nm=110_000, max_px=60
    )
    assert img.shape[2] == 1
    img = img[:, :, 0]
    size = img.shape[0]
    assert img.shape == (size, size)
    centre = img[size // 2 - 5 : size // 2 + 5, size // 2 - 5 : size // 2 + 5]
    assert np.all(centre == 255)  # fully etched tiles
    assert img[0, size // 2] == 128  # plate edge drawn
    write_image(tmp_path / "p.png", img[:, :, None])
    assert np.array_equal(read_image(tmp_path / "p.png"), img)


def test_plate_preview_draws_both_frames_on_their_edge_pixels():
    # 1 um preview pixels: the plate (+-20 um) spans pixels 0..39, the aperture (+-12 um)
    # pixels 8..31; each frame is drawn on the outermost pixels inside its edge.
    img = plate_preview(np.zeros((5, 5), bool), (2, 2), 1000, 20_000, 12_000)[:, :, 0]
    want = np.zeros((40, 40), np.uint8)
    want[[0, -1], :] = want[:, [0, -1]] = 128
    want[[8, 31], 8:32] = want[8:32, [8, 31]] = 128
    assert np.array_equal(img, want)


@settings(max_examples=40, deadline=None)
@given(
    arrays(bool, st.integers(1, 9).map(lambda n: (n, n))),
    st.tuples(st.integers(1, 4), st.integers(1, 4)),
    st.integers(1, 40),
)  # fmt: skip
def test_plate_preview_is_the_block_mean_of_the_tiled_plate(bitmap, tiles, max_px):
    """Reference: tile the plate, pad to whole blocks, average each f x f block."""
    n, pitch = bitmap.shape[0], 1000
    half = max(tiles) * n * pitch // 2 + 1
    img = plate_preview(bitmap, tiles, pitch, half, half, max_px=max_px)[:, :, 0]
    f = max(1, -(-2 * half // (pitch * max_px)))
    plate = np.tile(bitmap, (tiles[1], tiles[0]))
    h, w = -(-plate.shape[0] // f) * f, -(-plate.shape[1] // f) * f
    padded = np.zeros((h, w))
    padded[: plate.shape[0], : plate.shape[1]] = plate
    blocks = padded.reshape(h // f, f, w // f, f).mean(axis=(1, 3))
    expected = np.rint(blocks * 255).astype(np.uint8)
    size, s = img.shape[0], f * pitch
    top = round(size / 2 - plate.shape[0] * pitch / 2 / s)
    left = round(size / 2 - plate.shape[1] * pitch / 2 / s)
    inner = img[top : top + blocks.shape[0], left : left + blocks.shape[1]]
    # the outlines go under the array: one crossing its first row once hid the pattern
    assert np.array_equal(inner, expected[: inner.shape[0], : inner.shape[1]])
    assert img.sum(dtype=int) - 128 * int((img == 128).sum()) <= expected.sum(dtype=int)


def test_plate_preview_never_builds_the_whole_plate():
    """A 0.25 um pitch plate is ~3 gigapixels per mask; the preview must not tile it."""
    import tracemalloc

    n, tiles, pitch = 64, (300, 300), 250  # a 19,200^2 plate: 369 MB as uint8
    half = tiles[0] * n * pitch // 2  # array edge; the plate outline lies 10 % outside it
    bitmap = np.random.default_rng(0).random((n, n)) < 0.5
    tracemalloc.start()
    img = plate_preview(bitmap, tiles, pitch, half * 11 // 10, half * 11 // 10)[:, :, 0]
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert img.shape[0] <= 1024
    assert peak < 50e6, f"preview allocated {peak / 1e6:.0f} MB"
    f = -(-2 * (half * 11 // 10) // (pitch * 1024))
    inside = img[np.abs(np.arange(img.shape[0]) - img.shape[0] / 2) < 2 * half / pitch / f / 2]
    etched = inside[:, 1:-1].sum(dtype=float) / 255 * f**2  # columns 0, -1: the outline
    assert etched == pytest.approx(tiles[0] * tiles[1] * bitmap.sum(), rel=0.005)


@pytest.mark.parametrize("tiles", [(1, 1), (2, 5)])
def test_full_plate_raster_matches_tiled_levels(tmp_path, tiles):
    """Tiny KLayout read-back: flatten, sample every pixel centre, rebuild levels."""
    n = 7
    levels = random_levels(n, seed=9)
    path, masks, info = write_plate(tmp_path, levels, tiles)
    layout = read_layout(path)
    x0, y0 = info.array_origin_nm
    nx, ny = tiles[0] * n, tiles[1] * n
    depth = np.zeros((ny, nx))
    for mk in masks:
        region = flat_layer(layout, info.top_cell, mk.gds_layer)
        probe = region.rasterize(
            kdb.Point(x0 + PITCH // 2 - 1, y0 + PITCH // 2 - 1), kdb.Vector(PITCH, PITCH),
            kdb.Vector(2, 2), nx, ny,
        )  # fmt: skip
        depth += (np.array(probe) > 0) * mk.steps
    rebuilt = (L - 1) - np.flipud(depth).astype(int)
    assert np.array_equal(rebuilt, np.tile(levels, (tiles[1], tiles[0])))


@settings(max_examples=25, deadline=None)
@given(
    arrays(np.uint8, st.tuples(st.integers(1, 8)).map(lambda t: (t[0], t[0])),
           elements=st.integers(0, L - 1)),
    st.tuples(st.integers(1, 3), st.integers(1, 3)),
)  # fmt: skip
def test_any_tile_reads_back_exactly(levels, tiles):
    with tempfile.TemporaryDirectory() as tmp:
        path, masks, info = write_plate(Path(tmp), levels, tiles, marks=False)
        assert check_written_gds(path, info, masks) == []
        layout = read_layout(path)
        n = levels.shape[0]
        x0, y0 = info.array_origin_nm
        depth = np.zeros((tiles[1] * n, tiles[0] * n))
        for mk in masks:
            li = layout.find_layer(mk.gds_layer, 0)
            if li is None:  # a mask with nothing to etch has no shapes
                assert not mk.bitmap.any()
                continue
            region = kdb.Region(layout.cell(info.top_cell).begin_shapes_rec(li))
            probe = region.rasterize(
                kdb.Point(x0 + PITCH // 2 - 1, y0 + PITCH // 2 - 1), kdb.Vector(PITCH, PITCH),
                kdb.Vector(2, 2), tiles[0] * n, tiles[1] * n,
            )  # fmt: skip
            depth += (np.array(probe) > 0) * mk.steps
        rebuilt = (L - 1) - np.flipud(depth).astype(int)
        assert np.array_equal(rebuilt, np.tile(levels, (tiles[1], tiles[0])))


def test_worst_case_n175_design_stays_under_5_mb(tmp_path):
    """A checkerboard of levels 0 / L-1 makes every mask a checkerboard: the most rectangles
    row-run merging can produce (N^2 / 2 per mask)."""
    n = 175
    levels = ((np.add.outer(np.arange(n), np.arange(n)) % 2) * (L - 1)).astype(np.uint8)
    path, _, info = write_plate(tmp_path, levels, tiles=(16, 16))
    assert all(count == (n * n + 1) // 2 for count in info.polygon_counts.values())
    assert path.stat().st_size <= 5 * 10**6


def test_a_mask_that_etches_nothing_keeps_its_layer(tmp_path):
    # Level 5 = etch code 2: only the middle mask etches; the deep and shallow
    # masks are empty in the tile but must still exist (marks, label) so that a
    # reader finds every mask layer the manifest names.
    levels = np.full((10, 10), 5, np.uint8)
    path, masks, _ = write_plate(tmp_path, levels, (2, 2), aperture_nm=14_000_000)
    layout = read_layout(path)
    assert [mk.bitmap.any() for mk in masks] == [False, True, False]
    for mk in masks:
        assert layout.find_layer(mk.gds_layer, 0) is not None, f"{mk.name} layer missing"


@pytest.mark.parametrize(
    ("tiles", "aperture_nm"),
    [((1, 40), None), ((40, 1), None), ((2, 80), None), ((40, 40), 100_000)],
)
def test_marks_never_etch_inside_a_non_square_tiled_array(tiles, aperture_nm):
    # Without an aperture the marks go outside the tiled array: along its longer side too;
    # an aperture smaller than the array (here 0.1 mm < 2.4 mm) does not pull them inside.
    levels = np.random.default_rng(0).integers(0, 8, (12, 12)).astype(np.uint8)
    masks = masks_from_levels(levels, 8, STEP)
    lib, info = build_library(masks, 4990, tiles, "t", aperture_nm=aperture_nm)
    (top,) = [c for c in lib.cells if c.name == info.top_cell]
    x0, y0 = info.array_origin_nm
    array = gdstk.rectangle((x0 / 1000, y0 / 1000), (-x0 / 1000, -y0 / 1000))
    etched = [p for p in top.polygons if p.layer != mk_marks.OUTLINE_LAYER]
    assert etched, "marks and labels are drawn"
    assert sum(p.area() for p in gdstk.boolean(etched, [array], "and")) == 0
