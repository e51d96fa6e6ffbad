"""``doefab fab``: a complete, deterministic package; bad input refused (exit 2), nothing left."""

import hashlib
import json
import re

import numpy as np
import pytest
from package_helpers import corner_free_levels, make_design_dir

from doe.derived import derive, design_summary
from doe.design import load_design
from doe.fraunhofer import simulate_levels
from doe.infra.cli import main
from fab.package.layer_images import read_image
from fab.package.manifest import file_records
from fab.package.masks import masks_from_levels
from layouts.gds import PlateLayout
from layouts.readback import check_written_gds

CONTRACT_KEYS = {
    "wavelength_nm", "refractive_index", "levels", "level_step_nm", "pixel_pitch_nm",
    "tile_pixels", "tiles", "array_origin_nm", "gds", "top_cell", "tile_cell", "levels_file",
    "masks",
}  # fmt: skip
EXTRA_KEYS = {
    "design_name", "material", "substrate_thickness_mm", "kernel_size", "focal_length_mm",
    "tile_size_um", "lattice_pitch_um", "target_psf_file", "resist_tone", "data_polarity",
    "marks_layers", "acceptance",
}  # fmt: skip


def malitson_step_nm(wavelength_nm=655.0, n_levels=8):
    w2 = (wavelength_nm / 1000) ** 2
    terms = ((0.6961663, 0.0684043), (0.4079426, 0.1162414), (0.8974794, 9.896161))
    n = np.sqrt(1 + sum(b * w2 / (w2 - c**2) for b, c in terms))
    return wavelength_nm / (n - 1) / n_levels


@pytest.fixture(scope="module")
def package(tmp_path_factory):
    root = tmp_path_factory.mktemp("fab")
    levels = make_design_dir(root / "design")
    assert main(["fab", str(root / "design"), "--out", str(root / "out")]) == 0
    return root, levels


def test_manifest_records_the_kernel_of_the_target_not_the_designs(tmp_path):
    # A 7 x 7 target under the default design (K = 11): verify reads kernel_size from
    # the manifest and measured an 11 x 11 window against 7 x 7 tolerances.
    make_design_dir(tmp_path / "design", k=7)
    assert main(["fab", str(tmp_path / "design"), "--out", str(tmp_path / "out")]) == 0
    man = json.loads((tmp_path / "out" / "fab_manifest.json").read_text())
    assert man["kernel_size"] == 7 == np.load(tmp_path / "out" / man["target_psf_file"]).shape[0]
    # the design's own target file, not a re-encoding of it
    target = (tmp_path / "out" / man["target_psf_file"]).read_bytes()
    assert target == (tmp_path / "design" / "target_psf.npy").read_bytes()


def test_package_has_the_contract_manifest_and_files(package):
    root, levels = package
    out = root / "out"
    man = json.loads((out / "fab_manifest.json").read_text())
    assert CONTRACT_KEYS | EXTRA_KEYS <= set(man)
    assert man["levels"] == 8 and man["tile_pixels"] == 35 and man["tiles"] == [16, 16]
    assert isinstance(man["pixel_pitch_nm"], int)
    assert all(isinstance(v, int) for v in man["array_origin_nm"])
    p = man["pixel_pitch_nm"]
    assert man["array_origin_nm"] == [-(16 * 35 * p // 2)] * 2
    assert (out / man["gds"]).is_file() and (out / man["target_psf_file"]).is_file()
    assert np.array_equal(np.load(out / man["levels_file"]), levels)
    assert man["data_polarity"].startswith("a polygon marks area to etch")
    # Etch depths within 0.5 nm of the Sellmeier values, and exact multiples of the step.
    step = malitson_step_nm()
    assert abs(man["level_step_nm"] - step) < 0.5
    for mask, steps in zip(man["masks"], (4, 2, 1), strict=True):
        assert abs(mask["etch_depth_nm"] - steps * step) < 0.5
        assert mask["etch_depth_nm"] == steps * man["level_step_nm"]
    assert [m["exposure_order"] for m in man["masks"]] == [1, 2, 3]
    # The preset's values as typed, without the noise of their SI round trip.
    assert (man["wavelength_nm"], man["focal_length_mm"]) == (655.0, 50.0)
    assert (man["aperture_mm"], man["substrate_thickness_mm"]) == (14.0, 0.5)
    acc = man["acceptance"]
    assert {"correlation_min", "rmse_max", "efficiency_min", "zero_order_max"} <= set(acc)
    assert (out / "fab_report.md").is_file() and (out / "fab_report.html").is_file()


def test_pitch_is_resnapped_when_n_differs_from_the_design(package):
    root, _ = package
    man = json.loads((root / "out" / "fab_manifest.json").read_text())
    der = derive(load_design())
    assert der.tile_pixels == 174  # the preset's N; the test design has 35
    assert man["pixel_pitch_nm"] == round(der.tile_size_nominal / 35 * 1e9)
    assert abs(man["tile_size_um"] - 35 * man["pixel_pitch_nm"] / 1000) < 1e-9


def test_gds_and_layer_images_reproduce_the_levels(package):
    root, levels = package
    out = root / "out"
    man = json.loads((out / "fab_manifest.json").read_text())
    masks = masks_from_levels(levels, 8, man["level_step_nm"] * 1e-9)
    info = PlateLayout(
        top_cell=man["top_cell"], tile_cell=man["tile_cell"],
        pixel_pitch_nm=man["pixel_pitch_nm"], tile_pixels=man["tile_pixels"],
        tiles=tuple(man["tiles"]), array_origin_nm=tuple(man["array_origin_nm"]),
    )  # fmt: skip
    assert check_written_gds(out / man["gds"], info, masks) == []
    for mk in masks:
        assert np.array_equal(read_image(out / f"{mk.name}_tile.tif"), mk.bitmap * np.uint8(255))
        assert read_image(out / f"{mk.name}_plate.png").ndim == 2


def test_same_design_gives_byte_identical_package(package, tmp_path):
    root, _ = package
    assert main(["fab", str(root / "design"), "--out", str(tmp_path / "again")]) == 0
    first = sorted(p.name for p in (root / "out").iterdir())
    second = sorted(p.name for p in (tmp_path / "again").iterdir())
    assert first == second
    for name in first:
        assert (root / "out" / name).read_bytes() == (tmp_path / "again" / name).read_bytes(), name


def test_existing_output_is_refused_without_force(package, capsys):
    root, _ = package
    before = (root / "out" / "mask.gds").stat().st_mtime_ns
    assert main(["fab", str(root / "design"), "--out", str(root / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--force" in err
    assert (root / "out" / "mask.gds").stat().st_mtime_ns == before


def _bad_levels(kind, d):
    rng = np.random.default_rng(1)
    if kind == "out_of_range":
        lv = rng.integers(0, 8, (9, 9)).astype(np.uint8)
        lv[3, 4] = 8
        np.save(d / "levels.npy", lv)
    elif kind == "non_square":
        np.save(d / "levels.npy", rng.integers(0, 8, (9, 8)).astype(np.uint8))
    elif kind == "wrong_dtype":
        np.save(d / "levels.npy", rng.integers(0, 8, (9, 9)).astype(np.int64))
    elif kind == "not_npy":
        (d / "levels.npy").write_text("not an array")
    elif kind == "missing":
        pass
    return d / "levels.npy"


@pytest.mark.parametrize(
    "kind", ["out_of_range", "non_square", "wrong_dtype", "not_npy", "missing"]
)
def test_bad_levels_exit_2_and_leave_nothing(tmp_path, capsys, kind):
    d = tmp_path / "design"
    d.mkdir()
    named = _bad_levels(kind, d)
    out = tmp_path / "out"
    assert main(["fab", str(d), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(named) in err
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["design"]  # no staging leftovers


def test_missing_design_dir_and_bad_target_exit_2(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["fab", str(tmp_path / "nope"), "--out", str(out)]) == 2
    assert "nope" in capsys.readouterr().err
    d = tmp_path / "design"
    make_design_dir(d, n=15, target=False)
    np.save(d / "target_psf.npy", -np.ones((5, 5)) / 25)
    assert main(["fab", str(d), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "target_psf.npy" in err and "negative" in err
    assert not out.exists()


def test_levels_mismatch_with_retrieval_json_exit_2(tmp_path, capsys):
    d = tmp_path / "design"
    make_design_dir(d, n=15)
    (d / "retrieval.json").write_text(json.dumps({"levels": 4}))
    assert main(["fab", str(d), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err  # and what the --config must say
    assert "retrieval.json" in err and "a --config whose [fabrication] levels = 4" in err
    assert not (tmp_path / "out").exists()


def test_tile_made_for_another_design_exit_2(tmp_path, capsys):
    # a tile retrieved for a 532 nm design, fabricated with the default (655 nm) design,
    # would get the wrong etch depths and dot pitch
    cfg = tmp_path / "green.toml"
    cfg.write_text('name = "green"\n[optics]\nwavelength_nm = 532.0\n')
    d = tmp_path / "design"
    make_design_dir(d, n=15)
    record = {"levels": 8, "design": design_summary(load_design(cfg))}
    (d / "retrieval.json").write_text(json.dumps(record))
    out = tmp_path / "out"
    assert main(["fab", str(d), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "retrieval.json" in err and "wavelength_nm 532 -> 655" in err
    assert not out.exists()
    assert main(["fab", str(d), "--out", str(out), "--config", str(cfg)]) == 0
    assert json.loads((out / "fab_manifest.json").read_text())["wavelength_nm"] == 532.0
    # retrieve --levels 4 under the default design, fabricated with a 4-level design
    four = tmp_path / "four.toml"
    four.write_text("[fabrication]\nlevels = 4\n")
    make_design_dir(d, n=15, n_levels=4)
    record = {"levels": 4, "design": design_summary(load_design())}
    (d / "retrieval.json").write_text(json.dumps(record))
    assert main(["fab", str(d), "--out", str(tmp_path / "four"), "--config", str(four)]) == 0


def test_missing_target_uses_the_simulated_psf_and_says_so(tmp_path, capsys):
    d = tmp_path / "design"
    levels = make_design_dir(d, n=21, target=False)
    out = tmp_path / "out"
    assert main(["fab", str(d), "--out", str(out), "--oasis"]) == 0
    assert "simulated" in capsys.readouterr().err
    man = json.loads((out / "fab_manifest.json").read_text())
    assert "simulated" in man["target_psf_source"]
    want, _ = simulate_levels(levels, 8, man["kernel_size"])
    assert np.allclose(np.load(out / "target_psf.npy"), want)
    assert man["oasis"] == "mask.oas" and (out / "mask.oas").stat().st_size > 0


def test_force_removes_the_old_package_files_it_does_not_write_again(tmp_path, capsys):
    # an old mask.oas or a 4-level package's mask images beside the new GDS would
    # describe another plate; a file fab never writes stays
    d = tmp_path / "design"
    make_design_dir(d, n=21)
    out = tmp_path / "out"
    four = tmp_path / "four.toml"
    four.write_text('name = "four"\n[fabrication]\nlevels = 4\n')
    (d / "retrieval.json").write_text(json.dumps({"levels": 4}))
    np.save(d / "levels.npy", np.load(d / "levels.npy") % 4)
    assert main(["fab", str(d), "--out", str(out), "--oasis", "--config", str(four)]) == 0
    (out / "notes.txt").write_text("the lab's own file")
    (d / "retrieval.json").write_text(json.dumps({"levels": 8}))
    assert main(["fab", str(d), "--out", str(out), "--force"]) == 0
    man = json.loads((out / "fab_manifest.json").read_text())
    drawn = {mk["name"] for mk in man["masks"]}
    images = {p.name.rsplit("_", 1)[0] for p in out.glob("*_tile.tif")}
    assert len(drawn) == 3 and images == drawn
    assert not (out / "mask.oas").exists() and (out / "notes.txt").exists()


def test_four_level_config_gives_two_masks(tmp_path, capsys):
    cfg = tmp_path / "four.toml"
    cfg.write_text('name = "four"\n[fabrication]\nlevels = 4\n')
    d = tmp_path / "design"
    make_design_dir(d, n=15, n_levels=4)
    out = tmp_path / "out"
    assert main(["fab", str(d), "--out", str(out), "--config", str(cfg)]) == 0
    man = json.loads((out / "fab_manifest.json").read_text())
    assert [m["name"] for m in man["masks"]] == ["M1_deep", "M2_shallow"]
    assert abs(man["masks"][0]["etch_depth_nm"] - 2 * malitson_step_nm(n_levels=4)) < 0.5
    assert man["top_cell"].startswith("four")
    # an 8-level map does not fit a 4-level design
    make_design_dir(tmp_path / "eight", n=15, n_levels=8, seed=3)
    code = main(["fab", str(tmp_path / "eight"), "--out", str(tmp_path / "o2"),
                 "--config", str(cfg)])  # fmt: skip
    assert code == 2 and "0..3" in capsys.readouterr().err


@pytest.mark.slow
def test_dense_default_design_fits_the_size_budget(tmp_path):
    d = tmp_path / "design"
    # the default's N = 174 pixels of 5019 nm, random levels without corner contacts:
    # the design-rule check finds nothing
    make_design_dir(d, n=174, seed=11)
    out = tmp_path / "out"
    assert main(["fab", str(d), "--out", str(out)]) == 0
    assert (out / "mask.gds").stat().st_size <= 5 * 2**20
    man = json.loads((out / "fab_manifest.json").read_text())
    assert man["pixel_pitch_nm"] == 5019 and man["tiles"] == [16, 16]
    assert man["drc"]["total"] == 0


def _wrong_dbu(*args):
    raise ValueError("out.gds: DBU is 0.0001 um, not 0.001")


@pytest.mark.parametrize(
    "name, fake",
    [("check_written_gds", lambda *a: ["layer 1: 3 differ"]), ("rasterise_tile", _wrong_dbu)],
)
def test_failed_readback_exits_1_and_releases_nothing(tmp_path, monkeypatch, capsys, name, fake):
    # a file unlike the one meant is a failed check (exit 1), not an internal error (3)
    import layouts.readback

    monkeypatch.setattr(layouts.readback, name, fake)
    d = tmp_path / "design"
    make_design_dir(d, n=15)
    out = tmp_path / "out"
    assert main(["fab", str(d), "--out", str(out)]) == 1
    assert "FAIL" in capsys.readouterr().err
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["design"]


def test_kernel_larger_than_tile_exit_2(tmp_path, capsys):
    d = tmp_path / "design"
    make_design_dir(d, n=9, k=11)
    assert main(["fab", str(d), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "exceeds" in err and "target_psf.npy" in err
    assert not (tmp_path / "out").exists()
    # without a target the design's kernel size is too large: blame what exists
    (d / "target_psf.npy").unlink()
    assert main(["fab", str(d), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "levels.npy" in err and "K = 11" in err and "target_psf.npy:" not in err
    assert not (tmp_path / "out").exists()


def test_a_grid_too_coarse_for_the_tiles_pitch_exit_2(tmp_path, capsys):
    # 1 um grid: N = 174 snaps 5019.2 nm to 5000 nm (dot lattice 0.38 % off: fine), but
    # N = 400 snaps 2183.3 nm to 2000 nm, which shrinks the PSF by 8 %: a wrong plate.
    cfg = tmp_path / "coarse.toml"
    cfg.write_text("[fabrication]\ngrid_nm = 1000\n")
    d = tmp_path / "design"
    make_design_dir(d, n=400)
    assert main(["fab", str(d), "--out", str(tmp_path / "out"), "--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "levels.npy: N = 400 pixels per tile: the 1000 nm grid snaps" in err
    assert "+9.17% off the sub-pixel pitch" in err, err
    assert not (tmp_path / "out").exists()


def test_a_tile_finer_than_the_feature_size_is_made_with_a_warning(tmp_path, capsys):
    # 97 um features make the design's 873 um tile N = 9 pixels; N = 11 prints 79.4 um
    # pixels, which the process was not chosen for. The warning and the note on the
    # missing target come once the output folder is accepted: a refusal is one line.
    cfg = tmp_path / "coarse.toml"
    cfg.write_text("[fabrication]\nfeature_size_um = 97.0\n[psf]\nkernel_size = 3\n")
    d = tmp_path / "design"
    make_design_dir(d, n=11, target=False)
    # its single-pixel lines are design-rule violations at 97 um: allowed here
    args = ["fab", str(d), "--out", str(tmp_path / "out"), "--config", str(cfg), "--allow-drc"]
    assert main(args) == 0
    err = capsys.readouterr().err
    pitch = json.loads((tmp_path / "out" / "fab_manifest.json").read_text())["pixel_pitch_nm"]
    assert f"warning: N = 11 gives {pitch} nm mask pixels, finer than the design's 97 um" in err
    assert "(N = 9, [fabrication] feature_size_um)" in err and "no target_psf.npy" in err
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--force" in err


def test_a_tile_of_more_pixels_than_any_design_is_refused(tmp_path, capsys):
    # N = 5000 went through with 175 nm pixels (2 GB, 136 s for a uniform map)
    d = tmp_path / "design"
    d.mkdir()
    np.save(d / "levels.npy", np.zeros((4097, 4097), np.uint8))
    assert main(["fab", str(d), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert f"{d / 'levels.npy'}: N = 4097 pixels per tile, more than 4096" in err
    assert not (tmp_path / "out").exists()


def test_a_tile_whose_pitch_rounds_to_no_grid_step_exit_2(tmp_path, capsys):
    # 100 um grid: the design's N = 9 pixels of its 873 um tile snap to 100 um each,
    # but N = 20 pixels of 43.7 um round to no grid step at all
    cfg = tmp_path / "coarse.toml"
    cfg.write_text(
        "[fabrication]\ngrid_nm = 100000\nfeature_size_um = 97.0\n[psf]\nkernel_size = 3\n"
    )
    d = tmp_path / "design"
    make_design_dir(d, n=20, target=False)
    assert main(["fab", str(d), "--out", str(tmp_path / "out"), "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert (
        f"{d / 'levels.npy'}: N = 20 pixels per tile gives a pixel pitch below the 100000 nm grid"
        in err
    )
    assert not (tmp_path / "out").exists()


def test_report_summary_describes_the_fabricated_tile():
    from fab.package.build import tile_derived, tile_summary

    design = load_design()
    summary = tile_summary(design, tile_derived(design, 35))["derived"]
    assert summary["tile_pixels"] == 35
    assert summary["mask_pixel_pitch_nm"] == round(derive(design).tile_size_nominal / 35 * 1e9)
    assert abs(summary["tile_size_um"] - 35 * summary["mask_pixel_pitch_nm"] / 1000) < 1e-6


def test_a_plate_missing_the_goals_is_made_with_a_warning(tmp_path, capsys):
    # The report's Summary judged only the contract's model: a 21-pixel tile against
    # its own PSF read "met" while, etched in square pixels, it missed the goals.
    d = tmp_path / "design"
    levels = make_design_dir(d, n=21)
    assert main(["fab", str(d), "--out", str(tmp_path / "own")]) == 0
    err = capsys.readouterr().err
    assert "warning: the design meets the goals, but a plate of square pixels misses" in err
    # against another PSF the nominal plate misses them in the contract's model too
    other = simulate_levels(np.roll(levels, 3, axis=1)[::-1], 8, 11)[0]
    np.save(d / "target_psf.npy", other)
    assert main(["fab", str(d), "--out", str(tmp_path / "other")]) == 0
    err = capsys.readouterr().err
    assert "warning: the nominal plate misses the design goals (correlation" in err
    assert "square pixels" not in err


def test_a_gds_cut_short_by_a_full_disk_is_exit_2(tmp_path, capsys, monkeypatch):
    # gdstk truncates on a full disk without a word; KLayout's read-back then raised a
    # RuntimeError traceback (exit 1).
    import layouts.gds

    real = layouts.gds.write_gds

    def cut_short(lib, path):
        real(lib, path)
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])

    monkeypatch.setattr(layouts.gds, "write_gds", cut_short)
    d = tmp_path / "design"
    make_design_dir(d, n=21)
    out = tmp_path / "out"
    assert main(["fab", str(d), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"{out / 'mask.gds'}: KLayout cannot read" in err
    assert not out.exists()


def test_file_records_are_sha256_and_byte_counts_of_the_files(tmp_path):
    # a lab checks the package with `sha256sum`; the record must be the SHA-256 and size
    (tmp_path / "sub").mkdir()
    blobs = {"b.bin": bytes(range(256)) * 3, "sub/a.txt": b"hello\n", "empty": b""}
    for name, data in blobs.items():
        (tmp_path / name).write_bytes(data)
    recs = file_records(tmp_path, list(blobs))
    assert [r["path"] for r in recs] == sorted(blobs)
    for r in recs:
        data = blobs[r["path"]]
        assert r["sha256"] == hashlib.sha256(data).hexdigest()
        assert r["bytes"] == len(data)


def test_manifest_lattice_pitch_is_lambda_f_over_tile_size(tmp_path):
    # verify finds the lattice at lattice_pitch_um: lambda f / (N p), N pixels of pitch p
    n = 35
    design_dir = tmp_path / "design"
    design_dir.mkdir()
    np.save(design_dir / "levels.npy", corner_free_levels(n, 8, seed=0))
    assert main(["fab", str(design_dir), "--out", str(tmp_path / "out")]) == 0
    man = json.loads((tmp_path / "out" / "fab_manifest.json").read_text())
    design = load_design()
    tile_m = man["tile_pixels"] * man["pixel_pitch_nm"] * 1e-9
    assert man["tile_pixels"] == n
    assert man["tile_size_um"] * 1e-6 == pytest.approx(tile_m, rel=1e-12)
    expected_um = design.optics.wavelength * design.optics.focal_length / tile_m * 1e6
    assert abs(man["lattice_pitch_um"] - expected_um) < 1e-9 * expected_um


def test_report_summary_gives_the_tiles_own_figures_against_its_target(
    tmp_path, window_from_contract
):
    # The target (what retrieval aimed at) is not the PSF the tile forms: the report's
    # nominal figures are the tile's PSF (CONVENTIONS.md forward model) against it.
    n, k = 15, 7
    d = tmp_path / "design"
    levels = make_design_dir(d, n=n, target=False)
    other = make_design_dir(tmp_path / "other", n=n, seed=5, target=False)
    target = simulate_levels(other, 8, k)[0]
    np.save(d / "target_psf.npy", target)
    out = tmp_path / "out"
    assert main(["fab", str(d), "--out", str(out)]) == 0
    window = window_from_contract(levels, 8, k)
    sim = window / window.sum()
    corr = np.corrcoef(sim.ravel(), target.ravel())[0, 1]
    rmse = np.sqrt(np.mean((sim / sim.max() - target / target.max()) ** 2))
    md = (out / "fab_report.md").read_text()
    eff = re.search(r"^\| window efficiency \(nominal\) \| ([\d.]+) \|$", md, re.M)
    assert float(eff[1]) == pytest.approx(window.sum(), abs=6e-5)
    row = re.search(r"^\| correlation / rmse vs target \(nominal\) \| (\S+) / (\S+) \|$", md, re.M)
    assert float(row[1]) == pytest.approx(corr, abs=1e-6) and corr < 0.9
    assert float(row[2]) == pytest.approx(rmse, abs=1e-5)
    # a random tile's masks hold single-pixel features: the smallest is one mask pixel
    pitch_um = json.loads((out / "fab_manifest.json").read_text())["pixel_pitch_nm"] / 1000
    minima = re.findall(r"^\| \d \| M\d_\w+ \|.* \| ([\d.]+) \|$", md, re.M)
    assert len(minima) == 3 and all(float(v) == pytest.approx(pitch_um) for v in minima)
