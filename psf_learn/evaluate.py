"""Evaluation of a learned camera on whole images: PSNR and SSIM in two conventions.

Each grayscale image is cropped to a multiple of the factor f, captured through
the PSF with the sensor model (mirror padding at the borders, photon noise
from a fixed seed per image, so evaluation is deterministic), super-resolved,
clipped to [0, 1] and compared after cropping ``border`` = f pixels on every
side (the usual SR-benchmark border crop). ``psnr`` / ``ssim`` score full-range
grey (SSIM: scikit-image's default 7 x 7 uniform window); ``psnr_y`` /
``ssim_y`` score the SR papers' MATLAB Y of the estimate stored as 8 bits, as
BasicSR does (:mod:`psf_learn.scores`): 1.32 dB higher on the same images.

:func:`evaluate_folder` is the library of ``doefab evaluate``: a model folder
scored on a folder of images, optionally with another PSF, written as JSON.

Example
-------
>>> from psf_learn.evaluate import evaluate_folder
>>> scores = evaluate_folder("model", "set5/", out="set5.json")
>>> scores.psnr, scores.psnr_y, scores.images["baby.png"]["ssim_y"]
"""

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from doe.infra.errors import InputError
from psf_learn.scores import image_scores, mean_scores
from psf_learn.sensor import simulate_capture

EVAL_SEED = 20200714


def evaluate_image(model, image, psf=None, seed=EVAL_SEED, index=0, border=None):
    """Return (psnr_db, ssim, estimate) for one float (H, W) image in [0, 1]."""
    scores, estimate = score_image(model, image, psf, seed, index, border)
    return scores["psnr"], scores["ssim"], estimate


def score_image(model, image, psf=None, seed=EVAL_SEED, index=0, border=None):
    """Return ({"psnr", "ssim", "psnr_y", "ssim_y"}, estimate) for one (H, W) image in [0, 1]."""
    f = model.sensor.factor
    border = f if border is None else border
    psf = model.psf if psf is None else psf
    h, w = (image.shape[0] // f) * f, (image.shape[1] // f) * f
    scene = torch.from_numpy(np.ascontiguousarray(image[:h, :w], dtype=np.float32))[None, None]
    with torch.no_grad():
        frame = simulate_capture(
            scene,
            torch.from_numpy(np.asarray(psf)).float(),
            model.sensor,
            padding="reflect",
            seeds=[(seed, index)],
        )
        estimate = model.net(frame).clamp(0, 1)[0, 0].double().numpy()
    return image_scores(estimate, scene[0, 0].double().numpy(), border), estimate


def evaluate(model, names, images, psf=None, seed=EVAL_SEED, progress=False):
    """Return {"psnr", "ssim", "psnr_y", "ssim_y", "images": {name: {the four}}}, means first.

    ``progress`` shows a tqdm bar of images on stderr.
    """
    from tqdm import tqdm

    pairs = tqdm(
        zip(names, images, strict=True),
        total=len(names),
        desc="evaluate",
        unit="image",
        disable=not progress,
    )
    per = {name: score_image(model, img, psf, seed, i)[0] for i, (name, img) in enumerate(pairs)}
    return {**mean_scores(per), "images": per}


@dataclass(frozen=True)
class Evaluation:
    """Scores of a model on a folder of images (what ``doefab evaluate`` prints and writes).

    Attributes
    ----------
    psnr, ssim : float
        Means over the images, full-range grey.
    psnr_y, ssim_y : float
        Means over the images, MATLAB Y (16-235) of the 8-bit estimate, as SR papers
        and BasicSR score (:mod:`psf_learn.scores`).
    images : dict
        ``{name: {"psnr", "ssim", "psnr_y", "ssim_y"}}`` in the folder's order.
    model_dir : path
        The model folder evaluated.
    images_folder : path
        The folder of test images.
    psf_file : path or None
        The PSF evaluated with, None for the model's own.
    """

    psnr: float
    ssim: float
    images: dict
    model_dir: object
    images_folder: object
    psf_file: object
    psnr_y: float = float("nan")
    ssim_y: float = float("nan")

    def to_dict(self):
        """Return the JSON object written for the evaluation."""
        return {
            "psnr": self.psnr,
            "ssim": self.ssim,
            "psnr_y": self.psnr_y,
            "ssim_y": self.ssim_y,
            "images": self.images,
            "model": str(self.model_dir),
            "images_folder": self.images_folder,
            "psf_file": self.psf_file,
        }


def evaluate_folder(
    model_dir, images, *, psf_file=None, seed=None, out=None, force=False, progress=False
):
    """Score a learned model on every image of a folder; return an :class:`Evaluation`.

    Parameters
    ----------
    model_dir : path
        A folder written by ``doefab learn``.
    images : path
        Folder of grayscale test images.
    psf_file : path, optional
        Evaluate with this PSF (e.g. the realised plate's) instead of the model's;
        refused when its report says it was made for another sub-pixel grid.
    seed : int, optional
        Noise seed (default :data:`EVAL_SEED`).
    out : path, optional
        Write the scores to this JSON file (refused before the evaluation if it
        exists, unless ``force``).
    progress : bool
        Show a progress bar of images on stderr.

    Raises
    ------
    doe.infra.errors.InputError
        For a bad seed, output path, model, PSF or image, and for a model whose
        estimates are not finite.
    """
    from doe.infra import flags
    from psf_learn import images as imgio
    from psf_learn.sr import load_model

    flags.seed("--seed", seed)
    torch.set_num_threads(1)
    out = results_path(out, force)
    model = load_model(model_dir)
    psf = _evaluation_psf(model, psf_file)
    # The capture mirrors each image by K // 2 at its borders: narrower ones cannot be.
    k = (model.psf if psf is None else psf).shape[0]
    psf_path = psf_file or Path(model_dir) / "psf.npy"
    names, scenes = imgio.read_folder(
        images,
        min_size=max(4 * model.sensor.factor, k),
        why=f"the {k}x{k} PSF of {psf_path} needs {k} pixels"
        if k > 4 * model.sensor.factor
        else "",
    )
    res = evaluate(
        model, names, scenes, psf, EVAL_SEED if seed is None else seed, progress=progress
    )
    if not math.isfinite(res["psnr"]):  # images in [0, 1]: only weights past float32 give this
        raise InputError(Path(model_dir) / "model.pt", "gives non-finite estimates")
    result = Evaluation(
        res["psnr"],
        res["ssim"],
        res["images"],
        model_dir,
        images,
        psf_file,
        psnr_y=res["psnr_y"],
        ssim_y=res["ssim_y"],
    )
    if out is not None:
        write_evaluation(out, result)
    return result


def _evaluation_psf(model, psf_file):
    """Return the PSF of ``psf_file`` checked against the model's grid, or None."""
    if not psf_file:
        return None
    from doe.infra.files import read_psf
    from doe.records.psf_source import check_measured_psf, psf_grid_problem

    psf = read_psf(psf_file)
    check_measured_psf(psf_file)
    summary = model.learn.design if model.learn is not None else None  # no record: no check
    problem = psf_grid_problem(psf_file, summary, "the model")
    if problem:
        path, text = problem
        raise InputError(path, f"{text}; --psf-file must be made for the model's grid")
    return psf


def results_path(out, force=False):
    """Return ``out`` as a Path (None stays None) if the scores can be written there.

    Refused (InputError) now, not after the evaluation: a folder, an existing file
    or link without ``force``, a path inside a file.
    """
    out = Path(out) if out else None
    if out is not None and out.is_dir():
        raise InputError(out, "is a folder; --out names the JSON file to write")
    if out is not None and (out.exists() or out.is_symlink()) and not force:
        raise InputError(out, "exists; use --force or another --out")
    parent = next((q for q in (out.parents if out else ()) if q.exists()), None)
    if parent is not None and not parent.is_dir():
        raise InputError(parent, f"is a file, so {out.name} cannot be written inside it")
    return out


def write_evaluation(out, result):
    """Write an :class:`Evaluation` as the JSON file ``out`` (its folders made)."""
    from doe.infra.files import write_json

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json(out, result.to_dict())
