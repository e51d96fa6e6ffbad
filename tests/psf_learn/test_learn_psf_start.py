"""``doefab learn --psf-start`` and ``--psf-until``: where a learned PSF starts, how long."""

import json

import numpy as np
import pytest

from doe.design import load_design
from doe.infra.cli import main
from psf_learn.psf import baseline_psf, gaussian_psf, starting_psf
from psf_learn.sensor import sensor_from_design

K = 11
SMALL = ["--steps", "3", "--features", "4", "--stages", "1", "--batch", "2", "--patch", "16"]
pytestmark = pytest.mark.usefixtures("on_the_cpu")  # only CPU runs repeat bit for bit


def test_a_learned_psf_starts_where_psf_start_says_and_learn_json_records_it(trained, tmp_path):
    _, images = trained
    out = tmp_path / "m"
    start = ["--psf-start", "gaussian:1.5", "--psf-until", "0.5"]
    assert main(["learn", "--out", str(out), "--images", str(images), *start, *SMALL]) == 0
    config = json.loads((out / "learn.json").read_text())["config"]
    assert config["psf_start"] == "gaussian:1.5" and config["psf_until"] == 0.5
    psf = np.load(out / "psf.npy")
    wide, narrow = baseline_psf("gaussian:1.5", K), gaussian_psf(K)
    # three steps move the PSF a little from where it started, nowhere near the default
    assert np.abs(psf - wide).max() < 0.1 * np.abs(psf - narrow).max()
    assert not np.allclose(psf, wide)


@pytest.mark.parametrize("preset, patch", [("swissspad", "12"), ("pf32", "16")])
def test_psf_start_on_other_sensors_takes_their_window_and_centre(
    image_folder, tmp_path, preset, patch
):
    images = image_folder(tmp_path / "images")
    design = load_design(preset)
    k = design.kernel_size
    out = tmp_path / "m"
    small = ["--steps", "2", "--features", "4", "--stages", "1", "--batch", "2"]
    flags = ["--config", preset, "--patch", patch, "--psf-start", "gaussian:1.5", "--lr", "1e-9"]
    args = ["learn", "--out", str(out), "--images", str(images), "--no-baseline"]
    assert main([*args, *small, *flags, "--psf-lr", "1e-9"]) == 0
    psf = np.load(out / "psf.npy")
    assert psf.shape == (k, k)
    weights = np.asarray(sensor_from_design(design).weights)
    # two steps at a vanishing learning rate leave the start: the design's own centring
    np.testing.assert_allclose(psf, baseline_psf("gaussian:1.5", k, weights), atol=1e-6)


@pytest.mark.parametrize(
    "extra, says",
    [
        (["--psf", "box", "--psf-start", "random"], "not a fixed PSF (--psf box)"),
        (["--psf-start", "spiral"], "no file and none of"),
        (["--psf-start", "dots:0"], "dots:N needs a whole N"),
        (["--psf", "box", "--psf-until", "0.5"], "this one is fixed"),
        (["--freeze-psf", "--psf-until", "0.5"], "this one is fixed"),
        (["--psf-until", "0"], "finite number > 0"),
        (["--psf-until", "1.5"], "at most 1 (the whole run)"),
    ],
)
def test_a_psf_start_or_until_that_cannot_be_is_refused(tmp_path, capsys, extra, says):
    out = tmp_path / "m"
    assert main(["learn", "--out", str(out), *SMALL, *extra]) == 2
    err = capsys.readouterr().err.strip()
    flag = "--psf-until" if "--psf-until" in extra else "--psf-start"
    assert len(err.splitlines()) == 1 and flag in err and says in err
    assert not out.exists()


def test_a_psf_start_with_an_init_model_is_refused(trained, tmp_path, capsys):
    model, images = trained
    out = tmp_path / "m"
    flags = ["--init", str(model), "--psf-start", "box", "--images", str(images)]
    assert main(["learn", "--out", str(out), *SMALL, *flags]) == 2
    assert "an --init model's PSF" in capsys.readouterr().err
    assert not out.exists()


def test_a_psf_start_file_is_the_start_and_a_frozen_one_stays(trained, tmp_path):
    _, images = trained
    start = starting_psf("dots:4", K, seed=3)
    np.save(tmp_path / "start.npy", start)
    out = tmp_path / "m"
    flags = ["--psf-start", str(tmp_path / "start.npy"), "--freeze-psf"]
    assert main(["learn", "--out", str(out), "--images", str(images), *flags, *SMALL]) == 0
    np.testing.assert_allclose(np.load(out / "psf.npy"), start, atol=1e-7)


def test_a_psf_start_file_of_another_window_is_refused_naming_it(tmp_path, capsys):
    path = tmp_path / "seven.npy"
    np.save(path, gaussian_psf(7))
    out = tmp_path / "m"
    assert main(["learn", "--out", str(out), *SMALL, "--psf-start", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(path) in err and "is 7 x 7" in err
    assert not out.exists()
