"""The stage libraries called from Python: learn(), evaluate_folder(), super_resolve_files()."""

import json
import os

import numpy as np
import pytest
import torch

from doe.infra.cli import main
from doe.infra.errors import InputError
from doe.records.learn import read_learn
from psf_learn.evaluate import Evaluation, evaluate_folder, results_path
from psf_learn.learn import LearnOptions, LearnResult, learn
from psf_learn.sr import SRFrame, load_model, super_resolve_files

SMALL = ["--steps", "3", "--features", "4", "--stages", "1", "--batch", "2", "--patch", "16"]
# SMALL as learn()'s keyword arguments
TINY = {"steps": 3, "features": 4, "stages": 1, "batch": 2, "patch": 16}
pytestmark = pytest.mark.usefixtures("on_the_cpu")  # only CPU runs repeat bit for bit


# --- learn --------------------------------------------------------------------------------


def test_learn_returns_what_it_wrote(trained, tmp_path):
    # The command's fixture run and the library's, with the same settings, write the same
    # files (a steps run on the CPU repeats bit for bit); the result is what was written.
    out, images = trained
    result = learn(tmp_path / "m", images=images, **TINY)
    assert isinstance(result, LearnResult) and result.out == tmp_path / "m"
    for name in ("psf.npy", "model.pt"):
        assert (result.out / name).read_bytes() == (out / name).read_bytes()
    assert result.record == read_learn(result.out / "learn.json")
    assert result.record == load_model(result.out).learn
    np.testing.assert_array_equal(result.psf, np.load(result.out / "psf.npy"))
    assert result.psf_spec == "learned" and result.device == "cpu" and result.notes == ()
    assert result.steps == result.record.steps == 3
    assert result.final_psnr_db == result.record.final_psnr_db
    assert result.final_loss == result.record.final_loss
    assert result.seconds == pytest.approx(result.record.seconds, abs=1e-3)
    assert not (result.out / "checkpoint.pt").exists()
    command = read_learn(out / "learn.json").to_dict()
    library = result.record.to_dict()
    for record in (command, library):
        record.pop("seconds")
    assert library == command


def test_learn_takes_the_flags_as_keyword_arguments(tmp_path):
    flags = {"images", "psf", "minutes", "steps", "seed", "init", "freeze_psf", "features"}
    flags |= {"stages", "arch", "batch", "patch", "lr", "psf_lr", "photons", "dark_counts"}
    flags |= {"threads", "device", "restart", "force", "eval_images", "no_baseline"}
    flags |= {"psf_start", "psf_until"}
    assert set(LearnOptions.__dataclass_fields__) == flags  # each `doefab learn` flag
    with pytest.raises(TypeError, match="stpes"):
        learn(tmp_path / "m", stpes=3)
    assert not (tmp_path / "m").exists()


@pytest.mark.parametrize(
    "options, message",
    [
        ({"steps": 0}, "--steps: must be a finite number > 0"),
        ({"minutes": 1.0, "steps": 3}, "--minutes: not with --steps"),  # argparse's exclusion
        ({"psf": "gausian", "steps": 1}, "--psf: 'gausian' is no file"),
        ({"photons": 0.0, "dark_counts": 5.0, "steps": 1}, "--dark-counts: needs photon noise"),
    ],
)
def test_learn_refuses_bad_settings_with_an_input_error(tmp_path, options, message):
    with pytest.raises(InputError, match=message):
        learn(tmp_path / "m", **options)
    assert not (tmp_path / "m").exists()


def test_learn_on_a_rank_other_than_0_returns_no_record(trained, tmp_path, fake_process_group):
    calls = fake_process_group(rank=1, size=1)
    result = learn(tmp_path / "m", images=trained[1], **TINY)
    assert calls == ["barrier", "destroy"]
    assert result.record is None and result.steps == 3 and result.psf.shape == (11, 11)
    assert list((tmp_path / "m").iterdir()) == []


def test_idle_cores_take_omp_num_threads_or_the_cores_not_busy(monkeypatch):
    from psf_learn.learn_plan import idle_cores

    monkeypatch.setattr(os, "cpu_count", lambda: 8)
    monkeypatch.setattr(os, "getloadavg", lambda: (2.5, 0.0, 0.0))
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert idle_cores() == 3
    monkeypatch.setenv("OMP_NUM_THREADS", "0")
    assert idle_cores() == 1
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert idle_cores() == 5  # 8 cores, 2.5 busy
    monkeypatch.setattr(os, "getloadavg", lambda: (20.0, 0.0, 0.0))
    assert idle_cores() == 1

    def no_load_average():
        raise OSError("no load average here")

    monkeypatch.setattr(os, "getloadavg", no_load_average)
    assert idle_cores() == 8


def test_learn_records_an_unknown_version_when_doefab_is_not_installed(monkeypatch):
    import importlib.metadata

    from psf_learn.store import doefab_version

    def not_installed(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "version", not_installed)
    assert doefab_version() == "unknown"


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_learn_on_a_gpu_gives_its_note_before_training(trained, tmp_path, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    notes = []
    result = learn(tmp_path / "m", images=trained[1], device="cuda", on_note=notes.append, **TINY)
    assert len(notes) == 1 and notes == list(result.notes)
    assert notes[0].startswith("note: training on cuda:0 (") and "--device cpu" in notes[0]
    assert result.device.startswith("cuda:0 (") and result.record.device == result.device


# --- evaluate -----------------------------------------------------------------------------


def test_evaluate_folder_returns_and_writes_what_the_command_prints(trained, tmp_path, capsys):
    out, images = trained
    result = evaluate_folder(out, images, out=tmp_path / "e.json")
    assert isinstance(result, Evaluation) and set(result.images) == {"img0.png", "img1.png"}
    assert json.loads((tmp_path / "e.json").read_text()) == {
        "psnr": result.psnr,
        "ssim": result.ssim,
        "psnr_y": result.psnr_y,
        "ssim_y": result.ssim_y,
        "images": result.images,
        "model": str(out),
        "images_folder": str(images),
        "psf_file": None,
    }
    capsys.readouterr()
    assert main(["evaluate", str(out), "--images", str(images)]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[-1] == (
        f"{'mean':32s} PSNR {result.psnr:6.2f} dB  SSIM {result.ssim:.4f}  "
        f"PSNR {result.psnr_y:6.2f} dB  SSIM {result.ssim_y:.4f}"
    )
    assert set(result.images["img0.png"]) == {"psnr", "ssim", "psnr_y", "ssim_y"}
    with pytest.raises(InputError, match="exists; use --force"):  # before evaluating
        evaluate_folder(out, images, out=tmp_path / "e.json")


def test_results_path_refuses_what_cannot_be_written(tmp_path):
    assert results_path(None) is None
    assert results_path(str(tmp_path / "new.json")) == tmp_path / "new.json"
    with pytest.raises(InputError, match="is a folder"):
        results_path(tmp_path, force=True)
    (tmp_path / "old.json").write_text("{}")
    with pytest.raises(InputError, match="exists; use --force"):
        results_path(tmp_path / "old.json")
    assert results_path(tmp_path / "old.json", force=True) == tmp_path / "old.json"
    with pytest.raises(InputError, match=r"is a file, so x\.json cannot be written inside it"):
        results_path(tmp_path / "old.json" / "x.json")


# --- sr -----------------------------------------------------------------------------------


def test_super_resolve_files_reports_each_frame_in_order(trained, tmp_path):
    out, _ = trained
    white = load_model(out).sensor.photons
    np.save(tmp_path / "a.npy", np.full((2, 6, 5), white))
    np.save(tmp_path / "b.npy", np.full((4, 4), 8 * white))  # far brighter than white
    events = []
    result = super_resolve_files(
        out,
        [tmp_path / "a.npy", tmp_path / "b.npy"],
        tmp_path / "sr",
        on_note=lambda note: events.append(("note", note)),
        on_frame=lambda frame: events.append(("frame", frame.stem)),
    )
    assert [kind for kind, _ in events] == ["frame", "note", "frame"]
    assert events[1][1].startswith(f"{tmp_path / 'b.npy'}: 1 % of its counts exceed")
    assert result.outputs == tuple(f"{s}_sr{e}" for s in "ab" for e in (".npy", ".png", ".json"))
    assert sorted(p.name for p in (tmp_path / "sr").iterdir()) == sorted(result.outputs)
    a, b = result.frames
    assert isinstance(a, SRFrame) and a.input_shape == (2, 6, 5) and a.output_shape == (2, 24, 20)
    assert a.notes == () and b.notes == (events[1][1],)
    record = json.loads((tmp_path / "sr" / "b_sr.json").read_text())
    assert record["notes"] == list(b.notes) and record["output_shape"] == [16, 16]
    with pytest.raises(InputError, match="--photons"):
        super_resolve_files(out, [tmp_path / "a.npy"], tmp_path / "sr2", photons=0.0)
    assert not (tmp_path / "sr2").exists()
