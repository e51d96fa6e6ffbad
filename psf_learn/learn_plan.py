"""Planning a training for ``doefab learn``: its settings and inputs, checked before it starts.

:func:`plan_learning` turns :class:`LearnOptions` (the command's flags) and a
design into a :class:`LearnPlan`: the training's configuration, the starting PSF
and network, the training images and an output folder it can write to. Each bad
setting or input is refused here, naming its flag or file, before any training.
"""

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from doe.design import load_design
from doe.design_match import check_psf_kernel
from doe.infra import flags
from doe.infra.errors import InputError
from doe.infra.files import _refuse_overwrite, check_out_folder, read_psf
from doe.records.learn import LEARN_JSON
from doe.records.psf_source import check_psf_grid
from psf_learn import images as imgio
from psf_learn import store
from psf_learn.network import FEATURES_MAX, STAGES_MAX, check_arch
from psf_learn.psf import START_KINDS, baseline_psf, gaussian_psf, starting_psf
from psf_learn.sensor import sensor_from_design
from psf_learn.sr import load_model
from psf_learn.train import (
    TrainConfig,
    augment_scales,
    default_patch,
    pick_device,
    with_overrides,
)

PSF_CHOICES = ("learned", "delta", "box", "gaussian")
OUTPUTS = ("psf.npy", "model.pt", LEARN_JSON)
# Sizes past these exhaust a workstation's memory (a traceback, not a message).
SIZE_LIMITS = (("batch", 1024), ("patch", 512), ("features", FEATURES_MAX), ("stages", STAGES_MAX))


@dataclass(frozen=True)
class LearnOptions:
    """The settings of a training: the flags of ``doefab learn`` (``--psf-lr`` is ``psf_lr``).

    Attributes
    ----------
    images : path, optional
        Folder of grayscale training images (default: the embedded set).
    psf : str
        ``learned`` (default), ``delta``, ``box``, ``gaussian``, ``gaussian:SIGMA``
        (sub-pixels), or a ``psf.npy`` file (fixed).
    minutes, steps : float or int, optional
        The budget, one or neither: wall-clock minutes (default: the design's
        ``[learning] minutes``) or a number of steps (deterministic on the CPU).
    seed : int, optional
        Random seed (default: the design's).
    init : path, optional
        A model folder to fine-tune.
    freeze_psf : bool
        Keep a ``learned`` PSF fixed.
    psf_start : str, optional
        Where a ``learned`` PSF starts: a baseline name, ``gaussian:SIGMA``, ``random``,
        ``dots[:N]`` or a ``psf.npy`` file (default: the Gaussian of sigma 0.459 centred
        on the axis; ``gaussian`` is the baseline, centred on the pixel).
    psf_until : float, optional
        Fraction of the run in which the PSF learns (default 1); the network alone
        trains on for the rest, for the PSF it ends with.
    features, stages, arch, batch, patch, lr, psf_lr : optional
        Network and training settings (defaults: :class:`psf_learn.train.TrainConfig`'s;
        the patch is the largest multiple of the factor up to 64).
    photons, dark_counts : float, optional
        Counts of a white pixel (default: the design's; 0 = no noise) and dark counts.
    threads : int, optional
        CPU threads (default: 1 with ``steps``, else the idle cores).
    device : {"auto", "cpu", "cuda"}
        Where to train; only CPU runs repeat bit for bit.
    restart, force : bool
        Ignore an existing checkpoint; overwrite existing outputs.
    eval_images : path, optional
        Folder of held-back images the model and the no-plate model are scored on
        (default: the embedded set's held-out photos).
    no_baseline : bool
        Leave out the no-plate (``delta``) model trained the same way for comparison.
    """

    images: object = None
    psf: str = "learned"
    minutes: float | None = None
    steps: int | None = None
    seed: int | None = None
    init: object = None
    freeze_psf: bool = False
    psf_start: str | None = None
    psf_until: float | None = None
    features: int | None = None
    stages: int | None = None
    arch: str | None = None
    batch: int | None = None
    patch: int | None = None
    lr: float | None = None
    psf_lr: float | None = None
    photons: float | None = None
    dark_counts: float = 0.0
    threads: int | None = None
    device: str = "auto"
    restart: bool = False
    force: bool = False
    eval_images: object = None
    no_baseline: bool = False


@dataclass(frozen=True)
class LearnPlan:
    """A training ready to run: every input checked, the output folder made.

    Attributes
    ----------
    out : Path
        The output folder (made; ``created`` says whether by this run).
    opts : LearnOptions
    design : doe.design.Design
    sensor : psf_learn.sensor.SensorModel
    config : TrainConfig
        The training's settings, the design's under the options'.
    init_state : dict or None
        The network weights to start from (``init``).
    psf0 : (K, K) array
        The starting, or fixed, PSF.
    names, scenes : list
        The training images' names and the scenes drawn from (2x-downscaled copies added).
    source : str
        Where the images came from (a folder, or the embedded set).
    created : bool
        Whether ``out`` was made by this run (a run that fails removes it if empty).
    device : torch.device
        Where it trains.
    eval_names, eval_scenes : tuple
        The held-back images scored after the training (:mod:`psf_learn.heldout`).
    eval_source : str
        Where they came from.
    """

    out: Path
    opts: LearnOptions
    design: object
    sensor: object
    config: TrainConfig
    init_state: dict | None
    psf0: np.ndarray
    names: list
    scenes: list
    source: str
    created: bool
    device: torch.device
    eval_names: tuple = ()
    eval_scenes: tuple = ()
    eval_source: str = ""

    @property
    def checkpoint(self):
        """Return the checkpoint file of the run, in ``out``."""
        return self.out / "checkpoint.pt"


def plan_learning(out, design_config, opts):
    """Check every setting and input of a training and make ``out``; return a :class:`LearnPlan`.

    Parameters
    ----------
    out : Path
        Output folder.
    design_config : path or str or None
        Design TOML file or preset name.
    opts : LearnOptions

    Raises
    ------
    doe.infra.errors.InputError
        Naming the flag or file at fault, the first in the order ``doefab learn``
        checks them.
    """
    _check_numbers(opts)
    # The thread count changes a run's last bits: a steps run (deterministic,
    # resumable) takes a fixed one, not one read from the load of the moment.
    torch.set_num_threads(opts.threads or (1 if opts.steps else idle_cores()))
    design = load_design(design_config)
    sensor = sensor_from_design(design, photons=opts.photons, dark_counts=opts.dark_counts)
    if sensor.photons <= 0 and sensor.dark_counts > 0:  # model.pt would record them all the same
        raise InputError("--dark-counts", "needs photon noise: --photons 0 simulates no counts")
    config = _train_config(opts, design, sensor)
    config, init_state, init_psf = _start_from_init(opts, design, sensor, config)
    psf0, learn_psf = _starting_psf(opts, design, sensor, init_psf)
    if opts.psf_until is not None and not learn_psf:  # a flag that would do nothing
        raise InputError("--psf-until", "sets how long a learned PSF learns; this one is fixed")
    config = with_overrides(config, learn_psf=learn_psf)
    names, scenes, source = _training_images(opts, config, psf0, sensor.factor)
    held_out = _held_out_images(opts, psf0.shape[0], sensor.factor)
    created = _ready_out(out, opts)
    device = torch.device("cpu") if opts.device == "cpu" else pick_device()
    return LearnPlan(
        out, opts, design, sensor, config, init_state, psf0, names, scenes, source, created, device,
        *held_out,
    )  # fmt: skip


def _check_numbers(opts):
    """Refuse numbers out of range and a CUDA device torch cannot see (InputError)."""
    if opts.minutes is not None and opts.steps is not None:  # the command's flags exclude it
        raise InputError("--minutes", "not with --steps: give one budget")
    for flag in ("steps", "minutes", "batch", "patch", "features", "stages", "threads"):
        flags.positive(f"--{flag}", getattr(opts, flag))
    for flag, limit in SIZE_LIMITS:
        flags.at_most(f"--{flag}", getattr(opts, flag), limit, "larger runs out of memory")
    flags.at_most("--minutes", opts.minutes, flags.MINUTES_MAX, "two years")
    flags.at_most("--steps", opts.steps, flags.STEPS_MAX, "years of training")
    flags.positive("--lr", opts.lr)
    flags.positive("--psf-lr", opts.psf_lr)
    flags.positive("--psf-until", opts.psf_until)
    flags.at_most("--psf-until", opts.psf_until, 1.0, "the whole run")
    for flag, value in (("--photons", opts.photons), ("--dark-counts", opts.dark_counts)):
        flags.at_most(flag, flags.non_negative(flag, value), flags.PHOTONS_MAX, "counts per pixel")
    flags.seed("--seed", opts.seed)
    if opts.device == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda", "torch sees no CUDA device on this machine")


def _train_config(opts, design, sensor):
    """Return the TrainConfig of the options over the design's; refuse what cannot train."""
    config = with_overrides(
        TrainConfig(minutes=design.learning.minutes, seed=design.learning.seed),
        steps=opts.steps,
        minutes=None if opts.steps else opts.minutes,
        seed=opts.seed,
        batch=opts.batch,
        patch=opts.patch or default_patch(sensor.factor),
        lr=opts.lr,
        psf_lr=opts.psf_lr,
        psf_until=opts.psf_until,
        features=opts.features,
        stages=opts.stages,
        arch=opts.arch,
    )
    if opts.steps:
        config = with_overrides(config, minutes=0.0)
    try:
        check_arch(config.arch, sensor.factor)  # found now, not by a step of the training
    except ValueError as e:
        raise InputError("--arch", str(e)) from None
    if config.patch % sensor.factor:
        raise InputError("--patch", f"must be a multiple of {sensor.factor}, got {config.patch}")
    world = int(os.environ.get("WORLD_SIZE", "1"))  # torchrun's processes share each batch
    if config.batch % world:
        raise InputError(
            "--batch", f"{config.batch} does not split among the {world} processes of this job"
        )
    return config


def _start_from_init(opts, design, sensor, config):
    """Return (config, network state, PSF) of the ``init`` model, or (config, None, None).

    Fine-tuning keeps the model's network: its factor must be the design's, and
    features, stages and arch given otherwise are refused.
    """
    if not opts.init:
        return config, None, None
    base = load_model(opts.init)
    check_psf_grid(Path(opts.init) / "psf.npy", design)  # as a fixed PSF file is
    record, _, _ = store.load_model_dir(opts.init)
    net = record["network"]
    if net["factor"] != sensor.factor:
        raise InputError(
            opts.init,
            f"the model super-resolves by {net['factor']}, the design by {sensor.factor}; "
            "pass the design it was trained for with --config",
        )
    for key in ("features", "stages", "arch"):
        given = getattr(opts, key)
        if given is not None and given != net[key]:
            raise InputError(
                f"--{key}",
                f"{given} differs from the --init model's {net[key]}; "
                "fine-tuning keeps the network, drop the flag",
            )
    network = {key: net[key] for key in ("features", "stages", "arch")}
    config = with_overrides(config, **network)
    return config, base.net.state_dict(), base.psf


def _starting_psf(opts, design, sensor, init_psf):
    """Return (starting PSF, whether it is learned) of the ``psf`` option."""
    spec, k = opts.psf, design.kernel_size
    if opts.psf_start and (spec != "learned" or init_psf is not None):
        why = "an --init model's PSF" if spec == "learned" else f"a fixed PSF (--psf {spec})"
        raise InputError("--psf-start", f"sets where a learned PSF starts, not {why}")
    if spec == "learned":
        psf0 = init_psf if init_psf is not None else gaussian_psf(k)
        if opts.psf_start:
            psf0 = _start_psf(opts.psf_start, design, sensor, opts.seed)
        learn_psf = not opts.freeze_psf
    elif spec in PSF_CHOICES or spec.startswith("gaussian:"):
        try:
            psf0 = baseline_psf(spec, k, sensor.weights)
        except ValueError as e:
            raise InputError("--psf", str(e)) from None
        learn_psf = False
    else:
        if not Path(spec).exists():  # a misspelt name, or a file that is not there
            raise InputError(
                "--psf", f"{spec!r} is no file and none of {', '.join(PSF_CHOICES)}, gaussian:SIGMA"
            )
        psf0, learn_psf = read_psf(spec), False
        check_psf_grid(spec, design)
    learned_from = Path(opts.init) / "psf.npy" if opts.init else None
    check_psf_kernel(psf0, learned_from if spec == "learned" else spec, design)
    return psf0, learn_psf


def _start_psf(spec, design, sensor, seed):
    """Return the PSF ``--psf-start`` names: a baseline, ``random``, ``dots[:N]`` or a file."""
    k = design.kernel_size
    named = spec in PSF_CHOICES[1:] + START_KINDS or spec.partition(":")[0] in ("gaussian", "dots")
    if not named:
        if not Path(spec).exists():
            raise InputError(
                "--psf-start",
                f"{spec!r} is no file and none of {', '.join(PSF_CHOICES[1:] + START_KINDS)}, "
                "gaussian:SIGMA, dots:N",
            )
        check_psf_grid(spec, design)
        psf = read_psf(spec)
        check_psf_kernel(psf, spec, design)
        return psf
    try:
        seed = design.learning.seed if seed is None else seed
        return starting_psf(spec, k, sensor.weights, seed)
    except ValueError as e:
        raise InputError("--psf-start", str(e)) from None


def _training_images(opts, config, psf0, factor):
    """Return (names, scenes with their 2x-downscaled copies, source) to train on."""
    margin = psf0.shape[0] - 1
    need = config.patch + margin  # a patch blurred by the PSF without padding
    why = f"--patch {config.patch} plus the PSF's {margin}-pixel margin"
    if opts.images:
        names, images = imgio.read_folder(opts.images, need, f"{why}; a smaller --patch fits")
        source = str(opts.images)
    else:
        names, images = imgio.default_images(seed=0)
        source = "embedded (scikit-image bundled photos + dead leaves)"
        smallest = min(min(img.shape) for img in images)
        if smallest < need:  # a batch would draw a patch larger than the image
            fits = (smallest - margin) // factor * factor
            raise InputError(
                "--patch",
                f"{why} needs images of {need} pixels, the smallest embedded one has "
                f"{smallest}: use --patch {fits} or less, or --images",
            )
    return names, augment_scales(images, config.patch + margin), source


def _held_out_images(opts, k, factor):
    """Return (names, images, source) of the held-back images the models are scored on.

    The capture mirrors each image by K // 2 at its borders: narrower ones cannot be.
    """
    if not opts.eval_images:
        names, images = imgio.held_out_images()
        return tuple(names), tuple(images), "embedded held-out photos (scikit-image)"
    need = max(4 * factor, k)
    why = "--eval-images: the capture mirrors each image by K // 2"
    names, images = imgio.read_folder(opts.eval_images, min_size=need, why=why)
    return tuple(names), tuple(images), str(opts.eval_images)


def _ready_out(out, opts):
    """Make the output folder, refusing one it cannot write to; return whether it was made.

    The checkpoint is written there during the training: a folder it cannot write to
    is refused now, not after the training.
    """
    check_out_folder(out)
    if not opts.force:
        _refuse_overwrite(out, OUTPUTS)
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as e:
        raise InputError(out, f"cannot write here ({e.strerror})") from None
    if opts.restart:  # every rank of a torchrun job gets here before any reads it
        (out / "checkpoint.pt").unlink(missing_ok=True)
        (out / "checkpoint_delta.pt").unlink(missing_ok=True)  # the no-plate model's
    return created


def idle_cores():
    """Return the CPU threads to use: OMP_NUM_THREADS if set, else the cores not busy now."""
    if os.environ.get("OMP_NUM_THREADS", "").isdigit():
        return max(1, int(os.environ["OMP_NUM_THREADS"]))
    cores = os.cpu_count() or 1
    try:
        busy = os.getloadavg()[0]
    except OSError:
        busy = 0.0
    return max(1, min(cores, int(cores - busy)))
