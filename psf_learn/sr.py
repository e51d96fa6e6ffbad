"""Super-resolve SPAD frames with a learned model: the Python API.

Example
-------
>>> from psf_learn.sr import super_resolve
>>> hr = super_resolve("model_dir", counts)   # counts (..., h, w) -> (..., 4 h, 4 w)
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from doe.infra.flags import PHOTONS_MAX
from psf_learn.network import FEATURES_MAX, STAGES_MAX, SRNet, check_arch
from psf_learn.sensor import SensorModel


@dataclass(frozen=True)
class SRModel:
    """A loaded model: the network, the PSF it was trained with, its sensor model."""

    net: SRNet
    psf: np.ndarray
    sensor: SensorModel
    learn: dict | None


def load_model(model_dir):
    """Load a model folder written by ``doefab learn`` (raises InputError if unusable)."""
    from doe.infra.errors import InputError
    from psf_learn import store

    record, psf, learn = store.load_model_dir(model_dir)
    try:
        _check_network(record["network"])
        s = record["sensor"]
        sensor = SensorModel(
            tuple(tuple(r) for r in s["weights"]), _count(s, "photons"), _count(s, "dark_counts")
        )
        _check_sensor(sensor, record["network"]["factor"])
        _check_weights(record["state_dict"])
        net = SRNet(**record["network"])
        net.load_state_dict(record["state_dict"])
    except (KeyError, TypeError, RuntimeError, ValueError) as e:
        raise InputError(Path(model_dir) / "model.pt", f"inconsistent model ({e})") from None
    net.eval()
    return SRModel(net, psf, sensor, learn)


def _check_network(network):
    """Raise ValueError unless ``network`` is a configuration ``learn`` writes.

    Checked before the network is built: 10**6 features asked torch for terabytes,
    10**6 stages built modules for minutes, and a missing key took SRNet's default.
    """
    keys = ("factor", "features", "stages", "arch")
    if not isinstance(network, dict) or set(network) != set(keys):
        raise ValueError(f"network must hold {', '.join(keys)} and nothing else")
    for key, limit in (("factor", None), ("features", FEATURES_MAX), ("stages", STAGES_MAX)):
        value = network[key]
        if not _is_int(value) or value < 1 or (limit is not None and value > limit):
            upto = f" to {limit}" if limit is not None else ""
            raise ValueError(f"network {key} must be a whole number from 1{upto}, got {value!r}")
    check_arch(network["arch"], network["factor"])


def _check_weights(state):
    """Raise ValueError unless every entry of ``state`` is a tensor of finite floats.

    load_state_dict takes what it is given: NaN weights wrote NaN images (exit 0),
    complex ones lost their imaginary part and integer ones their fractions.
    """
    if not isinstance(state, dict):
        raise ValueError(f"state_dict must be a table of tensors, got {type(state).__name__}")
    for name, value in state.items():
        if not isinstance(name, str):  # load_state_dict raised AttributeError (exit 3)
            raise ValueError(f"state_dict keys must be parameter names, got {name!r}")
        if not (isinstance(value, torch.Tensor) and value.is_floating_point()):
            kind = value.dtype if isinstance(value, torch.Tensor) else type(value).__name__
            raise ValueError(f"state_dict {name} must be a float tensor, got {kind}")
        if not bool(torch.isfinite(value).all()):
            raise ValueError(f"state_dict {name} holds NaN or infinite weights")


def _is_int(value):
    return isinstance(value, int) and not isinstance(value, bool)


def _check_sensor(sensor, factor):
    """Raise ValueError unless the sensor record is one the network can be run with."""
    w = np.asarray(sensor.weights, dtype=np.float64)
    if w.shape != (factor, factor) or not (np.isfinite(w).all() and (w >= 0).all()):
        raise ValueError(f"sensor weights must be {factor} x {factor} finite values >= 0")
    if not abs(w.sum() - 1) < 1e-6:
        raise ValueError(f"sensor weights sum to {w.sum():g}, not 1")
    for name in ("photons", "dark_counts"):
        value = getattr(sensor, name)
        # learn's own limit: past it numpy's Poisson draws fail (evaluate, exit 3)
        if not (np.isfinite(value) and 0 <= value <= PHOTONS_MAX):
            raise ValueError(
                f"sensor {name} must be a number from 0 to {PHOTONS_MAX:g}, got {value}"
            )


def _count(record, name):
    """Return ``record[name]`` as a float, or raise ValueError unless it is a number.

    float() took "100" and True, and raised OverflowError (exit 3) on a 400-digit integer.
    """
    value = record[name]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"sensor {name} must be a number, got {value!r}")
    try:
        return float(value)
    except OverflowError:
        raise ValueError(f"sensor {name} is past any float") from None


def white_counts(model, photons=None):
    """Return the counts that mean a white scene: ``photons``, or the model's by default."""
    if photons is None:
        # A model trained without noise (photons 0) saw frames scaled to white = 1.
        return float(model.sensor.photons or 1.0)
    if not (np.isfinite(photons) and photons > 0):
        raise ValueError(f"photons must be a finite number > 0, got {photons}")
    return float(photons)


def super_resolve(model, frames, photons=None, chunk=16):
    """Super-resolve SPAD frames of photon counts.

    Parameters
    ----------
    model : SRModel or path
        A loaded model or a model folder.
    frames : (..., h, w) array
        Photon counts per SPAD pixel and frame (any h, w >= 2).
    photons : float, optional
        Counts that mean a white scene, > 0 (default: the photon level the model
        was trained at, or 1 for a model trained without noise). Counts are
        divided by it (after removing the model's dark counts) before the
        network and multiplied back afterwards.

    Returns
    -------
    (..., f h, f w) float64 array
        The scene on the sub-pixel grid, in the same count units as ``frames``
        (counts a whole SPAD pixel would collect from it).
    """
    if not isinstance(model, SRModel):
        model = load_model(model)
    frames = np.asarray(frames, dtype=np.float64)
    if frames.ndim < 2:
        raise ValueError(f"frames must be (..., h, w), got shape {frames.shape}")
    photons = white_counts(model, photons)
    f = model.sensor.factor
    lead, (h, w) = frames.shape[:-2], frames.shape[-2:]
    flat = frames.reshape(-1, 1, h, w)
    out = np.empty((flat.shape[0], 1, f * h, f * w))
    with torch.no_grad():
        for i in range(0, flat.shape[0], chunk):
            x = (flat[i : i + chunk] - model.sensor.dark_counts) / photons
            y = model.net(torch.from_numpy(x).float())
            out[i : i + chunk] = y.double().numpy() * photons
    return out.reshape(*lead, f * h, f * w)
