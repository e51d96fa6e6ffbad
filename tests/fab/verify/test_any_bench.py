"""verify on any bench: captures from ``doefab simulate-capture`` of two non-default designs
on cameras of 2.2, 3.45 and 5.86 um pixels, verified without ``--pixel-pitch-um``."""

import json

import numpy as np
import pytest

from doe.derived import design_summary
from doe.design import load_design
from doe.fraunhofer import simulate_levels
from doe.infra.cli import main
from doe.records.capture import read_capture_record
from doe.retrieval import retrieve_phase
from doe.targets import make_target

# 532 nm, BK7, 4 levels, 12.7 mm aperture, a 100 um SPAD seen 4x finer: 25 um orders
GREEN = """name = "green"
[sensor]
pixel_pitch_um = 100.0
active_area_um = 20.0
[optics]
wavelength_nm = 532.0
[material]
name = "bk7"
[fabrication]
levels = 4
aperture_mm = 12.7
"""
# 780 nm, fused silica, 8 levels, 10 um features, a 120 um pixel seen 4x finer: 30 um orders
NIR = """name = "nir"
[sensor]
pixel_pitch_um = 120.0
active_area_um = 25.0
[optics]
wavelength_nm = 780.0
focal_length_mm = 40.0
[fabrication]
levels = 8
feature_size_um = 10.0
aperture_mm = 10.0
"""


def _retrieve_dir(path, toml, n, k, seed, target="asymmetric"):
    """A retrieve folder of an N-pixel tile for the design ``toml``; return it."""
    path.mkdir(parents=True)
    (path.parent / f"{path.name}.toml").write_text(toml)
    design = load_design(path.parent / f"{path.name}.toml")
    levels_n = design.fabrication.levels
    levels = retrieve_phase(make_target(target, k), n, levels_n, seed=seed).levels
    np.save(path / "levels.npy", levels)
    np.save(path / "target_psf.npy", simulate_levels(levels, levels_n, k)[0])
    record = {"levels": levels_n, "kernel_size": k, "design": design_summary(design, n)}
    (path / "retrieval.json").write_text(json.dumps(record))
    return path


@pytest.fixture(scope="module")
def designs(tmp_path_factory):
    root = tmp_path_factory.mktemp("designs")
    return {
        "green": _retrieve_dir(root / "green", GREEN, 35, 11, 0),
        # another lab design of the same tile: a plate made from it by mistake
        "green_other": _retrieve_dir(root / "green_other", GREEN, 35, 11, 5, "anisotropic"),
        "nir": _retrieve_dir(root / "nir", NIR, 25, 7, 1),
    }


# the spot on each camera: its pixels of 2.2, 3.45, 5.86 um see a lens's blur of 1-4 um
SPOT_UM = {2.2: 1.0, 3.45: 1.0, 5.86: 4.1}


def _capture(tmp_path, design, camera_um, *faults, name="cap"):
    out = tmp_path / name
    args = ["simulate-capture", str(design), "--out", str(out), "--pixel-pitch-um"]
    args += [str(camera_um), "--spot-sigma-um", str(SPOT_UM[camera_um]), *faults]
    assert main(args) == 0
    return out


def _verify(tmp_path, design, capture, *flags):
    out = tmp_path / "verify"
    args = ["verify", str(design), str(capture / "capture.tif"), "--dark"]
    args += [str(capture / "dark.tif"), "--out", str(out), "--force", *flags]
    code = main(args)
    report = json.loads((out / "verify.json").read_text()) if code in (0, 1) else None
    return code, report


@pytest.mark.parametrize(
    ("design", "camera_um"), [("green", 2.2), ("green", 3.45), ("green", 5.86), ("nir", 5.86)]
)
def test_a_nominal_plate_passes_on_any_camera_without_its_pixel_pitch(
    tmp_path, designs, design, camera_um
):
    capture = _capture(tmp_path, designs[design], camera_um)
    bench = read_capture_record(capture / "capture.json").bench
    code, report = _verify(tmp_path, designs[design], capture)
    assert code == 0, report["diagnosis"]
    # the lattice pitch measured, not assumed: the capture's own, to 0.2 %
    assert report["lattice"]["pitch_px"] == pytest.approx(bench["lattice_pitch_px"], rel=2e-3)
    assert report["implied_pixel_pitch_um"] == pytest.approx(camera_um, rel=2e-3)
    assert report["pixel_pitch_um"] is None


@pytest.mark.parametrize(
    ("camera_um", "faults", "code"),
    [
        (5.86, ("--etch-error", "M1_deep=0.15"), "deep_etch_error"),
        (2.2, ("--conjugate",), "conjugate_plate"),
        (3.45, ("--mirrored",), "mirrored"),
        (5.86, ("--other-design", "green_other"), "other_design"),
    ],
)
def test_a_faulty_plate_fails_with_its_diagnosis(tmp_path, designs, camera_um, faults, code):
    faults = tuple(str(designs[f]) if f in designs else f for f in faults)
    capture = _capture(tmp_path, designs["green"], camera_um, *faults)
    exit_code, report = _verify(tmp_path, designs["green"], capture)
    assert exit_code == 1 and code in report["diagnosis"], report["diagnosis"]


def test_a_contradicting_pixel_pitch_is_exit_2_with_both_numbers(tmp_path, designs, capsys):
    capture = _capture(tmp_path, designs["green"], 2.2)
    capsys.readouterr()
    code, _ = _verify(tmp_path, designs["green"], capture, "--pixel-pitch-um", "3.45")
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1
    # measured 25 um / 2.2 um = 11.36 px; stated 25 / 3.45 = 7.246 px
    assert "11.36 px apart (measured)" in err and "give 7.246 px" in err
    assert not (tmp_path / "verify").exists()
    # the right pitch is accepted, and agrees
    code, report = _verify(tmp_path, designs["green"], capture, "--pixel-pitch-um", "2.2")
    assert code == 0 and report["pixel_pitch_um"] == 2.2


def test_swapped_files_name_the_dark_frame_on_a_tight_lattice(tmp_path, designs, capsys):
    # 4.27 px apart: the dark frame is named only when its dots carry the light
    capture = _capture(tmp_path, designs["green"], 5.86)
    capsys.readouterr()
    swapped = tmp_path / "swapped"
    swapped.mkdir()
    (swapped / "capture.tif").write_bytes((capture / "dark.tif").read_bytes())
    (swapped / "dark.tif").write_bytes((capture / "capture.tif").read_bytes())
    code, _ = _verify(tmp_path, designs["green"], swapped)
    err = capsys.readouterr().err
    assert code == 2 and "dark.tif" in err and "swapped" in err
