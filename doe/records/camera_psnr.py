"""``camera_psnr.json``: a learned model's reconstruction PSNR with the plate in a camera.

``doefab camera-psnr`` writes it (:func:`write_camera_psnr`); ``doefab fab
--camera-psnr`` reads it (:func:`read_camera_psnr`) into the report's "In the camera"
section. The file is a JSON object (indented, keys sorted) with

- ``levels_sha256``, ``levels_shape``: the tile the effective PSFs were computed for
  (the reader refuses a file made for another tile);
- ``model_dir``; ``images``: ``source`` (a folder, or the embedded held-back photos),
  ``names`` and ``crop`` (the centre crop scored, in pixels);
- ``model_psf``: ``psnr`` with the model's own PSF; ``nominal``: ``psnr`` and
  ``collected_fraction`` in the nominal camera (the design wavelength, the square
  clear aperture, in focus, unrotated);
- ``allowance_db``: the PSNR loss from the nominal camera a setting may cost;
- ``axes``: per setting (``bandwidth_nm``, ``f_number``, ``defocus_um``,
  ``rotation_deg``) its ``values``, their ``psnr`` (dB, mean over the images) and
  ``within_budget`` (:func:`doe.camera_budget.budget_range` of the loss: ``range``,
  ``ends``, ``why``);
- ``seconds``, ``versions``.
"""

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from doe.infra.errors import InputError
from doe.infra.files import read_json, write_json

CAMERA_PSNR_JSON = "camera_psnr.json"
_KEYS = ("levels_sha256", "nominal", "model_psf", "allowance_db", "axes", "images", "model_dir")


def levels_digest(levels):
    """Return the SHA-256 of a level map (its uint8 values, row-major) as hex."""
    return hashlib.sha256(np.ascontiguousarray(levels, dtype=np.uint8).tobytes()).hexdigest()


@dataclass(frozen=True)
class CameraPsnrRecord:
    """One ``camera_psnr.json``: its path and the whole object."""

    path: Path
    data: dict = field(default_factory=dict, repr=False)


def read_camera_psnr(path, levels=None):
    """Read a ``camera_psnr.json`` (or the folder holding one).

    InputError naming the file when it is missing, not a JSON object, lacks a key or
    (with ``levels``) was made for another tile.
    """
    path = Path(path)
    if path.is_dir():
        path = path / CAMERA_PSNR_JSON
    obj = read_json(path)
    missing = [k for k in _KEYS if k not in obj]
    if missing:
        raise InputError(path, f"lacks {', '.join(missing)}: not written by doefab camera-psnr")
    if levels is not None and obj["levels_sha256"] != levels_digest(levels):
        raise InputError(path, "was computed for another tile than this design folder's levels")
    return CameraPsnrRecord(path, obj)


def write_camera_psnr(path, record):
    """Write a ``camera_psnr.json`` (a dict), atomically."""
    write_json(path, record)
