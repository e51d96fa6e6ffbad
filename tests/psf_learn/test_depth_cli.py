"""The depth and transient commands: files written, warnings, refusals, super-resolution."""

import json
import subprocess
import sys
import types

import numpy as np
import pytest
from depth_helpers import PS, SHIFT, T, scene

from doe.infra.cli import main
from psf_learn.cubes import scan_gaps, write_frame_png16
from psf_learn.depth import (
    SPEED_OF_LIGHT,
    GateModel,
    gate_response,
    scan_times,
)
from psf_learn.depth_sim import simulate_cube


@pytest.fixture(scope="module")
def response():
    return gate_response(GateModel())


def write_scene_cube(tmp_path, response, shape=(6, 10), amplitude=80.0, background=2.0, seed=12):
    a, mu, b = scene(shape, amplitude, background, response, seed)
    a[0, 0] = 0.0
    cube = simulate_cube(a, mu, b, T, SHIFT, response, np.random.default_rng(seed + 1))
    path = tmp_path / "cube.npy"
    np.save(path, cube.astype(np.uint16))
    return path, mu


def write_frame_folder(folder, cube, names):
    folder.mkdir()
    for k, name in enumerate(names):
        write_frame_png16(folder / name, cube[..., k] / 65535.0)
    return folder


# --- depth ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "names, note",
    [
        ([f"shift_{k}.png" for k in range(12) if k != 5], "from shift_4.png to shift_6.png (1"),
        ([f"gate_{0.02 * k:g}ns.png" for k in (0, 1, 2, 5, 6, 8)],
         "by 0.02 but jump from gate_0.04ns.png to gate_0.1ns.png (3"),
        ([f"t_{k}ps.png" for k in range(-60, 60, 20)], None),  # signed, complete
        ([f"gate_{0.02 * k:g}ns.png" for k in range(9)], None),  # decimals, complete
        ([f"img_{k}.png" for k in (1003, 1017, 1052, 1060)], None),  # no common step
        ([f"cam{k % 2}_{k}.png" for k in (0, 1, 3, 4)], None),  # two numbers vary
    ],
)  # fmt: skip
def test_a_frame_missing_from_a_numbered_scan_is_noted(tmp_path, names, note):
    # Every frame is one scan step: a lost frame moved every later return by a step, and
    # a folder with one missing was accepted without a word.
    cube = np.zeros((2, 3, len(names)), np.uint16)
    folder = write_frame_folder(tmp_path / "frames", cube, names)
    gaps = scan_gaps(folder)
    if note is None:
        assert gaps == []
    else:
        assert len(gaps) == 1 and note in gaps[0]
    np.save(tmp_path / "cube.npy", cube)
    assert scan_gaps(tmp_path / "cube.npy") == []


def test_cli_depth_warns_of_a_frame_missing_from_the_scan(tmp_path, response, capsys):
    path, _ = write_scene_cube(tmp_path, response, shape=(2, 3))
    cube = np.load(path)
    names = [f"shift_{k:03d}.png" for k in range(T + 1) if k != 40]  # frame 40 lost
    folder = write_frame_folder(tmp_path / "frames", cube, names)
    assert main(["depth", str(folder), "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "depth: warning: the frame names step by 1 but jump from shift_039.png" in err
    warnings = json.loads((tmp_path / "out" / "depth.json").read_text())["warnings"]
    assert any("shift_041.png (1 frame(s) missing" in w for w in warnings)
    assert main(["transient", str(folder), "--out", str(tmp_path / "tr")]) == 0
    assert "transient: warning: the frame names step by 1" in capsys.readouterr().err
    assert json.loads((tmp_path / "tr" / "transient.json").read_text())["warnings"]


def test_cli_depth_round_trip(tmp_path, response, capsys):
    path, mu = write_scene_cube(tmp_path, response)
    out = tmp_path / "out"
    assert main(["depth", str(path), "--shift-ps", "20", "--out", str(out)]) == 0
    timing = np.load(out / "timing_ps.npy")
    depth = np.load(out / "depth_m.npy")
    valid = np.load(out / "valid.npy")
    assert timing.shape == depth.shape == valid.shape == mu.shape
    assert not valid[0, 0] and np.isnan(depth[0, 0])
    assert valid.sum() == valid.size - 1
    np.testing.assert_allclose(timing[valid], mu[valid] / PS, atol=25)
    np.testing.assert_allclose(depth[valid], SPEED_OF_LIGHT * timing[valid] * PS / 2)
    for name in ("amplitude", "background", "fit_quality"):
        assert np.load(out / f"{name}.npy").shape == mu.shape
    for name in ("intensity.png", "depth.png", "pixel_fits.png", "depth.json"):
        assert (out / name).stat().st_size > 0
    first = {p.name: p.read_bytes() for p in out.iterdir()}
    # A second run refuses to overwrite; with --force it writes identical bytes.
    assert main(["depth", str(path), "--out", str(out)]) == 2
    assert "--force" in capsys.readouterr().err
    assert main(["depth", str(path), "--out", str(out), "--force"]) == 0
    assert {p.name: p.read_bytes() for p in out.iterdir()} == first


def test_cli_depth_of_a_dark_scene_reports_no_returns(tmp_path, capsys):
    # A cube without any return once printed "timing nan .. nan ps".
    path = tmp_path / "dark.npy"
    np.save(path, np.random.default_rng(3).poisson(2.0, (4, 5, T)).astype(np.uint16))
    assert main(["depth", str(path), "--out", str(tmp_path / "out")]) == 0
    line = capsys.readouterr().out
    assert "0/20 pixels with a return, no timing" in line and "nan" not in line
    assert not np.load(tmp_path / "out" / "valid.npy").any()


def test_cli_depth_with_irf(tmp_path, response, capsys):
    path, mu = write_scene_cube(tmp_path, response)
    np.save(tmp_path / "irf.npy", response(scan_times(T, SHIFT) - 1000 * PS))
    out = tmp_path / "out"
    irf = ["--irf", str(tmp_path / "irf.npy"), "--irf-t0-ps", "1000"]
    assert main(["depth", str(path), *irf, "--out", str(out)]) == 0
    timing, valid = np.load(out / "timing_ps.npy"), np.load(out / "valid.npy")
    np.testing.assert_allclose(timing[valid], mu[valid] / PS, atol=25)
    # The IRF replaces the gate model: giving both is a usage error.
    assert main(["depth", str(path), "--irf", str(tmp_path / "irf.npy"), "--rise-ps", "30",
                 "--out", str(tmp_path / "o2")]) == 2  # fmt: skip
    for t0 in ("nan", "inf"):
        args = [*irf[:2], "--irf-t0-ps", t0, "--out", str(tmp_path / "o2")]
        assert main(["depth", str(path), *args]) == 2
        assert "--irf-t0-ps: must be a finite number" in capsys.readouterr().err
    assert not (tmp_path / "o2").exists()


def test_cli_depth_warns_when_the_profiles_do_not_follow_the_model(tmp_path, response, capsys):
    path, _ = write_scene_cube(tmp_path, response, shape=(4, 40), amplitude=300.0)
    cube = np.load(path)
    out = tmp_path / "out"
    assert main(["depth", str(path), "--out", str(out)]) == 0
    assert "warning" not in capsys.readouterr().err
    assert json.loads((out / "depth.json").read_text())["warnings"] == []
    # The same counts with the time axis first: (T, H, W) read as (H, W, T).
    wrong = tmp_path / "wrong.npy"
    np.save(wrong, np.ascontiguousarray(np.moveaxis(cube, -1, 0)))
    assert main(["depth", str(wrong), "--out", str(tmp_path / "o2")]) == 0
    err = capsys.readouterr().err
    assert "do not follow the response model" in err and "(H, W, T)" in err
    assert json.loads((tmp_path / "o2" / "depth.json").read_text())["warnings"]


def test_cli_depth_warns_when_the_irf_is_cut_high_up(tmp_path, response, capsys):
    path, _ = write_scene_cube(tmp_path, response)
    x = response.times[response.values >= 0.8]  # cut at 0.8 of the peak, at the end
    t_ref = (T - 1) * SHIFT - x[-1]
    np.save(tmp_path / "irf.npy", response(scan_times(T, SHIFT) - t_ref))
    args = ["--irf", str(tmp_path / "irf.npy"), "--irf-t0-ps", str(t_ref / PS)]
    assert main(["depth", str(path), *args, "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "IRF is cut at 0.8" in err and "end of the scan" in err
    warnings = json.loads((tmp_path / "out" / "depth.json").read_text())["warnings"]
    assert len(warnings) == 1 and "IRF" in warnings[0]
    # Cut past its peak: refused, naming the file (it passed with the same warning).
    t_ref = (T - 1) * SHIFT - response.times[np.argmax(response.values)] + 3 * SHIFT
    np.save(tmp_path / "past.npy", response(scan_times(T, SHIFT) - t_ref))
    args = ["--irf", str(tmp_path / "past.npy"), "--irf-t0-ps", str(t_ref / PS)]
    assert main(["depth", str(path), *args, "--out", str(tmp_path / "o2")]) == 2
    assert "past.npy: the IRF peaks at its last sample" in capsys.readouterr().err
    assert not (tmp_path / "o2").exists()


def bad_cubes():
    good = np.ones((4, 5, 10))
    nan = good.copy()
    nan[1, 2, 3] = np.nan
    neg = good.copy()
    neg[0, 0, 0] = -1
    return {"rank2": good[0], "rank4": good[None], "nan": nan, "negative": neg,
            "short": good[..., :3], "complex": good.astype(complex)}  # fmt: skip


@pytest.mark.parametrize("kind", sorted(bad_cubes()))
def test_bad_cubes_are_refused(tmp_path, kind):
    path = tmp_path / f"{kind}.npy"
    np.save(path, bad_cubes()[kind])
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "doe", "depth", str(path), "--out", str(out)],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and str(path) in lines[0]
    assert not out.exists()


def test_bad_flags_are_refused(tmp_path, response, capsys):
    path, _ = write_scene_cube(tmp_path, response, shape=(2, 2))
    # The last four once ended in tracebacks or were silently ignored: a 1 ms fall
    # time needs a 25 us response, a 1 ns step samples the ~312 ps response less
    # than once, 0.1 ps steps scan 12 ps of it.
    for flags in (["--shift-ps", "0"], ["--gate-width-ps", "-5"], ["--tau-ps", "10"],
                  ["--pulse", "emg"], ["--irf", str(tmp_path / "missing.npy")],
                  ["--fall-ps", "1e9"], ["--shift-ps", "1000"], ["--shift-ps", "0.1"],
                  ["--irf-t0-ps", "5"]):  # fmt: skip
        assert main(["depth", str(path), "--out", str(tmp_path / "o"), *flags]) == 2
        assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()
    for fps in ("0", "60", "1000"):  # a GIF frame of under 2 centiseconds plays as 10
        assert main(["transient", str(path), "--out", str(tmp_path / "t"), "--fps", fps]) == 2
        assert "--fps" in capsys.readouterr().err
    assert not (tmp_path / "t").exists()


# --- figures --------------------------------------------------------------------------


def test_example_fits_show_each_pixel_once_and_a_non_return_only_if_there_is_one():
    # pixel_fits.png: brightest, median and dimmest return, then the first non-return;
    # with one or two returns some of these are the same pixel, shown once
    from psf_learn.depth_plots import example_pixels

    def picks(valid, amplitude):
        fit = types.SimpleNamespace(valid=np.array(valid), amplitude=np.array(amplitude, float))
        return [(int(r), int(c), why) for r, c, why in example_pixels(fit)]

    every = picks([[True, True], [True, True]], [[3, 1], [4, 2]])  # every pixel returns
    assert every == [(1, 0, "brightest"), (0, 0, "median"), (0, 1, "dimmest")]
    one = picks([[False, True], [False, False]], [[0, 7], [0, 0]])
    assert one == [(0, 1, "brightest"), (0, 0, "no return")]
    two = picks([[True, True]], [[5, 2]])  # the median of two is the brightest
    assert two == [(0, 0, "brightest"), (0, 1, "dimmest")]


def test_example_fits_of_an_odd_count_leave_the_last_cell_blank(tmp_path, saved_figures):
    from psf_learn.depth_plots import save_pixel_fits

    profiles = np.ones((3, T))
    save_pixel_fits(tmp_path / "f.png", scan_times(T, SHIFT), profiles, [None] * 3, list("abc"))
    assert [ax.axison for ax in saved_figures[-1].axes] == [True, True, True, False]


def test_depth_maps_show_row_0_at_the_top_and_invalid_pixels_grey(
    tmp_path, saved_figures, colour_at
):
    from psf_learn.depth_plots import save_map

    image = np.zeros((3, 5))
    image[0, 4] = 1.0  # top right, lit
    valid = np.ones((3, 5), bool)
    valid[2, 0] = False  # bottom left, no fit
    save_map(tmp_path / "map.png", image, "depth", "m", valid=valid)
    (ax,) = [a for a in saved_figures[-1].axes if a.images]

    def at(row, col):  # the centre of a cell, from the top left as displayed
        return colour_at(ax, (col + 0.5) / 5, 1 - (row + 0.5) / 3, space="axes")

    assert at(0, 4).min() > 200 and at(0, 0).max() < 60  # grey scale: white is 1, black 0
    assert np.all(np.abs(at(2, 0) - 0.6 * 255) < 3)  # "0.6" grey
    assert at(2, 4).max() < 60 and at(1, 2).max() < 60


# --- transient ------------------------------------------------------------------------


@pytest.mark.parametrize(
    "fps, centiseconds", [(10, 10), (30, 3), (50, 2), (0.5, 200), (41, 3), (29, 4)]
)
def test_preview_gif_plays_at_the_nearest_rate(tmp_path, response, fps, centiseconds):
    # 41 fps: 3 cs plays 33.3, nearer than 2 cs (50); 29 fps: 4 cs (25) beats 3 cs (33.3).
    from PIL import Image

    path, _ = write_scene_cube(tmp_path, response, shape=(2, 2))
    out = tmp_path / "t"
    assert main(["transient", str(path), "--out", str(out), "--fps", str(fps)]) == 0
    with Image.open(out / "preview.gif") as gif:
        gif.seek(1)
        assert gif.info["duration"] == 10 * centiseconds
    played = json.loads((out / "transient.json").read_text())["gif_fps"]
    assert played == pytest.approx(100 / centiseconds)


def test_cli_transient(tmp_path, response):
    path, _ = write_scene_cube(tmp_path, response, shape=(4, 6))
    out = tmp_path / "out"
    assert main(["transient", str(path), "--out", str(out)]) == 0
    frames = np.load(out / "frames.npy")
    cube = np.load(path)
    np.testing.assert_array_equal(frames, np.moveaxis(cube, -1, 0))
    assert len(list((out / "frames").glob("frame_*.png"))) == T
    assert (out / "preview.gif").read_bytes()[:6] in (b"GIF89a", b"GIF87a")
    times = json.loads((out / "transient.json").read_text())["times_ps"]
    assert times == [k * 20.0 for k in range(T)] and times[5] == 100.0  # not 99.99999999999999


def test_cli_transient_shows_one_frame_and_a_tall_sensor(tmp_path):
    # Frames need no fit: one is enough. A 300 x 1 sensor enlarged to 256 px wide
    # would be 76800 px tall, more than a GIF can hold.
    from PIL import Image

    np.save(tmp_path / "one.npy", np.full((3, 2, 1), 7.0))
    assert main(["transient", str(tmp_path / "one.npy"), "--out", str(tmp_path / "a")]) == 0
    assert np.load(tmp_path / "a" / "frames.npy").shape == (1, 3, 2)
    np.save(tmp_path / "tall.npy", np.arange(600.0).reshape(300, 1, 2))
    assert main(["transient", str(tmp_path / "tall.npy"), "--out", str(tmp_path / "b")]) == 0
    with Image.open(tmp_path / "b" / "preview.gif") as gif:
        assert gif.size == (218, 300 * 218)  # the largest whole factor within 65535


def test_transient_refuses_frames_too_wide_for_a_gif(tmp_path, capsys):
    np.save(tmp_path / "wide.npy", np.ones((1, 65536, 1)))
    out = tmp_path / "t"
    assert main(["transient", str(tmp_path / "wide.npy"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "wide.npy: frames of 1 x 65536 pixels" in err
    assert "at most 65535 pixels a side" in err and not out.exists()


# --- super-resolved cubes -------------------------------------------------------------


def fake_sr_module():
    """A stand-in for psf_learn.sr: 4x nearest-neighbour upsampling of (..., h, w)."""

    def super_resolve(model, frames, photons=None):
        frames = np.asarray(frames, dtype=np.float64)
        return np.repeat(np.repeat(frames, 4, axis=-2), 4, axis=-1)

    return types.SimpleNamespace(super_resolve=super_resolve)


@pytest.fixture
def sr_model(tmp_path, monkeypatch):
    """A model folder for --sr, with psf_learn.sr replaced by :func:`fake_sr_module`."""
    monkeypatch.setitem(sys.modules, "psf_learn.sr", fake_sr_module())
    model = tmp_path / "model"
    model.mkdir()
    return model


def test_cli_depth_and_transient_super_resolve(tmp_path, response, sr_model):
    path, _ = write_scene_cube(tmp_path, response, shape=(3, 4))
    out = tmp_path / "out"
    assert main(["depth", str(path), "--out", str(out), "--sr", str(sr_model)]) == 0
    native = np.load(out / "timing_ps.npy")
    sr = np.load(out / "sr" / "timing_ps.npy")
    assert sr.shape == (12, 16)
    np.testing.assert_allclose(sr, np.repeat(np.repeat(native, 4, 0), 4, 1), atol=0.05)
    short = tmp_path / "short.npy"
    np.save(short, np.load(path)[..., :5])
    out2 = tmp_path / "out2"
    assert main(["transient", str(short), "--out", str(out2), "--sr", str(sr_model)]) == 0
    frames = np.load(out2 / "frames.npy")
    assert frames.shape == (5, 12, 16)
    np.testing.assert_array_equal(frames[:, ::4, ::4], np.moveaxis(np.load(short), -1, 0))


def test_a_super_resolved_cube_has_one_white_its_maximum_and_no_negative_counts(
    tmp_path, monkeypatch
):
    # One white level keeps the frames on a common scale; a network's undershoot below 0
    # is not a count. The stand-in records its white and undershoots by half of it.
    from psf_learn.cubes import super_resolve_cube

    whites = []

    def super_resolve(model, frames, photons=None):
        whites.append(photons)
        return np.repeat(np.repeat(frames, 4, axis=-2), 4, axis=-1) - 0.5 * photons

    sr = types.SimpleNamespace(super_resolve=super_resolve)
    monkeypatch.setitem(sys.modules, "psf_learn.sr", sr)
    cube = np.random.default_rng(3).integers(0, 50, size=(3, 4, 6)).astype(np.float64)
    cube[1, 2, 3] = 80.0
    hr = super_resolve_cube(tmp_path, cube)
    assert whites == [80.0]
    upsampled = np.repeat(np.repeat(cube, 4, axis=0), 4, axis=1)
    np.testing.assert_array_equal(hr, np.clip(upsampled - 40.0, 0.0, None))


def test_cli_force_leaves_no_frames_or_sr_maps_of_an_older_cube(tmp_path, response, sr_model):
    path, _ = write_scene_cube(tmp_path, response, shape=(3, 4))
    short = tmp_path / "short.npy"
    np.save(short, np.load(path)[..., :5])
    out = tmp_path / "t"
    assert main(["transient", str(path), "--out", str(out)]) == 0
    assert main(["transient", str(short), "--out", str(out), "--force"]) == 0
    assert len(list((out / "frames").glob("frame_*.png"))) == 5
    out = tmp_path / "d"
    assert main(["depth", str(path), "--out", str(out), "--sr", str(sr_model)]) == 0
    assert main(["depth", str(path), "--out", str(out), "--force"]) == 0
    assert not (out / "sr").exists()
    # a lab's own sr/ files, in a folder no run with --sr wrote, are not the run's to remove
    (out / "sr").mkdir()
    (out / "sr" / "depth.png").write_text("the lab's")
    assert main(["depth", str(path), "--out", str(out), "--force"]) == 0
    assert (out / "sr" / "depth.png").read_text() == "the lab's"


def test_sr_needs_a_model_folder(tmp_path, response, sr_model, capsys):
    path, _ = write_scene_cube(tmp_path, response, shape=(2, 2))
    gone, hint = tmp_path / "gone", "(write one with 'doefab learn')"
    for command in ("depth", "transient"):
        assert main([command, str(path), "--out", str(tmp_path / "o"), "--sr", str(gone)]) == 2
        err = capsys.readouterr().err.strip()
        assert err == f"doefab {command}: error: {gone}: no such model folder {hint}"
    assert not (tmp_path / "o").exists()
