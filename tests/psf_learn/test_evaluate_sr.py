"""Evaluation (PSNR, SSIM) and super-resolution: the functions and the evaluate and sr commands."""

import hashlib
import json

import numpy as np
import pytest
import torch
from model_helpers import POINT, fixed_model
from skimage import io

from doe.derived import design_summary
from doe.design import load_design
from doe.infra.cli import main
from psf_learn.evaluate import evaluate, evaluate_image
from psf_learn.images import dead_leaves
from psf_learn.network import SRNet
from psf_learn.psf import delta_psf, gaussian_psf
from psf_learn.sensor import SensorModel
from psf_learn.sr import SRModel, load_model, super_resolve, white_counts

K = 11
SMALL = ["--steps", "3", "--features", "4", "--stages", "1", "--batch", "2", "--patch", "16"]
pytestmark = pytest.mark.usefixtures("on_the_cpu")  # only CPU runs repeat bit for bit


# --- evaluation -----------------------------------------------------------------------


def _flat_model(photons=0.0):
    """A network whose residual is zero: it returns the bilinear upsampling of the frame."""
    net = SRNet(4, features=4, stages=1)
    for p in net.tail.parameters():
        torch.nn.init.zeros_(p)
    return SRModel(net.eval(), delta_psf(K), SensorModel(POINT, photons), None)


def test_evaluation_of_a_constant_image_is_perfect():
    psnr, ssim, est = evaluate_image(_flat_model(), np.full((30, 41), 0.3))
    assert est.shape == (28, 40)
    assert psnr > 100 and ssim == pytest.approx(1)


def test_evaluation_is_deterministic_and_noisy():
    img = [dead_leaves(64, np.random.default_rng(0), n_disks=200)]
    a = evaluate(_flat_model(100.0), ["x"], img)
    b = evaluate(_flat_model(100.0), ["x"], img)
    assert a == b
    assert evaluate(_flat_model(0.0), ["x"], img)["psnr"] > a["psnr"]


def test_psnr_and_ssim_of_a_known_error_inside_the_border_crop():
    # catches 20 log10 of the MSE, a border cropped on one side only (or transposed, or
    # none by default), SSIM of the wrong pair or with a data range of 255
    image = np.full((24, 32), 0.5)
    estimate = np.full((24, 32), 0.6)
    estimate[:4], estimate[-4:], estimate[:, :4], estimate[:, -4:] = 0.0, 1.0, 0.0, 1.0
    psnr, ssim, _ = evaluate_image(fixed_model(estimate), image)
    assert psnr == pytest.approx(20.0, abs=1e-4)  # MSE 0.1^2 -> 10 log10(1 / 0.01)
    # constant images: SSIM is the luminance term alone, C1 = (0.01 * data range)^2
    c1 = 0.01**2
    assert ssim == pytest.approx((2 * 0.5 * 0.6 + c1) / (0.5**2 + 0.6**2 + c1), rel=1e-5)


def test_the_estimate_is_clipped_to_the_unit_range_before_scoring():
    # catches a dropped clamp: 1.05 counts as 1.0 against 0.95, an MSE of 0.05^2
    psnr, _, est = evaluate_image(fixed_model(np.full((24, 32), 1.05)), np.full((24, 32), 0.95))
    assert est.max() == 1.0
    assert psnr == pytest.approx(10 * np.log10(1 / 0.05**2), abs=1e-4)


def test_each_image_gets_its_own_noise():
    # catches one noise seed reused for every image: equal images would then score equally
    img = dead_leaves(32, np.random.default_rng(0), n_disks=100)
    per = evaluate(_flat_model(100.0), ["a", "b"], [img, img])["images"]
    assert per["a"]["psnr"] != per["b"]["psnr"]


# --- super-resolution -----------------------------------------------------------------


def test_super_resolve_removes_the_dark_counts_the_model_was_trained_with():
    # the flat model upsamples: a uniform frame of 50 counts, 5 of them dark, is 45 of light
    model = _flat_model(100.0)
    dark = SRModel(model.net, model.psf, SensorModel(POINT, 100.0, dark_counts=5.0), None)
    np.testing.assert_allclose(super_resolve(dark, np.full((4, 5), 50.0)), 45.0, atol=1e-5)


def test_super_resolve_shapes_and_photon_scaling():
    model = _flat_model(100.0)
    frames = np.random.default_rng(0).poisson(50, size=(2, 3, 6, 5)).astype(float)
    hr = super_resolve(model, frames)
    assert hr.shape == (2, 3, 24, 20)
    torch.manual_seed(0)
    model.net.tail[0].weight.data.normal_()  # a non-trivial network
    np.testing.assert_allclose(
        super_resolve(model, 3 * frames, photons=300),
        3 * super_resolve(model, frames),
        rtol=1e-5,
        atol=1e-6,
    )
    # A model trained without noise saw frames scaled to white = 1.
    assert white_counts(model) == 100.0 and white_counts(_flat_model(0.0)) == 1.0
    # A white level of 0 or NaN has no meaning: refused, not replaced or spread as NaN.
    for white in (0.0, -5.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="photons"):
            super_resolve(model, frames, photons=white)


def test_super_resolve_takes_a_model_folder_and_refuses_a_row(trained):
    out, _ = trained
    frames = np.random.default_rng(5).poisson(150, size=(2, 6, 5)).astype(float)
    np.testing.assert_array_equal(
        super_resolve(out, frames), super_resolve(load_model(out), frames)
    )
    with pytest.raises(ValueError, match=r"frames must be \(\.\.\., h, w\), got shape \(5,\)"):
        super_resolve(out, frames[0, 0])


# --- the evaluate and sr commands -----------------------------------------------------


def test_evaluate_writes_json(trained, tmp_path, capsys):
    out, images = trained
    res = tmp_path / "eval.json"
    assert main(["evaluate", str(out), "--images", str(images), "--out", str(res)]) == 0
    data = json.loads(res.read_text())
    assert set(data["images"]) == {"img0.png", "img1.png"}
    assert data["psnr"] == pytest.approx(np.mean([v["psnr"] for v in data["images"].values()]))
    assert 0 < data["ssim"] <= 1
    assert "PSNR" in capsys.readouterr().out
    # deterministic
    again = tmp_path / "again.json"
    main(["evaluate", str(out), "--images", str(images), "--out", str(again)])
    assert again.read_text() == res.read_text()


def test_evaluate_shows_progress_on_a_terminal(trained, capsys):
    # A long image folder once ran without a sign of life.
    from psf_learn import images as imgio
    from psf_learn.evaluate import evaluate
    from psf_learn.sr import load_model

    out, images = trained
    model = load_model(out)
    names, imgs = imgio.read_folder(images)
    quiet = evaluate(model, names, imgs)
    assert "evaluate" not in capsys.readouterr().err
    shown = evaluate(model, names, imgs, progress=True)
    err = capsys.readouterr().err
    assert "evaluate" in err and "2/2" in err
    assert shown == quiet


def test_evaluate_refuses_a_psf_made_for_another_grid(trained, tmp_path, capsys):
    # A factor-4 model evaluated with a PSF learned, or measured, on a factor-2 grid
    # gave a PSNR as if nothing were wrong.
    from doe.derived import derive

    out, images = trained
    (tmp_path / "factor2.toml").write_text("[sensor]\nsuperres_factor = 2\n")
    factor2 = load_design(tmp_path / "factor2.toml")
    reports = {
        "learn.json": {"design": design_summary(factor2)},
        "verify.json": {"lattice_pitch_um": derive(factor2).lattice_pitch * 1e6},
        "camera.json": {"design": design_summary(factor2)},
    }
    for name, report in reports.items():
        folder = tmp_path / name.split(".")[0]
        folder.mkdir()
        np.save(folder / "psf.npy", gaussian_psf(K))
        argv = ["evaluate", str(out), "--images", str(images), "--psf-file"]
        assert main([*argv, str(folder / "psf.npy")]) == 0  # no report: nothing to compare
        (folder / name).write_text(json.dumps(report))
        assert main([*argv, str(folder / "psf.npy")]) == 2
        err = capsys.readouterr().err
        assert f"{folder / name}:" in err and "the model" in err and "PSNR" not in err


def test_sr_on_npy_stack_and_16_bit_image(trained, tmp_path):
    out, _ = trained
    rng = np.random.default_rng(1)
    np.save(tmp_path / "stack.npy", rng.poisson(300, size=(3, 8, 6)).astype(np.uint16))
    io.imsave(
        tmp_path / "frame.png",
        rng.integers(0, 4000, size=(5, 7)).astype(np.uint16),
        check_contrast=False,
    )
    dest = tmp_path / "sr"
    assert (
        main(
            [
                "sr",
                str(out),
                str(tmp_path / "stack.npy"),
                str(tmp_path / "frame.png"),
                "--out",
                str(dest),
            ]
        )
        == 0
    )
    assert np.load(dest / "stack_sr.npy").shape == (3, 32, 24)
    hr = np.load(dest / "frame_sr.npy")
    assert hr.shape == (20, 28)
    np.testing.assert_allclose(
        hr, super_resolve(load_model(out), io.imread(tmp_path / "frame.png").astype(float))
    )


def test_sr_records_what_made_each_output_and_gathers_batches(trained, tmp_path):
    # A super-resolved frame must say which model, photon level and input made it.
    out, _ = trained
    rng = np.random.default_rng(2)
    dest = tmp_path / "sr"
    for name in ("a", "b"):  # two batches into one folder need no --force
        np.save(tmp_path / f"{name}.npy", rng.poisson(300, size=(6, 5)).astype(np.uint16))
        assert main(["sr", str(out), str(tmp_path / f"{name}.npy"), "--out", str(dest)]) == 0
    record = json.loads((dest / "b_sr.json").read_text())
    digest = hashlib.sha256((tmp_path / "b.npy").read_bytes()).hexdigest()
    assert record["input"] == str(tmp_path / "b.npy") and record["input_sha256"] == digest
    assert record["input_shape"] == [6, 5] and record["output_shape"] == [24, 20]
    assert record["model_sha256"] == hashlib.sha256((out / "model.pt").read_bytes()).hexdigest()
    assert record["photons"] == load_model(out).sensor.photons
    for name in ("b_sr.npy", "b_sr.png"):
        assert record["files"][name] == hashlib.sha256((dest / name).read_bytes()).hexdigest()
    assert sorted(p.name for p in dest.iterdir()) == [
        f"{n}_sr.{ext}" for n in "ab" for ext in ("json", "npy", "png")
    ]
    np.save(tmp_path / "c.npy", np.full((4, 4), 50, np.uint16))
    assert (
        main(["sr", str(out), str(tmp_path / "c.npy"), "--out", str(dest), "--photons", "80"]) == 0
    )
    assert json.loads((dest / "c_sr.json").read_text())["photons"] == 80


@pytest.mark.parametrize("scale, noted", [(1.0, False), (1.5, False), (8.0, True)])
def test_sr_notes_frames_far_brighter_than_the_white_it_was_trained_at(
    trained, tmp_path, capsys, scale, noted
):
    # A frame of camera codes (or a longer exposure) was super-resolved without a word.
    out, _ = trained
    white = 300.0
    frame = np.random.default_rng(3).poisson(scale * white, size=(6, 5)).astype(np.uint16)
    np.save(tmp_path / "f.npy", frame)
    argv = ["sr", str(out), str(tmp_path / "f.npy"), "--out", str(tmp_path / "o")]
    assert main([*argv, "--photons", str(white)]) == 0
    notes = json.loads((tmp_path / "o" / "f_sr.json").read_text())["notes"]
    assert len(notes) == int(noted)
    if noted:
        top = np.percentile(frame, 99)
        assert f"f.npy: 1 % of its counts exceed {top:.4g}, {top / white:.3g} times" in notes[0]
        assert "--photons" in notes[0] and notes[0] in capsys.readouterr().err


def test_evaluate_and_sr_refuse_bad_numbers(trained, tmp_path, capsys):
    out, images = trained
    raw = tmp_path / "raw.npy"
    np.save(raw, np.ones((6, 6)))
    for photons in ("nan", "0", "-1", "1e300"):
        assert (
            main(["sr", str(out), str(raw), "--photons", photons, "--out", str(tmp_path / "sr")])
            == 2
        )
        assert "--photons" in capsys.readouterr().err
    assert not (tmp_path / "sr").exists()
    res = tmp_path / "e.json"
    assert (
        main(["evaluate", str(out), "--images", str(images), "--seed", "-1", "--out", str(res)])
        == 2
    )
    assert "--seed" in capsys.readouterr().err and not res.exists()


def test_evaluate_and_sr_refuse_bad_inputs(trained, tmp_path, capsys):
    out, images = trained
    psf_file = tmp_path / "bad.npy"
    np.save(psf_file, -gaussian_psf(K))
    res = tmp_path / "e.json"
    assert (
        main(
            [
                "evaluate",
                str(out),
                "--images",
                str(images),
                "--psf-file",
                str(psf_file),
                "--out",
                str(res),
            ]
        )
        == 2
    )
    assert str(psf_file) in capsys.readouterr().err and not res.exists()
    assert main(["evaluate", str(tmp_path), "--images", str(images)]) == 2
    assert "model.pt" in capsys.readouterr().err
    assert main(["evaluate", str(tmp_path / "gone"), "--images", str(images)]) == 2
    assert f"{tmp_path / 'gone'}: not a model folder" in capsys.readouterr().err
    # --out names a file; a folder there is refused by name, --force or not
    for force in ([], ["--force"]):
        args = ["evaluate", str(out), "--images", str(images), "--out", str(tmp_path), *force]
        assert main(args) == 2
        assert f"{tmp_path}: is a folder" in capsys.readouterr().err
    # --out inside a file: refused before the evaluation, not by mkdir after it
    (tmp_path / "notes.txt").write_text("the lab's")
    args = ["evaluate", str(out), "--images", str(images), "--out"]
    assert main([*args, str(tmp_path / "notes.txt" / "e.json")]) == 2
    assert f"{tmp_path / 'notes.txt'}: is a file, so e.json" in capsys.readouterr().err
    # a PSF wider than an image cannot be mirrored at its borders: torch raised
    small = tmp_path / "small"
    small.mkdir()
    io.imsave(small / "s.png", np.arange(324, dtype=np.uint8).reshape(18, 18))
    wide = tmp_path / "wide.npy"
    np.save(wide, gaussian_psf(41))
    assert main(["evaluate", str(out), "--images", str(small), "--psf-file", str(wide)]) == 2
    err = capsys.readouterr().err  # the image and the PSF that sets the size are named
    assert f"s.png: image (18, 18) is smaller than 41 pixels (the 41x41 PSF of {wide}" in err
    bad = tmp_path / "raw.npy"
    np.save(bad, np.zeros((2, 3, 4, 5)))
    assert main(["sr", str(out), str(bad), "--out", str(tmp_path / "sr")]) == 2
    assert str(bad) in capsys.readouterr().err
    assert not (tmp_path / "sr").exists()


def test_sr_names_both_inputs_that_collide_and_evaluate_keeps_a_link(trained, tmp_path, capsys):
    out, images = trained
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        np.save(tmp_path / folder / "frame.npy", np.ones((6, 6)))
    a, b = tmp_path / "a" / "frame.npy", tmp_path / "b" / "frame.npy"
    assert main(["sr", str(out), str(a), str(b), "--out", str(tmp_path / "sr")]) == 2
    err = capsys.readouterr().err
    assert f"{b}: shares its name with {a}" in err  # only the first was named
    # a dangling link at --out was replaced without --force
    link = tmp_path / "e.json"
    link.symlink_to(tmp_path / "elsewhere.json")
    assert main(["evaluate", str(out), "--images", str(images), "--out", str(link)]) == 2
    assert "--force" in capsys.readouterr().err and link.is_symlink()
