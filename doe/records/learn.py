"""``learn.json``: the record ``doefab learn`` writes beside ``psf.npy`` and ``model.pt``.

The one reader and the one writer of the file. Its keys (all written by every
``doefab learn``; older or hand-made records may lack any of them, and the
readers then skip what they would compare):

``config``
    the training's settings (:class:`psf_learn.train.TrainConfig` fields, the
    ``--psf`` given, kernel size, photon level, dark counts, sample cell, design
    name, ``--init`` folder).
``design``
    :func:`doe.derived.design_summary` of the design trained for: the sub-pixel
    grid ``psf.npy`` is sampled on, which the PSF-provenance checks compare.
``images``
    ``{"source", "count"}`` of the training images.
``steps``, ``seconds``
    steps trained and their wall-clock seconds (``doefab run`` moves the seconds
    out and leaves null).
``final_loss``, ``final_psnr_db``
    the mean L1 loss and PSNR (dB) over the last 50 steps (null where undefined).
``heldout``
    what the plate buys: ``{"images": {"source", "names"}, "model", "no_plate",
    "plate_gain_db"}``. ``model`` and ``no_plate`` are the scores of the trained
    model and of the no-plate (``delta`` PSF) model trained the same way on
    held-back images, ``{"psnr", "ssim", "psnr_y", "ssim_y", "images": {name:
    the four}}`` (``psnr_y``: the SR papers' MATLAB Y convention);
    ``plate_gain_db`` is ``{"psnr", "psnr_y"}``, model minus no-plate. ``no_plate``
    and ``plate_gain_db`` are null when ``--no-baseline`` left that model out.
``seed``, ``device``, ``versions``
    what the run repeats with.
``files``
    SHA-256 of ``model.pt`` and ``psf.npy``, so that files of another run beside
    this record are told apart (older records hold none).

doe does not import torch: the record holds plain JSON values only.
"""

import copy
from dataclasses import dataclass, field

from doe.infra.files import read_json, write_json

LEARN_JSON = "learn.json"  # its name in a model folder, beside psf.npy and model.pt


def _number(value):
    """Return ``value`` if it is a JSON number (not a bool), else None."""
    return value if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def _table(value):
    """Return ``value`` if it is a JSON object, else None."""
    return value if isinstance(value, dict) else None


@dataclass(frozen=True)
class LearnRecord:
    """The contents of a ``learn.json``.

    Each attribute is the key of that name, or None where the record lacks it or
    holds another type there (a partial or hand-edited record is read, not refused:
    the checks that use a key skip it when it is missing).

    Attributes
    ----------
    config : dict or None
        The training's settings.
    design : dict or None
        :func:`doe.derived.design_summary` of the design learned for.
    images : dict or None
        ``{"source": str, "count": int}`` of the training images.
    steps : int or None
        Steps trained.
    seconds : float or None
        Wall-clock seconds of the training (None once ``doefab run`` moved them).
    final_loss, final_psnr_db : float or None
        Mean loss and training PSNR (dB) of the last 50 steps.
    seed : int or None
        Random seed of the run.
    device : str or None
        Where it trained, e.g. ``cpu`` or ``cuda:0 (NVIDIA H100 80GB HBM3)``.
    versions : dict or None
        Versions of torch, numpy, Python and doefab.
    files : dict or None
        ``{"model.pt": sha256, "psf.npy": sha256}`` of the files written with it.
    heldout : dict or None
        The model and the no-plate model scored on held-back images, and the
        difference (see the module's ``heldout``).
    data : dict
        The whole JSON object, as read or given: what :func:`write_learn` writes.
    """

    config: dict | None
    design: dict | None
    images: dict | None
    steps: int | None
    seconds: float | None
    final_loss: float | None
    final_psnr_db: float | None
    seed: int | None
    device: str | None
    versions: dict | None
    files: dict | None
    data: dict = field(repr=False)
    heldout: dict | None = None

    @classmethod
    def from_dict(cls, data):
        """Return the record of a ``learn.json`` object (a dict, kept as a copy)."""
        data = copy.deepcopy(dict(data))
        device = data.get("device")
        return cls(
            config=_table(data.get("config")),
            design=_table(data.get("design")),
            images=_table(data.get("images")),
            steps=_number(data.get("steps")),
            seconds=_number(data.get("seconds")),
            final_loss=_number(data.get("final_loss")),
            final_psnr_db=_number(data.get("final_psnr_db")),
            seed=_number(data.get("seed")),
            device=device if isinstance(device, str) else None,
            versions=_table(data.get("versions")),
            files=_table(data.get("files")),
            data=data,
            heldout=_table(data.get("heldout")),
        )

    def to_dict(self):
        """Return the JSON object of the record (a copy)."""
        return copy.deepcopy(self.data)

    def plate_gain(self):
        """Return (model, no-plate model, gain) dicts of the held-back scores, or None.

        None when the record holds no no-plate model's scores (``--no-baseline``, an
        older record).
        """
        held = self.heldout or {}
        parts = [_table(held.get(k)) for k in ("model", "no_plate", "plate_gain_db")]
        return None if None in parts else tuple(parts)


def read_learn(path):
    """Read a ``learn.json``; return a :class:`LearnRecord`.

    Raises
    ------
    doe.infra.errors.InputError
        Naming ``path`` when it is missing, not JSON or not a JSON object.
    """
    return LearnRecord.from_dict(read_json(path))


def write_learn(path, record):
    """Write ``record`` (a :class:`LearnRecord` or its dict) as ``path``, atomically.

    Key-sorted, indented JSON (:func:`doe.infra.files.write_json`); non-finite
    figures are written as null.
    """
    data = record.to_dict() if isinstance(record, LearnRecord) else record
    write_json(path, data)
