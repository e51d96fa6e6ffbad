"""PSF parametrisation, SR network, training (resume, DDP), and the learn/evaluate/sr commands."""

import hashlib
import json
import os
import re
import socket

import numpy as np
import pytest
import torch
from skimage import io

from doe.design import design_summary, load_design
from doe.infra.cli import main
from doe.infra.files import check_psf
from psf_learn.evaluate import evaluate, evaluate_image
from psf_learn.images import dead_leaves
from psf_learn.network import SRNet
from psf_learn.psf import LearnedPSF, baseline_psf, box_psf, delta_psf, gaussian_psf
from psf_learn.sensor import SensorModel
from psf_learn.sr import SRModel, load_model, super_resolve, white_counts
from psf_learn.train import (
    CodedCamera,
    TrainConfig,
    default_patch,
    lr_factor,
    make_batch,
    train,
)

K = 11
POINT = tuple(map(tuple, np.eye(4)[[2]].T @ np.eye(4)[[2]]))
TINY = TrainConfig(steps=6, minutes=0.0, batch=4, patch=16, features=6, stages=1, lr=3e-3)
HAS_CUDA = torch.cuda.is_available()


@pytest.fixture(scope="module", autouse=True)
def _on_the_cpu():
    """Train on the CPU in these tests, GPU or not: only CPU runs repeat bit for bit.

    The tests of the CUDA path (``gpu``) put the GPU back; they run where there is one.
    """
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(torch.cuda, "is_available", lambda: False)
        yield


def _images(n=3, size=48, seed=0):
    rng = np.random.default_rng(seed)
    return [dead_leaves(size, rng, n_disks=300) for _ in range(n)]


def _params(camera):
    return torch.cat([p.detach().reshape(-1) for p in camera.parameters()])


# --- PSF -----------------------------------------------------------------------------------


def test_learned_psf_is_normalised_for_any_logits():
    psf = LearnedPSF(delta_psf(K))
    psf.logits.data = torch.randn(K, K, generator=torch.Generator().manual_seed(0)) * 5
    p = psf()
    # softmax ignores a common offset, even one whose exp overflows (float32 logits
    # near 1000 are rounded to 6e-5)
    shifted = LearnedPSF(delta_psf(K))
    shifted.logits.data = psf.logits.data + 1000
    np.testing.assert_allclose(shifted.numpy(), psf.numpy(), rtol=1e-4)
    assert (p >= 0).all()
    assert p.sum().item() == pytest.approx(1, abs=1e-6)
    exact = psf.numpy()
    assert exact.dtype == np.float64 and exact.shape == (K, K)
    assert exact.sum() == pytest.approx(1, abs=1e-14)
    check_psf(exact, "learned")  # the psf.npy contract


def test_learned_psf_starts_at_its_initial_psf_and_frozen_keeps_zeros():
    g = gaussian_psf(K)
    np.testing.assert_allclose(LearnedPSF(g).numpy(), g, atol=K * K * 1e-6 * g.max())
    frozen = LearnedPSF(box_psf(K), trainable=False)
    assert not frozen.logits.requires_grad
    np.testing.assert_allclose(frozen.numpy(), box_psf(K), atol=1e-12)


def test_a_learned_psf_started_from_a_delta_can_move_light_to_any_cell():
    # Zeros of the start are floored at 1e-6 of the peak: at log 0 the softmax would
    # hold them at exactly 0, with zero gradient, for ever.
    psf = LearnedPSF(delta_psf(K))
    (-psf()[0, 0]).backward()  # a loss that wants light in the corner
    p0 = 1e-6 / (1 + (K * K - 1) * 1e-6)  # the corner's share at the start
    # d(-p_0)/dz_0 = -p_0 (1 - p_0) for a softmax
    assert psf.logits.grad[0, 0].item() == pytest.approx(-p0 * (1 - p0), rel=1e-4)


@pytest.mark.parametrize("sigma", [0.01, 1e-200])
def test_a_gaussian_narrower_than_a_cell_tends_to_its_limit(sigma):
    # Centred between cells every sample underflowed: 0 / 0, then a flat 11 x 11 PSF.
    between = gaussian_psf(K, sigma, centre=(0.5, 0.5))
    expected = np.zeros((K, K))
    expected[K // 2 : K // 2 + 2, K // 2 : K // 2 + 2] = 0.25  # the four nearest cells
    np.testing.assert_allclose(between, expected, atol=1e-12)
    on_axis = gaussian_psf(K, sigma)
    assert on_axis[K // 2, K // 2] == pytest.approx(1)


@pytest.mark.parametrize("sigma", [0.8, 1.0, 1.2])
def test_a_gaussian_psf_has_the_variance_of_its_sigma(sigma):
    # A sampled Gaussian's variance is sigma^2 but for aliasing (Poisson summation:
    # terms in exp(-2 pi^2 sigma^2), 3e-6 at sigma 0.8) and the cut at 4.5 cells from a
    # centre between cells (3.7 sigma at sigma 1.2): both well under 1e-3.
    r = np.arange(K) - K // 2
    for centre in [(0.0, 0.0), (0.5, 0.5)]:
        g = gaussian_psf(K, sigma, centre)
        for axis, c in enumerate(centre):
            marginal = g.sum(axis=1 - axis)
            mean = marginal @ r
            assert mean == pytest.approx(c, abs=1e-12)
            assert marginal @ (r - mean) ** 2 == pytest.approx(sigma**2, rel=1e-3)


@pytest.mark.parametrize("centre", [(1.5, -1.0), (-2.0, 0.5)])
def test_a_gaussian_psf_keeps_its_centroid_at_any_centre(centre):
    # The window is cut symmetric about the centre (whole or half cells: the pixel
    # centres of point samples), which a wide Gaussian's tails reach.
    g = gaussian_psf(K, 3.0, centre)
    r = np.arange(K) - K // 2
    np.testing.assert_allclose((g.sum(axis=1) @ r, g.sum(axis=0) @ r), centre, atol=1e-12)


def test_baseline_psfs():
    g = gaussian_psf(K)
    assert g.sum() == pytest.approx(1) and np.argmax(g) == (K // 2) * K + K // 2
    np.testing.assert_allclose(g, g.T)
    np.testing.assert_allclose(g, g[::-1, ::-1])
    b = box_psf(K)
    assert np.count_nonzero(b) == 16 and b.sum() == pytest.approx(1)
    # default sample cell (2, 2): offsets -1 .. +2 from the axis
    assert np.argwhere(b > 0).min(axis=0).tolist() == [K // 2 - 1] * 2
    assert np.argwhere(b > 0).max(axis=0).tolist() == [K // 2 + 2] * 2
    assert np.count_nonzero(box_psf(5)) == 16  # offsets -1 .. +2 fit in K = 5
    # the Gaussian baseline shares the box's centroid: the sampled pixel's centre
    r = np.arange(K)
    for name in ("gaussian", "gaussian:1.836"):
        p = baseline_psf(name, K)
        assert p.sum() == pytest.approx(1)
        for axis in (0, 1):
            centroid = (p.sum(axis=1 - axis) * r).sum()
            assert centroid == pytest.approx((b.sum(axis=1 - axis) * r).sum())
    with pytest.raises(ValueError):
        box_psf(5, sample_cell=(0, 0))  # offsets -3 .. 0 do not


# --- network --------------------------------------------------------------------------------


@pytest.mark.parametrize("arch", ["resnet", "dbpn"])
def test_network_upsamples_by_the_factor(arch):
    net = SRNet(4, features=4, stages=2, arch=arch)
    assert net(torch.rand(2, 1, 5, 7)).shape == (2, 1, 20, 28)


def test_count_parameters_counts_the_trainable_weights_and_biases():
    from psf_learn.network import count_parameters

    # resnet, F features, S stages, factor f: a 3 x 3 head 1 -> F, S blocks of two
    # 3 x 3 F -> F convolutions and a 3 x 3 tail F -> f^2, each with its biases
    f, features, stages = 4, 6, 2
    head, block, tail = 9 * features + features, 9 * features**2 + features, 9 * features * f**2
    expected = head + stages * 2 * block + tail + f**2
    net = SRNet(f, features=features, stages=stages)
    assert count_parameters(net) == expected
    net.head.requires_grad_(False)
    assert count_parameters(net) == expected - head


# --- training -------------------------------------------------------------------------------


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


# --- evaluation and super-resolution ---------------------------------------------------------


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


class _Fixed(torch.nn.Module):
    """A "network" that ignores the frame and returns a fixed (H, W) estimate."""

    def __init__(self, estimate):
        super().__init__()
        self.estimate = torch.as_tensor(estimate, dtype=torch.float32)[None, None]

    def forward(self, frame):
        return self.estimate


def _fixed_model(estimate):
    return SRModel(_Fixed(estimate), delta_psf(K), SensorModel(POINT, 0.0), None)


def test_psnr_and_ssim_of_a_known_error_inside_the_border_crop():
    # catches 20 log10 of the MSE, a border cropped on one side only (or transposed, or
    # none by default), SSIM of the wrong pair or with a data range of 255
    image = np.full((24, 32), 0.5)
    estimate = np.full((24, 32), 0.6)
    estimate[:4], estimate[-4:], estimate[:, :4], estimate[:, -4:] = 0.0, 1.0, 0.0, 1.0
    psnr, ssim, _ = evaluate_image(_fixed_model(estimate), image)
    assert psnr == pytest.approx(20.0, abs=1e-4)  # MSE 0.1^2 -> 10 log10(1 / 0.01)
    # constant images: SSIM is the luminance term alone, C1 = (0.01 * data range)^2
    c1 = 0.01**2
    assert ssim == pytest.approx((2 * 0.5 * 0.6 + c1) / (0.5**2 + 0.6**2 + c1), rel=1e-5)


def test_the_estimate_is_clipped_to_the_unit_range_before_scoring():
    # catches a dropped clamp: 1.05 counts as 1.0 against 0.95, an MSE of 0.05^2
    psnr, _, est = evaluate_image(_fixed_model(np.full((24, 32), 1.05)), np.full((24, 32), 0.95))
    assert est.max() == 1.0
    assert psnr == pytest.approx(10 * np.log10(1 / 0.05**2), abs=1e-4)


def test_each_image_gets_its_own_noise():
    # catches one noise seed reused for every image: equal images would then score equally
    img = dead_leaves(32, np.random.default_rng(0), n_disks=100)
    per = evaluate(_flat_model(100.0), ["a", "b"], [img, img])["images"]
    assert per["a"]["psnr"] != per["b"]["psnr"]


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


# --- command line ----------------------------------------------------------------------------

SMALL = ["--steps", "3", "--features", "4", "--stages", "1", "--batch", "2", "--patch", "16"]


def _image_folder(path, n=2, size=40):
    path.mkdir()
    rng = np.random.default_rng(0)
    for i in range(n):
        img = (dead_leaves(size, rng, n_disks=100) * 255).astype(np.uint8)
        io.imsave(path / f"img{i}.png", img, check_contrast=False)
    return path


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("learn")
    images = _image_folder(root / "images")
    out = root / "model"
    assert main(["learn", "--out", str(out), "--images", str(images), *SMALL]) == 0
    return out, images


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


def test_default_patch_holds_whole_pixels_of_any_factor(tmp_path):
    # 64 sub-pixels, the prototype's patch, is no whole number of 3 x 3 SPAD pixels
    design = tmp_path / "factor3.toml"
    design.write_text("[sensor]\nsuperres_factor = 3\n[psf]\nkernel_size = 9\n")
    images = _image_folder(tmp_path / "images", size=80)
    out = tmp_path / "model"
    tiny = ["--steps", "1", "--features", "4", "--stages", "1", "--batch", "2"]
    args = ["learn", "--out", str(out), "--images", str(images), "--config", str(design)]
    assert main([*args, *tiny]) == 0
    assert json.loads((out / "learn.json").read_text())["config"]["patch"] == 63
    assert [default_patch(f) for f in (1, 2, 3, 4, 5, 8, 100)] == [64, 64, 63, 64, 60, 64, 100]


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
    from doe.design import check_psf_grid, derive

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
    from doe.design import check_psf_grid, psf_grid_problem

    np.save(tmp_path / "psf.npy", gaussian_psf(K))
    (tmp_path / name).write_text(text)
    check_psf_grid(tmp_path / "psf.npy", load_design(None))
    assert psf_grid_problem(tmp_path / "psf.npy", {"sensor": {}}, "the model") is None


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
    from doe.design import derive

    out, images = trained
    (tmp_path / "factor2.toml").write_text("[sensor]\nsuperres_factor = 2\n")
    factor2 = load_design(tmp_path / "factor2.toml")
    reports = {
        "learn.json": {"design": design_summary(factor2)},
        "verify.json": {"lattice_pitch_um": derive(factor2).lattice_pitch * 1e6},
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


def _bad_input(tmp_path, kind):
    folder = tmp_path / "imgs"
    if kind == "empty":
        folder.mkdir()
        (folder / "notes.txt").write_text("no images here")
        return ["--images", str(folder)], folder
    if kind == "corrupt":
        _image_folder(folder)
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


def test_a_steps_run_takes_one_thread_whatever_the_load(trained, tmp_path, monkeypatch):
    # The default once came from the load average, and 1 or 2 threads give different
    # last bits: the same --steps command gave another model.pt on a busier machine.
    from psf_learn.commands import learn as learn_cli

    _, images = trained
    monkeypatch.setattr(learn_cli, "idle_cores", lambda: 2)
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


def test_device_cuda_without_a_gpu_is_refused(tmp_path, capsys):
    out = tmp_path / "model"
    assert main(["learn", "--out", str(out), "--device", "cuda", *SMALL]) == 2
    err = capsys.readouterr().err
    assert "--device cuda: torch sees no CUDA device" in err and not out.exists()


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA device")
def test_training_on_cuda_returns_a_cpu_camera_and_says_where(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    result = train(TINY, _images(), SensorModel(POINT, 200.0), gaussian_psf(K))
    assert {p.device.type for p in result.camera.parameters()} == {"cpu"}
    images = _image_folder(tmp_path / "images")
    for device, name in (("auto", "cuda:0 ("), ("cuda", "cuda:0 ("), ("cpu", "cpu")):
        out = tmp_path / device
        args = ["learn", "--out", str(out), "--images", str(images), "--device", device]
        assert main([*args, *SMALL]) == 0
        assert json.loads((out / "learn.json").read_text())["device"].startswith(name)
        note = "--device cpu repeats bit for bit" in capsys.readouterr().err
        assert note == (device != "cpu")


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


def test_a_training_that_diverges_is_refused_naming_the_learning_rate(tmp_path, capsys):
    # --lr 1e8 made the weights overflow, the PSF NaN, and the next capture's Poisson
    # draw raised: a traceback, exit 3. Nothing is written but the last checkpoint.
    folder = _image_folder(tmp_path / "imgs")
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


def test_a_checkpoint_whose_history_holds_an_exact_batch_resumes(tmp_path):
    # A batch estimated exactly has an infinite PSNR: a figure, not damage.
    def exact(state):
        state["history"][1][1] = float("inf")

    images, sensor, ckpt = edited_checkpoint(tmp_path, exact)
    result = train(TINY, images, sensor, gaussian_psf(K), checkpoint=ckpt, stop_at_step=4)
    assert len(result.history) == 4 and result.history[1][1] == float("inf")


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


def fake_process_group(monkeypatch, rank, size):
    """Make torch.distributed report a process group; return the list of collective calls."""
    calls = []
    dist = torch.distributed
    monkeypatch.setattr(dist, "is_initialized", lambda: True)
    monkeypatch.setattr(dist, "get_rank", lambda: rank)
    monkeypatch.setattr(dist, "get_world_size", lambda: size)
    monkeypatch.setattr(dist, "barrier", lambda: calls.append("barrier"))
    monkeypatch.setattr(dist, "destroy_process_group", lambda: calls.append("destroy"))
    return calls


def test_a_rank_other_than_0_resumes_in_silence(tmp_path, capsys, monkeypatch):
    # Every rank of a torchrun job resumes the checkpoint that rank 0 wrote, or ignores
    # another run's; rank 0 alone says so. The process group is faked: rank 1 of one.
    torch.set_num_threads(1)
    images, sensor, ckpt = _images(), SensorModel(POINT, 200.0), tmp_path / "ckpt.pt"
    part = train(TINY, images, sensor, gaussian_psf(K), checkpoint=ckpt, stop_at_step=3)
    capsys.readouterr()
    fake_process_group(monkeypatch, rank=1, size=1)
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


@pytest.mark.parametrize("kind", ["empty", "corrupt", "negative", "unnormalised", "even"])
def test_learn_refuses_bad_inputs_with_exit_2(tmp_path, capsys, kind):
    extra, culprit = _bad_input(tmp_path, kind)
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
def test_a_damaged_model_record_is_refused_in_one_line(trained, tmp_path, capsys, damage):
    model = _damaged_model(trained[0], tmp_path / "model", damage)
    np.save(tmp_path / "raw.npy", np.ones((6, 6)))
    assert main(["sr", str(model), str(tmp_path / "raw.npy"), "--out", str(tmp_path / "sr")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(model / "model.pt") in err
    assert not (tmp_path / "sr").exists()


@pytest.mark.parametrize("name", ["photons", "dark_counts"])
def test_counts_past_learns_limit_are_refused_before_evaluating(trained, tmp_path, capsys, name):
    # numpy's Poisson draw refused them: a traceback, exit 3
    out, images = trained
    model = _damaged_model(out, tmp_path / "model", lambda r: r["sensor"].update({name: 1e300}))
    assert main(["evaluate", str(model), "--images", str(images)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(model / "model.pt") in err and name in err


def test_weights_that_overflow_float32_write_no_images_or_scores(trained, tmp_path, capsys):
    # finite weights, yet white frames came out NaN: written, and NaN dB printed, exit 0
    out, images = trained
    model = _damaged_model(
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


def _damaged_model(out, model, damage):
    """A copy of model folder ``out`` whose model.pt record went through ``damage``."""
    import shutil

    shutil.copytree(out, model)
    (model / "learn.json").unlink()  # its hashes would catch the edit first
    record = torch.load(model / "model.pt", weights_only=True)
    damage(record)
    torch.save(record, model / "model.pt")
    return model


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
    trained, tmp_path, monkeypatch, network
):
    from doe.infra.errors import InputError

    def build(**config):
        raise AssertionError(f"built the network {config}")

    def damage(record):
        record["network"].update(network)
        record["network"] = {k: v for k, v in record["network"].items() if v is not None}

    model = _damaged_model(trained[0], tmp_path / "model", damage)
    monkeypatch.setattr("psf_learn.sr.SRNet", build)
    with pytest.raises(InputError, match=r"model\.pt: inconsistent model \(network"):
        load_model(model)


def test_dbpn_at_an_odd_factor_is_refused_before_training_or_running(
    trained, tmp_path, capsys, monkeypatch
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

    model = _damaged_model(out, tmp_path / "model", damage)
    np.save(tmp_path / "raw.npy", np.ones((6, 6)))
    assert main(["sr", str(model), str(tmp_path / "raw.npy"), "--out", str(tmp_path / "sr")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(model / "model.pt") in err and "even" in err
    assert not (tmp_path / "sr").exists()


def test_an_init_model_without_its_arch_is_refused_in_one_line(trained, tmp_path, capsys):
    out, images = trained
    model = _damaged_model(out, tmp_path / "model", lambda r: r["network"].pop("arch"))
    args = ["learn", "--init", str(model), "--out", str(tmp_path / "m"), "--images", str(images)]
    assert main([*args, *SMALL]) == 2  # SRNet's default arch, then a KeyError: exit 3
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(model / "model.pt") in err
    assert not (tmp_path / "m").exists()


def test_an_init_model_whose_weights_overflow_diverges_and_is_named(trained, tmp_path, capsys):
    # Finite weights of 1e30: the first step's activations overflow float32. The
    # training stops, naming the learning rate and the model it started from.
    out, images = trained

    def inflate(record):
        for value in record["state_dict"].values():
            value.mul_(1e30)

    model = _damaged_model(out, tmp_path / "model", inflate)
    args = ["learn", "--init", str(model), "--out", str(tmp_path / "m"), "--images", str(images)]
    assert main([*args, *SMALL]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "diverged" in err[0] and err[0].endswith("another --init model")
    assert not (tmp_path / "m" / "model.pt").exists()


def test_dark_counts_without_noise_are_refused(tmp_path, capsys):
    # Noise is off at --photons 0, dark counts included, yet model.pt recorded them and
    # sr subtracted them: a 0.5 grey frame came out at -4.4.
    out = tmp_path / "m"
    assert main(["learn", "--out", str(out), "--photons", "0", "--dark-counts", "5", *SMALL]) == 2
    err = capsys.readouterr().err
    assert "--dark-counts" in err and "--photons 0" in err and not out.exists()


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


# --- from a coverage run: paths no test took ------------------------------------------------


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


def test_a_named_baseline_psf_is_trained_with_as_given(trained, tmp_path):
    _, images = trained
    out = tmp_path / "m"
    assert main(["learn", "--out", str(out), "--images", str(images), "--psf", "box", *SMALL]) == 0
    np.testing.assert_array_equal(np.load(out / "psf.npy"), box_psf(K))
    assert json.loads((out / "learn.json").read_text())["config"]["psf"] == "box"


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


def test_a_rank_other_than_0_trains_but_writes_nothing(trained, tmp_path, capsys, monkeypatch):
    # A torchrun job: every rank trains, rank 0 alone writes, and all leave together.
    # The process group is faked: rank 1 of a group of one.
    calls = fake_process_group(monkeypatch, rank=1, size=1)
    out = tmp_path / "out"
    assert main(["learn", "--out", str(out), "--images", str(trained[1]), *SMALL]) == 0
    assert calls == ["barrier", "destroy"]
    assert list(out.iterdir()) == [] and "trained" not in capsys.readouterr().out


def test_rank_0_of_a_job_writes_the_model_and_leaves_with_the_others(
    trained, tmp_path, monkeypatch
):
    # The other side of the test above: rank 0 writes the package, after the barrier.
    # In a group of one it trains what a lone process does (the trained fixture's run).
    calls = fake_process_group(monkeypatch, rank=0, size=1)
    out = tmp_path / "out"
    assert main(["learn", "--out", str(out), "--images", str(trained[1]), *SMALL]) == 0
    assert calls == ["barrier", "destroy"]
    assert sorted(p.name for p in out.iterdir()) == ["learn.json", "model.pt", "psf.npy"]
    assert (out / "psf.npy").read_bytes() == (trained[0] / "psf.npy").read_bytes()


def test_learn_for_minutes_trains_until_the_time_is_spent(trained, tmp_path):
    # Without --steps (the default), --minutes is the budget of training time.
    out = tmp_path / "out"
    budget = ["--minutes", "0.005", "--threads", "1"]  # 0.3 s
    assert main(["learn", "--out", str(out), "--images", str(trained[1]), *budget, *SMALL[2:]]) == 0
    info = json.loads((out / "learn.json").read_text())
    assert info["config"]["steps"] is None and info["config"]["minutes"] == 0.005
    assert info["steps"] >= 1 and info["seconds"] >= 0.3


def test_idle_cores_take_omp_num_threads_or_the_cores_not_busy(monkeypatch):
    from psf_learn.commands.learn import idle_cores

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

    from psf_learn.commands.learn import _version

    def not_installed(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "version", not_installed)
    assert _version() == "unknown"


def test_training_shows_its_loss_on_a_terminal(capsys):
    train(TINY, _images(), SensorModel(POINT, 200.0), gaussian_psf(K))
    assert "loss" not in capsys.readouterr().err
    train(TINY, _images(), SensorModel(POINT, 200.0), gaussian_psf(K), progress=True)
    err = capsys.readouterr().err
    assert "6/6" in err and "loss=" in err and "psnr=" in err


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


def test_super_resolve_takes_a_model_folder_and_refuses_a_row(trained):
    out, _ = trained
    frames = np.random.default_rng(5).poisson(150, size=(2, 6, 5)).astype(float)
    np.testing.assert_array_equal(
        super_resolve(out, frames), super_resolve(load_model(out), frames)
    )
    with pytest.raises(ValueError, match=r"frames must be \(\.\.\., h, w\), got shape \(5,\)"):
        super_resolve(out, frames[0, 0])


def test_train_refuses_a_batch_its_processes_cannot_share(monkeypatch):
    # The Python API's own guard (learn checks --batch first); the process group of
    # two is faked, as no process stands beside this one.
    fake_process_group(monkeypatch, rank=0, size=2)
    odd = TrainConfig(**{**TINY.__dict__, "batch": 3})
    with pytest.raises(ValueError, match="batch 3 is not divisible by 2 processes"):
        train(odd, _images(), SensorModel(POINT, 200.0), gaussian_psf(K))
