"""Training end to end: batches, learning rate, resume from checkpoints, DDP, devices."""

import json
import os
import socket

import numpy as np
import pytest
import torch

from doe.infra.cli import main
from doe.infra.files import check_psf
from psf_learn.images import dead_leaves
from psf_learn.psf import box_psf, gaussian_psf
from psf_learn.sensor import SensorModel
from psf_learn.train import CodedCamera, TrainConfig, lr_factor, make_batch, train

K = 11
POINT = tuple(map(tuple, np.eye(4)[[2]].T @ np.eye(4)[[2]]))
TINY = TrainConfig(steps=6, minutes=0.0, batch=4, patch=16, features=6, stages=1, lr=3e-3)
SMALL = ["--steps", "3", "--features", "4", "--stages", "1", "--batch", "2", "--patch", "16"]
HAS_CUDA = torch.cuda.is_available()
pytestmark = pytest.mark.usefixtures("on_the_cpu")  # only CPU runs repeat bit for bit


def _images(n=3, size=48, seed=0):
    rng = np.random.default_rng(seed)
    return [dead_leaves(size, rng, n_disks=300) for _ in range(n)]


def _params(camera):
    return torch.cat([p.detach().reshape(-1) for p in camera.parameters()])


# --- a step ---------------------------------------------------------------------------


def test_the_training_target_is_the_scene_the_camera_estimates():
    # Box PSF + point sample = the block means; a ramp's block means, upsampled by the
    # untrained network (bicubic, a = -0.75), come back as the ramp but for an error
    # odd about the samples, zero on average over whole pixels. A target one
    # sub-pixel off is off by the ramp's slope.
    camera = CodedCamera(box_psf(K), SensorModel(POINT, 0.0), TINY)
    patch = 32
    rows, cols = np.mgrid[0 : patch + K - 1, 0 : patch + K - 1].astype(np.float32)
    for ramp in (rows, cols, 3 * rows - 2 * cols):
        scenes = torch.from_numpy(ramp)[None, None]
        with torch.no_grad():
            error = (camera(scenes, [(0, 0, 0, 1)]) - camera.centres(scenes))[0, 0, 8:-8, 8:-8]
        assert camera.centres(scenes).shape[-2:] == (patch, patch)
        assert abs(error.mean().item()) < 1e-3  # float32 rounding of values near 100
        assert error.abs().max().item() < 1.0


def test_make_batch_is_keyed_and_in_range():
    imgs = _images()
    a = make_batch(imgs, [(0, 1, i, 0) for i in range(3)], 20)
    b = make_batch(imgs, [(0, 1, i, 0) for i in range(3)], 20)
    assert a.shape == (3, 1, 20, 20) and torch.equal(a, b)
    assert not torch.equal(a, make_batch(imgs, [(0, 2, i, 0) for i in range(3)], 20))


def test_learning_rate_warms_up_then_follows_a_cosine_to_a_twentieth():
    assert [lr_factor(p) for p in (-1.0, 0.0, 0.01, 0.02)] == pytest.approx([0.05, 0.05, 0.525, 1])
    # halfway through the cosine (progress 0.51) it is halfway between 1 and 0.05
    assert [lr_factor(p) for p in (0.51, 1.0, 2.0)] == pytest.approx([0.525, 0.05, 0.05])
    assert lr_factor(0.265) == pytest.approx(0.05 + 0.95 * (1 + np.cos(np.pi / 4)) / 2)


def test_make_batch_draws_every_window_and_each_of_the_eight_flips():
    from numpy.lib.stride_tricks import sliding_window_view

    rng = np.random.default_rng(4)
    imgs = [rng.random((24, 31), dtype=np.float32), rng.random((26, 22), dtype=np.float32)]
    dihedral = [lambda p: p, lambda p: p[::-1], lambda p: p[:, ::-1], lambda p: p[::-1, ::-1]]
    dihedral += [lambda p, f=f: f(p).T for f in dihedral]
    seen = set()
    for patch in make_batch(imgs, [(5, 0, i, 0) for i in range(400)], 20)[:, 0].numpy():
        found = [
            (i, t, r, c)
            for i, img in enumerate(imgs)
            for t, f in enumerate(dihedral)
            for r, c in np.argwhere(
                (sliding_window_view(img, (20, 20)) == f(patch)[None, None]).all(axis=(2, 3))
            )
        ]
        assert len(found) == 1  # every patch is a window of an image, flipped one way
        seen.add(found[0])
    assert {i for i, *_ in seen} == {0, 1} and {t for _, t, *_ in seen} == set(range(8))
    for i, img in enumerate(imgs):  # the first and the last rows and columns are drawn
        assert {r for j, _, r, _ in seen if j == i} >= {0, img.shape[0] - 20}
        assert {c for j, _, _, c in seen if j == i} >= {0, img.shape[1] - 20}


def _fixed_batch_loss(camera, images):
    scenes = make_batch(images, [(99, 0, i, 0) for i in range(8)], 16 + K - 1)
    with torch.no_grad():
        estimate = camera(scenes, [(99, 0, i, 1) for i in range(8)])
    return float((estimate - camera.centres(scenes)).abs().mean())


def test_short_training_lowers_the_loss():
    torch.set_num_threads(1)
    images = _images()
    sensor = SensorModel(POINT, 1000.0)
    start = train(TrainConfig(**{**TINY.__dict__, "steps": 0}), images, sensor, gaussian_psf(K))
    config = TrainConfig(**{**TINY.__dict__, "steps": 80, "lr": 1e-2})
    end = train(config, images, sensor, gaussian_psf(K))
    before = _fixed_batch_loss(start.camera, images)  # an untrained model is bicubic upsampling
    after = _fixed_batch_loss(end.camera, images)
    assert after < 0.97 * before
    assert end.steps == 80 and len(end.history) == 80
    # the PSF moved, and is still a PSF
    assert not np.allclose(end.camera.psf.numpy(), start.camera.psf.numpy())
    check_psf(end.camera.psf.numpy(), "trained")


def test_training_shows_its_loss_on_a_terminal(capsys):
    train(TINY, _images(), SensorModel(POINT, 200.0), gaussian_psf(K))
    assert "loss" not in capsys.readouterr().err
    train(TINY, _images(), SensorModel(POINT, 200.0), gaussian_psf(K), progress=True)
    err = capsys.readouterr().err
    assert "6/6" in err and "loss=" in err and "psnr=" in err


# --- checkpoints and resume -----------------------------------------------------------


def test_resume_from_checkpoint_equals_uninterrupted_run(tmp_path):
    torch.set_num_threads(1)
    images = _images()
    sensor = SensorModel(POINT, 200.0)
    full = train(TINY, images, sensor, gaussian_psf(K))
    ckpt = tmp_path / "ckpt.pt"
    part = train(TINY, images, sensor, gaussian_psf(K), checkpoint=ckpt, stop_at_step=3)
    assert part.steps == 3 and ckpt.exists()
    resumed = train(TINY, images, sensor, gaussian_psf(K), checkpoint=ckpt)
    assert resumed.steps == 6
    assert torch.equal(_params(resumed.camera), _params(full.camera))
    assert resumed.history == full.history
    # the checkpoint holds only tensors and plain types
    torch.load(ckpt, weights_only=True)
    # Another sensor, starting PSF, set of images or starting network is another run:
    # its checkpoint is not resumed (a different kernel size once crashed on the old
    # PSF logits; other images once resumed the old weights and recorded only the new).
    flipped = [np.ascontiguousarray(im[::-1]) for im in images]
    start = full.camera.net.state_dict()
    for other_sensor, other_psf, other_images, init in (
        (SensorModel(POINT, 50.0), gaussian_psf(K), images, None),
        (sensor, gaussian_psf(K - 2), images, None),
        (sensor, gaussian_psf(K), flipped, None),
        (sensor, gaussian_psf(K), images, start),
    ):
        train(TINY, images, sensor, gaussian_psf(K), checkpoint=ckpt, stop_at_step=3)
        fresh = train(
            TINY, other_images, other_sensor, other_psf, init, checkpoint=ckpt, stop_at_step=1
        )
        assert fresh.steps == 1


def edited_checkpoint(tmp_path, edit):
    """Train TINY 3 steps, apply ``edit`` to its checkpoint; return (images, sensor, path)."""
    torch.set_num_threads(1)
    images, sensor, ckpt = _images(), SensorModel(POINT, 200.0), tmp_path / "checkpoint.pt"
    train(TINY, images, sensor, gaussian_psf(K), checkpoint=ckpt, stop_at_step=3)
    state = torch.load(ckpt, weights_only=True)
    edit(state)
    torch.save(state, ckpt)
    return images, sensor, ckpt


@pytest.mark.parametrize(
    "damage",
    [
        lambda s: s["camera"].update({"net.head.bias": torch.zeros(3)}),  # RuntimeError
        lambda s: s["camera"]["psf.logits"].fill_(float("nan")),  # a traceback further on
        lambda s: s["camera"]["net.head.weight"].fill_(float("nan")),
        lambda s: s.update(optimizer=None),
        lambda s: [m.update(exp_avg=torch.zeros(2)) for m in s["optimizer"]["state"].values()],
        lambda s: s.update(step="3"),
        lambda s: s.update(step=10**12),  # "trained" 10**12 steps in no time
        lambda s: s.update(elapsed=float("nan")),  # a --minutes budget was never spent
        lambda s: s.update(history=[[1.0], "x"]),
        lambda s: s["history"][1].__setitem__(0, float("nan")),  # a diverged step's loss
    ],
)
def test_a_damaged_checkpoint_of_this_run_is_refused(tmp_path, damage):
    # Its identity is this run's, what it holds is not what a run saves.
    from doe.infra.errors import InputError

    images, sensor, ckpt = edited_checkpoint(tmp_path, damage)
    with pytest.raises(InputError, match=r"checkpoint\.pt: damaged .*--restart"):
        train(TINY, images, sensor, gaussian_psf(K), checkpoint=ckpt)


def test_a_checkpoint_whose_history_holds_an_exact_batch_resumes(tmp_path):
    # A batch estimated exactly has an infinite PSNR: a figure, not damage.
    def exact(state):
        state["history"][1][1] = float("inf")

    images, sensor, ckpt = edited_checkpoint(tmp_path, exact)
    result = train(TINY, images, sensor, gaussian_psf(K), checkpoint=ckpt, stop_at_step=4)
    assert len(result.history) == 4 and result.history[1][1] == float("inf")


def test_a_rank_other_than_0_resumes_in_silence(fake_process_group, tmp_path, capsys, monkeypatch):
    # Every rank of a torchrun job resumes the checkpoint that rank 0 wrote, or ignores
    # another run's; rank 0 alone says so. The process group is faked: rank 1 of one.
    torch.set_num_threads(1)
    images, sensor, ckpt = _images(), SensorModel(POINT, 200.0), tmp_path / "ckpt.pt"
    part = train(TINY, images, sensor, gaussian_psf(K), checkpoint=ckpt, stop_at_step=3)
    capsys.readouterr()
    fake_process_group(rank=1, size=1)
    resumed = train(TINY, images, sensor, gaussian_psf(K), checkpoint=ckpt)
    assert resumed.steps == 6 and resumed.history[:3] == part.history
    other = train(TINY, images, SensorModel(POINT, 50.0), gaussian_psf(K), checkpoint=ckpt)
    assert other.steps == 6 and other.history[:3] != part.history  # started afresh
    assert capsys.readouterr().err == ""


def test_resuming_with_another_thread_count_says_so(tmp_path, capsys):
    before = torch.get_num_threads()
    ckpt = tmp_path / "ckpt.pt"

    def train_to(step, threads):
        torch.set_num_threads(threads)
        psf, sensor = gaussian_psf(K), SensorModel(POINT, 200.0)
        train(TINY, _images(), sensor, psf, checkpoint=ckpt, stop_at_step=step)
        return capsys.readouterr().err

    try:
        train_to(2, threads=1)
        assert "written with 1 threads" in train_to(3, threads=2)
        assert "threads" not in train_to(4, threads=2)
    finally:
        torch.set_num_threads(before)


def test_a_checkpoint_is_written_every_checkpoint_seconds(tmp_path, monkeypatch):
    from psf_learn import store

    saved = []
    monkeypatch.setattr(store, "save_checkpoint", lambda path, state: saved.append(state["step"]))
    every_step = TrainConfig(**{**TINY.__dict__, "checkpoint_seconds": 0.0})
    train(
        every_step,
        _images(),
        SensorModel(POINT, 200.0),
        gaussian_psf(K),
        checkpoint=tmp_path / "c.pt",
    )
    assert saved == [1, 2, 3, 4, 5, 6, 6]  # after each step, and at the end
    saved.clear()
    train(TINY, _images(), SensorModel(POINT, 200.0), gaussian_psf(K), checkpoint=tmp_path / "c.pt")
    assert saved == [6]  # a minute apart: only at the end


# --- processes and devices ------------------------------------------------------------


def _ddp_worker(rank, world, port, out, config=TINY):
    os.environ.update(
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        RANK=str(rank),
        WORLD_SIZE=str(world),
        LOCAL_RANK=str(rank),
    )
    torch.set_num_threads(1)
    # a new process, which sees the GPU if there is one: gloo and the CPU, as in one process
    result = train(config, _images(), SensorModel(POINT, 200.0), gaussian_psf(K), device="cpu")
    torch.save(_params(result.camera), out / f"rank{rank}.pt")
    torch.save(torch.tensor(result.history), out / f"history{rank}.pt")
    # Both ranks leave together: a rank tearing gloo down while the other still
    # talked once aborted ("terminate called without an active exception").
    torch.distributed.barrier()
    torch.distributed.destroy_process_group()


@pytest.mark.slow  # spawns two Python processes that import torch
def test_ddp_with_gloo_on_two_processes_matches_one_process(tmp_path):
    r0, r1 = _spawn_two_ranks(tmp_path, TINY)
    assert torch.equal(r0, r1)  # DDP keeps the replicas identical
    single = train(TINY, _images(), SensorModel(POINT, 200.0), gaussian_psf(K))
    # each rank took half of the same global batch: same run up to summation order
    torch.testing.assert_close(r0, _params(single.camera), atol=2e-5, rtol=1e-4)
    # the recorded loss and PSNR are the global batch's (each rank's half once)
    h0, h1 = torch.load(tmp_path / "history0.pt"), torch.load(tmp_path / "history1.pt")
    assert torch.equal(h0, h1)
    torch.testing.assert_close(h0, torch.tensor(single.history), atol=1e-5, rtol=1e-5)
    assert not torch.allclose(
        r0,
        _params(
            train(
                TrainConfig(**{**TINY.__dict__, "steps": 0}),
                _images(),
                SensorModel(POINT, 200.0),
                gaussian_psf(K),
            ).camera
        ),
    )


def _spawn_two_ranks(tmp_path, config):
    import torch.multiprocessing as mp

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    mp.spawn(_ddp_worker, args=(2, port, tmp_path, config), nprocs=2, join=True)
    return torch.load(tmp_path / "rank0.pt"), torch.load(tmp_path / "rank1.pt")


@pytest.mark.slow  # spawns two Python processes that import torch
def test_ddp_with_a_time_budget_keeps_the_replicas_identical(tmp_path):
    # Under --minutes each rank once took its learning rate from its own clock.
    r0, r1 = _spawn_two_ranks(
        tmp_path, TrainConfig(**{**TINY.__dict__, "steps": None, "minutes": 0.02})
    )
    assert torch.equal(r0, r1)


def test_train_refuses_a_batch_its_processes_cannot_share(fake_process_group, monkeypatch):
    # The Python API's own guard (learn checks --batch first); the process group of
    # two is faked, as no process stands beside this one.
    fake_process_group(rank=0, size=2)
    odd = TrainConfig(**{**TINY.__dict__, "batch": 3})
    with pytest.raises(ValueError, match="batch 3 is not divisible by 2 processes"):
        train(odd, _images(), SensorModel(POINT, 200.0), gaussian_psf(K))


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA device")
def test_training_on_cuda_returns_a_cpu_camera_and_says_where(
    image_folder, tmp_path, capsys, monkeypatch
):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    result = train(TINY, _images(), SensorModel(POINT, 200.0), gaussian_psf(K))
    assert {p.device.type for p in result.camera.parameters()} == {"cpu"}
    images = image_folder(tmp_path / "images")
    for device, name in (("auto", "cuda:0 ("), ("cuda", "cuda:0 ("), ("cpu", "cpu")):
        out = tmp_path / device
        args = ["learn", "--out", str(out), "--images", str(images), "--device", device]
        assert main([*args, *SMALL]) == 0
        assert json.loads((out / "learn.json").read_text())["device"].startswith(name)
        note = "--device cpu repeats bit for bit" in capsys.readouterr().err
        assert note == (device != "cpu")


# --- the PSF's share of the run -------------------------------------------------------


def test_past_psf_until_the_network_alone_trains():
    torch.set_num_threads(1)
    images, sensor = _images(), SensorModel(POINT, 200.0)
    config = TrainConfig(**{**TINY.__dict__, "psf_until": 0.5})
    start = gaussian_psf(K)
    half = train(config, images, sensor, start, stop_at_step=3)
    full = train(config, images, sensor, start)
    assert not np.allclose(half.camera.psf.numpy(), start)  # the PSF learned until then
    np.testing.assert_array_equal(full.camera.psf.numpy(), half.camera.psf.numpy())
    assert full.camera.psf.logits.grad is None  # left out of the step, and of the clipping
    assert not torch.equal(
        torch.cat([p.reshape(-1) for p in full.camera.net.parameters()]),
        torch.cat([p.reshape(-1) for p in half.camera.net.parameters()]),
    )
    # the whole run (the default): the PSF still moves in the second half
    always = train(TINY, images, sensor, start)
    assert not np.allclose(always.camera.psf.numpy(), half.camera.psf.numpy())
    assert always.camera.psf.logits.grad is not None
