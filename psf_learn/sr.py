"""Super-resolve SPAD frames with a learned model: the Python API and ``doefab sr``'s library.

Example
-------
>>> from psf_learn.sr import super_resolve, super_resolve_files
>>> hr = super_resolve("model_dir", counts)   # counts (..., h, w) -> (..., 4 h, 4 w)
>>> done = super_resolve_files("model_dir", ["a.npy", "b.png"], "sr_out")
>>> done.outputs   # a_sr.npy, a_sr.png, a_sr.json, b_sr.npy, ...
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from doe.infra.flags import PHOTONS_MAX
from doe.records.learn import LearnRecord
from psf_learn.network import FEATURES_MAX, STAGES_MAX, SRNet, check_arch
from psf_learn.sensor import SensorModel


@dataclass(frozen=True)
class SRModel:
    """A loaded model: the network, the PSF it was trained with, its sensor model.

    ``learn`` is the :class:`doe.records.learn.LearnRecord` of the folder's
    ``learn.json``, None for a model without one (saved from Python).
    """

    net: SRNet
    psf: np.ndarray
    sensor: SensorModel
    learn: LearnRecord | None


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

    Checked before the network is built: 10**6 features would ask torch for terabytes,
    10**6 stages would build modules for minutes, and a missing key would take SRNet's
    default.
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

    load_state_dict takes what it is given: NaN weights would write NaN images (exit 0),
    complex ones lose their imaginary part and integer ones their fractions.
    """
    if not isinstance(state, dict):
        raise ValueError(f"state_dict must be a table of tensors, got {type(state).__name__}")
    for name, value in state.items():
        if not isinstance(name, str):  # load_state_dict would raise AttributeError (exit 3)
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

    float() takes "100" and True, and raises OverflowError on a 400-digit integer.
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


# A frame whose 99th-percentile counts pass this many times its white level is noted.
OVER_WHITE = 2.0


@dataclass(frozen=True)
class SRFrame:
    """One input of :func:`super_resolve_files` and what was written for it.

    Attributes
    ----------
    input : path
        The raw frame file.
    stem : str
        Its name without suffix: the outputs are ``<stem>_sr.npy``, ``.png``, ``.json``.
    input_shape, output_shape : tuple of int
        Shapes of the counts read and of the super-resolved array.
    notes : tuple of str
        Notes on the frame (far brighter than the white the network was trained at).
    """

    input: object
    stem: str
    input_shape: tuple
    output_shape: tuple
    notes: tuple


@dataclass(frozen=True)
class SRResult:
    """What :func:`super_resolve_files` wrote.

    Attributes
    ----------
    out : Path
        The output folder.
    outputs : tuple of str
        The files written, three per input in the inputs' order.
    frames : tuple of SRFrame
        One per input.
    """

    out: Path
    outputs: tuple
    frames: tuple


def super_resolve_files(
    model_dir, raw, out, *, photons=None, force=False, progress=None, on_note=None, on_frame=None
):
    """Super-resolve raw frame files into a folder: ``<stem>_sr.npy``, ``.png`` and ``.json``.

    Each output has its own JSON record (model, its hash, photon level, input and
    its hash, shapes, the files' hashes, notes), so that one folder can gather
    several batches. Nothing is written unless every input succeeds.

    Parameters
    ----------
    model_dir : path
        A folder written by ``doefab learn``.
    raw : list of paths
        Raw frames: ``.npy`` (H, W) or (T, H, W), or image files; their stems must differ.
    out : path
        Output folder.
    photons : float, optional
        Counts of a white scene (default: the model's).
    force : bool
        Overwrite existing outputs.
    progress : bool, optional
        Show a progress bar of inputs (default: when stderr is a terminal).
    on_note : callable, optional
        Called with each note on a frame, before that frame is super-resolved.
    on_frame : callable, optional
        Called with each :class:`SRFrame` once its files are staged.

    Returns
    -------
    SRResult
    """
    import torch
    from tqdm import tqdm

    from doe.infra import flags
    from doe.infra.errors import InputError
    from doe.infra.files import save_npy, sha256_file, staged_output, write_json
    from psf_learn import images as imgio
    from psf_learn.store import doefab_version

    flags.positive("--photons", photons)
    flags.at_most("--photons", photons, flags.PHOTONS_MAX, "counts per pixel")
    torch.set_num_threads(1)
    model = load_model(model_dir)
    model_file = Path(model_dir) / "model.pt"
    stems = _distinct_stems(raw)
    frames = [imgio.read_raw(r) for r in raw]
    names = [f"{s}_sr{ext}" for s in stems for ext in (".npy", ".png", ".json")]
    record = {
        "model": str(model_dir),
        "model_sha256": sha256_file(model_file),
        "photons": white_counts(model, photons),
        "dark_counts": model.sensor.dark_counts,
        "doefab": doefab_version(),
    }
    done = []
    disable = None if progress is None else not progress
    with staged_output(out, force=force, names=names) as stage:
        bar = tqdm(frames, desc="sr", unit="input", disable=disable)
        for raw_path, stem, counts in zip(raw, stems, bar, strict=True):
            notes = exposure_notes(counts, raw_path, record["photons"], model.sensor.dark_counts)
            for note in notes:
                if on_note is not None:
                    on_note(note)
            hr = super_resolve(model, counts, photons=photons)
            if not np.isfinite(hr).all():  # weights (or counts) past float32's range
                raise InputError(model_file, f"gives non-finite values on {raw_path}")
            made = (f"{stem}_sr.npy", f"{stem}_sr.png")
            save_npy(stage / made[0], hr)
            _write_preview(stage / made[1], hr if hr.ndim == 2 else hr.mean(axis=0))
            write_json(
                stage / f"{stem}_sr.json",
                {
                    **record,
                    "input": str(raw_path),
                    "input_sha256": sha256_file(raw_path),
                    "input_shape": list(counts.shape),
                    "output_shape": list(hr.shape),
                    "files": {n: sha256_file(stage / n) for n in made},
                    "notes": notes,
                },
            )
            frame = SRFrame(raw_path, stem, counts.shape, hr.shape, tuple(notes))
            done.append(frame)
            if on_frame is not None:
                on_frame(frame)
    return SRResult(Path(out), tuple(names), tuple(done))


def _distinct_stems(raw):
    """Return the inputs' stems; refuse two that share one (their outputs would collide)."""
    from doe.infra.errors import InputError

    stems = [Path(r).stem for r in raw]
    for i, stem in enumerate(stems):
        if stem in stems[:i]:
            first = raw[stems.index(stem)]
            raise InputError(raw[i], f"shares its name with {first}; their outputs would collide")
    return stems


def exposure_notes(raw, raw_path, white, dark_counts):
    """Return a note when a frame is far brighter than the white the network was trained on.

    A camera frame of 16-bit codes, or a SPAD exposed longer than the model's photon
    level, is no scene the network has seen (none was brighter than white), and its
    output then means little.
    """
    top = float(np.percentile(raw, 99)) - dark_counts
    if not top > OVER_WHITE * white:
        return []
    return [
        f"{raw_path}: 1 % of its counts exceed {top:.4g}, {top / white:.3g} times the white "
        f"level {white:g} the network was trained at: give --photons as the counts a white "
        "scene gives these frames"
    ]


def _write_preview(path, image):
    """Write an 8-bit PNG scaled to the image's 99.9th percentile (a viewing aid)."""
    from skimage import io

    top = float(np.percentile(image, 99.9)) or 1.0
    io.imsave(
        path, (np.clip(image / top, 0, 1) * 255).round().astype(np.uint8), check_contrast=False
    )
