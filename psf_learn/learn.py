"""Learn a PSF and a super-resolution network end to end: the library of ``doefab learn``.

Example
-------
>>> from psf_learn.learn import learn
>>> result = learn("model", steps=200, threads=1, seed=0)   # writes model/psf.npy, ...
>>> result.heldout["plate_gain_db"], result.record.files["psf.npy"]

Each keyword argument is the ``doefab learn`` flag of that name (``--psf-lr`` is
``psf_lr``, see :class:`LearnOptions`), and bad input raises
:class:`doe.infra.errors.InputError` naming the flag or file as the command does.
"""

import os
import platform
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from doe.derived import design_summary
from doe.infra.files import save_npy, sha256_file, staged_output
from doe.records.learn import LEARN_JSON, LearnRecord, write_learn
from psf_learn import heldout, store
from psf_learn.heldout import wants_baseline
from psf_learn.learn_plan import OUTPUTS, LearnOptions, plan_learning
from psf_learn.store import doefab_version
from psf_learn.train import device_name, train


@dataclass(frozen=True)
class LearnResult:
    """What :func:`learn` trained and wrote.

    Attributes
    ----------
    out : Path
        The output folder.
    psf_spec : str
        The ``psf`` argument: ``learned``, a baseline name or a PSF file.
    psf : (K, K) float64 array
        The PSF written as ``psf.npy`` (the learned one, or the fixed one as given).
    steps : int
        Steps trained in all (a resumed run counts those before the checkpoint).
    seconds : float
        Wall-clock seconds of the training.
    final_loss, final_psnr_db : float
        Mean L1 loss and training PSNR (dB) over the last 50 steps.
    device : str
        Where it trained, e.g. ``cpu``.
    record : LearnRecord or None
        The ``learn.json`` written; None on a torchrun process other than rank 0,
        which trains but writes nothing.
    notes : tuple of str
        What the command prints on stderr before training (a GPU run's note).
    heldout : dict
        learn.json's ``heldout``: the model and the no-plate model scored on held-back
        images, and the difference (:mod:`psf_learn.heldout`).
    """

    out: Path
    psf_spec: str
    psf: np.ndarray
    steps: int
    seconds: float
    final_loss: float
    final_psnr_db: float
    device: str
    record: LearnRecord | None
    notes: tuple
    heldout: dict | None = None


def learn(out, *, config=None, progress=None, on_note=None, **options):
    """Train a PSF and a super-resolution network; write psf.npy, model.pt and learn.json.

    Unless ``no_baseline``, the no-plate (``delta``) model is trained the same way too,
    and both are scored on held-back images (learn.json's ``heldout``).

    Parameters
    ----------
    out : path
        Output folder; a ``checkpoint.pt`` there resumes the same run (``restart``
        ignores it) and is removed once the outputs are written.
    config : path or str, optional
        Design TOML file or preset name (default: the default preset).
    progress : bool, optional
        Show a progress bar on stderr (default: when stderr is a terminal).
    on_note : callable, optional
        Called with each note on the run (a GPU steps run will not repeat) before
        the training starts; the notes are in the result too.
    **options
        The :class:`LearnOptions` fields: ``steps=200, threads=1, psf="box"``, ...

    Returns
    -------
    LearnResult

    Raises
    ------
    doe.infra.errors.InputError
        For bad settings or inputs, naming the flag or file as ``doefab learn``
        does, and for a training that diverges (naming ``--lr``).
    """
    opts = LearnOptions(**options)
    plan = plan_learning(Path(out), config, opts)
    notes = _notes(opts, plan.device)
    for note in notes if on_note is not None else ():
        on_note(note)
    result = _train(plan, progress)
    baseline = _train(plan, progress, heldout.train_baseline) if wants_baseline(opts) else None
    # A fixed PSF is written as given (a round trip through float32 logits moves it by ~4e-7).
    learned = plan.config.learn_psf
    psf = result.camera.psf.numpy() if learned else np.asarray(plan.psf0, dtype=np.float64)
    scores = heldout.heldout_record(
        plan,
        heldout.score(result.camera, psf, plan),
        heldout.score(baseline.camera, baseline.camera.psf.numpy(), plan) if baseline else None,
    )
    record = None
    if _leave_process_group():
        record = _write_outputs(plan, psf, result, scores)
        plan.checkpoint.unlink(missing_ok=True)
        plan.checkpoint.with_name(heldout.BASELINE_CHECKPOINT).unlink(missing_ok=True)
    return LearnResult(
        out=plan.out,
        psf_spec=opts.psf,
        psf=psf,
        steps=result.steps,
        seconds=result.seconds,
        final_loss=result.loss,
        final_psnr_db=result.psnr,
        device=device_name(plan.device),
        record=record,
        notes=tuple(notes),
        heldout=scores,
    )


def _notes(opts, device):
    """Return the notes a run gives before training: a GPU steps run will not repeat."""
    if opts.steps and device.type == "cuda" and os.environ.get("RANK", "0") == "0":
        return [
            f"note: training on {device_name(device)}: two runs of this command will differ "
            "(GPU gradients sum in a varying order; on an H100, PSFs 4e-4 apart after 150 "
            "steps); --device cpu repeats bit for bit"
        ]
    return []


def _train_model(plan, progress):
    """Train the plan's own model: :func:`psf_learn.train.train` of its PSF."""
    return train(
        plan.config,
        plan.scenes,
        plan.sensor,
        plan.psf0,
        init_state=plan.init_state,
        checkpoint=plan.checkpoint,
        progress=progress,
        device=plan.device,
    )


def _train(plan, progress, how=_train_model):
    """Run a training (``how(plan, progress)``); a first run that fails leaves no empty folder."""
    try:
        return how(plan, progress)
    except BaseException:
        if plan.created and not any(plan.out.iterdir()):
            plan.out.rmdir()
        raise


def _leave_process_group():
    """Return whether this process writes the outputs: the only one, or rank 0 of a job.

    The processes of a torchrun job wait for each other here and leave their group.
    """
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        rank = torch.distributed.get_rank()
        torch.distributed.barrier()
        torch.distributed.destroy_process_group()
        return rank == 0
    return True


def _record(plan, psf, result, scores):
    """Return the learn.json dict of a training, without the files' hashes."""
    opts, config, sensor = plan.opts, plan.config, plan.sensor
    return {
        "config": {
            **config.identity(),
            "psf": opts.psf,
            "kernel_size": int(psf.shape[0]),
            "photons_per_pixel": sensor.photons,
            "dark_counts": sensor.dark_counts,
            "sample_cell": list(sensor.sample_cell),
            "design": plan.design.name,
            "init": str(opts.init) if opts.init else None,
            "psf_start": opts.psf_start,
        },
        "design": design_summary(plan.design),
        "images": {"source": plan.source, "count": len(plan.names)},
        "steps": result.steps,
        "seconds": round(result.seconds, 3),
        "final_loss": result.loss,
        "final_psnr_db": result.psnr,
        "seed": config.seed,
        "heldout": scores,
        "device": device_name(plan.device),
        "versions": {
            "torch": torch.__version__,
            "numpy": np.__version__,
            "python": platform.python_version(),
            "doefab": doefab_version(),
        },
    }


def _write_outputs(plan, psf, result, scores):
    """Write psf.npy, model.pt and learn.json together; return the LearnRecord written."""
    info = _record(plan, psf, result, scores)
    with staged_output(plan.out, force=plan.opts.force, names=OUTPUTS) as stage:
        save_npy(stage / "psf.npy", psf)
        model = store.model_record(result.camera.net, result.camera.net_config, plan.sensor)
        store.save_model(stage / "model.pt", model)
        # so that a model.pt or psf.npy from another run is not taken for this one's
        info["files"] = {n: sha256_file(stage / n) for n in ("model.pt", "psf.npy")}
        record = LearnRecord.from_dict(info)
        write_learn(stage / LEARN_JSON, record)
    return record
