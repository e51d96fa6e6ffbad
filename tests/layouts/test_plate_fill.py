"""The plate fills its clear aperture: clipped edge cells continue the periodic pattern
(KLayout read-back of the whole plate, Euclidean DRC), the read-back checks them, and
several dies sit on a substrate by one AREF with dicing lanes."""

import klayout.db as kdb
import numpy as np
import pytest

from fab.package.masks import masks_from_levels
from layouts.gds import build_library, write_gds
from layouts.marks import plate_half_size_nm
from layouts.plate_plan import DICING_LANE_LAYER, edge_pixels
from layouts.plate_raster import aperture_match
from layouts.readback import check_written_gds

L, STEP, PITCH, N = 4, 100e-9, 5000, 12
TILE = N * PITCH
APERTURE = round(3.3 * TILE)  # 3 whole tiles and 0.15 of a tile on each side


def plate(tmp_path, levels, mode, tiles=(3, 3), aperture=APERTURE, **kw):
    masks = masks_from_levels(levels, L, STEP)
    # marks=False: the marks sit 0.75 mm out and are sized by their own module
    lib, info = build_library(
        masks, PITCH, tiles, "fill", aperture, mode=mode, marks=kw.pop("marks", False), **kw
    )
    path = tmp_path / f"{mode}.gds"
    write_gds(lib, path)
    return path, masks, info


def test_edge_pixels_count_every_pixel_that_overlaps_the_aperture():
    rng = np.random.default_rng(1)
    for _ in range(200):
        p = int(rng.integers(3, 40))
        lo, hi = int(rng.integers(-500, 1)), int(rng.integers(0, 500))  # around the centre
        a = int(rng.integers(1, 700))
        below, above = edge_pixels(lo, hi, a, p)
        # brute force: pixel [lo - k p, lo - (k - 1) p] overlaps (-a, a) in more than a point
        want_below = sum(1 for k in range(1, 500) if lo - (k - 1) * p > -a and lo - k * p < a)
        want_above = sum(1 for k in range(1, 500) if hi + (k - 1) * p < a and hi + k * p > -a)
        assert (below, above) == (want_below, want_above)


@pytest.mark.parametrize("tiles", [(3, 3), (3, 2)])
def test_fill_puts_the_periodic_pattern_over_the_whole_aperture(tmp_path, tiles):
    levels = np.random.default_rng(0).integers(0, L, (N, N)).astype(np.uint8)
    path, masks, info = plate(tmp_path, levels, "fill", tiles=tiles)
    assert check_written_gds(path, info, masks) == []
    fraction, written, periodic = aperture_match(path, info.plate_cell, masks, levels, info.plate)
    assert fraction == 1.0 and written.shape == periodic.shape == (40, 40)  # 3.3 x 12 pixels
    assert info.plate.patterned_fraction() == 1.0
    # the pattern reaches past the aperture by less than one pixel on every side
    layout = kdb.Layout()
    layout.read(str(path))
    top = layout.cell(info.plate_cell)
    box = kdb.Region()
    for mk in masks:
        box += kdb.Region(top.begin_shapes_rec(layout.find_layer(mk.gds_layer, 0)))
    bb, a = box.bbox(), APERTURE // 2
    for edge in (-bb.left, -bb.bottom, bb.right, bb.top):
        assert a <= edge < a + PITCH
    assert len(info.edge_cells) == 8  # 4 strips, 4 corners: one cell each


def test_whole_tiles_in_the_frame_leave_plain_glass(tmp_path):
    levels = np.random.default_rng(0).integers(0, L, (N, N)).astype(np.uint8)
    path, masks, info = plate(tmp_path, levels, "glass")
    assert info.edge_cells == ()
    fraction, written, periodic = aperture_match(path, info.plate_cell, masks, levels, info.plate)
    inside = np.zeros(written.shape, bool)
    inside[2:38, 2:38] = True  # the 36 x 36 pixels of the whole tiles
    assert (written[inside] == periodic[inside]).all() and (written[~inside] == L - 1).all()
    glass = ~inside
    want = (inside.sum() + np.count_nonzero(periodic[glass] == L - 1)) / inside.size
    assert fraction == pytest.approx(want)
    assert info.plate.patterned_fraction() == pytest.approx((36 / 39.6) ** 2)


def test_fill_passes_a_euclidean_width_and_space_check_at_the_pixel(tmp_path):
    # stripes one to three pixels wide along x and y: no corner contacts in the tile, so
    # any violation would be a sliver cut from a pixel at the aperture's edge
    cols = np.repeat(np.arange(6) % 2, [1, 2, 3, 1, 3, 2])
    rows = np.repeat(np.arange(4) % 2, [3, 3, 2, 4])
    etched = (cols[None, :] == 1) & (rows[:, None] == 0)  # separated rectangles
    levels = np.where(etched, 0, L - 1).astype(np.uint8)
    path, masks, info = plate(tmp_path, levels, "fill")
    layout = kdb.Layout()
    layout.read(str(path))
    top = layout.cell(info.plate_cell)
    for mk in masks:
        region = kdb.Region(top.begin_shapes_rec(layout.find_layer(mk.gds_layer, 0))).merged()
        assert not region.is_empty()
        width = region.width_check(PITCH, False, kdb.Metrics.Euclidian)
        space = region.space_check(PITCH, False, kdb.Metrics.Euclidian)
        assert width.count() == 0 and space.count() == 0, mk.name


def _tamper_edge(path, info, how):
    layout = kdb.Layout()
    layout.read(str(path))
    name = info.edge_cells[0][0]
    cell = layout.cell(name)
    if how == "pixels":
        cell.clear_shapes()
    else:
        top = layout.cell(info.plate_cell)
        for inst in top.each_inst():
            if inst.cell_index == cell.cell_index():
                inst.transform(kdb.Trans(PITCH, 0))
    out = path.with_name("tampered.gds")
    layout.write(str(out))
    return out


@pytest.mark.parametrize("how", ["pixels", "placement"])
def test_readback_refuses_an_edge_cell_that_is_not_the_periodic_pattern(tmp_path, how):
    levels = np.random.default_rng(5).integers(0, L, (N, N)).astype(np.uint8)
    path, masks, info = plate(tmp_path, levels, "fill")
    problems = check_written_gds(_tamper_edge(path, info, how), info, masks)
    name = info.edge_cells[0][0]
    assert problems and all(name in p for p in problems)


def test_dies_place_the_plate_cell_by_one_aref_with_lanes_outside_the_masks(tmp_path):
    levels = np.random.default_rng(2).integers(0, L, (N, N)).astype(np.uint8)
    path, masks, info = plate(tmp_path, levels, "fill", dies=(2, 3), lane_nm=150_000, marks=True)
    assert check_written_gds(path, info, masks) == []
    dies = info.dies
    plate_nm = 2 * plate_half_size_nm(APERTURE // 2)
    assert (dies.plate_nm, dies.pitch_nm) == (plate_nm, plate_nm + 150_000)
    assert dies.substrate_nm == (2 * dies.pitch_nm, 3 * dies.pitch_nm)
    layout = kdb.Layout()
    layout.read(str(path))
    (top,) = layout.top_cells()
    assert top.name == info.top_cell != info.plate_cell
    (inst,) = list(top.each_inst())
    assert inst.is_regular_array() and inst.na * inst.nb == 6
    # the lanes lie between the plates, on their own layer, never on a mask layer
    lanes = kdb.Region(top.shapes(layout.find_layer(DICING_LANE_LAYER, 0))).merged()
    w, h = dies.substrate_nm
    assert lanes.bbox() == kdb.Box(-w // 2, -h // 2, w // 2, h // 2)
    for mk in masks:
        etched = kdb.Region(top.begin_shapes_rec(layout.find_layer(mk.gds_layer, 0)))
        assert (etched & lanes).is_empty()
    ox, oy = dies.origin_nm
    got = sorted((t.disp.x, t.disp.y) for t in inst.cell_inst.each_cplx_trans())
    pitch = dies.pitch_nm
    assert got == sorted((ox + i * pitch, oy + j * pitch) for i in range(2) for j in range(3))


def test_the_plate_preview_averages_whole_and_edge_tiles_on_the_array_grid():
    from fab.package.layer_images import plate_preview

    bitmap = np.random.default_rng(6).random((N, N)) < 0.5
    edges, f, pitch = (3, 5, 2, 4), 4, 1000
    half = 40_000  # 80 mask pixels across: f = 1 pixel at max_px 80, f = 4 at max_px 20
    img = plate_preview(bitmap, (3, 2), pitch, half, half, max_px=20, edge_pixels=edges)[:, :, 0]
    # brute force: the plate pixel by pixel (array centred), then 4 x 4 block means
    canvas = np.zeros((80, 80))
    # the 36 x 24 pixel array's upper-left pixel: centred, on the preview's block grid
    left, top = f * round((40 - 18) / f), f * round((40 - 12) / f)
    for r in range(-edges[3], 24 + edges[2]):
        for c in range(-edges[0], 36 + edges[1]):
            canvas[top + r, left + c] = bitmap[r % N, c % N]
    want = np.rint(canvas.reshape(20, f, 20, f).mean(axis=(1, 3)) * 255)
    inner = np.s_[1:19, 1:19]  # inside the grey plate outline
    assert np.array_equal(img[inner], want[inner]) and want[inner].any()
