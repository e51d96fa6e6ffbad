"""Design-rule checks (layouts.drc): counts against brute force on the bitmap and a flat
KLayout run on the whole GDS, single rules on drawn shapes, the marker database and the deck."""

import shutil
import subprocess

import gdstk
import klayout.db as kdb
import numpy as np
import pytest

from fab.package.masks import masks_from_levels
from layouts.drc import RULES, check_plate, plate_rules
from layouts.drc_deck import deck_text, deck_xml
from layouts.drc_rdb import MAX_ITEMS, category_name, read_lyrdb_counts, write_lyrdb
from layouts.gds import build_library, write_gds

PITCH = 5000


def corner_contacts(bitmap):
    """Brute force: 2 x 2 windows set on one diagonal only, the plate padded with clear."""
    b = np.pad(bitmap, 1)
    a, r, c, d = b[:-1, :-1], b[1:, :-1], b[:-1, 1:], b[1:, 1:]
    return int(np.count_nonzero((a & d & ~r & ~c) | (r & c & ~a & ~d)))


def checker_levels(n, seed):
    """A 4-level tile: random 2 x 2 blocks (no corner contacts) plus hand-placed
    checkerboard patches, some on the tile's edges so that contacts cross tiles."""
    rng = np.random.default_rng(seed)
    levels = np.kron(rng.integers(0, 4, (n // 2, n // 2)), np.ones((2, 2), int))
    board = (np.indices((4, 4)).sum(axis=0) % 2) * 3
    levels[1:5, 1:5] = board
    levels[n - 3 :, 3:7] = board[:3]  # bottom edge: touches the next tile's top row
    levels[5:9, n - 2 :] = board[:, :2]  # right edge
    return levels.astype(np.uint8)


@pytest.fixture(scope="module")
def plate(tmp_path_factory):
    """A 3 x 2 array of a 12-pixel, 2-mask tile without marks, and its DRC."""
    path = tmp_path_factory.mktemp("drc") / "plate.gds"
    levels = checker_levels(12, seed=1)
    masks = masks_from_levels(levels, 4, 1e-7)
    lib, _ = build_library(masks, PITCH, (3, 2), "drc", marks=False)
    write_gds(lib, path)
    rules = plate_rules([mk.gds_layer for mk in masks], PITCH, 1)
    return path, masks, rules, check_plate(path, rules)


def flat_counts(path, rules):
    """An independent run: the whole GDS flattened, KLayout's checks at the same values."""
    layout = kdb.Layout()
    layout.read(str(path))
    top, euclid, out = layout.top_cell(), kdb.Metrics.Euclidian, {}
    for layer in rules.layers:
        region = kdb.Region(top.begin_shapes_rec(layout.find_layer(layer, 0)))
        out[(layer, "width")] = region.width_check(rules.min_width_nm, False, euclid).count()
        out[(layer, "space")] = region.space_check(rules.min_space_nm, False, euclid).count()
        out[(layer, "notch")] = region.notch_check(rules.min_space_nm, False, euclid).count()
        out[(layer, "area")] = region.with_area(0, rules.min_area_nm2, False).count()
    return out


def test_corner_contacts_match_brute_force_across_tiles(plate):
    _, masks, _, result = plate
    by_rule = {(c.layer, c.rule): c for c in result.counts}
    for mk in masks:
        tiled = np.tile(mk.bitmap, (2, 3))  # rows of tiles along y, columns along x
        want = corner_contacts(tiled)
        assert want > 2 * corner_contacts(mk.bitmap)  # some contacts cross tile edges
        assert result.corner_contacts[mk.gds_layer] == want
        # every marker is a corner contact: a pixel is as wide as the feature size
        for rule in ("width", "space", "notch"):
            c = by_rule[(mk.gds_layer, rule)]
            assert c.count == c.at_corners == 2 * want
        assert by_rule[(mk.gds_layer, "area")].count == 0
        assert by_rule[(mk.gds_layer, "off_grid")].count == 0


def test_hierarchical_counts_equal_a_flat_run_on_the_whole_gds(plate):
    path, _, rules, result = plate
    ours = {(c.layer, c.rule): c.count for c in result.counts}
    for key, count in flat_counts(path, rules).items():
        assert ours[key] == count


@pytest.mark.parametrize("feature", [PITCH, PITCH + 1500])
def test_a_large_array_counted_from_small_ones_equals_a_flat_run(tmp_path, feature):
    # 7 x 6 tiles: counted from 3 x 3 ... 4 x 4 arrays; with the feature above the pitch
    # every single-pixel line, gap and pixel is a marker too, many across the seams
    levels = np.random.default_rng(5).integers(0, 4, (10, 10)).astype(np.uint8)
    masks = masks_from_levels(levels, 4, 1e-7)
    lib, _ = build_library(masks, PITCH, (7, 6), "drc", marks=False)
    write_gds(lib, tmp_path / "big.gds")
    rules = plate_rules([1, 2], feature, 1)
    result = check_plate(tmp_path / "big.gds", rules)
    ours = {(c.layer, c.rule): c.count for c in result.counts}
    flat = flat_counts(tmp_path / "big.gds", rules)
    assert sum(flat.values()) > 0 and ours == {**ours, **flat}
    for mk in masks:
        want = corner_contacts(np.tile(mk.bitmap, (6, 7)))
        assert result.corner_contacts[mk.gds_layer] == want


@pytest.mark.parametrize(
    ("tiles", "aperture", "feature"),
    [((7, 6), 380_000, PITCH), ((3, 2), 180_000, PITCH)],
)
def test_a_filled_plate_counts_its_edge_tiles_as_a_flat_run_does(
    tmp_path, tiles, aperture, feature
):
    # clipped edge tiles complete the aperture round the array: 3 pixel columns and 8
    # rows each side; 7 x 6 tiles are counted from small plates, 3 x 2 checked whole
    levels = np.random.default_rng(5).integers(0, 4, (10, 10)).astype(np.uint8)
    masks = masks_from_levels(levels, 4, 1e-7)
    lib, info = build_library(
        masks, PITCH, tiles, "drc", aperture_nm=aperture, marks=False, mode="fill"
    )
    assert len(info.edge_cells) == 8 and info.plate.edge_pixels == (3, 3, 8, 8)
    write_gds(lib, tmp_path / "filled.gds")
    rules = plate_rules([1, 2], feature, 1)
    result = check_plate(tmp_path / "filled.gds", rules)
    ours = {(c.layer, c.rule): c.count for c in result.counts}
    flat = flat_counts(tmp_path / "filled.gds", rules)
    assert sum(flat.values()) > 0 and ours == {**ours, **flat}
    (c0, c1), (r0, r1) = info.plate.pixel_span()
    for mk in masks:
        pixels = mk.bitmap[np.ix_(np.arange(r0, r1) % 10, np.arange(c0, c1) % 10)]
        assert result.corner_contacts[mk.gds_layer] == corner_contacts(pixels)


def _gds(path, rects, layer=1):
    lib = gdstk.Library(unit=1e-6, precision=1e-9)
    cell = lib.new_cell("TOP")
    cell.add(*(gdstk.rectangle(a, b, layer=layer) for a, b in rects))
    lib.write_gds(str(path))
    return path


def _counts(result):
    return {c.rule: (c.count, c.at_corners) for c in result.counts}


def test_a_narrow_line_a_small_gap_and_a_small_square(tmp_path):
    path = _gds(
        tmp_path / "a.gds",
        [
            ((0, 0), (4, 100)),  # 4 um wide line
            ((7, 0), (20, 100)),  # 3 um from it
            ((100, 0), (103, 3)),  # 3 x 3 um square
        ],
    )
    got = _counts(check_plate(path, plate_rules([1], 5000, 1)))
    assert got["width"] == (3, 0)  # the line's long sides, and the square both ways
    assert got["space"] == (1, 0)
    assert got["notch"] == (0, 0)  # the gap lies between two polygons
    assert got["area"] == (1, 0)  # 9 um^2 < 25 um^2
    assert got["off_grid"] == (0, 0)


def test_off_grid_vertices_are_found(tmp_path):
    path = _gds(tmp_path / "g.gds", [((0, 0), (20.003, 20)), ((40, 0), (60, 20))])
    got = _counts(check_plate(path, plate_rules([1], 5000, 5)))
    assert got["off_grid"] == (2, 0)  # the two vertices at x = 20.003 um
    assert _counts(check_plate(path, plate_rules([1], 5000, 1)))["off_grid"] == (0, 0)


def test_a_notch_inside_one_polygon(tmp_path):
    # a U: two arms 3 um apart joined at the bottom
    path = _gds(tmp_path / "u.gds", [((0, 0), (23, 10)), ((0, 10), (10, 30)), ((13, 10), (23, 30))])
    got = _counts(check_plate(path, plate_rules([1], 5000, 1)))
    assert got["notch"] == (1, 0) and got["space"] == (1, 0) and got["width"] == (0, 0)


def test_marker_database_loads_back_with_the_counts(plate, tmp_path):
    path, _, _, result = plate
    write_lyrdb(tmp_path / "m.lyrdb", result, path.name, "drc")
    counts = read_lyrdb_counts(tmp_path / "m.lyrdb")
    want = {category_name(c.layer, c.rule): c.count for c in result.counts}
    assert all(v <= MAX_ITEMS for v in want.values()) and sum(want.values()) > 0
    assert counts == want


def test_deck_names_every_layer_and_rule(plate):
    _, _, rules, _ = plate
    text = deck_text(rules, "drc")
    for layer in rules.layers:
        assert f"input({layer}, 0)" in text
        assert all(f'output("{category_name(layer, rule)}"' in text for rule in RULES)
    assert "euclidian" in text and "5.um" in text
    assert deck_xml(rules, "drc").startswith('<?xml version="1.0"')


@pytest.mark.skipif(shutil.which("klayout") is None, reason="no KLayout binary")
def test_the_deck_run_in_klayout_finds_the_same_counts(plate, tmp_path):
    path, _, rules, result = plate
    deck = tmp_path / "drc.lydrc"
    deck.write_text(deck_xml(rules, "drc"))
    report = tmp_path / "k.lyrdb"
    cmd = ["klayout", "-b", "-r", str(deck), "-rd", f"input={path}", "-rd", f"report={report}"]
    run = subprocess.run(
        [*cmd, "-rd", "flat=1"], check=True, timeout=300, capture_output=True, text=True
    )
    want = {category_name(c.layer, c.rule): c.count for c in result.counts}
    printed = dict(line.split() for line in run.stdout.splitlines() if line.startswith("L"))
    assert {k: int(v) for k, v in printed.items()} == want
    assert read_lyrdb_counts(report) == want  # flat: one item per marker, as ours
