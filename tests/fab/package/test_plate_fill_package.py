"""``doefab fab`` fills the clear aperture, or says what fewer tiles cost; ``--dies``; the
plate preview, the manifest, the report and the meshes' aperture scene show the edge tiles."""

import json

import numpy as np
import pytest
import trimesh
from package_helpers import make_design_dir

import fab.package.report as report
from doe.infra.cli import main
from doe.infra.errors import InputError
from doe.records.fab_manifest import read_fab_manifest
from fab.package.build import build_package
from fab.package.layer_images import read_image
from fab.package.masks import masks_from_levels
from layouts.marks import plate_half_size_nm

N, K = 15, 7
# the default design's 0.873 mm tile at N = 15: 3 whole tiles in 3 mm, 0.218 mm of ring
CONFIG = 'name = "small"\n[psf]\nkernel_size = 7\n[fabrication]\naperture_mm = 3.0\n'


@pytest.fixture(scope="module")
def packages(tmp_path_factory):
    root = tmp_path_factory.mktemp("fill")
    levels = make_design_dir(root / "design", n=N, k=K)
    (root / "small.toml").write_text(CONFIG)
    runs = {
        "fill": {},
        "glass": {"tiles": 2, "keep_aperture": True},
        "shrink": {"whole_tiles": True},
        "dies": {"dies": (2, 1), "lane_um": 300},
    }
    out = {}
    with pytest.MonkeyPatch.context() as mp:  # the figures are tested elsewhere (seconds each)
        mp.setattr(report, "_write_figures", lambda out_dir, context: [])
        for name, kw in runs.items():
            out[name] = build_package(
                root / "design", root / name, config=str(root / "small.toml"), progress=False, **kw
            )
    return root, levels, out


def test_the_pattern_fills_the_aperture_in_the_manifest_and_report(packages):
    root, _, out = packages
    man = out["fill"].manifest
    plate = man.fields["plate"]
    pitch = man.fields["pixel_pitch_nm"]
    # 3 tiles of 15 pixels in 3 mm: (3 mm - 45 p) / 2 per side, rounded up to pixels
    ring = (3_000_000 - 45 * pitch) / 2
    assert plate["edge_pixels"] == dict.fromkeys(("left", "right", "bottom", "top"), 4)
    assert 3 * pitch < ring <= 4 * pitch
    assert plate["patterned_fraction"] == 1.0 and len(plate["edge_cells"]) == 8
    assert read_fab_manifest(man.path).tile_geometry().edge_pixels == (4, 4, 4, 4)
    assert read_fab_manifest(man.path).plate_reference().patterned_fraction == 1.0
    text = (root / "fill" / "fab_report.md").read_text()
    assert "## Plate and clear aperture" in text
    assert "| patterned fraction of the clear aperture | 100.0000% |" in text
    assert f"| tiles across the clear aperture | {53 / 15:.3f} x {53 / 15:.3f} |" in text
    assert man.fields["as_built"]["patterned_fraction"] == 1.0


def test_the_plate_preview_shows_the_edge_tiles(packages):
    root, levels, out = packages
    man = out["fill"].manifest.fields
    masks = masks_from_levels(levels, 8, man["level_step_nm"] * 1e-9)
    pitch = man["pixel_pitch_nm"]
    half = plate_half_size_nm(1_500_000)
    size = -(-2 * half // pitch)  # one preview pixel per mask pixel on this small plate
    for mk in masks:
        img = read_image(root / "fill" / f"{mk.name}_plate.png")
        assert img.shape == (size, size)
        top = round(size / 2 - (45 / 2 + 4) * pitch / pitch)
        got = img[top : top + 53, top : top + 53]
        rows = np.arange(-4, 49) % N
        want = mk.bitmap[np.ix_(rows, rows)] * 255
        assert np.array_equal(got, want), mk.name


def test_fewer_tiles_in_the_frame_are_judged_as_built(packages):
    root, _, out = packages
    glass = out["glass"]
    plate = glass.manifest.fields["plate"]
    # 2 whole tiles (30 pixels) in the 3 mm frame
    side = 30 * glass.manifest.fields["pixel_pitch_nm"] / 3e6
    assert plate["patterned_fraction"] == pytest.approx(side**2)
    assert any(
        f"{1 - side**2:.1%} of the clear aperture is plain glass" in w for w in glass.warnings
    )
    built = glass.manifest.fields["as_built"]
    assert not built["goals_met"] and built["zero_order"] > 0.1
    text = (root / "glass" / "fab_report.md").read_text()
    assert "| design goals as built (the pattern over its clear aperture) | MISSED: " in text
    # the target is the tile's own PSF: the tile meets the goals, the plate as built does not
    assert "met by the tile repeated without end; MISSED by the plate as built" in text


def test_whole_tiles_shrink_the_frame_and_say_what_it_costs(packages):
    root, _, out = packages
    shrink = out["shrink"].manifest.fields
    side = 45 * shrink["pixel_pitch_nm"]
    assert shrink["plate"]["clear_aperture_nm"] == side
    lost = 1 - (side / 3e6) ** 2
    assert shrink["plate"]["aperture_light_kept"] == pytest.approx(1 - lost)
    assert any(f"{lost:.1%} of the light" in w for w in out["shrink"].warnings)
    assert (
        f"{lost:.2%} of the design's light lost" in (root / "shrink" / "fab_report.md").read_text()
    )


def test_dies_are_recorded_for_the_order_sheet(packages):
    root, _, out = packages
    man = out["dies"].manifest.fields
    dies = man["dies"]
    plate = man["plate_size_nm"][0]
    assert (dies["nx"], dies["ny"], dies["lane_nm"]) == (2, 1, 300_000)
    assert dies["plate_size_nm"] == [plate, plate]
    assert dies["pitch_nm"] == [plate + 300_000] * 2
    assert dies["substrate_size_nm"] == [2 * (plate + 300_000), plate + 300_000]
    assert "| dies (plates) | 2 x 1 " in (root / "dies" / "fab_report.md").read_text()
    order = json.loads((root / "dies" / "mask_order.json").read_text())
    assert order["dies"]["field_size_nm"] == [2 * plate + 300_000, plate]
    assert {d["gds_layer"] for d in order["do_not_write"]} == {200, 201}
    single = out["fill"].manifest.fields["dies"]
    assert (single["nx"], single["ny"]) == (1, 1)


def test_the_aperture_scenes_instance_the_tiles_and_the_edge_pieces(packages, tmp_path):
    root, levels, out = packages
    assert main(["mesh", str(root / "fill"), "--out", str(tmp_path), "--formats", "glb"]) == 0
    tiles = trimesh.load(tmp_path / "aperture.glb")
    edge = trimesh.load(tmp_path / "aperture_edge.glb")
    report_ = json.loads((tmp_path / "mesh_report.json").read_text())["aperture"]
    # 9 whole tiles (one geometry); 4 strips of 3 and 4 corners beside them
    assert (report_["instances"], report_["edge_pieces"], report_["edge_instances"]) == (9, 8, 16)
    assert len(tiles.graph.nodes_geometry) == 9 and len(tiles.geometry) == 1
    assert len(edge.graph.nodes_geometry) == 16 and len(edge.geometry) == 8
    x0, y0, x1, y1 = (v / 1e6 for v in out["fill"].manifest.fields["plate"]["pattern_extent_nm"])
    bounds = np.concatenate([tiles.bounds, edge.bounds])[:, :2]
    assert np.allclose(
        [bounds[:, :2].min(0), bounds[:, :2].max(0)], [[x0, y0], [x1, y1]], atol=1e-9
    )
    # every piece is closed, and the scenes' volume is the pattern's, pixel by pixel
    man = out["fill"].manifest.fields
    step, p_mm = man["level_step_nm"] * 1e-6, man["pixel_pitch_nm"] * 1e-6
    thickness = man["substrate_thickness_mm"]
    volume = 0.0
    for scene in (tiles, edge):
        for node in scene.graph.nodes_geometry:
            geometry = scene.geometry[scene.graph[node][1]]
            assert geometry.is_watertight and geometry.is_winding_consistent
            volume += geometry.volume
    span = np.arange(-4, 49) % N
    tops = thickness - (8 - 1 - levels[np.ix_(span, span)]) * step
    assert volume == pytest.approx(tops.sum() * p_mm**2, rel=1e-6)  # GLB: float32


@pytest.mark.parametrize(
    "flags, flag",
    [
        (["--tiles", "9"], "--tiles"),
        (["--keep-aperture"], "--keep-aperture"),
        (["--dies", "0", "1"], "--dies"),
        (["--lane-um", "-5"], "--lane-um"),
    ],
)
def test_unusable_plate_flags_exit_2_naming_the_flag(packages, tmp_path, capsys, flags, flag):
    root, _, _ = packages
    cfg = str(root / "small.toml")
    assert (
        main(["fab", str(root / "design"), "--out", str(tmp_path / "o"), "--config", cfg, *flags])
        == 2
    )
    assert flag in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("plate", [[1, 2], {"edge_pixels": [4, 4]}, {"edge_pixels": {"left": 99}}])
def test_a_malformed_plate_record_is_an_input_error(packages, tmp_path, plate):
    out = packages[2]
    fields = dict(out["fill"].manifest.fields, plate=plate)
    path = tmp_path / "fab_manifest.json"
    path.write_text(json.dumps(fields))
    with pytest.raises(InputError) as e:
        read_fab_manifest(path).tile_geometry()
    assert e.value.source == str(path)
