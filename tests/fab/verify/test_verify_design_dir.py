"""Design folders verify reads: fab manifests, retrieve folders, acceptance, target PSFs,
and the refusals that name the file."""

import json

import numpy as np
import pytest
from verify_helpers import PITCH_PX, PITCH_UM, K, L, N, make_design_dir, run_verify

from doe.fraunhofer import simulate_levels
from doe.infra.cli import main
from doe.infra.files import save_npy, write_json
from fab.verify.analysis import resolve_thresholds
from fab.verify.capture import write_image
from fab.verify.simulate import simulate_capture

ACCEPTANCE_KEYS = ("correlation_min", "rmse_max", "efficiency_min", "zero_order_max")


@pytest.mark.parametrize("value", [None, float("nan"), "0.9", True])
def test_an_acceptance_threshold_that_is_no_number_is_refused(value):
    # fab writes a null correlation_min for a 1 x 1 PSF (no correlation): float(None)
    # was a TypeError traceback in verify, and NaN passed every plate
    acceptance = {"correlation_min": value, "rmse_max": 1, "efficiency_min": 0.5}
    acceptance["zero_order_max"] = 0.01
    with pytest.raises(ValueError, match=r"acceptance correlation_min is .*not a finite number"):
        resolve_thresholds(acceptance, 0.9, 0)
    with pytest.raises(ValueError, match="deep_etch_error_max"):
        resolve_thresholds(
            {**acceptance, "correlation_min": 0.9, "deep_etch_error_max": value}, 0.9, 0
        )


def test_plate_measured_on_a_bench_lens_hands_its_psf_to_the_design(tmp_path, levels):
    # A bench lens of twice the focal length doubles the dot lattice on the camera;
    # the PSF in orders is the same, and learn once refused it as another grid.
    from doe.design import load_design
    from doe.records.psf_source import check_psf_grid

    code, report, _ = run_verify(
        tmp_path,
        levels,
        dict(seed=1, pitch_px=2 * PITCH_PX),
        flags=("--lattice-pitch-um", str(2 * PITCH_UM)),
    )
    assert code == 0, report["diagnosis"]
    assert report["lattice_pitch_um"] == pytest.approx(2 * PITCH_UM)
    assert report["design_lattice_pitch_um"] == pytest.approx(PITCH_UM)
    assert report["measured_psf_usable"] is True
    check_psf_grid(tmp_path / "out" / "measured_psf.npy", load_design(None))  # 37.5 um grid


def verify_refusal(tmp_path, design, levels, capsys):
    """Verify a capture of ``levels`` against ``design``: exit 2, one line, nothing left.

    Returns the line.
    """
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, shape=(200, 200), seed=20)
    write_image(tmp_path / "cap.png", sim["capture"])
    out = tmp_path / "o"
    assert main(["verify", str(design), str(tmp_path / "cap.png"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and not out.exists(), err
    return err


@pytest.mark.parametrize("key", ["levels", "kernel_size", "lattice_pitch_um"])
def test_a_manifest_number_beyond_any_float_exits_2(tmp_path, levels, capsys, key):
    # JSON reads 1e400 as infinity, and int() of it raised OverflowError: exit 3
    design = make_design_dir(tmp_path / "design", levels)
    text = (design / "fab_manifest.json").read_text()
    manifest = json.loads(text)
    (design / "fab_manifest.json").write_text(
        text.replace(f'"{key}": {json.dumps(manifest[key])}', f'"{key}": 1e400')
    )
    assert json.loads((design / "fab_manifest.json").read_text())[key] == float("inf")
    assert "fab_manifest.json" in verify_refusal(tmp_path, design, levels, capsys)


@pytest.mark.parametrize(
    "change, culprit",
    [
        ({"levels": 0}, "fab_manifest.json"),
        ({"target_psf_file": "gone.npy"}, "gone.npy"),
        ({"kernel_size": 10}, "fab_manifest.json"),  # even: no centre order
        ({"kernel_size": N + 2}, "fab_manifest.json"),  # a window wider than the tile
        # odd, but no window: a traceback (exit 3) from an empty PSF
        ({"kernel_size": -1}, "fab_manifest.json: kernel_size -1 must be odd, 1 .. N"),
        # the 11 x 11 target was left out of the verdict without a word
        ({"kernel_size": 9}, "target_psf.npy: is 11x11, not the fab_manifest.json's kernel_size 9"),
        ({"acceptance": 0.95}, "fab_manifest.json"),  # not a table of thresholds
        ({"lattice_pitch_um": 0}, "fab_manifest.json"),
        ({"acceptance": dict.fromkeys(ACCEPTANCE_KEYS, "0.9")}, "fab_manifest.json"),  # text
        ({"kernel_size": "eleven"}, "fab_manifest.json: malformed manifest"),
        ({"masks": [{"etch_depth_nm": 717.6}]}, "fab_manifest.json: malformed manifest"),
        (
            {"acceptance": {"correlation_min": 0.9}},
            "fab_manifest.json: acceptance lacks ['efficiency_min', 'rmse_max', 'zero_order_max']",
        ),
    ],
)
def test_inconsistent_manifest_exits_2(tmp_path, levels, capsys, change, culprit):
    # levels 0 was blamed on levels.npy ("must lie in 0..-1"); a target the manifest
    # names but that is missing was skipped, verifying without it.
    design = make_design_dir(tmp_path / "design", levels)
    manifest = json.loads((design / "fab_manifest.json").read_text())
    write_json(design / "fab_manifest.json", {**manifest, **change})
    assert culprit in verify_refusal(tmp_path, design, levels, capsys)


def test_manifest_acceptance_is_used(tmp_path, levels):
    acc = {
        "correlation_min": 0.999999,
        "rmse_max": 0.5,
        "efficiency_min": 0.0,
        "zero_order_max": 1.0,
    }
    design = make_design_dir(tmp_path / "design", levels, acceptance=acc)
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=17)
    write_image(tmp_path / "cap.png", sim["capture"])
    code = main(["verify", str(design), str(tmp_path / "cap.png"), "--out", str(tmp_path / "o")])
    report = json.loads((tmp_path / "o" / "verify.json").read_text())
    assert code == 1 and report["diagnosis"] == ["psf_mismatch"]
    assert report["thresholds"]["correlation_min"] == acc["correlation_min"]


def verified_without_dark(tmp_path, design, levels):
    """Verify a simulated capture of ``levels`` (seed 1, no dark) against ``design``."""
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=1)
    write_image(tmp_path / "cap.png", sim["capture"])
    out = tmp_path / "o"
    assert main(["verify", str(design), str(tmp_path / "cap.png"), "--out", str(out)]) == 0
    return json.loads((out / "verify.json").read_text()), out


def test_correlation_target_compares_the_measured_psf_with_the_target_psf(tmp_path, levels):
    # The target the tile was designed for is not the PSF its levels form: correlation
    # judges the plate against its levels, correlation_target the PSF against the target.
    design = make_design_dir(tmp_path / "design", levels)
    other = np.random.default_rng(3).integers(0, L, (N, N)).astype(np.uint8)
    target = simulate_levels(other, L, K)[0]
    save_npy(design / "target_psf.npy", target)
    report, out = verified_without_dark(tmp_path, design, levels)
    measured = np.load(out / "measured_psf.npy")
    pearson = np.corrcoef(measured.ravel(), target.ravel())[0, 1]
    assert report["correlation_target"] == pytest.approx(pearson, abs=1e-9)
    assert report["correlation_target"] < 0.5 < report["correlation"]


def test_a_plate_the_deep_mask_leaves_whole_verified_without_a_target_psf(tmp_path):
    # Levels 4..7 only: the deepest mask etches no pixel, so the zero order does not
    # depend on its depth (no implied error, nor its nm). The folder has no target PSF
    # (none named either): the plate is judged against its levels, with no
    # correlation_target. One run for the two, as each is a key left out.
    upper = np.random.default_rng(7).integers(L // 2, L, (N, N)).astype(np.uint8)
    design = make_design_dir(tmp_path / "design", upper)
    (design / "target_psf.npy").unlink()
    man = json.loads((design / "fab_manifest.json").read_text())
    del man["target_psf_file"]
    write_json(design / "fab_manifest.json", man)
    report, out = verified_without_dark(tmp_path, design, upper)
    assert report["pass"] is True and report["implied_deep_etch_error"] is None
    assert "implied_deep_etch_error_nm" not in report and "correlation_target" not in report
    assert report["inputs"]["design_files"] == ["fab_manifest.json", "levels.npy"]
    assert (out / "verify_report.html").is_file()


def test_manifest_without_lattice_pitch_takes_it_from_the_optics(tmp_path, levels):
    # the contract's keys only: lattice pitch = lambda f / (N p)
    design = make_design_dir(tmp_path / "design", levels)
    man = json.loads((design / "fab_manifest.json").read_text())
    del man["lattice_pitch_um"]
    pitch_nm, wavelength_nm, focal_mm = 24950, 655.0, 50.0
    man.update(
        tile_pixels=N,
        pixel_pitch_nm=pitch_nm,
        wavelength_nm=wavelength_nm,
        focal_length_mm=focal_mm,
    )
    write_json(design / "fab_manifest.json", man)
    report, _ = verified_without_dark(tmp_path, design, levels)
    expected_um = wavelength_nm * 1e-9 * focal_mm * 1e-3 / (N * pitch_nm * 1e-9) * 1e6
    assert report["design_lattice_pitch_um"] == pytest.approx(expected_um, rel=1e-12)
    assert report["lattice_pitch_um"] == pytest.approx(expected_um, rel=1e-12)


def test_retrieve_folder_is_accepted(tmp_path, levels):
    from doe.derived import design_summary
    from doe.design import load_design

    folder = tmp_path / "ret"
    folder.mkdir()
    save_npy(folder / "levels.npy", levels)
    save_npy(folder / "target_psf.npy", simulate_levels(levels, L, K)[0])
    write_json(
        folder / "retrieval.json",
        {"levels": L, "kernel_size": K, "design": design_summary(load_design())},
    )
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=18)
    write_image(tmp_path / "cap.png", sim["capture"])
    # N = 35 snaps the mask pitch to 24.95 um: the same 873.25 um tile, the same lattice.
    code = main(["verify", str(folder), str(tmp_path / "cap.png"), "--out", str(tmp_path / "o")])
    assert code == 0
    # the lattice of the plate fab makes of this tile: its pitch snapped to the GDS grid
    from doe.derived import derive

    design = load_design()
    pitch = derive(design, tile_pixels=N).mask_pixel_pitch
    expected_um = design.optics.wavelength * design.optics.focal_length / (N * pitch) * 1e6
    report = json.loads((tmp_path / "o" / "verify.json").read_text())
    assert report["design_lattice_pitch_um"] == pytest.approx(expected_um, rel=1e-9)


def test_a_design_folder_verify_cannot_read_exits_2_naming_it(tmp_path, levels, capsys):
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, shape=(200, 200), seed=20)
    write_image(tmp_path / "cap.png", sim["capture"])
    learn = tmp_path / "learn"  # a folder of another stage
    learn.mkdir()
    broken = tmp_path / "ret"
    broken.mkdir()
    save_npy(broken / "levels.npy", levels)
    write_json(broken / "retrieval.json", {"levels": L, "kernel_size": K})  # no "design"
    for folder, problem in (
        (tmp_path / "none", "none: no such design folder"),
        (learn, "learn: neither fab_manifest.json nor retrieval.json found"),
        (broken, "retrieval.json: malformed retrieval.json (KeyError('design')"),
    ):
        out = tmp_path / "o"
        assert main(["verify", str(folder), str(tmp_path / "cap.png"), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert problem in err and len(err.splitlines()) == 1 and not out.exists(), err


@pytest.mark.parametrize(
    ("section", "key", "value", "problem"),
    [
        ("fabrication", None, 8, "malformed retrieval.json (AttributeError"),
        ("fabrication", "grid_nm", 0, "malformed retrieval.json (ValueError('grid_nm and"),
        ("fabrication", "grid_nm", [1], "malformed retrieval.json (TypeError"),
        ("derived", "tile_size_nominal_um", {}, "malformed retrieval.json (TypeError"),
        ("fabrication", "grid_nm", 10**5, "its grid_nm is coarser than the mask pixels of N = 35"),
    ],
)
def test_a_retrieval_json_of_a_design_verify_cannot_use_exits_2(
    tmp_path, levels, capsys, section, key, value, problem
):
    # each of these ended in a traceback (exit 3): read after the checks, or divided by 0
    from doe.derived import design_summary
    from doe.design import load_design

    summary = design_summary(load_design())
    if key is None:
        summary[section] = value
    else:
        summary[section][key] = value
    folder = tmp_path / "ret"
    folder.mkdir()
    save_npy(folder / "levels.npy", levels)
    write_json(folder / "retrieval.json", {"levels": L, "kernel_size": K, "design": summary})
    assert f"retrieval.json: {problem}" in verify_refusal(tmp_path, folder, levels, capsys)


def test_the_thresholds_record_where_they_come_from():
    # verify.json names the defaults as it did before the modules moved
    defaults = resolve_thresholds(None, design_efficiency=0.8, design_zero_order=0.01)
    assert defaults["source"] == "defaults (fab.verify.DEFAULT_ACCEPTANCE)"
    manifest = dict(correlation_min=0.9, rmse_max=0.1, efficiency_min=0.5, zero_order_max=0.05)
    assert resolve_thresholds(manifest, 0.8, 0.01)["source"] == "fab_manifest.json acceptance"
