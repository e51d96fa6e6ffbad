"""The best non-negative PSF for a linear reconstruction: a reference for the learned one.

A SPAD pixel sees one number per f x f block of the PSF-blurred scene. For a
stationary scene of power spectrum P and white read-out noise of variance
sigma^2 per pixel, the best linear (MMSE, Wiener) reconstruction from those
samples has a closed form per frequency: the f^2 frequencies that alias onto one
frequency of the SPAD grid, w_k, reach it with weights T(w_k) / f (T: the PSF's
transfer function times that of the active area), and estimating their f^2
amplitudes from one noisy sum leaves the error

    sum_k P_k - (sum_k |T_k|^2 P_k^2) / (sum_k |T_k|^2 P_k + f^2 sigma^2)

(per frequency, ``P_k = P(w_k)``). Its mean over frequencies is the mean squared
error per sub-pixel. :func:`optimal_psf` minimises it over every non-negative
K x K PSF summing to one (a softmax, as the learned PSF): what the plate could
give a linear reconstruction, against which a learned PSF's network is judged
(docs/learn.md, "Levers").
"""

import numpy as np
import torch


def image_spectrum(images, size=64, patches=20, seed=0):
    """Return the (size, size) mean power spectrum of the images (per pixel, mean removed).

    ``patches`` windows (Hann, scaled to keep the power) per image at places drawn
    from ``seed``; ``sum(P) / size**2`` is the images' mean local variance.
    """
    rng = np.random.default_rng(seed)
    window = np.outer(np.hanning(size), np.hanning(size))
    window /= np.sqrt(np.mean(window**2))
    total, count = np.zeros((size, size)), 0
    for image in images:
        if min(image.shape) < size:
            continue
        for _ in range(patches):
            r = rng.integers(0, image.shape[0] - size + 1)
            c = rng.integers(0, image.shape[1] - size + 1)
            patch = np.asarray(image[r : r + size, c : c + size], dtype=np.float64)
            total += np.abs(np.fft.fft2((patch - patch.mean()) * window, norm="ortho")) ** 2
            count += 1
    if not count:
        raise ValueError(f"no image is {size} pixels wide")
    return total / count


def transfer(psf, weights, shape):
    """Return the complex transfer of a PSF and an f x f active area on a grid of ``shape``.

    ``shape`` is (rows, columns) or one size for both. The PSF's element [K//2, K//2]
    is the axis (index 0 of the grid); a pixel reads ``sum_s W[s] blurred[f m + s]``,
    a correlation with W, hence its conjugate.
    """
    rows, cols = (shape, shape) if np.isscalar(shape) else shape
    psf = torch.as_tensor(psf, dtype=torch.float64)
    k = psf.shape[-1]
    grid = torch.zeros((rows, cols), dtype=torch.float64)
    r, c = (torch.arange(k) - k // 2) % rows, (torch.arange(k) - k // 2) % cols
    # accumulate: a window wider than the grid wraps round, as a circular blur does
    grid = grid.index_put((r[:, None].expand(k, k), c[None, :].expand(k, k)), psf, accumulate=True)
    area = torch.zeros((rows, cols), dtype=torch.float64)
    w = torch.as_tensor(np.asarray(weights, dtype=np.float64))
    area[: w.shape[0], : w.shape[1]] = w
    return torch.fft.fft2(grid) * torch.fft.fft2(area).conj()


def linear_mse(psf, spectrum, weights, noise_var):
    """Return the MMSE linear reconstruction's mean squared error per sub-pixel (a tensor).

    ``spectrum`` (N, N, N a multiple of f) is the scene's power spectrum per pixel,
    ``noise_var`` the variance of a pixel's read-out in scene units.
    """
    p = torch.as_tensor(spectrum, dtype=torch.float64)
    n, f = p.shape[0], len(weights)
    if n % f:
        raise ValueError(f"the spectrum's {n} pixels are not whole SPAD pixels of {f}")
    gain = transfer(psf, weights, n).abs() ** 2 * p
    m = n // f
    seen = gain.reshape(f, m, f, m).sum(dim=(0, 2))
    kept = (gain * p).reshape(f, m, f, m).sum(dim=(0, 2))
    return (p.sum() - (kept / (seen + f**2 * noise_var)).sum()) / n**2


def optimal_psf(spectrum, weights, noise_var, k=11, steps=1500, start=None):
    """Return the (k, k) float64 non-negative PSF summing to one of least :func:`linear_mse`.

    Adam on softmax logits from ``start`` (default: uniform), as the learned PSF is
    parametrised; the problem is smooth and the tests find one optimum from
    several starts.
    """
    start = np.full((k, k), 1.0 / k**2) if start is None else np.asarray(start, np.float64)
    logits = torch.tensor(np.log(np.maximum(start, 1e-9 * start.max())), requires_grad=True)
    opt = torch.optim.Adam([logits], lr=0.05)
    for _ in range(steps):
        psf = torch.softmax(logits.reshape(-1), 0).reshape(k, k)
        loss = linear_mse(psf, spectrum, weights, noise_var)
        opt.zero_grad()
        loss.backward()
        opt.step()
    p = torch.softmax(logits.detach().reshape(-1), 0).reshape(k, k).numpy()
    return p / p.sum()


def linear_psnr(psf, spectrum, weights, noise_var):
    """Return the PSNR (dB, peak 1) of :func:`linear_mse`."""
    return float(-10 * np.log10(float(linear_mse(psf, spectrum, weights, noise_var))))
