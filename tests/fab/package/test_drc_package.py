"""``doefab fab``'s design-rule check: refusal, --allow-drc, manifest, report and markers,
checked against a flat KLayout run on the whole GDS and a brute-force count on the bitmap."""

import json
import re
from types import SimpleNamespace

import klayout.db as kdb
import numpy as np
import pytest

from doe.infra.cli import main
from doe.records.fab_manifest import DRC_DECK, DRC_MARKERS, MANIFEST_NAME, read_fab_manifest
from fab.package.build import build_package
from fab.package.drc import DrcRefused, allows_corner_contacts, refused_count, violation_summary
from fab.package.masks import masks_from_levels
from layouts.drc import check_plate, plate_rules
from layouts.drc_rdb import MAX_ITEMS, category_name, read_lyrdb_counts

# 532 nm, N-BK7, 4 levels, 10 um process, 2 x 2 tiles
GREEN = (
    'name = "green"\n[optics]\nwavelength_nm = 532.0\n[material]\nname = "bk7"\n'
    "[fabrication]\nlevels = 4\nfeature_size_um = 10.0\naperture_mm = 1.5\n"
)
# the default design at a 4 um process on a 2 mm aperture: every mark is at least 4 um
FINE = 'name = "fine"\n[fabrication]\nfeature_size_um = 4.0\naperture_mm = 2.0\n'


def corner_contacts(bitmap):
    """Brute force: 2 x 2 windows set on one diagonal only, the plate padded with clear."""
    b = np.pad(bitmap, 1)
    a, r, c, d = b[:-1, :-1], b[1:, :-1], b[:-1, 1:], b[1:, 1:]
    return int(np.count_nonzero((a & d & ~r & ~c) | (r & c & ~a & ~d)))


def plate_bitmap(bitmap, plate):
    """The filled plate's pixels: the tile repeated over the whole tiles and the edge
    pixels of the manifest's ``plate`` record (row 0 at the top)."""
    n, (nx, ny), e = bitmap.shape[0], plate["tiles"], plate["edge_pixels"]
    cols = np.arange(-e["left"], nx * n + e["right"]) % n
    rows = np.arange(-e["top"], ny * n + e["bottom"]) % n
    return bitmap[np.ix_(rows, cols)]


def design(root, toml, levels):
    root.mkdir(parents=True, exist_ok=True)
    (root / "design.toml").write_text(toml)
    np.save(root / "levels.npy", levels.astype(np.uint8))
    return root


def checker_levels(n, n_levels, seed=0):
    """Stripes (no corner contacts) with a checkerboard patch, one at the tile's corner."""
    levels = np.repeat(np.random.default_rng(seed).integers(0, n_levels, (n, 1)), n, axis=1)
    board = (np.indices((4, 4)).sum(axis=0) % 2) * (n_levels - 1)
    levels[2:6, 2:6] = board
    levels[n - 2 :, n - 2 :] = board[:2, :2]
    return levels


def flat_counts(gds, layers, feature_nm):
    layout = kdb.Layout()
    layout.read(str(gds))
    top, euclid, out = layout.top_cell(), kdb.Metrics.Euclidian, {}
    for layer in layers:
        region = kdb.Region(top.begin_shapes_rec(layout.find_layer(layer, 0)))
        out[(layer, "width")] = region.width_check(feature_nm, False, euclid).count()
        out[(layer, "space")] = region.space_check(feature_nm, False, euclid).count()
    return out


@pytest.fixture(scope="module")
def green(tmp_path_factory):
    root = tmp_path_factory.mktemp("green")
    levels = checker_levels(24, 4)
    d = design(root / "design", GREEN, levels)
    code = main(["fab", str(d), "--out", str(root / "out"), "--config", str(d / "design.toml"),
                 "--allow-drc"])  # fmt: skip
    assert code == 0
    return root, levels, read_fab_manifest(root / "out" / MANIFEST_NAME)


def test_refused_without_allow_drc_exit_2_and_nothing_written(green, tmp_path, capsys):
    root, _, manifest = green
    d = root / "design"
    code = main(["fab", str(d), "--out", str(tmp_path / "out"), "--config", str(d / "design.toml")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert not (tmp_path / "out").exists()
    lyrdb = re.match(r"doefab fab: error: (\S+\.lyrdb): ", err).group(1)
    counts = {(c["layer"], c["rule"]): c["count"] for c in manifest.drc()["counts"]}
    for (layer, rule), count in counts.items():
        if count:
            assert f"L{layer} {rule} {count}" in err
    assert "--allow-drc" in err
    assert read_lyrdb_counts(lyrdb) == {
        category_name(layer, rule): min(count, MAX_ITEMS) for (layer, rule), count in counts.items()
    }


def test_allowed_package_counts_equal_a_flat_klayout_run(green):
    root, levels, manifest = green
    drc = manifest.drc()
    assert (drc["deck"], drc["markers"]) == (DRC_DECK, DRC_MARKERS)
    assert drc["violations_allowed"] and not drc["corner_contacts_allowed"]
    assert drc["rules"]["min_width_nm"] == drc["rules"]["min_space_nm"] == 10_000
    ours = {(c["layer"], c["rule"]): c["count"] for c in drc["counts"]}
    flat = flat_counts(root / "out" / "mask.gds", drc["rules"]["layers"], 10_000)
    assert flat == {k: ours[k] for k in flat}
    assert drc["total"] == sum(ours.values()) > 0
    for mk in masks_from_levels(levels, 4, 1e-7):
        want = corner_contacts(plate_bitmap(mk.bitmap, manifest.fields["plate"]))
        assert want > 0 and drc["corner_contacts"][str(mk.gds_layer)] == want
    assert read_lyrdb_counts(root / "out" / DRC_MARKERS) == {
        category_name(*k): min(v, MAX_ITEMS) for k, v in ours.items()
    }


def test_report_lists_rules_counts_and_what_was_allowed(green):
    root, _, manifest = green
    report = (root / "out" / "fab_report.md").read_text()
    section = report.split("## Design rules")[1].split("\n## ")[0]
    assert "ALLOWED by --allow-drc" in section and DRC_DECK in section
    for c in manifest.drc()["counts"]:
        if c["count"]:
            x, y = c["examples_um"][0]
            assert f"| {c['layer']}/0 | " in section and f"({x:.3f}, {y:.3f})" in section
    files = {f for f in json.loads((root / "out" / MANIFEST_NAME).read_text())["drc"].values()
             if isinstance(f, str)}  # fmt: skip
    assert {DRC_DECK, DRC_MARKERS} <= files
    assert (root / "out" / DRC_DECK).read_text().startswith("<?xml")


def test_a_clean_plate_is_written_without_allow_drc(tmp_path):
    levels = np.repeat(np.random.default_rng(3).integers(0, 8, (24, 1)), 24, axis=1)
    d = design(tmp_path / "design", FINE, levels)
    result = build_package(d, tmp_path / "out", config=d / "design.toml", progress=False)
    drc = result.manifest.drc()
    assert drc["total"] == 0 and not drc["violations_allowed"]
    assert {DRC_DECK, DRC_MARKERS} <= set(result.files)
    assert "No violations." in (tmp_path / "out" / "fab_report.md").read_text()


def test_build_package_refuses_with_drc_refused(tmp_path):
    d = design(tmp_path / "design", FINE, checker_levels(24, 8))
    with pytest.raises(DrcRefused, match=r"L1 width \d+ \(all at corner contacts\)"):
        build_package(d, tmp_path / "out", config=d / "design.toml", progress=False)
    assert not (tmp_path / "out").exists()


def test_corner_contacts_refuse_unless_the_process_accepts_them(green):
    root, _, manifest = green
    rules = manifest.drc()["rules"]
    result = check_plate(root / "out" / "mask.gds", plate_rules(rules["layers"], 10_000, 1))
    assert result.total == manifest.drc()["total"] > 0
    assert refused_count(result, False) == result.total
    assert refused_count(result, True) == result.beyond_corners() == 0  # only corner contacts
    assert "(corner contacts, allowed)" in violation_summary(result, True)
    fab = SimpleNamespace(levels=4)  # a design object without the key: not allowed
    assert not allows_corner_contacts(SimpleNamespace(fabrication=fab))
    fab.allow_corner_contacts = True
    assert allows_corner_contacts(SimpleNamespace(fabrication=fab))


def test_a_process_accepting_corner_contacts_writes_them_without_allow_drc(tmp_path):
    toml = GREEN + "allow_corner_contacts = true\n"
    d = design(tmp_path / "design", toml, checker_levels(24, 4))
    result = build_package(d, tmp_path / "out", config=d / "design.toml", progress=False)
    drc = result.manifest.drc()
    assert drc["corner_contacts_allowed"] and not drc["violations_allowed"]
    assert drc["total"] == sum(c["at_corner_contacts"] for c in drc["counts"]) > 0
    report = (tmp_path / "out" / "fab_report.md").read_text()
    assert "which the design's process accepts" in report
