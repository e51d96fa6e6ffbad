"""The learn command: the files it writes, fine-tuning, and every input it refuses."""

import json
import os
import re

import numpy as np
import pytest
import torch
from skimage import io

from doe.derived import design_summary
from doe.design import load_design
from doe.infra.cli import main
from doe.infra.files import check_psf
from psf_learn.psf import baseline_psf, box_psf, gaussian_psf
from psf_learn.sr import load_model
from psf_learn.train import default_patch

K = 11
SMALL = ["--steps", "3", "--features", "4", "--stages", "1", "--batch", "2", "--patch", "16"]
pytestmark = pytest.mark.usefixtures("on_the_cpu")  # only CPU runs repeat bit for bit


# --- what it writes -------------------------------------------------------------------


def test_learn_writes_the_contract_files(trained):
    out, _ = trained
    assert sorted(p.name for p in out.iterdir()) == ["learn.json", "model.pt", "psf.npy"]
    psf = np.load(out / "psf.npy")
    assert psf.dtype == np.float64 and psf.shape == (K, K)
    check_psf(psf, "psf.npy")
    info = json.loads((out / "learn.json").read_text())
    assert info["steps"] == 3 and info["seed"] == 0 and info["config"]["psf"] == "learned"
    assert info["design"]["sensor"]["superres_factor"] == 4  # the grid psf.npy is sampled on
    assert {"final_loss", "final_psnr_db", "seconds", "versions"} <= set(info)
    assert info["device"] == "cpu"  # where it trained: only CPU runs repeat bit for bit
    torch.load(out / "model.pt", weights_only=True)


def test_default_patch_holds_whole_pixels_of_any_factor(image_folder, tmp_path):
    # 64 sub-pixels, the prototype's patch, is no whole number of 3 x 3 SPAD pixels
    design = tmp_path / "factor3.toml"
    design.write_text("[sensor]\nsuperres_factor = 3\n[psf]\nkernel_size = 9\n")
    images = image_folder(tmp_path / "images", size=80)
    out = tmp_path / "model"
    tiny = ["--steps", "1", "--features", "4", "--stages", "1", "--batch", "2"]
    args = ["learn", "--out", str(out), "--images", str(images), "--config", str(design)]
    assert main([*args, *tiny]) == 0
    assert json.loads((out / "learn.json").read_text())["config"]["patch"] == 63
    assert [default_patch(f) for f in (1, 2, 3, 4, 5, 8, 100)] == [64, 64, 63, 64, 60, 64, 100]


def test_learn_refuses_to_overwrite_without_force(trained, capsys):
    out, images = trained
    before = (out / "psf.npy").read_bytes()
    assert main(["learn", "--out", str(out), "--images", str(images), *SMALL]) == 2
    assert "--force" in capsys.readouterr().err
    assert (out / "psf.npy").read_bytes() == before
    # an --out taken by a file is named as such, --force or not
    for force in ([], ["--force"]):
        args = ["learn", "--out", str(out / "psf.npy"), "--images", str(images), *SMALL, *force]
        assert main(args) == 2
        assert "psf.npy: output path exists and is not a folder" in capsys.readouterr().err
    assert (out / "psf.npy").read_bytes() == before


def test_learn_with_fixed_psf_file_and_fine_tuning(trained, tmp_path, capsys):
    out, images = trained
    psf_file = tmp_path / "plate.npy"
    np.save(psf_file, gaussian_psf(K, 1.0))
    tuned = tmp_path / "tuned"
    argv = [
        "learn",
        "--out",
        str(tuned),
        "--images",
        str(images),
        "--init",
        str(out),
        "--psf",
        str(psf_file),
        "--freeze-psf",
        *SMALL[:2],
        "--batch",
        "2",
        "--patch",
        "16",
    ]
    assert main(argv) == 0
    np.testing.assert_array_equal(np.load(tuned / "psf.npy"), np.load(psf_file))  # as given
    assert json.loads((tuned / "learn.json").read_text())["config"]["features"] == 4
    # Fine-tuning keeps the network: a different --features/--arch was once ignored.
    for flag, value in (("--features", "8"), ("--arch", "dbpn")):
        again = tmp_path / f"again{flag}"
        assert main([*argv[:2], str(again), *argv[3:], flag, value]) == 2
        assert not again.exists()
    # a network that super-resolves by 4 cannot be fine-tuned for a factor-3 design
    factor3 = tmp_path / "factor3.toml"
    factor3.write_text("[sensor]\nsuperres_factor = 3\n")
    other = tmp_path / "factor3"
    assert main([*argv[:2], str(other), *argv[3:-1], "15", "--config", str(factor3)]) == 2
    assert str(out) in capsys.readouterr().err
    assert not other.exists()


def test_fine_tuning_starts_from_the_model_and_a_frozen_psf_stays(trained, tmp_path):
    # One step at a learning rate of 1e-12 moves no weight by more than ~1e-12: the
    # tuned network is the --init one, and --freeze-psf keeps its PSF exactly.
    out, images = trained
    tuned = tmp_path / "tuned"
    argv = ["learn", "--out", str(tuned), "--images", str(images), "--init", str(out)]
    argv += ["--freeze-psf", "--steps", "1", "--batch", "2", "--patch", "16", "--lr", "1e-12"]
    assert main(argv) == 0
    np.testing.assert_allclose(np.load(tuned / "psf.npy"), np.load(out / "psf.npy"), rtol=1e-12)
    before = load_model(out).net.state_dict()
    for name, weights in load_model(tuned).net.state_dict().items():
        np.testing.assert_allclose(weights, before[name], rtol=0, atol=1e-9, err_msg=name)


def test_a_cameras_effective_psf_tunes_a_model_with_its_psf_frozen(trained, tmp_path):
    # doefab camera's effective_psf.npy (camera.json beside it) is a PSF like any other
    from pathlib import Path

    out, images = trained
    plate = tmp_path / "plate"
    plate.mkdir()
    levels = np.load(Path(__file__).parents[1] / "data" / "default_levels.npy")
    np.save(plate / "levels.npy", levels)
    camera = tmp_path / "camera"
    assert main(["camera", str(plate), "--out", str(camera), "--f-number", "8"]) == 0
    psf = camera / "effective_psf.npy"
    tuned = tmp_path / "tuned"
    argv = ["learn", "--out", str(tuned), "--images", str(images), "--init", str(out)]
    argv += ["--psf", str(psf), "--freeze-psf", "--steps", "1", "--batch", "2", "--patch", "16"]
    assert main(argv) == 0
    np.testing.assert_allclose(np.load(tuned / "psf.npy"), np.load(psf), rtol=1e-12)
    assert main(["evaluate", str(tuned), "--images", str(images), "--psf-file", str(psf)]) == 0


def test_a_named_baseline_psf_is_trained_with_as_given(trained, tmp_path):
    _, images = trained
    out = tmp_path / "m"
    assert main(["learn", "--out", str(out), "--images", str(images), "--psf", "box", *SMALL]) == 0
    np.testing.assert_array_equal(np.load(out / "psf.npy"), box_psf(K))
    assert json.loads((out / "learn.json").read_text())["config"]["psf"] == "box"


def test_learn_for_minutes_trains_until_the_time_is_spent(trained, tmp_path):
    # Without --steps (the default), --minutes is the budget of training time.
    out = tmp_path / "out"
    budget = ["--minutes", "0.005", "--threads", "1"]  # 0.3 s
    assert main(["learn", "--out", str(out), "--images", str(trained[1]), *budget, *SMALL[2:]]) == 0
    info = json.loads((out / "learn.json").read_text())
    assert info["config"]["steps"] is None and info["config"]["minutes"] == 0.005
    assert info["steps"] >= 1 and info["seconds"] >= 0.3


def test_a_steps_run_takes_one_thread_whatever_the_load(trained, tmp_path, monkeypatch):
    # The default once came from the load average, and 1 or 2 threads give different
    # last bits: the same --steps command gave another model.pt on a busier machine.
    from psf_learn import learn_plan

    _, images = trained
    monkeypatch.setattr(learn_plan, "idle_cores", lambda: 2)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        assert main(["learn", "--out", str(tmp_path / "a"), "--images", str(images), *SMALL]) == 0
        assert torch.get_num_threads() == 1
        args = ["--out", str(tmp_path / "b"), "--images", str(images), "--threads", "2"]
        assert main(["learn", *args, *SMALL]) == 0
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_a_rank_other_than_0_trains_but_writes_nothing(
    fake_process_group, trained, tmp_path, capsys, monkeypatch
):
    # A torchrun job: every rank trains, rank 0 alone writes, and all leave together.
    # The process group is faked: rank 1 of a group of one.
    calls = fake_process_group(rank=1, size=1)
    out = tmp_path / "out"
    assert main(["learn", "--out", str(out), "--images", str(trained[1]), *SMALL]) == 0
    assert calls == ["barrier", "destroy"]
    assert list(out.iterdir()) == [] and "trained" not in capsys.readouterr().out


def test_rank_0_of_a_job_writes_the_model_and_leaves_with_the_others(
    fake_process_group, trained, tmp_path, monkeypatch
):
    # The other side of the test above: rank 0 writes the package, after the barrier.
    # In a group of one it trains what a lone process does (the trained fixture's run).
    calls = fake_process_group(rank=0, size=1)
    out = tmp_path / "out"
    assert main(["learn", "--out", str(out), "--images", str(trained[1]), *SMALL]) == 0
    assert calls == ["barrier", "destroy"]
    assert sorted(p.name for p in out.iterdir()) == ["learn.json", "model.pt", "psf.npy"]
    assert (out / "psf.npy").read_bytes() == (trained[0] / "psf.npy").read_bytes()


# --- a starting PSF made for another design -------------------------------------------


@pytest.mark.parametrize(
    "design_text, init, culprit",
    [
        ("[sensor]\npixel_pitch_um = 100\n", True, "learn.json"),  # another sub-pixel grid
        ("[psf]\nkernel_size = 15\n", True, "psf.npy"),  # once trained an 11 x 11 all the same
        ("[psf]\nkernel_size = 15\n", False, "fixed.npy"),
    ],
)
def test_a_starting_psf_must_fit_the_design(trained, tmp_path, capsys, design_text, init, culprit):
    out, images = trained
    design = tmp_path / "design.toml"
    design.write_text(design_text)
    np.save(tmp_path / "fixed.npy", gaussian_psf(K))
    start = ["--init", str(out)] if init else ["--psf", str(tmp_path / "fixed.npy")]
    args = ["--out", str(tmp_path / "m"), "--images", str(images), "--config", str(design)]
    assert main(["learn", *args, *start, *SMALL]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and culprit in err and "--config" in err
    assert not (tmp_path / "m").exists()


def test_fixed_psf_learned_for_another_grid_is_refused(tmp_path, capsys):
    # learn.json beside the PSF says it is sampled on a factor-3 grid, not the design's 4
    factor3 = tmp_path / "factor3.toml"
    factor3.write_text("[sensor]\nsuperres_factor = 3\n")
    np.save(tmp_path / "psf.npy", gaussian_psf(K))
    record = {"design": design_summary(load_design(factor3))}
    (tmp_path / "learn.json").write_text(json.dumps(record))
    out = tmp_path / "model"
    assert main(["learn", "--out", str(out), "--psf", str(tmp_path / "psf.npy"), *SMALL]) == 2
    err = capsys.readouterr().err
    assert "learn.json" in err and "superres_factor 3 -> 4" in err
    assert not out.exists()


def test_measured_psf_of_a_plate_for_another_grid_is_refused(tmp_path, capsys):
    # verify.json beside a measured PSF records the plate's dot lattice: 75 um for a
    # factor-2 design, twice the default design's 37.5 um sub-pixels.
    from doe.derived import derive
    from doe.records.psf_source import check_psf_grid

    factor2 = tmp_path / "factor2.toml"
    factor2.write_text("[sensor]\nsuperres_factor = 2\n")
    lattice_um = derive(load_design(factor2)).lattice_pitch * 1e6
    np.save(tmp_path / "measured_psf.npy", gaussian_psf(K))
    (tmp_path / "verify.json").write_text(json.dumps({"lattice_pitch_um": lattice_um}))
    psf, out = tmp_path / "measured_psf.npy", tmp_path / "model"
    assert main(["learn", "--out", str(out), "--psf", str(psf), *SMALL]) == 2
    err = capsys.readouterr().err
    assert "verify.json" in err and f"{lattice_um:g} um dot lattice" in err
    assert "design 'sun2020' has 37.5 um sub-pixels" in err
    assert not out.exists()
    check_psf_grid(psf, load_design(factor2))  # the design the plate was made for passes
    default_lattice = derive(load_design(None)).lattice_pitch * 1e6
    (tmp_path / "verify.json").write_text(json.dumps({"lattice_pitch_um": default_lattice}))
    check_psf_grid(psf, load_design(None))


@pytest.mark.parametrize(
    "name, text",
    [("verify.json", '{"lattice_pitch_um": "75"}'), ("verify.json", "{}"),
     ("learn.json", '{"design": 3}'), ("learn.json", '{"design": {"sensor": []}}'),
     ("learn.json", json.dumps({"design": design_summary(load_design(None))}))],
)  # fmt: skip
def test_psf_reports_without_a_grid_are_not_compared(tmp_path, name, text):
    from doe.records.psf_source import check_psf_grid, psf_grid_problem

    np.save(tmp_path / "psf.npy", gaussian_psf(K))
    (tmp_path / name).write_text(text)
    check_psf_grid(tmp_path / "psf.npy", load_design(None))
    assert psf_grid_problem(tmp_path / "psf.npy", {"sensor": {}}, "the model") is None


def test_an_init_model_for_another_factor_is_refused(trained, tmp_path, capsys):
    # Without learn.json (a model saved from Python) the grid check has nothing to
    # compare; the network's own factor must still match the design's.
    import shutil

    out, images = trained
    model = tmp_path / "model"
    model.mkdir()
    for name in ("model.pt", "psf.npy"):
        shutil.copy(out / name, model / name)
    factor2 = tmp_path / "factor2.toml"
    factor2.write_text("[sensor]\nsuperres_factor = 2\n")
    args = ["learn", "--out", str(tmp_path / "m"), "--images", str(images)]
    assert main([*args, "--init", str(model), "--config", str(factor2), *SMALL]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(model) in err
    assert "super-resolves by 4, the design by 2" in err
    assert not (tmp_path / "m").exists()


# --- refusals -------------------------------------------------------------------------


def test_training_images_must_hold_a_patch_and_the_psf_margin(tmp_path, capsys):
    # a 16 sub-pixel patch seen through an 11 x 11 PSF needs 26 x 26 pixels of scene
    images = tmp_path / "images"
    images.mkdir()
    io.imsave(images / "small.png", np.full((25, 40), 128, np.uint8), check_contrast=False)
    assert main(["learn", "--out", str(tmp_path / "out"), "--images", str(images), *SMALL]) == 2
    err = capsys.readouterr().err  # the image, and what sets the size, named
    assert "small.png: image (25, 40) is smaller than 26 pixels (--patch 16 plus the PSF's" in err
    assert not (tmp_path / "out").exists()
    io.imsave(images / "small.png", np.full((26, 40), 128, np.uint8), check_contrast=False)
    assert main(["learn", "--out", str(tmp_path / "out"), "--images", str(images), *SMALL]) == 0


def test_a_patch_larger_than_the_smallest_embedded_image_is_refused(tmp_path, capsys):
    # 248 + 10 > the 256 x 256 dead leaves: make_batch raised "high <= 0" (exit 3) when it
    # drew one, and an empty --out was left behind
    out = tmp_path / "out"
    args = ["learn", "--out", str(out), "--steps", "1", "--features", "4", "--stages", "1"]
    assert main([*args, "--batch", "2", "--patch", "248"]) == 2
    err = capsys.readouterr().err
    assert "--patch 248 plus the PSF's 10-pixel margin needs images of 258 pixels" in err
    assert "use --patch 244 or less, or --images" in err and not out.exists()


def test_a_psf_that_is_neither_a_file_nor_a_choice_is_refused_naming_the_choices(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["learn", "--out", str(out), "--psf", "gausian", *SMALL]) == 2
    err = capsys.readouterr().err
    assert "--psf: 'gausian' is no file and none of learned, delta, box, gaussian" in err
    assert not out.exists()


def test_gaussian_sigma_spec(tmp_path, capsys):
    np.testing.assert_allclose(baseline_psf("gaussian:1.5", K), gaussian_psf(K, 1.5, (0.5, 0.5)))
    np.testing.assert_allclose(baseline_psf("gaussian", K), gaussian_psf(K, 0.459, (0.5, 0.5)))
    out = tmp_path / "out"
    for spec in ("gaussian:-1", "gaussian:inf", "gaussian:nan", "gaussian:wide"):
        assert main(["learn", "--out", str(out), "--psf", spec, *SMALL]) == 2
        err = capsys.readouterr().err
        assert "--psf" in err and "gaussian:SIGMA needs a finite sigma" in err
        assert not out.exists()
    with pytest.raises(ValueError, match="unknown baseline PSF 'airy'"):
        baseline_psf("airy", K)
    # A sigma far beyond the window is its flat limit (1e300 ** 2 once overflowed).
    np.testing.assert_array_equal(gaussian_psf(K, 1e300), np.full((K, K), 1 / K**2))


def test_device_cuda_without_a_gpu_is_refused(tmp_path, capsys):
    out = tmp_path / "model"
    assert main(["learn", "--out", str(out), "--device", "cuda", *SMALL]) == 2
    err = capsys.readouterr().err
    assert "--device cuda: torch sees no CUDA device" in err and not out.exists()


def test_a_foreign_checkpoint_is_refused_in_one_line(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    torch.save(torch.zeros(3), out / "checkpoint.pt")  # once an AttributeError traceback
    assert main(["learn", "--out", str(out), *SMALL]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "checkpoint.pt" in err and "--restart" in err
    (out / "checkpoint.pt").write_text("not a torch file\n" * 5)  # torch's text: 6 lines
    assert main(["learn", "--out", str(out), *SMALL]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--restart" in err
    assert main(["learn", "--out", str(out), *SMALL, "--restart"]) == 0  # as it says
    assert not (out / "checkpoint.pt").exists()


def test_a_training_that_diverges_is_refused_naming_the_learning_rate(
    image_folder, tmp_path, capsys
):
    # --lr 1e8 made the weights overflow, the PSF NaN, and the next capture's Poisson
    # draw raised: a traceback, exit 3. Nothing is written but the last checkpoint.
    folder = image_folder(tmp_path / "imgs")
    out = tmp_path / "out"
    args = ["learn", "--out", str(out), "--images", str(folder), *SMALL]
    assert main([*args, "--lr", "1e8"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.search(
        r"--lr: the training diverged at step \d+ .*lower --lr", err[0]
    )
    assert not any((out / name).exists() for name in ("psf.npy", "model.pt", "learn.json"))
    # nor a folder left empty by a first run (a checkpoint, had one been written, stays)
    assert not out.exists() or any(out.iterdir())
    assert main([*args, "--restart"]) == 0  # a sane rate trains


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_an_unwritable_out_is_refused_before_training(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    out.chmod(0o555)
    try:
        assert main(["learn", "--out", str(out), *SMALL]) == 2
        err = capsys.readouterr().err
        assert f"{out}: cannot write here" in err and "trained" not in err
    finally:
        out.chmod(0o755)


def test_an_out_the_probe_cannot_write_in_is_refused_before_training(
    trained, tmp_path, capsys, monkeypatch
):
    # The read-only folder of test_an_unwritable_out_is_refused_before_training, as
    # root too: the write probe's refusal is one line naming --out.
    import tempfile

    def refused(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    out = tmp_path / "out"
    out.mkdir()
    monkeypatch.setattr(tempfile, "TemporaryFile", refused)
    assert main(["learn", "--out", str(out), "--images", str(trained[1]), *SMALL]) == 2
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [
        f"doefab learn: error: {out}: cannot write here (Permission denied)"
    ]
    assert not any(out.iterdir())


def test_a_batch_the_torchrun_processes_cannot_share_is_refused(tmp_path, capsys, monkeypatch):
    # Under torchrun each of WORLD_SIZE processes takes batch / WORLD_SIZE samples; an
    # odd --batch for two once ended in a traceback (exit 3) after making --out.
    monkeypatch.setenv("WORLD_SIZE", "2")
    out = tmp_path / "out"
    args = ["learn", "--out", str(out), *SMALL[:-4], "--batch", "3", "--patch", "16"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--batch" in err and "2 processes" in err
    assert not out.exists()


def _bad_input(image_folder, tmp_path, kind):
    folder = tmp_path / "imgs"
    if kind == "empty":
        folder.mkdir()
        (folder / "notes.txt").write_text("no images here")
        return ["--images", str(folder)], folder
    if kind == "corrupt":
        image_folder(folder)
        (folder / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
        return ["--images", str(folder)], folder / "broken.png"
    psf_file = tmp_path / "bad_psf.npy"
    bad = {
        "negative": gaussian_psf(K) - 0.01,
        "unnormalised": 2 * gaussian_psf(K),
        "even": np.full((4, 4), 1 / 16),
    }[kind]
    np.save(psf_file, bad)
    return ["--psf", str(psf_file)], psf_file


@pytest.mark.parametrize("kind", ["empty", "corrupt", "negative", "unnormalised", "even"])
def test_learn_refuses_bad_inputs_with_exit_2(image_folder, tmp_path, capsys, kind):
    extra, culprit = _bad_input(image_folder, tmp_path, kind)
    out = tmp_path / "out"
    assert main(["learn", "--out", str(out), *extra, *SMALL]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(culprit) in err
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize(
    "flag, value",
    [
        ("--lr", "nan"),
        ("--lr", "0"),
        ("--psf-lr", "inf"),
        ("--photons", "nan"),
        ("--dark-counts", "-1"),
        ("--threads", "-1"),
        ("--seed", "-1"),
        ("--minutes", "nan"),
        # too large: each once ended in a traceback (torch's seed overflow, numpy's
        # Poisson refusal, an allocation failure)
        ("--seed", str(2**63)),
        ("--photons", "1e300"),
        ("--dark-counts", "1e300"),
        ("--batch", "100000000"),
        ("--patch", "100000"),
        ("--patch", "18"),  # not whole SPAD pixels at factor 4
        ("--features", "100000"),
        ("--minutes", "1e308"),  # overflowed the deadline after the images had loaded
        ("--steps", str(10**9 + 1)),  # trained on for ever
    ],
)
def test_learn_refuses_bad_numbers_with_exit_2(tmp_path, capsys, flag, value):
    # NaN passes "value <= 0"; each of these once trained on NaN or raised a traceback.
    out = tmp_path / "out"
    budget = [] if flag == "--minutes" else SMALL
    assert main(["learn", "--out", str(out), *budget, flag, value]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and flag in err
    assert not out.exists()


def test_dark_counts_without_noise_are_refused(tmp_path, capsys):
    # Noise is off at --photons 0, dark counts included, yet model.pt recorded them and
    # sr subtracted them: a 0.5 grey frame came out at -4.4.
    out = tmp_path / "m"
    assert main(["learn", "--out", str(out), "--photons", "0", "--dark-counts", "5", *SMALL]) == 2
    err = capsys.readouterr().err
    assert "--dark-counts" in err and "--photons 0" in err and not out.exists()
