"""Camera orientation and reflected plates: the flag applied, never guessed; conjugate and
mirrored plates measured as what they are; the hints that name an orientation."""

import dataclasses
import json

import numpy as np
import pytest
from verify_helpers import CAMERA_UM, PITCH_PX, K, L, N, make_design_dir, run_verify

from doe.fraunhofer import simulate_levels
from doe.infra.cli import main
from doe.infra.errors import InputError
from doe.infra.files import read_psf
from fab.plate.model import PlateFaults
from fab.verify.capture import write_image


def test_conjugate_plate_fails_as_point_reflection(tmp_path, levels, capsys):
    code, report, _ = run_verify(tmp_path, levels, dict(seed=7, faults=PlateFaults(conjugate=True)))
    assert code == 1
    assert "conjugate_plate" in report["diagnosis"]
    # a verdict on the plate, not a capture to take again
    assert capsys.readouterr().out.startswith("FAIL: conjugate_plate")
    fc = report["frame_correlation"]
    assert fc["rot180"] > fc["design"] + 0.3


@pytest.fixture(scope="module")
def half_order_levels():
    """A tile whose PSF is a 6 x 6 apodised window centred half an order off the axis.

    Its point reflection about the zero order is the same window one order
    further up-left: within the K x K window a conjugate plate looks like the
    design shifted by one order.
    """
    from doe.retrieval import retrieve_phase

    taper = np.hanning(8)[1:-1]
    target = np.zeros((K, K))
    target[3:9, 3:9] = np.outer(taper, taper)
    target /= target.sum()
    return retrieve_phase(target, n_pixels=48, n_levels=L, seed=0).levels


def test_conjugate_of_half_order_symmetric_psf_fails(tmp_path, half_order_levels):
    psf, _ = simulate_levels(half_order_levels, L, K)
    # The premise: the reflected PSF is the PSF shifted by one order, not the PSF.
    reflected = psf[::-1, ::-1]
    assert np.corrcoef(psf[1:, 1:].ravel(), reflected[:-1, :-1].ravel())[0, 1] > 0.99
    assert np.corrcoef(psf.ravel(), reflected.ravel())[0, 1] < 0.9
    kwargs = dict(rotation_deg=1.5, centre=(290.4, 310.2))
    code, report, _ = run_verify(tmp_path / "good", half_order_levels, dict(seed=31, **kwargs))
    assert code == 0, report["diagnosis"]
    assert report["zero_order_search"]["delta_chi2"]["rot180"] < -25
    code, report, _ = run_verify(
        tmp_path / "conj",
        half_order_levels,
        dict(seed=32, faults=PlateFaults(conjugate=True), **kwargs),
    )
    assert code == 1
    assert report["diagnosis"] == ["conjugate_plate"]
    assert report["zero_order_search"]["delta_chi2"]["rot180"] > 25
    # A window search alone is fooled (the window one order off matches the design);
    # measured at its own zero order, the plate shows its own, reflected PSF.
    measured = read_psf(tmp_path / "conj" / "out" / "measured_psf.npy")
    assert np.corrcoef(measured.ravel(), reflected.ravel())[0, 1] > 0.99
    assert report["correlation"] < 0.9


def test_ambiguous_zero_order_is_reported_not_passed(tmp_path, half_order_levels):
    # A short exposure: the window stands out of the noise but the orders outside it,
    # which alone tell the design from its reflection, do not.
    code, report, _ = run_verify(
        tmp_path,
        half_order_levels,
        dict(seed=33, peak_fraction=0.06, faults=PlateFaults(conjugate=True)),
    )
    assert code == 1
    assert "zero_order_ambiguous" in report["diagnosis"]
    assert report["window_snr"] > 30  # not merely low signal
    assert any("ambiguous" in note for note in report["notes"])
    # catches handing on its PSF: measured at the wrong zero order, it may be the reflection's
    assert report["measured_psf_usable"] is False


def test_mirrored_plate_fails(tmp_path, levels):
    # The plate's pattern arrives left-right flipped while the flag says as-designed.
    code, report, _ = run_verify(tmp_path, levels, dict(seed=9, orientation="mirror-x"))
    assert code == 1 and "mirrored" in report["diagnosis"]
    # Its measured PSF is not the plate's in the design's frame: no network is tuned to it.
    from doe.design import load_design
    from doe.records.psf_source import check_psf_grid

    assert report["measured_psf_usable"] is False
    with pytest.raises(InputError, match="could not judge \\(mirrored\\)") as refused:
        check_psf_grid(tmp_path / "out" / "measured_psf.npy", load_design(None))
    assert refused.value.source == str(tmp_path / "out" / "verify.json")


def test_designed_conjugate_plate_fails(tmp_path, designed):
    code, report, _ = run_verify(
        tmp_path, designed, dict(seed=23, faults=PlateFaults(conjugate=True))
    )
    assert code == 1 and report["diagnosis"] == ["conjugate_plate"]


@pytest.mark.parametrize("fault", ["conjugate", "mirrored"])
def test_a_reflected_plate_is_measured_as_what_it_is(tmp_path, designed, fault):
    # Its figures were taken where the design would put its zero order, three orders
    # off: a 20 % "zero order", an "implied deep-etch error" of 338 nm, and a
    # measured_psf.npy that matched neither the design nor the plate.
    from doe.fraunhofer import correlation

    if fault == "conjugate":
        plate, faults, code_name = L - 1 - designed, PlateFaults(conjugate=True), "conjugate_plate"
    else:
        plate = np.ascontiguousarray(designed[:, ::-1])
        faults, code_name = PlateFaults(other_levels=plate), "mirrored"
    sim_kwargs = dict(seed=24, faults=faults, centre=(280.2, 310.6))
    code, report, sim = run_verify(tmp_path, designed, sim_kwargs)
    assert code == 1 and report["diagnosis"] == [code_name]
    assert np.allclose(report["zero_order_px"], sim["zero_order_px"], atol=0.3)
    measured = read_psf(tmp_path / "out" / "measured_psf.npy")
    assert correlation(measured, simulate_levels(plate, L, K)[0]) > 0.99
    assert report["correlation"] < 0.9  # still compared with the design
    # a reflection of the design has its efficiency and zero order
    assert report["efficiency"] == pytest.approx(report["design_efficiency"], abs=0.03)
    assert report["zero_order"] == pytest.approx(report["design_zero_order"], abs=0.005)
    html = (tmp_path / "out" / "verify_report.html").read_text()
    assert html.count("<td>not judged</td>") == 5


@pytest.mark.parametrize(
    "orientation", ["rot90", "rot180", "mirror-y", "transpose", "antitranspose"]
)
def test_orientation_flag_is_applied_never_guessed(tmp_path, levels, orientation):
    kwargs = dict(seed=10, orientation=orientation)
    code, report, _ = run_verify(
        tmp_path / "flag", levels, kwargs, flags=("--orientation", orientation)
    )
    assert code == 0, report["diagnosis"]
    code, report, _ = run_verify(tmp_path / "noflag", levels, kwargs)
    assert code == 1


@pytest.mark.parametrize("orientation", ["rot90", "transpose"])
def test_capture_seen_otherwise_than_the_flag_names_the_orientation_that_fits(
    tmp_path, levels, orientation
):
    code, report, _ = run_verify(tmp_path, levels, dict(seed=10, orientation=orientation))
    assert code == 1 and report["diagnosis"] == ["other_design"]
    hints = [n for n in report["notes"] if "the orders match the design seen with" in n]
    assert len(hints) == 1 and f"--orientation {orientation}:" in hints[0]


@pytest.fixture(scope="module")
def compact_levels():
    """A tile whose PSF is a compact, lopsided blob: every orientation correlates highly."""
    from doe.retrieval import retrieve_phase

    y, x = np.mgrid[-(K // 2) : K // 2 + 1, -(K // 2) : K // 2 + 1]
    target = np.exp(-((x - 1) ** 2 + y**2) / 2.5) + 0.4 * np.exp(
        -((x + 1.5) ** 2 + (y - 2) ** 2) / 1.2
    )
    return retrieve_phase(target / target.sum(), n_pixels=N, n_levels=L, seed=0).levels


@pytest.mark.parametrize("seen", ["rot90", "rot270", "mirror-x"])
def test_compact_design_seen_turned_is_not_left_as_a_mirrored_plate(tmp_path, compact_levels, seen):
    # Seen turned by 90 degrees, a compact design fits a reflection better than
    # itself and failed as "mirrored" with no word of the turn: a lab would remake
    # a good plate. The design seen turned fits far better, and the note says so.
    code, report, _ = run_verify(tmp_path, compact_levels, dict(seed=10, orientation=seen))
    assert code == 1 and {"mirrored", "conjugate_plate"} & set(report["diagnosis"])
    turned = [n for n in report["notes"] if "far better" in n]
    if seen == "mirror-x":  # a mirrored plate (or camera): the reflection is the best fit
        assert turned == []
    else:
        assert len(turned) == 1 and f"--orientation {seen} far better" in turned[0]


def test_no_orientation_is_hinted_when_every_one_fits_as_well(monkeypatch):
    # a capture that fits every orientation alike (a colour sensor's raw mosaic) listed
    # all seven others
    from types import SimpleNamespace

    from fab.verify import hints
    from fab.verify.analysis import ORIENTATIONS

    monkeypatch.setattr(hints, "orientations_matching", lambda *a: list(ORIENTATIONS))
    design = SimpleNamespace(levels=None, n_levels=8, kernel_size=11)
    result = {"diagnosis": ["other_design"]}
    assert hints.orientation_hint(result, None, design, "as-designed") is None
    monkeypatch.setattr(hints, "orientations_matching", lambda *a: ["rot90"])
    assert "--orientation rot90" in hints.orientation_hint(result, None, design, "as-designed")


def test_an_orientation_hint_never_names_the_orientation_given(monkeypatch):
    # The deep mask 12 um off once failed as other_design with the orders outside the
    # window matching the design as seen: "verify again with --orientation as-designed",
    # the flag just used, would have sent the lab round in a circle.
    import fab.verify.hints
    from fab.verify.hints import orientation_hint

    design = dataclasses.make_dataclass("D", ["levels", "n_levels", "kernel_size"])(0, L, K)
    result = {"diagnosis": ["other_design"]}
    matching = ["as-designed", "mirror-x"]
    monkeypatch.setattr(fab.verify.hints, "orientations_matching", lambda *args: matching)
    hint = orientation_hint(result, None, design, "as-designed")
    assert "--orientation mirror-x" in hint and "as-designed" not in hint
    matching = ["as-designed"]
    assert orientation_hint(result, None, design, "as-designed") is None


# How a camera sees an image array: (orientation, image transform, centre transform).
CAMERAS = [
    ("as-designed", lambda a: a, lambda rc, hw: rc),
    ("transpose", lambda a: a.T, lambda rc, hw: (rc[1], rc[0])),
    (
        "antitranspose",
        lambda a: a[::-1, ::-1].T,
        lambda rc, hw: (hw[1] - 1 - rc[1], hw[0] - 1 - rc[0]),
    ),
]


@pytest.mark.parametrize("orientation, seen, centre_seen", CAMERAS, ids=[c[0] for c in CAMERAS])
def test_orientation_against_the_foundation_renderer(tmp_path, orientation, seen, centre_seen):
    """A blazed tile sends most light to order (m, n) = (-2, +3): up 2, right 3.

    The capture comes from doe.fraunhofer.dot_lattice_image (not this package's
    simulator), seen by the camera as numpy turns the array; with the camera's
    --orientation, the measured PSF must peak at [K//2 - 2, K//2 + 3] as simulate_levels.
    """
    from doe.fraunhofer import dot_lattice_image, level_phase

    r, c = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    blaze = (-2 * r + 3 * c) / N  # phase ramp of order (-2, 3), in cycles
    lv = np.floor(np.mod(blaze, 1) * L).astype(np.uint8)
    design_psf, _ = simulate_levels(lv, L, K)
    assert np.unravel_index(np.argmax(design_psf), design_psf.shape) == (K // 2 - 2, K // 2 + 3)
    img = dot_lattice_image(level_phase(lv, L), (500, 520), PITCH_PX, centre=(240.3, 262.8))
    img = img / img.max() * 3000 + np.random.default_rng(27).normal(20, 1.0, img.shape)
    design = make_design_dir(tmp_path / "design", lv)
    write_image(tmp_path / "cap.exr", np.ascontiguousarray(seen(img)).astype(np.float32))
    out = tmp_path / "o"
    # a blazed tile lights one order: its dots' spacing is no pitch, the bench states it
    args = ["--orientation", orientation, "--out", str(out), "--pixel-pitch-um", str(CAMERA_UM)]
    code = main(["verify", str(design), str(tmp_path / "cap.exr"), *args])
    report = json.loads((out / "verify.json").read_text())
    psf = read_psf(out / "measured_psf.npy")
    assert np.unravel_index(np.argmax(psf), psf.shape) == (K // 2 - 2, K // 2 + 3)
    assert np.allclose(report["zero_order_px"], centre_seen((240.3, 262.8), img.shape), atol=0.3)
    assert report["correlation"] > 0.99
    assert code == 0, report["diagnosis"]
