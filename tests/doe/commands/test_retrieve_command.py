"""``doefab retrieve``: its flags, files, messages and exit codes."""

import hashlib
import json
import warnings

import numpy as np
import pytest

from doe import fraunhofer, retrieval, targets
from doe.derived import design_summary
from doe.design import load_design
from doe.infra.cli import main
from doe.infra.files import read_psf


def _psf_file(tmp_path, psf, name="psf.npy"):
    path = tmp_path / name
    np.save(path, psf)
    return path


def _run(args, capsys):
    code = main(["retrieve", *map(str, args)])
    return code, capsys.readouterr().err


def _retrieve_asymmetric(tmp_path, capsys, *flags):
    """Retrieve the 7 x 7 asymmetric target at N = 31 into tmp_path/out (exit 0).

    Returns (PSF file, out folder, retrieval.json as a dict, stderr).
    """
    psf = _psf_file(tmp_path, targets.asymmetric(7))
    out = tmp_path / "out"
    code, err = _run([psf, "--out", out, "--tile-pixels", 31, *flags], capsys)
    assert code == 0, err
    return psf, out, json.loads((out / "retrieval.json").read_text()), err


def test_cli_writes_the_contract_files(tmp_path, capsys, saved_figures, window_from_contract):
    target = targets.asymmetric(7)
    psf, out, info, err = _retrieve_asymmetric(tmp_path, capsys, "--seed", 2)
    levels = np.load(out / "levels.npy")
    assert levels.dtype == np.uint8 and levels.shape == (31, 31) and levels.max() < 8
    phase = np.load(out / "phase.npy")
    assert phase.dtype == np.float64 and phase.shape == (31, 31)
    np.testing.assert_array_equal(np.load(out / "target_psf.npy"), target)
    assert info["levels"] == 8 and info["tile_pixels"] == 31 and info["kernel_size"] == 7
    assert info["seed"] == 2 and info["design"]["name"] == "sun2020"
    assert set(info["versions"]) == {"numpy", "scipy", "nlopt", "doefab"}
    again = fraunhofer.quality(fraunhofer.level_phase(levels, 8), target)
    assert info["quantised"] == pytest.approx(again, rel=1e-12)
    goals = {"correlation_min": 0.9999, "rmse_max": 0.005, "met": True, "missed": []}
    assert info["goals"] == goals
    assert "misses the quality goals" not in err
    # at N = 31 the square pixels' envelope dims the window's corners by 6 %: that plate misses
    plate = fraunhofer.plate_quality(fraunhofer.level_phase(levels, 8), target)
    assert info["square_pixels"]["goals_met"] is False
    assert info["square_pixels"]["rmse"] == pytest.approx(plate["rmse"], rel=1e-12)
    assert "warning: the design meets the goals, but a plate of square pixels" in err
    assert (out / "retrieval.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the input named and hashed, not its path: `sha256sum psf.npy` checks it
    assert info["target_psf"] == "psf.npy"
    assert info["target_psf_sha256"] == hashlib.sha256(psf.read_bytes()).hexdigest()
    # the figure shows the quantised plate: its PSF (CONVENTIONS.md model) and figures
    window = window_from_contract(levels, 8, 7)
    fig = saved_figures[0]
    assert np.allclose(fig.axes[1].images[0].get_array(), window / window.max(), atol=1e-12)
    assert f"rmse {info['quantised']['rmse']:.5f}" in fig.get_suptitle()
    # same seed -> byte-identical level map and figure
    out2 = tmp_path / "out2"
    assert _run([psf, "--out", out2, "--tile-pixels", 31, "--seed", 2], capsys)[0] == 0
    for name in ("levels.npy", "phase.npy", "retrieval.png"):
        assert (out / name).read_bytes() == (out2 / name).read_bytes(), name


def test_cli_warns_when_the_design_misses_the_goals(tmp_path, capsys):
    # a binary plate's PSF is point-symmetric (|F(-u)| = |F(u)| for a real field),
    # so it cannot form an asymmetric target: the plate is written, with a warning
    _, _, info, err = _retrieve_asymmetric(tmp_path, capsys, "--levels", 2)
    q = info["quantised"]
    assert q["correlation"] < 0.9999 and q["rmse"] > 0.005
    assert info["goals"]["met"] is False
    assert info["goals"]["missed"] == [
        f"correlation {q['correlation']:.6f} < 0.9999",
        f"rmse {q['rmse']:.5f} > 0.005",
    ]
    assert "warning: the 2-level design misses the quality goals" in err
    assert f"rmse {q['rmse']:.5f} > 0.005" in err


def test_cli_warns_when_square_pixels_make_the_plate_miss_the_goals(tmp_path, capsys):
    # A flat top filling the window meets rmse 0.005 in the contract's model (0.00434),
    # but the square pixels' sinc^2 envelope dims its outer orders: 0.0054 as fabricated.
    psf = _psf_file(tmp_path, np.full((11, 11), 1 / 121))
    code, err = _run([psf, "--out", tmp_path / "out"], capsys)
    assert code == 0
    info = json.loads((tmp_path / "out" / "retrieval.json").read_text())
    lv = np.load(tmp_path / "out" / "levels.npy")
    target = np.load(tmp_path / "out" / "target_psf.npy")
    n = lv.shape[0]
    env = np.sinc((np.arange(11) - 5) / n) ** 2
    window = fraunhofer.window_power(fraunhofer.level_phase(lv, 8), 11) * np.outer(env, env)
    expected = fraunhofer.rmse(window, target)
    assert info["goals"]["met"] and info["quantised"]["rmse"] <= 0.005
    plate = info["square_pixels"]
    assert plate["rmse"] == pytest.approx(expected, rel=1e-12) and expected > 0.005
    assert plate["efficiency"] == pytest.approx(window.sum(), rel=1e-12)
    assert plate["goals_met"] is False and plate["missed"] == [f"rmse {expected:.5f} > 0.005"]
    assert "a plate of square pixels" in err and f"rmse {expected:.5f} > 0.005" in err


def test_cli_on_a_uniform_target_reports_the_correlation_as_undefined(
    tmp_path, capsys, read_strict_json
):
    # a flat top filling the window: Pearson's correlation is undefined, the rmse decides
    psf = _psf_file(tmp_path, np.full((5, 5), 1 / 25))
    out = tmp_path / "out"
    code = main(["retrieve", str(psf), "--out", str(out), "--tile-pixels", "21"])
    printed = capsys.readouterr().out
    assert code == 0 and "correlation undefined (uniform target)" in printed
    info = read_strict_json(out / "retrieval.json")
    assert info["quantised"]["correlation"] is None
    assert 0 < info["quantised"]["rmse"] < 0.05
    assert not any(m.startswith("correlation") for m in info["goals"]["missed"])


def test_cli_levels_and_tile_default_from_the_design(tmp_path, capsys):
    cfg = tmp_path / "d.toml"
    cfg.write_text("[fabrication]\nlevels = 4\n")
    psf = _psf_file(tmp_path, targets.compact_blob(5))
    out = tmp_path / "out"
    code, err = _run([psf, "--out", out, "--tile-pixels", 21, "--config", cfg], capsys)
    assert code == 0, err
    assert json.loads((out / "retrieval.json").read_text())["levels"] == 4
    assert np.load(out / "levels.npy").max() < 4
    # So does the seed, as doefab run passes it: run one by one, the stages gave another tile.
    cfg.write_text("[fabrication]\nlevels = 4\n[learning]\nseed = 3\n")
    seeded = tmp_path / "seeded"
    code, err = _run([psf, "--out", seeded, "--tile-pixels", 21, "--config", cfg], capsys)
    assert code == 0, err
    assert json.loads((seeded / "retrieval.json").read_text())["seed"] == 3
    expected = retrieval.retrieve_phase(read_psf(psf), 21, 4, seed=3).levels
    assert np.load(seeded / "levels.npy").tobytes() == expected.tobytes()


def test_cli_records_the_design_as_the_tile_realises_it(tmp_path, capsys):
    # With --tile-pixels 31 --levels 4 the record read N = 175 and 3 masks of 8 levels.
    _psf, _out, info, _err = _retrieve_asymmetric(tmp_path, capsys, "--levels", 4)
    derived = info["design"]["derived"]
    assert derived["tile_pixels"] == 31 and derived["masks"] == 2
    assert info["design"]["fabrication"]["levels"] == 4


def test_cli_refuses_a_psf_learned_for_another_sub_pixel_grid(tmp_path, capsys):
    # learn.json beside psf.npy says the PSF is sampled on a factor-3 grid (50 um)
    cfg = tmp_path / "factor3.toml"
    cfg.write_text("[sensor]\nsuperres_factor = 3\n")
    psf = _psf_file(tmp_path, targets.compact_blob(5))
    (tmp_path / "learn.json").write_text(json.dumps({"design": design_summary(load_design(cfg))}))
    out = tmp_path / "out"
    code, err = _run([psf, "--out", out, "--tile-pixels", 21], capsys)
    assert code == 2 and "learn.json" in err and "superres_factor 3 -> 4" in err
    assert not out.exists()
    code, err = _run([psf, "--out", out, "--tile-pixels", 21, "--config", cfg], capsys)
    assert code == 0, err


def _bad_inputs(tmp_path):
    good = targets.compact_blob(5)
    nan = good.copy()
    nan[0, 0] = np.nan
    neg = good.copy()
    neg[0, 0], neg[2, 2] = -0.01, neg[2, 2] + 0.01
    garbage = tmp_path / "garbage.npy"
    garbage.write_bytes(b"not an npy file")
    return {
        "nan": (_psf_file(tmp_path, nan, "nan.npy"), [], "NaN"),
        "negative": (_psf_file(tmp_path, neg, "neg.npy"), [], "negative"),
        "zero-sum": (_psf_file(tmp_path, np.zeros((5, 5)), "zero.npy"), [], "zero"),
        "even": (_psf_file(tmp_path, np.full((4, 4), 1 / 16), "even.npy"), [], "odd"),
        "non-square": (_psf_file(tmp_path, np.full((5, 3), 1 / 15), "rect.npy"), [], "square"),
        "int dtype": (_psf_file(tmp_path, np.eye(3, dtype=np.int64), "int.npy"), [], "dtype"),
        "K > N": (_psf_file(tmp_path, good, "big.npy"), ["--tile-pixels", 3], "exceeds"),
        "sum 2": (_psf_file(tmp_path, 2 * good, "sum2.npy"), [], "sum to 1"),
        "inf": (_psf_file(tmp_path, np.where(good > 0.1, np.inf, good), "inf.npy"), [], "inf"),
        "3-D": (_psf_file(tmp_path, np.full((3, 3, 3), 1 / 27), "cube.npy"), [], "square"),
        "seed": (_psf_file(tmp_path, good, "s.npy"), ["--seed", -1], "--seed"),
        "unreadable": (garbage, [], "is not a .npy file"),
        "missing": (tmp_path / "missing.npy", [], "no such file"),
        "levels 6": (_psf_file(tmp_path, good, "l6.npy"), ["--levels", 6], "--levels"),
        "levels 1": (_psf_file(tmp_path, good, "l1.npy"), ["--levels", 1], "--levels"),
        # 512 levels once wrapped around in uint8 levels.npy (correlation -0.07, exit 0)
        "levels 512": (_psf_file(tmp_path, good, "l512.npy"), ["--levels", 512], "--levels"),
        "tile 0": (_psf_file(tmp_path, good, "t0.npy"), ["--tile-pixels", 0], "--tile-pixels"),
        # N = 5000 once started a retrieval of hours and tens of GB
        "tile 5000": (
            _psf_file(tmp_path, good, "t5k.npy"),
            ["--tile-pixels", 5000],
            "--tile-pixels",
        ),
        "bad config": (
            _psf_file(tmp_path, good, "c.npy"),
            ["--config", tmp_path / "no.toml"],
            "no.toml",
        ),
    }


def test_cli_bad_inputs_exit_2_naming_the_problem_and_leave_nothing(tmp_path, capsys):
    inputs = tmp_path / "in"
    inputs.mkdir()
    for case, (path, extra, words) in _bad_inputs(inputs).items():
        out = tmp_path / "out"
        code, err = _run([path, "--out", out, "--tile-pixels", 15, *extra], capsys)
        assert code == 2, case
        lines = err.strip().splitlines()
        assert len(lines) == 1, (case, err)
        assert words in lines[0], (case, err)
        if not words.startswith("--") and case != "bad config":
            assert path.name in lines[0], (case, err)
        assert not out.exists(), case
        assert sorted(p.name for p in tmp_path.iterdir()) == ["in"], case


def test_cli_refuses_an_output_path_that_is_a_file(tmp_path, capsys):
    psf = _psf_file(tmp_path, targets.compact_blob(5))
    out = tmp_path / "out"
    out.write_text("a file")
    code, err = _run([psf, "--out", out, "--tile-pixels", 15], capsys)
    assert code == 2 and "out" in err and len(err.strip().splitlines()) == 1
    assert out.read_text() == "a file"


def test_cli_accepts_a_kernel_as_large_as_the_tile(tmp_path, capsys):
    # K = N: the window holds every order of the tile (K > N is refused)
    psf = _psf_file(tmp_path, targets.compact_blob(5))
    code, err = _run([psf, "--out", tmp_path / "out", "--tile-pixels", 5], capsys)
    assert code == 0, err
    assert np.load(tmp_path / "out" / "levels.npy").shape == (5, 5)


def test_cli_refuses_to_overwrite_without_force(tmp_path, capsys):
    psf = _psf_file(tmp_path, targets.compact_blob(5))
    out = tmp_path / "out"
    out.mkdir()
    (out / "levels.npy").write_bytes(b"keep me")
    code, err = _run([psf, "--out", out, "--tile-pixels", 15], capsys)
    assert code == 2 and "--force" in err and "levels.npy" in err
    assert (out / "levels.npy").read_bytes() == b"keep me"
    assert sorted(p.name for p in out.iterdir()) == ["levels.npy"]
    code, err = _run([psf, "--out", out, "--tile-pixels", 15, "--force"], capsys)
    assert code == 0, err
    assert np.load(out / "levels.npy").dtype == np.uint8


def test_one_order_target_is_an_unetched_plate_without_warnings(tmp_path, capsys):
    # K = 1 asks for the zero order alone: a flat plate, all the light in it, and no
    # 0 / 0 correlation of single orders on the way
    psf = _psf_file(tmp_path, np.ones((1, 1)))
    out = tmp_path / "out"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        code = main(["retrieve", str(psf), "--out", str(out), "--tile-pixels", "16"])
    assert code == 0 and "efficiency 1.0000" in capsys.readouterr().out
    levels = np.load(out / "levels.npy")
    assert levels.shape == (16, 16) and (levels == 7).all()


@pytest.mark.slow  # a subprocess that imports numpy and scipy, then retrieves N = 175
def test_sigterm_leaves_no_staging_folder(tmp_path):
    # SIGTERM (timeout, CI) killed the process and left .out.staging-* behind.
    import signal
    import subprocess
    import sys
    import time

    psf = _psf_file(tmp_path, targets.asymmetric(11))
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "doe", "retrieve", str(psf), "--out", str(out)]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 60
    while not list(tmp_path.glob(".out.staging-*")) and time.time() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, "retrieve ended before it could be stopped"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM and "terminated" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == [psf.name]


def test_the_command_gives_its_callers_sigterm_handler_back(capsys):
    # In-process callers (tests, doefab run's stages) keep their own SIGTERM handling.
    import signal

    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    assert main(["presets"]) == 0
    assert {s: signal.getsignal(s) for s in before} == before
