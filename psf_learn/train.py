"""End-to-end training of the PSF and the super-resolution network.

Determinism and resume. All randomness of a step is derived from
(seed, step, global sample index): the patch (image, position, flip) and the
photon noise of every sample get their own numpy generator, and the network is
initialised from ``torch.manual_seed(seed)``. A checkpoint therefore needs no
global RNG state: it stores the weights, the PSF, the Adam state, the step and
the elapsed time, and a resumed run repeats exactly what an uninterrupted one
would have done (bit for bit on the same machine's CPU, for a ``steps`` budget;
CUDA's convolution and bicubic-upsampling gradients sum in a varying order, so
runs on a GPU agree only to rounding that training amplifies). The
same keys make a DistributedDataParallel run over R processes (each taking
batch / R samples of the global batch) follow the single-process run.

Multi-GPU / multi-node: launch the same command with ``torchrun``; the process
group uses NCCL on CUDA and gloo on CPU.
"""

import hashlib
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from doe.infra.errors import InputError
from psf_learn import store
from psf_learn.network import SRNet
from psf_learn.psf import LearnedPSF
from psf_learn.sensor import simulate_capture


@dataclass(frozen=True)
class TrainConfig:
    """Hyper-parameters of a training run (plain values, stored in checkpoints and learn.json).

    ``steps`` set: a fixed number of steps (deterministic); else ``minutes`` of wall time.
    """

    steps: int | None = None
    minutes: float | None = 3.0
    seed: int = 0
    batch: int = 16
    patch: int = 64  # sub-pixels; learn takes default_patch(factor) when not given
    lr: float = 2e-3
    psf_lr: float = 0.05
    psf_until: float = 1.0  # fraction of the run the PSF learns; the network alone after it
    features: int = 24
    stages: int = 4
    arch: str = "resnet"
    learn_psf: bool = True
    checkpoint_seconds: float = 60.0

    def identity(self):
        """Return the fields that must match for a checkpoint to be resumed."""
        d = asdict(self)
        d.pop("checkpoint_seconds")
        return d


class CodedCamera(nn.Module):
    """Scene -> PSF -> SPAD capture -> super-resolved image, differentiable end to end."""

    def __init__(self, psf_init, sensor, config):
        super().__init__()
        self.sensor = sensor
        self.psf = LearnedPSF(psf_init, trainable=config.learn_psf)
        self.net = SRNet(sensor.factor, config.features, config.stages, config.arch)
        self.net_config = {
            "factor": sensor.factor,
            "features": config.features,
            "stages": config.stages,
            "arch": config.arch,
        }

    def forward(self, scenes, seeds):
        """Map (B, 1, P + K - 1, P + K - 1) scenes to (B, 1, P, P) estimates of their centres."""
        frames = simulate_capture(scenes, self.psf(), self.sensor, padding="valid", seeds=seeds)
        return self.net(frames)

    def centres(self, scenes):
        """Return the (B, 1, P, P) centres of scenes that :meth:`forward` estimates."""
        m = self.psf.logits.shape[-1] // 2  # the valid convolution trims K // 2 per side
        return scenes[..., m : scenes.shape[-2] - m, m : scenes.shape[-1] - m]


def augment_scales(images, min_size):
    """Return the images plus 2x-downscaled copies (area mean) still at least ``min_size``."""
    out = list(images)
    for img in images:
        h, w = (img.shape[0] // 2) * 2, (img.shape[1] // 2) * 2
        if min(h, w) // 2 >= min_size:
            out.append(img[:h, :w].reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3)))
    return out


def make_batch(images, keys, size):
    """Return a float32 (B, 1, size, size) batch: one random patch per key.

    ``keys[b]`` seeds the choice of image, position, flips and transpose.
    """
    batch = np.empty((len(keys), 1, size, size), dtype=np.float32)
    for b, key in enumerate(keys):
        rng = np.random.default_rng(np.random.SeedSequence(key))
        img = images[rng.integers(len(images))]
        r = rng.integers(img.shape[0] - size + 1)
        c = rng.integers(img.shape[1] - size + 1)
        p = img[r : r + size, c : c + size]
        if rng.integers(2):
            p = p[::-1]
        if rng.integers(2):
            p = p[:, ::-1]
        if rng.integers(2):
            p = p.T
        batch[b, 0] = p
    return torch.from_numpy(batch)


def psnr_from_mse(mse):
    """Return the PSNR (dB) of a mean squared error on a [0, 1] scale."""
    return 10 * math.log10(1.0 / max(mse, 1e-12))


def lr_factor(progress):
    """Cosine decay from 1 to 0.05 over the run, after a 2 % linear warm-up."""
    progress = min(max(progress, 0.0), 1.0)
    if progress < 0.02:
        return 0.05 + 0.95 * progress / 0.02
    return 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * (progress - 0.02) / 0.98))


@dataclass
class TrainResult:
    """The trained camera and a summary of the run."""

    camera: CodedCamera
    steps: int
    seconds: float
    loss: float
    psnr: float
    history: list


def _dist_setup(device):
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not torch.distributed.is_initialized():
        backend = "nccl" if device.type == "cuda" else "gloo"
        torch.distributed.init_process_group(backend)
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


def pick_device():
    """Return the CUDA device of this process (LOCAL_RANK) if available, else the CPU."""
    if torch.cuda.is_available():
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    return torch.device("cpu")


def device_name(device):
    """Return ``cpu`` or e.g. ``cuda:0 (NVIDIA H100 80GB HBM3)``, for the record of a run."""
    if device.type == "cuda":
        return f"{device} ({torch.cuda.get_device_name(device)})"
    return str(device)


def _digest(arrays):
    """Return the SHA-256 of arrays' shapes, types and bytes (a run's identity)."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.shape}{a.dtype.str}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def train(
    config,
    images,
    sensor,
    psf_init,
    init_state=None,
    checkpoint=None,
    stop_at_step=None,
    progress=None,
    device=None,
):
    """Train a coded camera; return a :class:`TrainResult` (same on every rank).

    The returned camera is on the CPU, whatever device trained it.

    Parameters
    ----------
    config : TrainConfig
    images : list of float32 (H, W) arrays in [0, 1]
        Training scenes on the sub-pixel grid, each at least patch + K - 1 wide.
    sensor : SensorModel
    psf_init : (K, K) array
        Initial (or, when ``config.learn_psf`` is False, fixed) PSF.
    init_state : dict, optional
        Network state_dict to start from (fine-tuning).
    checkpoint : path, optional
        Checkpoint file: resumed from when it exists and matches ``config``,
        written every ``config.checkpoint_seconds`` and at the end (rank 0).
    stop_at_step : int, optional
        Stop (and checkpoint) after this step, as if interrupted.
    progress : bool, optional
        Show a tqdm bar (default: when stderr is a terminal).
    device : torch.device or str, optional
        Where to train (default :func:`pick_device`: this process's GPU if there is one).
        Only CPU runs repeat bit for bit.
    """
    device = pick_device() if device is None else torch.device(device)
    rank, world = _dist_setup(device)
    if config.batch % world:
        raise ValueError(f"batch {config.batch} is not divisible by {world} processes")
    torch.manual_seed(config.seed)
    camera = CodedCamera(psf_init, sensor, config)
    if init_state is not None:
        camera.net.load_state_dict(init_state)
    camera.to(device)
    opt = _optimizer(camera, config)
    identity = _identity(config, images, sensor, psf_init, init_state)
    run = _Run(*_start(checkpoint, identity, camera, opt, rank))
    model = camera
    if world > 1:
        model = nn.parallel.DistributedDataParallel(
            camera, device_ids=[device.index] if device.type == "cuda" else None
        )

    def save():
        if checkpoint is not None and rank == 0:
            store.save_checkpoint(checkpoint, run.checkpoint(identity, camera, opt))

    by_steps = config.steps is not None
    budget = None if by_steps else 60.0 * (config.minutes or 0)
    bar = _progress_bar(config, run, budget, progress, rank)
    k = np.asarray(psf_init).shape[0]
    batch = _Batch(images, config.seed, config.patch + k - 1, rank, config.batch // world)
    last_save = time.monotonic()
    while True:
        done, frac = _budget_spent(config, run, budget, world, device)
        if done or (stop_at_step is not None and run.step >= stop_at_step):
            break
        t0 = time.monotonic()
        psf_learns = frac < config.psf_until
        for g in opt.param_groups:
            g["lr"] = g["base"] * lr_factor(frac)
        figures = _step(
            camera, model, opt, batch, run.step, device, init_state is not None, psf_learns
        )
        if world > 1:  # the global batch's figures, as one process would have them
            torch.distributed.all_reduce(figures)
            figures = figures / world
        run.history.append([float(figures[0]), psnr_from_mse(float(figures[1]))])
        run.step += 1
        dt = time.monotonic() - t0
        run.elapsed += dt
        if rank == 0 and bar.disable is False:
            _show(bar, run, 1 if by_steps else min(dt, max(budget - bar.n, 0)))
        if time.monotonic() - last_save > config.checkpoint_seconds:
            save()
            last_save = time.monotonic()
    bar.close()
    save()
    recent = run.history[-50:] or [[float("nan"), float("nan")]]
    return TrainResult(
        camera.cpu(),
        run.step,
        run.elapsed,
        float(np.mean([h[0] for h in recent])),
        float(np.mean([h[1] for h in recent])),
        run.history,
    )


def _optimizer(camera, config):
    """Return the Adam optimiser of the network (and the PSF's logits, if learned).

    Each group keeps its ``base`` learning rate, which :func:`lr_factor` scales.
    """
    groups = [{"params": list(camera.net.parameters()), "lr": config.lr, "base": config.lr}]
    if config.learn_psf:
        groups.append({"params": [camera.psf.logits], "lr": config.psf_lr, "base": config.psf_lr})
    return torch.optim.Adam(groups)


@dataclass
class _Run:
    """Where a training stands: steps done, seconds spent, (loss, PSNR) of each step."""

    step: int
    elapsed: float
    history: list

    def checkpoint(self, identity, camera, opt):
        """Return the checkpoint dict of the run at this point."""
        return {
            "identity": identity,
            "camera": camera.state_dict(),
            "optimizer": opt.state_dict(),
            "step": self.step,
            "elapsed": self.elapsed,
            "history": self.history,
            "threads": torch.get_num_threads(),
        }


@dataclass(frozen=True)
class _Batch:
    """The scenes of this process's share of each step's global batch.

    Sample i of step s is keyed (seed, s, i, 0) for its patch and (seed, s, i, 1) for
    its noise, whatever process draws it.
    """

    images: list
    seed: int
    size: int
    rank: int
    local: int

    def keys(self, step, use):
        """Return the keys of this process's samples of ``step`` (``use`` 0: patch, 1: noise)."""
        ids = range(self.rank * self.local, (self.rank + 1) * self.local)
        return [(self.seed, step, i, use) for i in ids]


def _identity(config, images, sensor, psf_init, init_state):
    """Return what a checkpoint must match to be resumed: the same run.

    Hyper-parameters, sensor, starting PSF, images and starting network: a
    checkpoint of another run is ignored, not resumed with the wrong weights.
    """
    return {
        "images": _digest(images),
        "init": _digest(v.detach().cpu().numpy() for v in init_state.values())
        if init_state is not None
        else None,
        "config": config.identity(),
        "sensor": [
            np.asarray(sensor.weights, dtype=np.float64).tolist(),
            float(sensor.photons),
            float(sensor.dark_counts),
        ],
        "psf_init": np.asarray(psf_init, dtype=np.float64).tolist(),
    }


def _start(checkpoint, identity, camera, opt, rank):
    """Return (step, elapsed, history): a checkpoint of this run's, resumed, or a fresh start.

    Rank 0 says on stderr what it did with a checkpoint it found.
    """
    if checkpoint is None or not os.path.exists(checkpoint):
        return 0, 0.0, []
    state = store.load_checkpoint(checkpoint)
    if state.get("identity") != identity:
        if rank == 0:
            print(f"ignoring {checkpoint}: it belongs to another configuration", file=sys.stderr)
        return 0, 0.0, []
    step, elapsed, history = _resume(state, camera, opt, checkpoint)
    if rank == 0:
        print(f"resuming from {checkpoint} at step {step}", file=sys.stderr)
        threads = state.get("threads")
        if threads is not None and threads != torch.get_num_threads():
            print(
                f"note: the checkpoint was written with {threads} threads, this run "
                f"has {torch.get_num_threads()}; the result will differ in the last "
                "bits from an uninterrupted run",
                file=sys.stderr,
            )
    return step, elapsed, history


def _progress_bar(config, run, budget, progress, rank):
    """Return the tqdm bar of a run: steps, or seconds of a time budget (rank 0 only)."""
    from tqdm import tqdm

    by_steps = budget is None
    show = sys.stderr.isatty() if progress is None else progress
    return tqdm(
        total=config.steps if by_steps else round(budget),
        initial=run.step if by_steps else min(round(run.elapsed), round(budget)),
        disable=not show or rank != 0,
        unit="step" if by_steps else "s",
        file=sys.stderr,
        dynamic_ncols=True,
    )


def _show(bar, run, advance):
    """Advance the bar, showing the mean loss and PSNR of the last 50 steps."""
    recent = run.history[-50:]
    bar.set_postfix(
        loss=f"{np.mean([h[0] for h in recent]):.4f}",
        psnr=f"{np.mean([h[1] for h in recent]):.2f}",
    )
    bar.update(advance)


def _budget_spent(config, run, budget, world, device):
    """Return (whether the budget is spent, the fraction of it spent) for this step.

    Rank 0's clock decides for all: every rank runs the same number of steps at
    the same learning rate.
    """
    by_steps = budget is None
    done = run.step >= config.steps if by_steps else run.elapsed >= budget
    frac = run.step / max(config.steps, 1) if by_steps else run.elapsed / max(budget, 1e-9)
    if world > 1:
        shared = torch.tensor([float(done), frac], dtype=torch.float64, device=device)
        torch.distributed.broadcast(shared, 0)
        done, frac = bool(shared[0].item()), float(shared[1].item())
    return done, frac


def _step(camera, model, opt, batch, step, device, fine_tuning, psf_learns=True):
    """Take one optimiser step; return the batch's (L1 loss, MSE of the clipped estimate).

    Past ``psf_until`` (``psf_learns`` False) the PSF's gradient is dropped before the
    clipping, so the network's steps are those of a fixed PSF.

    Raises InputError naming ``--lr`` when the gradients are no longer finite.
    """
    scenes = make_batch(batch.images, batch.keys(step, 0), batch.size).to(device)
    target = camera.centres(scenes)
    estimate = model(scenes, batch.keys(step, 1))
    loss = F.l1_loss(estimate, target)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    if not psf_learns:
        camera.psf.logits.grad = None  # Adam then leaves the PSF and its moments alone
    # long runs at a high learning rate spike without this
    norm = nn.utils.clip_grad_norm_(camera.parameters(), 1.0)
    if not torch.isfinite(norm):  # the same on every rank: the gradients are shared
        # One more step would make the PSF NaN, and the next capture's Poisson draw raise.
        raise InputError(
            "--lr",
            f"the training diverged at step {step + 1} (gradients no longer finite): "
            "lower --lr or --psf-lr"
            + (", or start from another --init model" if fine_tuning else ""),
        )
    opt.step()
    return torch.stack([loss.detach(), F.mse_loss(estimate.detach().clamp(0, 1), target)])


def _resume(state, camera, opt, path):
    """Load checkpoint ``state`` of this run into camera and opt; return (step, elapsed, history).

    Its identity matched, but what it holds must be what :func:`train` saves: else
    loading would raise (exit 3), NaN weights would train on to a NaN model, and a NaN
    elapsed time would never reach a --minutes budget. InputError naming ``path`` if not.
    """
    try:
        camera.load_state_dict(state["camera"])
        opt.load_state_dict(state["optimizer"])
        step, elapsed = state["step"], float(state["elapsed"])
        history = [[float(loss), float(psnr)] for loss, psnr in state["history"]]
        usable = (
            isinstance(step, int)
            and len(history) == step  # one row a step
            and math.isfinite(elapsed)
            and elapsed >= 0
            and not np.isnan(history).any()  # a PSNR may be inf (an exact batch), not NaN
            and all(bool(torch.isfinite(v).all()) for v in camera.state_dict().values())
            # Adam's moments of another shape load, then fail in the first step
            and all(
                v.shape == p.shape
                for p, s in opt.state.items()
                for k, v in s.items()
                if k != "step"
            )
        )
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError):
        usable = False  # torch's loaders raise any of these on what they cannot take
    if not usable:
        raise InputError(path, "damaged (not what a run saves); --restart trains afresh")
    return step, elapsed, history


def default_patch(factor, limit=64):
    """Return the largest multiple of ``factor`` up to ``limit`` sub-pixels (64 at factor 4).

    The patch must hold whole SPAD pixels; keeping it near 64 keeps a step's cost
    about the same for every super-resolution factor.
    """
    return max(factor, limit // factor * factor)


def with_overrides(config, **overrides):
    """Return ``config`` with the given non-None fields replaced."""
    return replace(config, **{k: v for k, v in overrides.items() if v is not None})
