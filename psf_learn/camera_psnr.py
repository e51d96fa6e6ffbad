"""The camera budget in dB: a learned model's reconstruction PSNR with the plate in a camera.

:func:`camera_psnr` computes the plate's effective PSF (:func:`doe.camera.effective_psf`)
at a few camera settings (:data:`PSNR_AXES`, each varied alone from the nominal camera:
the design wavelength, the plate's square clear aperture, in focus, unrotated), simulates
captures of held-back images through each (:func:`psf_learn.evaluate.evaluate`, the
model's own sensor and noise) and scores the model's reconstructions: the PSNR a lab
loses when its camera differs. A setting is within the dB budget while the PSNR stays
within ``allowance_db`` of the nominal camera's. ``doefab camera-psnr`` writes the
result as ``camera_psnr.json`` (:mod:`doe.records.camera_psnr`) for ``doefab fab
--camera-psnr``.

The images are the embedded photos held out of training (learn.json's ``heldout``,
:func:`psf_learn.images.held_out_images`) or a folder, scored on a centre crop of
``crop`` pixels: each setting costs one capture and one reconstruction per image.
"""

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from doe.infra.errors import InputError

# The ends of the fab report's budget curves (doe.camera_budget.BUDGET_AXES), fewer
# points between: each costs a capture and a reconstruction of every image.
PSNR_AXES = {
    "bandwidth_nm": (0.0, 20.0, 40.0),
    "f_number": (1.8, 4.0, 16.0),
    "defocus_um": (-500.0, -250.0, -100.0, 0.0, 100.0, 250.0, 500.0),
    "rotation_deg": (0.0, 2.5, 5.0),
}
# The PSNR a camera setting may cost against the nominal camera: a stated margin (half a
# dB), not one derived from a measurement; --allowance-db sets another.
ALLOWANCE_DB = 0.5
CROP = 128


@dataclass(frozen=True)
class CameraPsnr:
    """What :func:`camera_psnr` measured: the ``camera_psnr.json`` object and its time."""

    record: dict
    seconds: float


def camera_psnr(
    design_dir,
    model_dir,
    *,
    config=None,
    eval_images=None,
    axes=None,
    crop=CROP,
    allowance_db=ALLOWANCE_DB,
):
    """Return the :class:`CameraPsnr` of DESIGN_DIR's plate reconstructed by MODEL_DIR's model.

    Parameters
    ----------
    design_dir : path
        A fab or retrieve output (its levels.npy).
    model_dir : path
        ``doefab learn``'s output; its sensor's sub-pixel grid must be the design's.
    config : path or str or None
        The design the tile was made for (default preset if None).
    eval_images : path or None
        A folder of grey images instead of the embedded held-back photos.
    axes : dict or None
        Setting -> values (default :data:`PSNR_AXES`).
    crop : int
        The centre crop of each image scored (pixels; the whole image when smaller).
    allowance_db : float
        The PSNR loss from the nominal camera a setting may cost.

    Raises
    ------
    InputError
        A bad folder, model or image, or a model for another sub-pixel grid.
    """
    import torch

    from doe.camera import effective_psf
    from doe.camera_budget import budget_range
    from doe.camera_stage import read_plate_folder
    from doe.design import load_design
    from doe.records.camera_psnr import levels_digest
    from psf_learn.evaluate import evaluate
    from psf_learn.sr import load_model

    start = time.perf_counter()
    torch.set_num_threads(1)
    axes = PSNR_AXES if axes is None else axes
    if not (isinstance(crop, int) and crop > 0):
        raise InputError("--crop", f"must be a positive number of pixels, got {crop}")
    design = load_design(config)
    levels, _, _ = read_plate_folder(design_dir, design)
    model = load_model(model_dir)
    k, factor = model.psf.shape[0], model.sensor.factor
    if factor != design.sensor.superres_factor:
        raise InputError(
            Path(model_dir) / "model.pt",
            f"was trained for superres_factor {factor}, the design has "
            f"{design.sensor.superres_factor}",
        )
    names, images, source = _images(eval_images, crop, max(4 * factor, k), factor)

    def psnr(psf):
        return float(evaluate(model, names, images, psf)["psnr"])

    nominal = effective_psf(design, levels, kernel_size=k)
    out_axes = {}
    nominal_psnr = psnr(nominal.psf)
    for axis, values in axes.items():
        xs = sorted(float(v) for v in values)
        scores = [psnr(effective_psf(design, levels, kernel_size=k, **{axis: v}).psf) for v in xs]
        loss = [nominal_psnr - s for s in scores]
        within = budget_range(axis, xs, loss, allowance_db)
        if within["range"] is None:
            within["why"] = f"the loss {within['why']} dB"
        out_axes[axis] = {"values": xs, "psnr": scores, "within_budget": within}
    record = {
        "levels_sha256": levels_digest(levels),
        "levels_shape": list(levels.shape),
        "design_dir": str(design_dir),
        "model_dir": str(model_dir),
        "images": {"source": source, "names": list(names), "crop": crop},
        "model_psf": {"psnr": psnr(None)},
        "nominal": {"psnr": nominal_psnr, "collected_fraction": nominal.collected_fraction},
        "allowance_db": allowance_db,
        "axes": out_axes,
        "versions": {"numpy": np.__version__, "torch": torch.__version__},
    }
    record["seconds"] = time.perf_counter() - start
    return CameraPsnr(record, record["seconds"])


def _images(folder, crop, min_size, factor):
    """Return (names, centre crops, source) of the held-back photos or a folder's images."""
    from psf_learn import images as imgio

    if folder is None:
        names, images = imgio.held_out_images()
        source = "the embedded held-back photos"
        if not names:
            raise InputError("--eval-images", "no held-back photo ships here; give a folder")
    else:
        names, images = imgio.read_folder(folder, min_size=min_size)
        source = str(folder)
    side = max(min_size, (crop // factor) * factor)
    crops = []
    for img in images:
        h, w = min(side, img.shape[0]), min(side, img.shape[1])
        top, left = (img.shape[0] - h) // 2, (img.shape[1] - w) // 2
        crops.append(np.ascontiguousarray(img[top : top + h, left : left + w]))
    return list(names), crops, source
