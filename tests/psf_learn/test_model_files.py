"""The files of a learned model: model.pt and checkpoints written and read, damage refused."""

import hashlib
import json

import numpy as np
import pytest
import torch

from doe.infra.cli import main
from psf_learn.network import SRNet
from psf_learn.psf import gaussian_psf
from psf_learn.sensor import SensorModel
from psf_learn.sr import load_model

K = 11
SMALL = ["--steps", "3", "--features", "4", "--stages", "1", "--batch", "2", "--patch", "16"]
pytestmark = pytest.mark.usefixtures("on_the_cpu")  # only CPU runs repeat bit for bit


def test_a_refused_torch_write_is_one_line_and_leaves_no_part(tmp_path):
    # torch reports a full disk or a missing folder as a RuntimeError (a traceback from
    # learn, after the whole training) and leaves what it wrote.
    from doe.infra.errors import InputError
    from psf_learn import store

    target = tmp_path / "gone" / "model.pt"
    with pytest.raises(InputError, match=r"model\.pt: cannot be written"):
        store.save_model(target, {"format": "x"})
    assert not target.exists()


def _model_folder(path, record):
    """A model folder with ``record`` as model.pt, a PSF and no learn.json."""
    from doe.infra.files import save_npy

    path.mkdir()
    torch.save(record, path / "model.pt")
    save_npy(path / "psf.npy", gaussian_psf(K))
    return path


def test_model_record_keeps_the_sensor_and_weights_as_they_were(tmp_path):
    from psf_learn import store

    # An off-centre active area: weights that are not symmetric under a transpose.
    weights = ((0.0, 0.1, 0.0, 0.0), (0.0, 0.6, 0.2, 0.0), (0.0, 0.0, 0.1, 0.0), (0.0,) * 4)
    sensor = SensorModel(weights, photons=250.0, dark_counts=0.5)
    net = SRNet(factor=4, features=6, stages=1)
    config = {"factor": 4, "features": 6, "stages": 1}
    folder = _model_folder(tmp_path / "m", store.model_record(net, config, sensor))
    record, psf, learn = store.load_model_dir(folder)
    assert record["format"] == store.MODEL_FORMAT and record["network"] == config
    assert record["sensor"] == {"weights": [list(r) for r in weights], "photons": 250.0,
                                "dark_counts": 0.5}  # fmt: skip
    assert record["state_dict"].keys() == net.state_dict().keys()
    for k, v in net.state_dict().items():
        assert torch.equal(record["state_dict"][k], v)
    np.testing.assert_array_equal(psf, gaussian_psf(K))
    assert learn is None


def test_model_and_checkpoint_files_holding_code_or_another_format_are_refused(tmp_path):
    # weights_only: a torch file that unpickles anything but tensors and plain types could
    # run code; such a file is refused, not loaded
    import pickle
    import warnings
    from fractions import Fraction

    from doe.infra.errors import InputError
    from psf_learn import store

    pickled = {"format": store.MODEL_FORMAT, "x": Fraction(1, 3)}
    foreign = _model_folder(tmp_path / "pickled", pickled)
    with pytest.raises(InputError, match="not a readable model"):
        store.load_model_dir(foreign)
    other = _model_folder(tmp_path / "other", {"format": "doefab-sr-0", "network": {}})
    with pytest.raises(InputError, match="not a doefab-sr-1 model file"):
        store.load_model_dir(other)
    ckpt = tmp_path / "checkpoint.pt"
    torch.save({"identity": {}, "camera": {}, "step": 1, "x": Fraction(1, 3)}, ckpt)
    with pytest.raises(InputError, match="not readable"):
        store.load_checkpoint(ckpt)
    # A plain pickle, not torch's zip: torch warned on stderr beside the refusal.
    for path in (foreign / "model.pt", ckpt):
        path.write_bytes(pickle.dumps({"format": store.MODEL_FORMAT, "x": Fraction(1, 3)}))
    with warnings.catch_warnings(record=True) as warned:
        warnings.simplefilter("always")
        with pytest.raises(InputError, match="not a readable model"):
            store.load_model_dir(foreign)
        with pytest.raises(InputError, match="not readable"):
            store.load_checkpoint(ckpt)
    assert [str(w.message) for w in warned] == []
    torch.save({"camera": {}, "step": 1}, ckpt)  # no identity: not one of ours
    with pytest.raises(InputError, match="not a doefab checkpoint"):
        store.load_checkpoint(ckpt)


def test_a_checkpoint_write_that_fails_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    # A full disk while writing: the old checkpoint must survive whole and no part be left.
    from doe.infra.errors import InputError
    from psf_learn import store

    path = tmp_path / "run" / "sub" / "checkpoint.pt"  # the folders are made
    store.save_checkpoint(path, {"identity": "a", "camera": {}, "step": 3})
    assert store.load_checkpoint(path)["step"] == 3

    def full_disk(obj, f):
        with open(f, "wb") as out:
            out.write(b"PK\x03\x04 partial")
        raise RuntimeError("[enforce fail at inline_container.cc] : file write failed")

    monkeypatch.setattr(torch, "save", full_disk)
    with pytest.raises(InputError, match=r"checkpoint\.pt: cannot be written"):
        store.save_checkpoint(path, {"identity": "a", "camera": {}, "step": 4})
    monkeypatch.undo()
    assert store.load_checkpoint(path)["step"] == 3
    assert [p.name for p in path.parent.iterdir()] == ["checkpoint.pt"]


@pytest.mark.parametrize("swapped", ["model.pt", "psf.npy"])
def test_a_file_from_another_training_is_refused(trained, tmp_path, capsys, swapped):
    # A model.pt of another design (factor 3) beside this psf.npy and learn.json once
    # evaluated and super-resolved with exit 0.
    import shutil

    out, images = trained
    other = tmp_path / "other"
    assert main(["learn", "--out", str(other), "--images", str(images), *SMALL, "--seed", "1"]) == 0
    mixed = tmp_path / "mixed"
    shutil.copytree(out, mixed)
    shutil.copy(other / swapped, mixed / swapped)
    np.save(tmp_path / "raw.npy", np.ones((6, 6)))
    capsys.readouterr()
    for command in (
        ["evaluate", str(mixed), "--images", str(images)],
        ["sr", str(mixed), str(tmp_path / "raw.npy"), "--out", str(tmp_path / "sr")],
        ["learn", "--out", str(tmp_path / "tuned"), "--init", str(mixed), *SMALL],
    ):
        assert main(command) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and str(mixed / swapped) in err
    info = json.loads((out / "learn.json").read_text())
    assert info["files"]["psf.npy"] == hashlib.sha256((out / "psf.npy").read_bytes()).hexdigest()


@pytest.mark.parametrize(
    "damage",
    [
        lambda r: r["sensor"].update(photons=float("nan")),  # ran, writing NaN
        lambda r: r["sensor"].update(weights=[]),  # tracebacks: a broadcast error
        lambda r: r["sensor"].update(weights=[[1 / 9] * 3] * 3),  # for a factor-4 network
        lambda r: r["sensor"].update(weights=[[1 / 8] * 4] * 4),  # twice the light
        lambda r: r["sensor"].update(dark_counts=-1.0),
        lambda r: r["sensor"].update(photons=10**400),  # float() overflowed: exit 3
        lambda r: r["sensor"].update(photons="100"),  # taken as 100
        lambda r: r["sensor"].update(dark_counts=True),  # taken as 1
        lambda r: r["network"].update(factor=3),  # six lines of torch's size mismatches
        lambda r: r["state_dict"]["tail.0.bias"].fill_(float("nan")),  # wrote NaN, exit 0
        lambda r: r["state_dict"]["head.weight"].fill_(float("-inf")),
        lambda r: r["state_dict"].update({"head.bias": r["state_dict"]["head.bias"].int()}),
        lambda r: r["state_dict"].update(
            {"head.bias": r["state_dict"]["head.bias"].to(torch.complex64)}
        ),  # its imaginary part dropped, with a warning
        lambda r: r.update(state_dict=dict(enumerate(r["state_dict"].values()))),  # exit 3
        lambda r: r["network"].update(arch="transformer"),  # no such network
    ],
)
def test_a_damaged_model_record_is_refused_in_one_line(
    damaged_model, trained, tmp_path, capsys, damage
):
    model = damaged_model(trained[0], tmp_path / "model", damage)
    np.save(tmp_path / "raw.npy", np.ones((6, 6)))
    assert main(["sr", str(model), str(tmp_path / "raw.npy"), "--out", str(tmp_path / "sr")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(model / "model.pt") in err
    assert not (tmp_path / "sr").exists()


@pytest.mark.parametrize("name", ["photons", "dark_counts"])
def test_counts_past_learns_limit_are_refused_before_evaluating(
    damaged_model, trained, tmp_path, capsys, name
):
    # numpy's Poisson draw refused them: a traceback, exit 3
    out, images = trained
    model = damaged_model(out, tmp_path / "model", lambda r: r["sensor"].update({name: 1e300}))
    assert main(["evaluate", str(model), "--images", str(images)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(model / "model.pt") in err and name in err


def test_weights_that_overflow_float32_write_no_images_or_scores(
    damaged_model, trained, tmp_path, capsys
):
    # finite weights, yet white frames came out NaN: written, and NaN dB printed, exit 0
    out, images = trained
    model = damaged_model(
        out, tmp_path / "model", lambda r: r["state_dict"]["head.weight"].fill_(3e38)
    )
    white = json.loads((out / "learn.json").read_text())["config"]["photons_per_pixel"]
    np.save(tmp_path / "raw.npy", np.full((6, 6), white))
    results = tmp_path / "e.json"
    for args in (
        ["sr", str(model), str(tmp_path / "raw.npy"), "--out", str(tmp_path / "sr")],
        ["evaluate", str(model), "--images", str(images), "--out", str(results)],
    ):
        assert main(args) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and f"{model / 'model.pt'}: gives non-finite" in err
    assert not (tmp_path / "sr").exists() and not results.exists()


@pytest.mark.parametrize(
    "network",
    [
        {"features": 10**6},  # torch was asked for terabytes before shapes were compared
        {"stages": 10**6},  # a million blocks were built, for minutes
        {"features": 0},  # built, and torch's warnings went to stderr beside the refusal
        {"stages": True},
        {"arch": None},  # missing: SRNet's default stood in for it
        {"kernel_size": 11},
    ],
)
def test_a_network_learn_cannot_write_is_refused_before_it_is_built(
    damaged_model, trained, tmp_path, monkeypatch, network
):
    from doe.infra.errors import InputError

    def build(**config):
        raise AssertionError(f"built the network {config}")

    def damage(record):
        record["network"].update(network)
        record["network"] = {k: v for k, v in record["network"].items() if v is not None}

    model = damaged_model(trained[0], tmp_path / "model", damage)
    monkeypatch.setattr("psf_learn.sr.SRNet", build)
    with pytest.raises(InputError, match=r"model\.pt: inconsistent model \(network"):
        load_model(model)


def test_an_init_model_without_its_arch_is_refused_in_one_line(
    damaged_model, trained, tmp_path, capsys
):
    out, images = trained
    model = damaged_model(out, tmp_path / "model", lambda r: r["network"].pop("arch"))
    args = ["learn", "--init", str(model), "--out", str(tmp_path / "m"), "--images", str(images)]
    assert main([*args, *SMALL]) == 2  # SRNet's default arch, then a KeyError: exit 3
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(model / "model.pt") in err
    assert not (tmp_path / "m").exists()


def test_an_init_model_whose_weights_overflow_diverges_and_is_named(
    damaged_model, trained, tmp_path, capsys
):
    # Finite weights of 1e30: the first step's activations overflow float32. The
    # training stops, naming the learning rate and the model it started from.
    out, images = trained

    def inflate(record):
        for value in record["state_dict"].values():
            value.mul_(1e30)

    model = damaged_model(out, tmp_path / "model", inflate)
    args = ["learn", "--init", str(model), "--out", str(tmp_path / "m"), "--images", str(images)]
    assert main([*args, *SMALL]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "diverged" in err[0] and err[0].endswith("another --init model")
    assert not (tmp_path / "m" / "model.pt").exists()


def test_dbpn_at_an_odd_factor_is_refused_before_training_or_running(
    damaged_model, trained, tmp_path, capsys, monkeypatch
):
    # Its projections map h to f h + 1 at an odd f: a RuntimeError in the first step (exit
    # 3), and in sr for a model.pt of such a network.
    out, images = trained
    factor3 = tmp_path / "factor3.toml"
    factor3.write_text("[sensor]\nsuperres_factor = 3\n")
    args = ["learn", "--out", str(tmp_path / "m"), "--images", str(images), *SMALL]
    assert main([*args[:-1], "18", "--arch", "dbpn", "--config", str(factor3)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--arch: dbpn needs an even" in err
    assert not (tmp_path / "m").exists()
    monkeypatch.setattr("psf_learn.network.check_arch", lambda arch, factor: None, raising=False)
    network = SRNet(factor=3, features=4, stages=1, arch="dbpn")  # as a model.pt would hold
    monkeypatch.undo()

    def damage(record):
        record["network"].update(factor=3, arch="dbpn")
        record["sensor"]["weights"] = [[1 / 9] * 3] * 3
        record["state_dict"] = network.state_dict()

    model = damaged_model(out, tmp_path / "model", damage)
    np.save(tmp_path / "raw.npy", np.ones((6, 6)))
    assert main(["sr", str(model), str(tmp_path / "raw.npy"), "--out", str(tmp_path / "sr")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(model / "model.pt") in err and "even" in err
    assert not (tmp_path / "sr").exists()
