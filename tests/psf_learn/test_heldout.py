"""What the plate buys: learn's no-plate model and both scored on held-back images."""

import json

import numpy as np
import pytest

from doe.infra.cli import main
from doe.records.learn import read_learn
from fab.run.learn_headlines import learn_rows
from psf_learn.evaluate import evaluate_folder
from psf_learn.images import default_images, held_out_images
from psf_learn.learn import learn

TINY = {"steps": 3, "features": 4, "stages": 1, "batch": 2, "patch": 16}
pytestmark = pytest.mark.usefixtures("on_the_cpu")  # only CPU runs repeat bit for bit
FACTOR3 = "[sensor]\nsuperres_factor = 3\n[psf]\nkernel_size = 9\n"
PITCH = "[sensor]\npixel_pitch_um = 100.0\n[fabrication]\nfeature_size_um = 10.0\n"


@pytest.fixture(scope="module")
def folders(tmp_path_factory, image_folder):
    root = tmp_path_factory.mktemp("heldout")
    return image_folder(root / "train", size=40), image_folder(root / "held", n=2, size=36)


@pytest.mark.parametrize("design", [None, FACTOR3, PITCH], ids=["preset", "factor3", "pitch100"])
def test_the_no_plate_model_is_the_delta_model_trained_the_same_way(folders, tmp_path, design):
    # The baseline's scores are those of `learn --psf delta` with the same steps, seed and
    # images, scored on the same held-back folder by `doefab evaluate`'s code.
    train, held = folders
    config = None
    if design:
        config = tmp_path / "design.toml"
        config.write_text(design)
    tiny = {**TINY, "patch": 15 if design == FACTOR3 else 16}
    both = learn(tmp_path / "m", images=train, eval_images=held, config=config, **tiny)
    delta = learn(tmp_path / "d", images=train, eval_images=held, psf="delta", config=config,
                  **tiny)  # fmt: skip
    record = read_learn(tmp_path / "m" / "learn.json").heldout
    assert record == both.heldout == json.loads(json.dumps(record))
    assert record["images"] == {"source": str(held), "names": ["img0.png", "img1.png"]}
    assert record["no_plate"] == delta.heldout["model"] == delta.heldout["no_plate"]
    scored = evaluate_folder(tmp_path / "m", held)  # the written model, scored anew
    assert record["model"]["psnr"] == scored.psnr and record["model"]["images"] == scored.images
    for key in ("psnr", "psnr_y"):
        gain = record["model"][key] - record["no_plate"][key]
        assert record["plate_gain_db"][key] == pytest.approx(gain, abs=1e-12)
    assert delta.heldout["plate_gain_db"] == {"psnr": 0.0, "psnr_y": 0.0}
    assert not list((tmp_path / "m").glob("checkpoint*"))


def test_no_baseline_scores_the_model_alone(folders, tmp_path, capsys):
    train, held = folders
    args = ["learn", "--images", str(train), "--eval-images", str(held), "--steps", "3"]
    args += ["--features", "4", "--stages", "1", "--batch", "2", "--patch", "16"]
    assert main([*args, "--out", str(tmp_path / "a")]) == 0
    assert "the plate buys" in capsys.readouterr().out
    assert main([*args, "--out", str(tmp_path / "b"), "--no-baseline"]) == 0
    assert "no no-plate model (--no-baseline)" in capsys.readouterr().out
    a, b = (read_learn(tmp_path / n / "learn.json") for n in "ab")
    assert b.heldout["model"] == a.heldout["model"]  # the model's training is the same
    assert b.heldout["no_plate"] is None and b.heldout["plate_gain_db"] is None
    assert b.plate_gain() is None and a.plate_gain()[2] == a.heldout["plate_gain_db"]
    # the front page: both models and the difference in both conventions, or the model alone
    for name, record in (("a", a), ("b", b)):
        (tmp_path / "run" / name / "learn").mkdir(parents=True)
        (tmp_path / "run" / name / "learn" / "learn.json").write_text(json.dumps(record.data))
    rows = learn_rows(tmp_path / "run" / "a")
    model, base, gain = a.plate_gain()
    assert rows[0][1] == f"{model['psnr']:.2f} / {base['psnr']:.2f} / {gain['psnr']:+.2f}"
    assert rows[1][1] == f"{model['psnr_y']:.2f} / {base['psnr_y']:.2f} / {gain['psnr_y']:+.2f}"
    assert "2 held-back images (img0.png, img1.png)" in rows[0][0] and "PSNR-Y" in rows[1][0]
    (row,) = learn_rows(tmp_path / "run" / "b")
    assert row[1].startswith(f"{model['psnr']:.2f} ({model['psnr_y']:.2f})")
    assert learn_rows(tmp_path / "nothing") == []


def test_a_held_back_folder_is_checked_before_training(folders, tmp_path, capsys):
    train, _ = folders
    args = ["learn", "--out", str(tmp_path / "m"), "--images", str(train), "--patch", "16"]
    assert main([*args, "--eval-images", str(tmp_path / "none")]) == 2
    assert "none: not a folder of images" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()


def test_the_embedded_held_out_photos_are_never_trained_on():
    # held_out_images is the module's own (the tests' conftest gives learn a small stand-in)
    names, images = held_out_images()
    assert names == ["skimage:camera", "skimage:astronaut", "skimage:chelsea"]
    assert all(img.ndim == 2 and min(img.shape) >= 300 for img in images)
    trained_on, _ = default_images(n_dead_leaves=0)
    assert len(trained_on) == 8 and not set(names) & set(trained_on)
    assert np.all([0 <= img.min() and img.max() <= 1 for img in images])
