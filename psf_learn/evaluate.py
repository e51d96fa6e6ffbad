"""Evaluation of a learned camera on whole images: PSNR and SSIM.

Each grayscale image is cropped to a multiple of the factor f, captured through
the PSF with the sensor model (mirror padding at the borders, photon noise
from a fixed seed per image, so evaluation is deterministic), super-resolved,
clipped to [0, 1] and compared after cropping ``border`` = f pixels on every
side (the usual SR-benchmark border crop). SSIM is scikit-image's default
(7 x 7 uniform window), not the Gaussian window of Wang et al. 2004.
"""

import numpy as np
import torch
from skimage.metrics import structural_similarity

from psf_learn.sensor import simulate_capture

EVAL_SEED = 20200714


def evaluate_image(model, image, psf=None, seed=EVAL_SEED, index=0, border=None):
    """Return (psnr_db, ssim, estimate) for one float (H, W) image in [0, 1]."""
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
    ref = scene[0, 0].double().numpy()
    crop = (slice(border, h - border), slice(border, w - border))
    mse = float(np.mean((estimate[crop] - ref[crop]) ** 2))
    psnr = 10 * np.log10(1.0 / max(mse, 1e-12))
    ssim = float(structural_similarity(estimate[crop], ref[crop], data_range=1.0))
    return float(psnr), ssim, estimate


def evaluate(model, names, images, psf=None, seed=EVAL_SEED, progress=False):
    """Return {"psnr", "ssim", "images": {name: {"psnr", "ssim"}}} averaged over images.

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
    per = {}
    for i, (name, img) in enumerate(pairs):
        p, s, _ = evaluate_image(model, img, psf, seed, i)
        per[name] = {"psnr": p, "ssim": s}
    return {
        "psnr": float(np.mean([v["psnr"] for v in per.values()])),
        "ssim": float(np.mean([v["ssim"] for v in per.values()])),
        "images": per,
    }
