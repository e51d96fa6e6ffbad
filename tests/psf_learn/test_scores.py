"""Scores in the SR papers' convention (psnr_y, ssim_y) against BasicSR's published code.

basicsr is not installed (it pulls in OpenCV, torchvision and TensorBoard), so
``_basicsr_*`` below re-derive its ``calculate_psnr`` / ``calculate_ssim`` with
``test_y_channel=True`` line by line from basicsr 1.4.2
(basicsr/metrics/psnr_ssim.py, metric_util.py, utils/color_util.py): images
(H, W, 3) in BGR order on 0-255, border crop, ``to_y_channel`` (float32 / 255,
``bgr2ycbcr(y_only=True)``: ``dot([24.966, 128.553, 65.481]) + 16``, / 255 as
float32, * 255), float64 MSE; SSIM with OpenCV's 11-tap Gaussian of sigma 1.5
outer-multiplied, filtered and cut to the valid part. The SR output is the
8-bit image BasicSR's ``tensor2img`` makes of it (``(x * 255).round()``).
"""

import math

import numpy as np
import pytest
from model_helpers import fixed_model
from scipy.signal import correlate2d

from psf_learn.evaluate import evaluate, score_image
from psf_learn.images import dead_leaves
from psf_learn.scores import image_scores, y_channel


def _basicsr_y(img):
    """basicsr.metrics.metric_util.to_y_channel of an (H, W, 3) BGR image on 0-255."""
    img = img.astype(np.float32) / 255.0
    y = np.dot(img, [24.966, 128.553, 65.481]) + 16.0  # bgr2ycbcr(y_only=True)
    y = (y / 255.0).astype(np.float32)  # _convert_output_type_range(.., np.float32)
    return y[..., None] * 255.0


def _basicsr_psnr_y(img, img2, crop_border):
    img = img[crop_border:-crop_border, crop_border:-crop_border, ...]
    img2 = img2[crop_border:-crop_border, crop_border:-crop_border, ...]
    img, img2 = _basicsr_y(img).astype(np.float64), _basicsr_y(img2).astype(np.float64)
    mse = np.mean((img - img2) ** 2)
    return 10.0 * np.log10(255.0 * 255.0 / mse)


def _basicsr_ssim_y(img, img2, crop_border):
    img = img[crop_border:-crop_border, crop_border:-crop_border, ...]
    img2 = img2[crop_border:-crop_border, crop_border:-crop_border, ...]
    a, b = _basicsr_y(img)[..., 0].astype(np.float64), _basicsr_y(img2)[..., 0].astype(np.float64)
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    x = np.arange(11) - 5
    kernel = np.exp(-(x**2) / (2 * 1.5**2))  # cv2.getGaussianKernel(11, 1.5)
    window = np.outer(kernel / kernel.sum(), kernel / kernel.sum())

    def filt(v):  # cv2.filter2D(v, -1, window)[5:-5, 5:-5]: a correlation, valid part
        return correlate2d(v, window, mode="valid")

    mu1, mu2 = filt(a), filt(b)
    s1, s2, s12 = filt(a * a) - mu1**2, filt(b * b) - mu2**2, filt(a * b) - mu1 * mu2
    ssim_map = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1**2 + mu2**2 + c1) * (s1 + s2 + c2))
    return ssim_map.mean()


def _rgb(grey_uint8):
    """The grey image stored as a 3-channel one, R = G = B."""
    return np.repeat(grey_uint8[..., None], 3, axis=2)


def _pair():
    """A fixed (reference as 8-bit codes, estimate in [0, 1] off the 8-bit grid) pair."""
    rng = np.random.default_rng(7)
    ref = np.round(dead_leaves(48, rng, n_disks=150) * 255).astype(np.uint8)[:, :44]
    estimate = np.clip(ref / 255.0 + rng.normal(0, 0.03, ref.shape), 0, 1)
    return ref, estimate


def test_psnr_y_and_ssim_y_equal_basicsr_on_a_fixed_pair():
    # through evaluate's own path: a model whose "network" returns the estimate
    ref, estimate = _pair()
    model = fixed_model(estimate)
    scores, _ = score_image(model, ref / 255.0)
    sr = _rgb(np.round(estimate.astype(np.float32) * 255.0).astype(np.uint8))  # tensor2img
    assert scores["psnr_y"] == pytest.approx(_basicsr_psnr_y(sr, _rgb(ref), 4), abs=0.01)
    assert scores["ssim_y"] == pytest.approx(_basicsr_ssim_y(sr, _rgb(ref), 4), abs=1e-4)
    # the other convention is another figure: 1.32 dB lower, less the 8-bit rounding
    assert scores["psnr_y"] - scores["psnr"] == pytest.approx(20 * math.log10(255 / 219), abs=0.05)
    assert abs(scores["psnr_y"] - scores["psnr"] - 20 * math.log10(255 / 219)) > 1e-4


def test_psnr_y_is_psnr_plus_20_log10_255_over_219_without_rounding():
    # an estimate already on the 8-bit grid: Y = 16 + 219 v scales every error by 219 / 255
    ref, estimate = _pair()
    estimate = np.round(estimate * 255) / 255
    scores = image_scores(estimate, ref / 255.0, border=4)
    assert scores["psnr_y"] - scores["psnr"] == pytest.approx(20 * math.log10(255 / 219), abs=1e-9)
    assert scores["psnr_y"] == pytest.approx(_basicsr_psnr_y(_rgb(
        np.round(estimate * 255).astype(np.uint8)), _rgb(ref), 4), abs=1e-4)  # fmt: skip


def test_the_estimate_is_scored_as_an_8_bit_file_holds_it():
    # An error of 0.3 code rounds away: 8-bit storage holds the reference exactly.
    ref = np.round(np.linspace(0.1, 0.9, 32 * 32).reshape(32, 32) * 255) / 255
    scores = image_scores(ref + 0.3 / 255, ref, border=4)
    assert scores["psnr"] == pytest.approx(20 * math.log10(255 / 0.3), abs=1e-6)
    assert scores["psnr_y"] == pytest.approx(120.0) and scores["ssim_y"] == pytest.approx(1.0)
    assert y_channel(0.0) == 16.0 and y_channel(1.0) == pytest.approx(235.0)


def test_evaluate_gives_both_conventions_per_image_and_their_means():
    ref, estimate = _pair()
    model = fixed_model(estimate)
    other = np.clip(ref / 255.0 + 0.1, 0, 1)
    res = evaluate(model, ["a", "b"], [ref / 255.0, other])
    for key in ("psnr", "ssim", "psnr_y", "ssim_y"):
        assert res[key] == pytest.approx((res["images"]["a"][key] + res["images"]["b"][key]) / 2)
    assert res["images"]["a"]["psnr_y"] != res["images"]["b"]["psnr_y"]
