"""Files of a learned model: checkpoints, ``model.pt``, ``psf.npy``, ``learn.json``.

The only module of ``psf_learn`` that writes or reads torch files. Everything is
stored as tensors and plain Python types, so it loads with
``torch.load(..., weights_only=True)`` (no pickled code).
"""

import os
import warnings
from pathlib import Path

import torch

from doe.infra.errors import InputError, first_line
from doe.infra.files import read_psf, sha256_file
from doe.records.learn import LEARN_JSON, read_learn

MODEL_FORMAT = "doefab-sr-1"


def save_checkpoint(path, state):
    """Write a checkpoint dict atomically (a kill leaves the old or the new one)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    _save(state, tmp, shown_as=path)
    os.replace(tmp, path)


def _save(obj, path, shown_as=None):
    """torch.save, but a refused write (full disk, read-only folder) is one line, file gone.

    torch reports it as a RuntimeError, not an OSError, and leaves the part written.
    """
    try:
        torch.save(obj, path)
    except (RuntimeError, OSError) as e:
        Path(path).unlink(missing_ok=True)
        reason = e.strerror if isinstance(e, OSError) and e.strerror else first_line(e)
        raise InputError(shown_as or path, f"cannot be written ({reason})") from None


def load_checkpoint(path):
    """Read a checkpoint dict written by :func:`save_checkpoint` (InputError if it is not one)."""
    try:
        state = _load(path)
    except Exception as e:
        state, reason = None, f"not readable: {type(e).__name__}: {first_line(e)}"
    else:
        reason = "not a doefab checkpoint"
    if not isinstance(state, dict) or not {"identity", "camera", "step"} <= state.keys():
        raise InputError(path, f"{reason}; --restart trains afresh and replaces it")
    return state


def _load(path):
    """torch.load of tensors and plain types only, without torch's warnings.

    A plain pickle (not torch's zip) makes torch warn on stderr, two lines before the
    one-line refusal.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torch.load(path, map_location="cpu", weights_only=True)


def model_record(net, net_config, sensor):
    """Return the plain dict stored as ``model.pt``: the network's weights and how to rebuild it."""
    return {
        "format": MODEL_FORMAT,
        "network": dict(net_config),
        "sensor": {
            "weights": [list(r) for r in sensor.weights],
            "photons": sensor.photons,
            "dark_counts": sensor.dark_counts,
        },
        "state_dict": {k: v.detach().cpu().clone() for k, v in net.state_dict().items()},
    }


def save_model(path, record):
    """Write ``model.pt`` (a :func:`model_record`)."""
    _save(record, path)


def load_model_dir(model_dir):
    """Read a model folder; return (record, psf, learn) with the model.pt dict and psf.npy.

    ``learn`` is the :class:`doe.records.learn.LearnRecord` of ``learn.json``, or None
    when absent; the files' hashes it records must be those of model.pt and psf.npy.
    """
    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise InputError(model_dir, "not a model folder (expected model.pt and psf.npy)")
    path = model_dir / "model.pt"
    if not path.exists():
        raise InputError(path, "missing: train a model with `doefab learn --out DIR` first")
    try:
        record = _load(path)
    except Exception as e:
        raise InputError(
            path, f"not a readable model ({type(e).__name__}: {first_line(e)})"
        ) from None
    if not isinstance(record, dict) or record.get("format") != MODEL_FORMAT:
        raise InputError(path, f"not a {MODEL_FORMAT} model file")
    psf = read_psf(model_dir / "psf.npy")
    learn_path = model_dir / LEARN_JSON
    learn = read_learn(learn_path) if learn_path.exists() else None
    recorded = learn.files if learn is not None else None
    if recorded is not None:  # older records hold no hashes
        for name in ("model.pt", "psf.npy"):
            if name in recorded and sha256_file(model_dir / name) != recorded[name]:
                raise InputError(
                    model_dir / name,
                    f"is not the file {learn_path.name} beside it was written with (another "
                    "training's?); keep psf.npy, model.pt and learn.json of one run together",
                )
    return record, psf, learn


def doefab_version():
    """Return the installed doefab's version (recorded in the files), or ``unknown``."""
    try:
        from importlib.metadata import version

        return version("doefab")
    except Exception:
        return "unknown"
