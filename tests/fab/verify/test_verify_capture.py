"""Captures and dark frames: reading, refusals naming the file, saturation, too little signal."""

import dataclasses
import json
import re

import numpy as np
import pytest
from verify_helpers import CAMERA_UM, PITCH_PX, PITCH_UM, L, make_design_dir, run_verify

from doe.infra.cli import main
from doe.infra.errors import InputError
from fab.verify.capture import RawImage, read_capture, read_raw_image, write_image
from fab.verify.conditioning import (
    EXPOSURE_RTOL,
    PLATEAU_PIXELS,
    check_dark,
    condition_capture,
    hot_pixels_from_dark,
    repair_pixels,
)
from fab.verify.simulate import simulate_capture


def test_12bit_msb_png_is_detected(tmp_path, levels):
    code, report, _ = run_verify(tmp_path, levels, dict(seed=4, bits=12), dark=False)
    assert code == 0
    assert any("MSB-aligned" in n for n in report["notes"])


def test_capture_with_no_light_in_the_window_is_unusable(tmp_path, levels, capsys):
    # A lone bright pixel on a dark float frame once divided by a beam power of 0:
    # a ZeroDivisionError and exit 1, which for verify means "the plate fails".
    design = make_design_dir(tmp_path / "design", levels)
    image = np.zeros((200, 200), np.float32)
    image[100, 100] = 1.0
    write_image(tmp_path / "one_dot.exr", image)
    out = tmp_path / "out"
    argv = ["verify", str(design), str(tmp_path / "one_dot.exr"), "--out", str(out)]
    assert main(argv) == 2  # one dot has no neighbour: no pitch to measure
    err = capsys.readouterr().err
    assert "one_dot.exr: too few of its dots" in err and "give --pixel-pitch-um" in err
    assert main([*argv, "--pixel-pitch-um", str(CAMERA_UM)]) == 2
    err = capsys.readouterr().err
    assert "one_dot.exr: too little signal" in err and not out.exists()


def test_saturated_capture_fails_with_that_reason(tmp_path, levels, capsys):
    code, report, _ = run_verify(tmp_path, levels, dict(seed=12, peak_fraction=4.0))
    assert code == 1 and report["pass"] is False
    assert "saturated" in report["diagnosis"]
    assert report["saturated_dots"] > 0
    # said where the lab reads it, with its remedy: the plate was not judged
    out = capsys.readouterr()
    assert out.out.startswith("FAIL (capture not judged): saturated")
    assert "shorten the exposure" in out.err


def test_low_signal_fails(tmp_path, levels, capsys):
    code, report, _ = run_verify(
        tmp_path, levels, dict(seed=13, peak_fraction=0.01, read_noise_dn=3.0)
    )
    assert code == 1 and "low_signal" in report["diagnosis"]
    out = capsys.readouterr()  # "FAIL: low_signal" and nothing more was printed
    assert out.out.startswith("FAIL (capture not judged): low_signal")
    assert re.search(r"window SNR [\d.]+ is under 30: lengthen the exposure", out.err)
    # an 8-bit capture near full scale is told of the camera's deeper modes (it was told
    # to lengthen the exposure, which saturates it)
    code, report, _ = run_verify(
        tmp_path / "full", levels, dict(seed=13, bits=8, peak_fraction=0.94, read_noise_dn=6.0)
    )
    assert code == 1 and "low_signal" in report["diagnosis"]
    assert re.search(
        r"under 30: the brightest dot is near full scale already: use the camera's 12- or 16-bit",
        capsys.readouterr().err,
    )


@pytest.mark.parametrize(("peak", "advice"), [(240.0, "12- or 16-bit mode"), (100.0, "lengthen")])
def test_more_signal_is_not_a_longer_exposure_for_a_capture_near_full_scale(peak, advice):
    # an 8-bit capture at 94 % of full scale was told to lengthen the exposure, which the
    # next capture failed as saturated
    from types import SimpleNamespace

    from fab.verify.hints import more_signal

    capture = SimpleNamespace(full_scale=255.0, image=np.array([[3.0, peak]]))
    assert advice in more_signal(capture)


def test_truncated_capture_exits_2_naming_the_file(tmp_path, levels, capsys):
    design = make_design_dir(tmp_path / "design", levels)
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, shape=(200, 200), seed=14)
    write_image(tmp_path / "cap.png", sim["capture"])
    data = (tmp_path / "cap.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    code = main(["verify", str(design), str(tmp_path / "cut.png"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert "cut.png" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "name, save, refusal",
    [
        ("cap.jpg", dict(quality=95), "JPEG image"),
        ("cap.webp", dict(quality=95), "WEBP image"),
        ("cap.gif", {}, "GIF image"),
        ("cap.tif", dict(compression="jpeg"), "TIFF compressed with loss (jpeg)"),
    ],
)
def test_a_capture_stored_with_loss_is_refused(tmp_path, levels, capsys, name, save, refusal):
    # CONVENTIONS names TIFF, PNG and EXR: a JPEG capture's compression moved the weak
    # orders' counts, and verify judged the plate by them.
    from PIL import Image

    design = make_design_dir(tmp_path / "design", levels)
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, bits=8, seed=1)
    Image.fromarray(sim["capture"]).save(tmp_path / name, **save)
    write_image(tmp_path / "cap.png", sim["capture"])
    for capture, dark in ((name, None), ("cap.png", name)):
        argv = ["verify", str(design), str(tmp_path / capture), "--out", str(tmp_path / "o")]
        code = main(argv + (["--dark", str(tmp_path / dark)] if dark else []))
        err = capsys.readouterr().err.strip()
        assert code == 2 and f"{name}: {refusal}; give the capture as TIFF, PNG or EXR" in err
        assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("compression", ["dwaa", "b44"])
def test_an_exr_capture_compressed_with_loss_is_refused(tmp_path, compression):
    import OpenImageIO as oiio

    def exr(name, compression):
        spec = oiio.ImageSpec(32, 32, 1, "float")
        spec.attribute("compression", compression)
        out = oiio.ImageOutput.create(str(tmp_path / name))
        out.open(str(tmp_path / name), spec)
        out.write_image(np.ones((32, 32, 1), np.float32))
        out.close()
        return tmp_path / name

    with pytest.raises(InputError, match=f"EXR compressed with loss \\({compression}\\)"):
        read_capture(exr("cap.exr", compression))
    assert read_capture(exr("zip.exr", "zip")).image.shape == (32, 32)  # lossless: read


def test_dots_too_close_to_measure_exit_2(tmp_path, levels, capsys):
    # At 3 px apart the lattice fit is a few per cent off: this capture of a good
    # plate once failed as conjugate_plate; a pixel pitch in nm (1000x) once ran out of memory.
    design = make_design_dir(tmp_path / "design", levels)
    sim = simulate_capture(levels, L, pitch_px=3.0, shape=(300, 300), seed=16)
    write_image(tmp_path / "cap.png", sim["capture"], exposure=0.01)
    out = tmp_path / "o"
    for pixel_um in (PITCH_UM / 3.0, CAMERA_UM * 1000):
        argv = ["verify", str(design), str(tmp_path / "cap.png"), "--out", str(out)]
        assert main([*argv, "--pixel-pitch-um", str(pixel_um)]) == 2
        err = capsys.readouterr().err.strip()
        # the file, or the flag the capture contradicts (named with both pitches)
        assert "px apart" in err and len(err.splitlines()) == 1
        assert "cap.png" in err if pixel_um < 100 else "--pixel-pitch-um: " in err
        assert not out.exists()
    for flag, value in (("--pixel-pitch-um", "nan"), ("--lattice-pitch-um", "inf")):
        assert main([*argv, flag, value]) == 2
        assert flag in capsys.readouterr().err and not out.exists()


def test_dark_frame_of_another_size_or_exposure_exits_2(tmp_path, levels, capsys):
    design = make_design_dir(tmp_path / "design", levels)
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, shape=(300, 300), seed=15)
    write_image(tmp_path / "cap.png", sim["capture"], exposure=0.01)
    write_image(tmp_path / "small.png", sim["dark"][:200], exposure=0.01)
    write_image(tmp_path / "long.png", sim["dark"], exposure=0.5)
    for dark in ("small.png", "long.png"):
        code = main(
            [
                "verify",
                str(design),
                str(tmp_path / "cap.png"),
                "--dark",
                str(tmp_path / dark),
                "--out",
                str(tmp_path / "o"),
            ]
        )
        err = capsys.readouterr().err
        assert code == 2 and dark in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("mixup", ["swapped", "lit dark"])
def test_a_dark_frame_holding_the_dots_is_named(tmp_path, levels, capsys, mixup):
    # Both failed as "capture.png: no dot stands 8 sigma above the noise", which sent
    # the lab to its plate and camera rather than to the dark frame.
    design = make_design_dir(tmp_path / "design", levels)
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=1)
    other = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=5)["capture"]
    capture, dark = (sim["dark"], sim["capture"]) if mixup == "swapped" else (sim["capture"], other)
    write_image(tmp_path / "cap.png", capture, exposure=0.01)
    write_image(tmp_path / "dark.png", dark, exposure=0.01)
    argv = ["verify", str(design), str(tmp_path / "cap.png"), "--dark", str(tmp_path / "dark.png")]
    assert main([*argv, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "dark.png: the dark frame holds" in err and ("swapped" in err) == (mixup == "swapped")
    assert not (tmp_path / "o").exists()


def test_a_dark_frame_that_saw_light_is_refused(tmp_path, levels, capsys):
    # A dark saturated everywhere was subtracted and the plate passed as if it were one.
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, shape=(300, 300), seed=15)
    raw = RawImage(sim["capture"] >> 4, 4095.0, None, encoding="uint16-msb12")
    dark = sim["dark"] >> 4
    spots = np.random.default_rng(0).random(dark.shape)
    for share, refused in ((0.005, False), (0.02, True), (1.0, True)):
        lit = np.where(spots < share, 4095, dark)
        lit_raw = RawImage(lit, 4095.0, None, encoding="uint16-msb12")
        if refused:
            with pytest.raises(InputError, match=r"dark.png: .* at full scale \(4095\): it saw"):
                check_dark(raw, lit_raw, tmp_path / "dark.png")
        else:  # a few hot pixels at full scale are a dark frame's own
            check_dark(raw, lit_raw, tmp_path / "dark.png")


@pytest.mark.parametrize("rise", [0, 200])
def test_a_dark_floor_above_the_capture_is_noted(levels, rise):
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, shape=(300, 300), seed=15)
    raw = RawImage(sim["capture"] >> 4, 4095.0, None, encoding="uint16-msb12")
    dark = RawImage((sim["dark"] >> 4) + rise, 4095.0, None, encoding="uint16-msb12")
    notes = condition_capture(raw, dark).notes
    assert any(f"floor is {rise} DN above" in n for n in notes) == (rise > 0)


@pytest.mark.parametrize("seconds", [-0.01, float("nan"), float("inf")])
def test_an_exposure_time_that_is_no_time_is_ignored_and_noted(tmp_path, seconds):
    # Equal negative ExposureTimes were refused as "dark exposure -0.01 s differs from
    # the capture's -0.01 s"; a NaN one passed every comparison, an infinite one failed it.
    image = np.full((8, 8), 100, np.float32)
    write_image(tmp_path / "cap.exr", image, exposure=seconds)
    write_image(tmp_path / "dark.exr", image, exposure=seconds)
    capture = read_capture(tmp_path / "cap.exr", tmp_path / "dark.exr")
    assert read_raw_image(tmp_path / "cap.exr").exposure is None
    assert f"cap.exr: the file's ExposureTime {seconds:g} s is no exposure time" in capture.notes[0]


def test_blank_capture_exits_2(tmp_path, levels, capsys):
    design = make_design_dir(tmp_path / "design", levels)
    rng = np.random.default_rng(16)
    write_image(tmp_path / "blank.tif", rng.normal(100, 2, (300, 300)).astype(np.float32))
    code = main(["verify", str(design), str(tmp_path / "blank.tif"), "--out", str(tmp_path / "o")])
    assert code == 2 and "blank.tif" in capsys.readouterr().err


def test_a_saturated_pixel_off_the_dots_is_noted_and_does_not_fail(tmp_path, levels):
    design = make_design_dir(tmp_path / "design", levels)
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=1)
    capture = sim["capture"].copy()
    # half a pitch off a lattice site in both directions: as far from any dot as can be
    row, col = np.round(np.array(sim["zero_order_px"]) + 5.5 * PITCH_PX).astype(int)
    capture[row, col] = 4095 << 4  # full scale of the 12-bit data, MSB-aligned
    write_image(tmp_path / "cap.png", capture)
    out = tmp_path / "o"
    assert main(["verify", str(design), str(tmp_path / "cap.png"), "--out", str(out)]) == 0
    report = json.loads((out / "verify.json").read_text())
    assert report["saturated_dots"] == 0
    assert "1 saturated pixel(s) outside the dots" in report["notes"]


def test_clipped_14bit_capture_is_flagged_saturated(tmp_path, levels):
    """A 16-bit file from a 14-bit sensor (LSB-aligned): clipping shows as a plateau."""
    sim = simulate_capture(
        levels, L, pitch_px=PITCH_PX, seed=26, bits=16, peak_fraction=3.0, full_well_e=16383 * 2.0
    )
    clipped = np.minimum(sim["capture"], 16383).astype(np.uint16)
    design = make_design_dir(tmp_path / "design", levels)
    write_image(tmp_path / "cap.tif", clipped)
    code = main(["verify", str(design), str(tmp_path / "cap.tif"), "--out", str(tmp_path / "o")])
    report = json.loads((tmp_path / "o" / "verify.json").read_text())
    assert code == 1 and "saturated" in report["diagnosis"]


@pytest.mark.parametrize("bits", [10, 8])
def test_clipped_capture_msb_aligned_from_fewer_bits_is_flagged_saturated(tmp_path, levels, bits):
    """10-bit data shifted into 16 bits (low 6 bits zero), or 8-bit data scaled by 256."""
    top = (1 << bits) - 1
    sim = simulate_capture(
        levels, L, pitch_px=PITCH_PX, seed=27, bits=16, peak_fraction=3.0, full_well_e=top * 2.0
    )
    codes = np.minimum(sim["capture"], top).astype(np.uint16)
    clipped = int(np.count_nonzero(codes == top))
    assert clipped >= 3
    write_image(tmp_path / "cap.tif", codes << (16 - bits))
    raw = read_raw_image(tmp_path / "cap.tif")
    assert raw.full_scale == top << (12 - bits)  # the sensor's top code in 12-bit DN
    assert raw.quantum == 1 << (12 - bits)  # and its step
    assert np.count_nonzero(condition_capture(raw).saturated) == clipped
    design = make_design_dir(tmp_path / "design", levels)
    code = main(["verify", str(design), str(tmp_path / "cap.tif"), "--out", str(tmp_path / "o")])
    report = json.loads((tmp_path / "o" / "verify.json").read_text())
    assert code == 1 and "saturated" in report["diagnosis"]


@pytest.mark.parametrize("dark", [False, True])
def test_quiet_8bit_capture_of_a_good_plate_passes(tmp_path, levels, dark):
    """Read noise well below 1 DN: nearly all the background is one code (spread 0)."""
    kwargs = dict(seed=29, bits=8, read_noise_dn=0.2, dark_level_dn=3.0)
    code, report, sim = run_verify(tmp_path, levels, kwargs, dark=dark)
    background = sim["capture"][:40, :40]
    assert np.mean(background == np.median(background)) > 0.9
    assert code == 0, report and report["diagnosis"]
    assert report["window_snr"] > 10


def test_repair_pixels_uses_the_neighbour_median():
    img = np.arange(25, dtype=np.float32).reshape(5, 5)
    img[1, 1] = 500.0  # a bright neighbour (a dot's peak): a mean of the neighbours follows it
    bad = np.zeros((5, 5), bool)
    bad[2, 2] = True
    img2 = img.copy()
    img2[2, 2] = 1e6
    out = repair_pixels(img2, bad)
    assert out[2, 2] == np.median(np.delete(img[1:4, 1:4].ravel(), 4))
    assert img2[2, 2] == 1e6  # the argument is not modified


def test_hot_pixels_are_flagged_from_the_dark_and_the_dark_subtracted(levels):
    sim = simulate_capture(
        levels, L, pitch_px=PITCH_PX, shape=(300, 300), seed=19, hot_pixels=25, bits=16
    )
    cap = condition_capture(
        RawImage(sim["capture"], 65535.0, None), RawImage(sim["dark"], 65535.0, None)
    )
    assert cap.hot.sum() >= 20
    assert np.array_equal(cap.image, sim["capture"].astype(np.float32) - sim["dark"])


def test_16bit_file_with_only_three_low_bits_zero_is_read_as_stored(tmp_path):
    # catches taking it for 12-bit MSB-aligned data (four low bits zero): a negative shift crashed
    codes = np.random.default_rng(5).integers(0, 1 << 13, (20, 20)).astype(np.uint16) << 3
    codes[0, 0] = 8  # bit 3 set
    write_image(tmp_path / "cap.tif", codes)
    raw = read_raw_image(tmp_path / "cap.tif")
    assert raw.encoding == "uint16" and raw.quantum == 8.0  # 13-bit codes, 8 apart
    assert np.array_equal(raw.data, codes)


@pytest.mark.parametrize("bits", [13, 14, 15])
def test_one_clipped_pixel_of_a_msb_aligned_13_to_15_bit_capture_is_saturated(tmp_path, bits):
    # at 65535 the sensor's top code (65532 for 14 bits) went unflagged, below a plateau
    shift = 16 - bits
    codes = np.random.default_rng(bits).integers(50, 3000, (40, 40)).astype(np.uint16) << shift
    codes[7, 9] = ((1 << bits) - 1) << shift
    write_image(tmp_path / "cap.tif", codes)
    raw = read_raw_image(tmp_path / "cap.tif")
    assert raw.full_scale == 65536 - 2**shift and raw.quantum == 2**shift
    assert np.argwhere(condition_capture(raw).saturated).tolist() == [[7, 9]]


def test_16bit_file_that_reaches_4095_is_12bit_data_clipped_there(tmp_path):
    # catches "< 4095": a 12-bit capture with a clipped pixel read as 16-bit data, not saturated
    codes = np.random.default_rng(6).integers(50, 200, (40, 40)).astype(np.uint16)
    codes[20, 20] = 4095
    write_image(tmp_path / "cap.tif", codes)
    raw = read_raw_image(tmp_path / "cap.tif")
    assert raw.full_scale == 4095
    assert np.argwhere(condition_capture(raw).saturated).tolist() == [[20, 20]]


def test_dark_frame_exposure_must_match_the_capture_within_the_tolerance():
    # catches a tolerance ten times too loose: a dark 3 % longer was subtracted
    raw = RawImage(np.zeros((4, 4), np.uint16), 65535.0, 0.01, encoding="uint16")
    check_dark(raw, dataclasses.replace(raw, exposure=0.01 * (1 + EXPOSURE_RTOL / 2)), "d.tif")
    with pytest.raises(InputError, match=r"d\.tif: dark exposure"):
        check_dark(
            raw, dataclasses.replace(raw, exposure=0.01 * (1 + 1.5 * EXPOSURE_RTOL)), "d.tif"
        )


def test_a_12_bit_dark_written_msb_aligned_serves_a_12_bit_tiff_capture(tmp_path):
    # the same camera's 12-bit codes, one file written with BitsPerSample 12, the other
    # MSB-aligned in 16 bits, were refused as "other camera settings"
    import OpenImageIO as oiio

    rng = np.random.default_rng(8)
    codes = rng.integers(50, 4000, (30, 30)).astype(np.uint16)
    spec = oiio.ImageSpec(30, 30, 1, "uint16")
    spec.attribute("oiio:BitsPerSample", 12)
    out = oiio.ImageOutput.create(str(tmp_path / "cap.tif"))
    out.open(str(tmp_path / "cap.tif"), spec)
    out.write_image(np.ascontiguousarray((codes << 4)[..., None]))  # OIIO keeps the top 12
    out.close()
    dark = rng.integers(55, 66, (30, 30)).astype(np.uint16)
    write_image(tmp_path / "dark.png", dark << 4)
    capture = read_capture(tmp_path / "cap.tif", tmp_path / "dark.png")
    assert read_raw_image(tmp_path / "cap.tif").encoding == "uint12"
    np.testing.assert_allclose(capture.image, codes.astype(float) - dark, atol=1e-3)


def test_dark_frame_stored_otherwise_than_the_capture_is_refused(tmp_path):
    # catches subtracting a 16-bit LSB dark (DN) from a 12-bit MSB-aligned capture as is
    rng = np.random.default_rng(8)
    write_image(tmp_path / "cap.tif", rng.integers(50, 4000, (30, 30)).astype(np.uint16) << 4)
    write_image(tmp_path / "dark.tif", rng.integers(55, 66, (30, 30)).astype(np.uint16))
    with pytest.raises(InputError, match=r"dark\.tif: dark frame is stored as uint16 but"):
        read_capture(tmp_path / "cap.tif", tmp_path / "dark.tif")


def test_hot_pixel_ten_sigmas_above_a_2dn_dark_is_flagged():
    # catches a noise floor of 5 DN: a 2 DN dark then flagged only pixels 50 DN above it
    dark = np.rint(np.random.default_rng(9).normal(60.0, 2.0, (90, 90))).astype(np.float32)
    dark[45, 45] += 40.0  # 20 sigma
    dark[10, 10] += 12.0  # 6 sigma: noise, not hot
    assert np.argwhere(hot_pixels_from_dark(dark)).tolist() == [[45, 45]]


def test_plateau_of_exactly_the_plateau_pixels_marks_a_float_capture_clipped():
    # catches "> PLATEAU_PIXELS": a plateau of exactly that many pixels was not taken as clipped
    image = np.random.default_rng(10).normal(10.0, 1.0, (50, 50)).astype(np.float32)
    rows, cols = np.arange(PLATEAU_PIXELS) * 7 + 5, np.arange(PLATEAU_PIXELS) * 9 + 3
    image[rows, cols] = 1000.0
    raw = RawImage(image, None, None, encoding="float", quantum=0.0)
    assert np.argwhere(condition_capture(raw).saturated).tolist() == np.c_[rows, cols].tolist()
    fewer = image.copy()
    fewer[rows[0], cols[0]] = 999.0  # one pixel fewer at the maximum: a peak, not a plateau
    assert not condition_capture(dataclasses.replace(raw, data=fewer)).saturated.any()


def test_a_faint_dot_centred_on_a_pixel_keeps_its_light_and_a_hot_pixel_does_not():
    # Every dot of an 11 px lattice centred on a pixel puts 82 % of its light in it
    # (a 0.3 px sigma spot); at 16 sigma the noise hides its neighbours' share in some
    # apertures, which must not pass for hot pixels. Four sites without a dot hold a
    # single hot pixel each.
    from scipy.special import erf

    from fab.verify.lattice import Lattice
    from fab.verify.photometry import measure_orders

    pitch, power, noise = 11, 200.0, 1.5
    edges = np.arange(-5, 6)
    profile = 0.5 * (
        erf((edges + 0.5) / (0.3 * np.sqrt(2))) - erf((edges - 0.5) / (0.3 * np.sqrt(2)))
    )
    dot = power * np.outer(profile, profile)
    img = np.random.default_rng(3).normal(0.0, noise, (21 * pitch, 21 * pitch))
    hot = {(3, 4), (7, 12), (15, 2), (18, 18)}
    for u in range(1, 20):
        for v in range(1, 20):
            r, c = u * pitch, v * pitch
            if (u, v) in hot:
                img[r, c] += 400.0
            else:
                img[r - 5 : r + 6, c - 5 : c + 6] += dot
    lattice = Lattice(origin=np.zeros(2), basis=np.eye(2) * pitch)
    grid = measure_orders(img, lattice)
    assert grid.spike_orders == len(hot)
    at = {(int(u), int(v)): (i, j) for i, u in enumerate(grid.u) for j, v in enumerate(grid.v)}
    dots = [grid.power[at[u, v]] for u in range(1, 20) for v in range(1, 20) if (u, v) not in hot]
    sigma = float(np.median(grid.sigma[grid.valid]))
    assert 12 < power / sigma < 20  # faint: the light around the peak is within the noise
    assert np.min(dots) > power - 5 * sigma and np.mean(dots) == pytest.approx(power, rel=0.01)
    assert all(abs(grid.power[at[h]]) < 5 * sigma for h in hot)
