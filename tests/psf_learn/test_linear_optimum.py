"""The linear (Wiener) reference: its error against a brute-force LMMSE and closed forms."""

import numpy as np
import pytest

from psf_learn.linear_optimum import (
    image_spectrum,
    linear_mse,
    linear_psnr,
    optimal_psf,
    transfer,
)
from psf_learn.psf import baseline_psf, box_psf, delta_psf, gaussian_psf, point_sample_weights


def _symmetric_spectrum(n, rng):
    q = rng.random((n, n)) + 0.1
    return q + np.roll(np.flip(q, (0, 1)), 1, (0, 1))  # P(w) = P(-w): a real scene


def _brute_force_mse(psf, spectrum, weights, noise_var):
    """tr(C - C A^T (A C A^T + s^2 I)^-1 A C) / N^2 with every matrix written out."""
    n, f, k = spectrum.shape[0], len(weights), psf.shape[0]
    cov_of_shift = np.real(np.fft.ifft2(spectrum))
    idx = np.arange(n * n)
    rows, cols = np.divmod(idx, n)
    cov = cov_of_shift[(rows[:, None] - rows[None, :]) % n, (cols[:, None] - cols[None, :]) % n]
    blur = np.zeros((n * n, n * n))
    for (i, j), v in np.ndenumerate(psf):  # blurred[p] += psf[K//2 + o] scene[p - o]
        o = (i - k // 2, j - k // 2)
        blur[idx, ((rows - o[0]) % n) * n + (cols - o[1]) % n] += v
    m = n // f
    sample = np.zeros((m * m, n * n))
    for a in range(m * m):
        r, c = divmod(a, m)
        for (i, j), v in np.ndenumerate(np.asarray(weights)):
            sample[a, ((f * r + i) % n) * n + (f * c + j) % n] += v
    a = sample @ blur
    gain = cov @ a.T @ np.linalg.solve(a @ cov @ a.T + noise_var * np.eye(m * m), a @ cov)
    return np.trace(cov - gain) / n**2


@pytest.mark.parametrize("f, weights", [(2, "point"), (2, "area"), (3, "point"), (4, "point")])
def test_the_closed_form_equals_the_brute_force_lmmse(f, weights):
    rng = np.random.default_rng(f)
    n = 4 * f
    spectrum = _symmetric_spectrum(n, rng)
    w = point_sample_weights(f, (1, 1)) if weights == "point" else rng.random((f, f))
    w = w / w.sum()
    psf = rng.random((3, 3))
    psf /= psf.sum()
    for noise in (0.0, 0.05):
        brute = _brute_force_mse(psf, spectrum, w, noise)
        assert float(linear_mse(psf, spectrum, w, noise)) == pytest.approx(brute, rel=1e-9)


def test_a_white_scene_gives_the_closed_forms_whatever_the_psf():
    f, n, p = 4, 32, 0.3
    white = np.full((n, n), p)
    w = point_sample_weights()
    for psf in (delta_psf(11), box_psf(11), gaussian_psf(11, 1.5)):
        # no noise: the sampled fraction 1 / f^2 is known, the rest is guessed at its mean
        assert float(linear_mse(psf, white, w, 0.0)) == pytest.approx(p * (1 - 1 / f**2))
    s2 = 0.1  # a point sample with noise: a Wiener shrink of the sampled pixels
    expected = p - p**2 / (p + s2) / f**2
    assert float(linear_mse(delta_psf(11), white, w, s2)) == pytest.approx(expected)


def test_the_optimum_beats_every_fixed_psf_and_one_start_finds_what_another_does():
    rng = np.random.default_rng(3)
    images = [
        np.cumsum(np.cumsum(rng.standard_normal((96, 96)), 0), 1) / 400 for _ in range(3)
    ]  # a red spectrum, as photos have
    spectrum = image_spectrum(images, size=32, patches=4)
    w, noise = point_sample_weights(), 1e-4
    best = optimal_psf(spectrum, w, noise, k=7, steps=800)
    again = optimal_psf(spectrum, w, noise, k=7, steps=800, start=baseline_psf("box", 7))
    assert np.all(best >= 0) and best.sum() == pytest.approx(1.0, abs=1e-12)
    top = linear_psnr(best, spectrum, w, noise)
    assert linear_psnr(again, spectrum, w, noise) == pytest.approx(top, abs=0.01)
    for name in ("delta", "box", "gaussian:1", "gaussian:1.5", "gaussian:2"):
        assert top >= linear_psnr(baseline_psf(name, 7), spectrum, w, noise) - 1e-6


def test_the_spectrum_holds_the_images_variance():
    rng = np.random.default_rng(0)
    images = [rng.normal(0.5, 0.1, (80, 80)) for _ in range(4)]
    spectrum = image_spectrum(images, size=32, patches=10)
    assert spectrum.sum() / 32**2 == pytest.approx(0.01, rel=0.05)
    with pytest.raises(ValueError, match="no image is 128"):
        image_spectrum(images, size=128)


@pytest.mark.parametrize("shape", [(12, 12), (8, 12)])
def test_the_transfer_is_the_blur_then_the_active_area_read_out(shape):
    rng = np.random.default_rng(5)
    scene, psf, weights = rng.random(shape), rng.random((5, 5)), rng.random((4, 4))
    blurred = np.zeros(shape)  # blurred[p] = sum_o psf[K//2 + o] scene[p - o], circularly
    for (i, j), v in np.ndenumerate(psf):
        blurred += v * np.roll(scene, (i - 2, j - 2), axis=(0, 1))
    read = np.zeros(shape)  # read[n] = sum_s W[s] blurred[n + s]
    for (i, j), v in np.ndenumerate(weights):
        read += v * np.roll(blurred, (-i, -j), axis=(0, 1))
    expected = np.fft.fft2(read)
    got = np.fft.fft2(scene) * transfer(psf, weights, shape).numpy()
    np.testing.assert_allclose(got, expected, atol=1e-10)
