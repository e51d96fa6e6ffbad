"""``verify_plate`` called as a library: its result, the files it writes, its refusals."""

import json

import numpy as np
import pytest
from verify_helpers import PITCH_PX, K, L, make_design_dir

from doe.infra.errors import InputError
from doe.infra.files import write_json
from doe.records.verify import read_verify
from fab.plate.model import PlateFaults
from fab.verify.capture import write_image
from fab.verify.design_ref import read_design_dir
from fab.verify.plate_check import VERIFY_FILES, VerifyResult, save_verify, verify_plate
from fab.verify.simulate import simulate_capture

# A lab's acceptance tighter than the defaults.
STRICT_ACCEPTANCE = dict(
    correlation_min=0.99, rmse_max=0.02, efficiency_min=0.5, zero_order_max=0.05
)


def captured(tmp_path, levels, **sim_kwargs):
    """Write a simulated capture of a plate of ``levels`` and its dark frame; return both."""
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, **sim_kwargs)
    capture, dark = tmp_path / "capture.png", tmp_path / "dark.png"
    write_image(capture, sim["capture"], exposure=0.01)
    write_image(dark, sim["dark"], exposure=0.01)
    return capture, dark


def test_a_good_plate_passes_and_its_files_hold_the_result(tmp_path, levels):
    design = make_design_dir(tmp_path / "design", levels)
    capture, dark = captured(tmp_path, levels, seed=1)
    out = tmp_path / "out"
    result = verify_plate(design, capture, dark=dark, out=out)
    assert isinstance(result, VerifyResult)
    assert result.passed and result.verdict == "PASS" and result.diagnosis == ("ok",)
    assert result.hints == () and result.remedies == ()
    assert result.summary.startswith("PASS: ok  correlation 0.99")
    psf = result.measured_psf
    assert psf.shape == (K, K) and psf.min() >= 0 and psf.sum() == pytest.approx(1.0)
    assert result.out == out and result.files == tuple(out / name for name in VERIFY_FILES)
    assert all(path.is_file() for path in result.files)
    assert np.array_equal(np.load(out / "measured_psf.npy"), psf)
    record = read_verify(out / "verify.json")
    assert record.passed is True and record.diagnosis == ["ok"]
    assert record.measured_psf_usable is True
    assert record.design_lattice_pitch_um == pytest.approx(37.504)
    assert record.data["correlation"] == result.report["correlation"]
    assert result.record.diagnosis == record.diagnosis and result.notes == tuple(
        record.data["notes"]
    )


def test_without_out_nothing_is_written_until_saved(tmp_path, levels):
    design = make_design_dir(tmp_path / "design", levels)
    capture, dark = captured(tmp_path, levels, seed=1)
    result = verify_plate(design, capture, dark=dark)
    assert result.out is None and result.files == () and not (tmp_path / "out").exists()
    saved = save_verify(result, tmp_path / "out")
    assert saved.files and all(path.is_file() for path in saved.files)
    with pytest.raises(InputError) as refused:  # the files exist: not overwritten
        save_verify(result, tmp_path / "out")
    assert "verify.json" in str(refused.value)
    assert save_verify(result, tmp_path / "out", force=True).passed


def test_a_design_folder_read_already_verifies_the_same(tmp_path, levels):
    design = make_design_dir(tmp_path / "design", levels)
    capture, dark = captured(tmp_path, levels, seed=1)
    by_folder = verify_plate(design, capture, dark=dark)
    by_ref = verify_plate(read_design_dir(design), capture, dark=dark)
    assert np.array_equal(by_ref.measured_psf, by_folder.measured_psf)
    assert by_ref.report["correlation"] == by_folder.report["correlation"]
    assert by_folder.report["inputs"]["design_dir"] == str(design)
    assert by_ref.report["inputs"]["design_dir"] is None


def test_a_conjugate_plate_fails_with_its_diagnosis_and_remedies(tmp_path, levels):
    design = make_design_dir(tmp_path / "design", levels)
    capture, dark = captured(tmp_path, levels, seed=4, faults=PlateFaults(conjugate=True))
    result = verify_plate(design, capture, dark=dark)
    assert not result.passed and result.verdict == "FAIL"
    assert result.diagnosis == ("conjugate_plate",)
    assert result.report["measured_as"] == "rot180"
    assert any("reflection of the design" in note for note in result.remedies)
    assert all(note in result.notes for note in result.remedies)


def test_a_plate_with_an_etch_off_fails_and_the_hint_names_the_mask(tmp_path, designed):
    design = make_design_dir(tmp_path / "design", designed, acceptance=STRICT_ACCEPTANCE)
    manifest = design / "fab_manifest.json"
    write_json(manifest, {**json.loads(manifest.read_text()), "pixel_pitch_nm": 4990})
    faults = PlateFaults(etch_errors=(0.0, 0.2, 0.0))
    capture, dark = captured(tmp_path, designed, seed=11, faults=faults)
    result = verify_plate(design, capture, dark=dark)
    assert not result.passed and result.diagnosis[0] == "etch_depth_error"
    (hint,) = result.hints
    assert "M2_mid" in hint and "too deep" in hint and hint in result.notes


def test_a_capture_not_judged_says_so(tmp_path, levels):
    design = make_design_dir(tmp_path / "design", levels)
    capture, dark = captured(tmp_path, levels, seed=12, peak_fraction=4.0)
    result = verify_plate(design, capture, dark=dark)
    assert result.verdict == "FAIL (capture not judged)" and "saturated" in result.diagnosis
    assert result.record.measured_psf_usable is False


@pytest.mark.parametrize("missing", ["capture", "dark", "design"])
def test_a_refusal_raises_input_error_naming_the_file(tmp_path, levels, missing):
    design = make_design_dir(tmp_path / "design", levels)
    capture, dark = captured(tmp_path, levels, seed=1)
    gone = {"capture": capture, "dark": dark, "design": design}[missing]
    named = gone.with_name("nowhere" + gone.suffix)
    args = {"design": design, "capture": capture, "dark": dark, missing: named}
    with pytest.raises(InputError) as refused:
        verify_plate(args["design"], args["capture"], dark=args["dark"])
    assert refused.value.source == str(named)


def test_a_dark_frame_holding_the_dots_is_refused_naming_it(tmp_path, levels):
    design = make_design_dir(tmp_path / "design", levels)
    capture, dark = captured(tmp_path, levels, seed=1)
    with pytest.raises(InputError, match="are the capture and --dark swapped") as refused:
        verify_plate(design, dark, dark=capture)
    assert refused.value.source == str(capture)


@pytest.mark.parametrize(
    "kwargs, culprit",
    [
        (dict(pixel_pitch_um=0.0), "pixel_pitch_um"),
        (dict(lattice_pitch_um=float("nan")), "lattice_pitch_um"),
        (dict(orientation="upside-down"), "orientation"),
    ],
)
def test_arguments_out_of_range_are_refused_naming_them(tmp_path, levels, kwargs, culprit):
    design = make_design_dir(tmp_path / "design", levels)
    with pytest.raises(InputError) as refused:
        verify_plate(design, tmp_path / "capture.png", **kwargs)
    assert refused.value.source == culprit
