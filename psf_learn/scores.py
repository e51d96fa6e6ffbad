"""Image scores in both conventions: full-range grey, and the SR papers' MATLAB Y.

``psnr`` / ``ssim`` compare the estimate and the reference as grey values in
[0, 1] (SSIM: scikit-image's default 7 x 7 uniform window). ``psnr_y`` /
``ssim_y`` are what SR papers publish (BasicSR's ``calculate_psnr`` /
``calculate_ssim`` with ``test_y_channel=True``, the D-DBPN MATLAB code): the
estimate stored as an 8-bit image (rounded, as BasicSR's ``tensor2img`` and a
saved PNG do), both images turned to MATLAB ``rgb2ycbcr``'s Y on 0-255,
``Y = 16 + 65.481 R + 128.553 G + 24.966 B`` with R, G, B in [0, 1] (grey is
R = G = B, so ``Y = 16 + 219 v``), and SSIM with the 11 x 11 Gaussian window of
sigma 1.5 of Wang et al. 2004. Both conventions crop the same border. Y spans
219 of 255 codes, so on the same images ``psnr_y - psnr = 20 log10(255 / 219)
= 1.32 dB``; the rounding of the estimate moves ``psnr_y`` by a few 0.001 dB more.

Example
-------
>>> import numpy as np
>>> from psf_learn.scores import image_scores
>>> ref = np.linspace(0, 1, 64 * 64).reshape(64, 64)
>>> image_scores(ref + 0.01, ref, border=4)["psnr_y"]   # 40 + 1.32 dB, less rounding
"""

import numpy as np
from skimage.metrics import structural_similarity

# MATLAB rgb2ycbcr's luma row for R, G, B in [0, 1] (BasicSR's bgr2ycbcr reversed).
Y_WEIGHTS = (65.481, 128.553, 24.966)
Y_OFFSET = 16.0
SCORE_KEYS = ("psnr", "ssim", "psnr_y", "ssim_y")


def y_channel(grey):
    """Return MATLAB ``rgb2ycbcr``'s Y (0-255 scale, 16-235) of grey values in [0, 1].

    Grey is the colour R = G = B = ``grey``.
    """
    grey = np.asarray(grey, dtype=np.float64)
    return Y_OFFSET + sum(Y_WEIGHTS) * grey


def stored_8bit(image):
    """Return an image in [0, 1] as an 8-bit file holds it: clipped, rounded to k / 255."""
    return np.round(np.clip(np.asarray(image, dtype=np.float64), 0, 1) * 255) / 255


def psnr(a, b, peak):
    """Return the PSNR (dB) of two arrays on a scale whose peak is ``peak``.

    Equal arrays read 120 dB, not infinity: a mean over images stays finite.
    """
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float(10 * np.log10(peak**2 / max(mse, 1e-12 * peak**2)))


def image_scores(estimate, reference, border):
    """Return {"psnr", "ssim", "psnr_y", "ssim_y"} of an estimate against its reference.

    Parameters
    ----------
    estimate, reference : (H, W) arrays
        Grey values in [0, 1] (the estimate is clipped to it).
    border : int
        Pixels cropped on every side before scoring (the SR factor).
    """
    estimate = np.clip(np.asarray(estimate, dtype=np.float64), 0, 1)
    reference = np.asarray(reference, dtype=np.float64)
    h, w = reference.shape
    crop = (slice(border, h - border), slice(border, w - border))
    est, ref = estimate[crop], reference[crop]
    est_y, ref_y = y_channel(stored_8bit(estimate)[crop]), y_channel(ref)
    return {
        "psnr": psnr(est, ref, 1.0),
        "ssim": float(structural_similarity(est, ref, data_range=1.0)),
        "psnr_y": psnr(est_y, ref_y, 255.0),
        # Wang et al.'s window, as BasicSR's calculate_ssim (its MATLAB port) applies it
        "ssim_y": float(
            structural_similarity(
                est_y,
                ref_y,
                data_range=255.0,
                gaussian_weights=True,
                sigma=1.5,
                use_sample_covariance=False,
            )
        ),
    }


def mean_scores(per_image):
    """Return the mean of each score over ``{name: scores}``."""
    return {key: float(np.mean([v[key] for v in per_image.values()])) for key in SCORE_KEYS}
