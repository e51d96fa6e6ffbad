"""The mask order sheet of ``doefab fab``: every field, and its numbers against the GDS
(read back with KLayout) and the manifest, for a 3-mask and a 2-mask (4-level) design."""

import hashlib
import json

import klayout.db as kdb
import pytest
from package_helpers import GREEN_FOUR_LEVELS, make_design_dir

from doe.records.fab_manifest import read_fab_manifest
from fab.package.build import build_package
from fab.package.order import BLANK_BORDER_MM, BLANKS, ORDER_JSON, ORDER_MD

FIELDS = {
    "mask", "exposure_order", "gds_file", "cell", "gds_layer", "gds_datatype", "tone",
    "polarity", "mirroring", "write_grid_nm", "address_unit_nm", "cd_nm", "cd_tolerance_nm",
    "cd_tolerance_source", "cd_structures_width_nm", "field_size_nm", "plate_size_nm",
    "blank", "etch_depth_nm",
}  # fmt: skip


@pytest.fixture(scope="module", params=["sun2020", "four_levels"])
def package(request, tmp_path_factory):
    root = tmp_path_factory.mktemp(request.param)
    config = None
    if request.param == "four_levels":
        config = root / "four.toml"
        config.write_text(GREEN_FOUR_LEVELS)
        make_design_dir(root / "design", n=9, n_levels=4, k=7)
    else:
        make_design_dir(root / "design", n=9, k=7)
    build_package(root / "design", root / "out", config=config, progress=False)
    out = root / "out"
    manifest = read_fab_manifest(out / "fab_manifest.json").fields
    order = json.loads((out / ORDER_JSON).read_text())
    return out, manifest, order


def test_one_entry_per_mask_with_every_field(package):
    _, manifest, order = package
    assert len(order["masks"]) == len(manifest["masks"]) in (2, 3)
    for entry in order["masks"]:
        assert set(entry) == FIELDS
        assert all(v not in (None, "", []) for v in entry.values()), entry
        assert entry["tone"] == "dark field" and "right-reading chrome-down" in entry["mirroring"]
    assert [e["exposure_order"] for e in order["masks"]] == list(range(1, len(order["masks"]) + 1))
    assert order["do_not_write"][0]["gds_layer"] == 200
    assert (order["dies"]["nx"], order["dies"]["ny"]) == (1, 1)


def test_order_matches_the_gds_read_back(package):
    out, manifest, order = package
    gds = out / order["gds"]["file"]
    data = gds.read_bytes()
    assert order["gds"]["sha256"] == hashlib.sha256(data).hexdigest()
    assert order["gds"]["bytes"] == len(data)
    layout = kdb.Layout()
    layout.read(str(gds))
    assert layout.dbu * 1e-6 == pytest.approx(order["gds"]["database_unit_m"])
    top = layout.cell(order["gds"]["top_cell"])
    assert top is not None
    outline = kdb.Region(top.begin_shapes_rec(layout.layer(200, 0)))
    for entry in order["masks"]:
        assert layout.cell(entry["cell"]) is not None
        layer = kdb.Region(top.begin_shapes_rec(layout.layer(entry["gds_layer"], 0)))
        assert not layer.is_empty()
        # the plate is layer 200's outer edge, and every mask lies within it
        w, h = entry["plate_size_nm"]
        assert outline.bbox() == kdb.Box(-w // 2, -h // 2, w // 2, h // 2)
        assert outline.bbox().contains(layer.bbox().p1) and outline.bbox().contains(layer.bbox().p2)
        assert entry["field_size_nm"] == [w, h]  # one die
        # every vertex of the layer (tile cell and marks) on the stated write grid
        g = entry["write_grid_nm"]
        for cell in (top, layout.cell(manifest["tile_cell"])):
            for shape in cell.shapes(layout.layer(entry["gds_layer"], 0)).each():
                assert all(p.x % g == 0 and p.y % g == 0 for p in shape.polygon.each_point_hull())
        for inst in top.each_inst():  # the AREF's origin and steps
            assert all(
                v % g == 0 for v in (inst.trans.disp.x, inst.trans.disp.y, inst.a.x, inst.b.y)
            )
        # the blank is the smallest standard one whose area inside the border holds the field
        side = entry["blank"]["side_mm"]
        fits = [s for _, s, _ in BLANKS if w / 1e6 <= s - 2 * BLANK_BORDER_MM]
        assert side == min(fits)


def test_order_matches_the_manifest_and_the_tolerance_budget(package):
    out, manifest, order = package
    by_name = {mk["name"]: mk for mk in manifest["masks"]}
    tolerance = json.loads((out / "fab_tolerance.json").read_text())
    cd_bias = next(x for x in tolerance["budget"] if x["kind"] == "cd_bias")
    assert manifest["mask_order"] == [ORDER_MD, ORDER_JSON]
    for entry in order["masks"]:
        mk = by_name[entry["mask"]]
        assert entry["etch_depth_nm"] == mk["etch_depth_nm"]
        assert entry["exposure_order"] == mk["exposure_order"]
        assert (entry["gds_layer"], entry["gds_datatype"]) == (mk["gds_layer"], 0)
        assert entry["gds_file"] == manifest["gds"] and entry["cell"] == manifest["top_cell"]
        assert entry["plate_size_nm"] == manifest["plate_size_nm"]
        assert entry["write_grid_nm"] == manifest["write_grid_nm"]
        assert entry["cd_nm"] == min(manifest["pixel_pitch_nm"], manifest["mark_feature_nm"])
        assert entry["cd_tolerance_nm"] == pytest.approx(cd_bias["value"] * 1000)
        assert "fab/plate/tolerance.py" in entry["cd_tolerance_source"]
        widths = sorted(
            {c["width_nm"] for c in manifest["cd_structures"] if c["mask"] == mk["name"]}
        )
        assert entry["cd_structures_width_nm"] == widths
    assert order["dies"]["pitch_nm"] == manifest["dies"]["pitch_nm"]
    # the sheet in Markdown carries the same figures; the report links it
    md = (out / ORDER_MD).read_text()
    for entry in order["masks"]:
        assert f"## {entry['mask']}" in md
        assert f"| layer/datatype | {entry['gds_layer']}/0 |" in md
        assert f"{entry['etch_depth_nm']:.2f} nm" in md
    assert "DO NOT WRITE layer 200/0" in md
    report = (out / "fab_report.md").read_text()
    assert ORDER_MD in report and ORDER_JSON in report
    for pad in manifest["etch_pads"]:
        assert f"{pad['depth_nm']:.2f}" in report
