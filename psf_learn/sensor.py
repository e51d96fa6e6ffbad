"""SPAD sensor model (torch): PSF convolution, low-fill-factor sampling, photon noise.

The scene lives on the sub-pixel grid (pitch = pixel pitch / superres factor,
37.5 um for the sun2020 preset). Sub-pixel cell (i, j) covers rows [i, i+1) and
columns [j, j+1) in sub-pixel units; SPAD pixel (m, n) covers the f x f block of
cells starting at (f m, f n). Row index grows downwards (-y), column index to
the right (+x), as in CONVENTIONS.md.

Sampling. Each SPAD pixel integrates the blurred image over its active area,
described by an f x f weight matrix over the cells of its block
(:func:`active_area_weights`). An active area no wider than one sub-pixel (the
default 30 um disc in a 150 um pixel is smaller than a 37.5 um sub-pixel) is a
point sample at the cell that holds its centre. The default centred disc has
its centre exactly on the corner shared by cells (1, 1), (1, 2), (2, 1), (2, 2);
ties go to the lower-right cell, so the point sample is cell (2, 2) of each
4 x 4 block, i.e. sub-pixel (4 m + 2, 4 n + 2). This amounts to registering the
sub-pixel grid half a sub-pixel (18.75 um) from the pixel grid, which a
shift-invariant scene prior cannot notice. A full fill-factor sensor (active
area = the whole pixel) gets uniform 1/16 weights, the 4 x 4 block mean.

Photon level. ``photons`` is the expected count of a SPAD pixel for a uniform
scene of value 1 (white). Every PSF sums to one, so all sampling schemes see
the same mean signal and compare at the same shot-noise level. The preset's
``photons_per_pixel = 10000`` gives 1 % shot noise at white and 3 % at a 0.1
grey: a bright intensity frame (about 1 Mcount/s for 10 ms, well inside a
16-bit SPAD counter). With it the low fill-factor baseline lands 0.08 dB
(Set5) and 0.44 dB (Set14) above Sun et al.'s Table 2, while 1000 counts leaves every model
noise-limited (see docs/learn.md).
"""

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F


@dataclass(frozen=True)
class SensorModel:
    """A SPAD sensor on the sub-pixel grid.

    Attributes
    ----------
    weights : tuple of tuples, (f, f)
        Weight of each sub-pixel cell of a block in the pixel's count; sums to 1.
    photons : float
        Expected counts of a pixel for a white (value 1) scene; <= 0 disables noise.
    dark_counts : float
        Expected dark counts per pixel and frame (subtracted again after sampling).
    """

    weights: tuple
    photons: float = 1000.0
    dark_counts: float = 0.0

    @property
    def factor(self):
        """Super-resolution factor f (sub-pixels per pixel along an axis)."""
        return len(self.weights)

    @property
    def sample_cell(self):
        """(row, col) of the cell with the largest weight (the point-sample cell)."""
        w = np.asarray(self.weights)
        return tuple(int(v) for v in np.unravel_index(np.argmax(w), w.shape))


def active_area_weights(design, supersample=64):
    """Return the (f, f) float64 weights of the active area over a pixel's sub-pixel cells.

    An active area no wider than a sub-pixel is a point sample (one-hot) at the
    cell holding its centre (ties to the lower-right cell); a wider one weights
    each cell by the fraction of the active area that covers it, computed on a
    ``supersample`` x ``supersample`` grid per cell.
    """
    s = design.sensor
    f = s.superres_factor
    sub = s.pixel_pitch / f
    # active-area centre from the pixel's top-left corner, in sub-pixels; y up = row down
    cx = (s.pixel_pitch / 2 + s.active_offset[0]) / sub
    cy = (s.pixel_pitch / 2 - s.active_offset[1]) / sub
    if s.active_area <= sub * (1 + 1e-9):
        row = min(max(int(np.floor(cy + 1e-9)), 0), f - 1)
        col = min(max(int(np.floor(cx + 1e-9)), 0), f - 1)
        w = np.zeros((f, f))
        w[row, col] = 1.0
        return w
    n = f * supersample
    centres = (np.arange(n) + 0.5) / supersample
    yy, xx = np.meshgrid(centres, centres, indexing="ij")
    half = s.active_area / sub / 2
    if s.active_area_shape == "circle":
        inside = (yy - cy) ** 2 + (xx - cx) ** 2 <= half**2
    else:
        inside = (np.abs(yy - cy) <= half) & (np.abs(xx - cx) <= half)
    w = inside.reshape(f, supersample, f, supersample).sum(axis=(1, 3)).astype(np.float64)
    if w.sum() == 0:
        raise ValueError("the active area does not overlap its pixel")
    return w / w.sum()


def sensor_from_design(design, photons=None, dark_counts=0.0):
    """Return the :class:`SensorModel` of a design (photons default: its learning section)."""
    w = active_area_weights(design)
    photons = design.learning.photons_per_pixel if photons is None else photons
    return SensorModel(tuple(map(tuple, w.tolist())), float(photons), float(dark_counts))


def _padded_and_flipped(images, psf, padding):
    """Return (images, kernel) for ``F.conv2d`` to compute a true convolution with ``psf``."""
    k = psf.shape[-1]
    kernel = torch.flip(psf, dims=(-2, -1)).reshape(1, 1, k, k).to(images.dtype)
    if padding == "reflect":
        images = F.pad(images, (k // 2,) * 4, mode="reflect")
    elif padding != "valid":
        raise ValueError(f"padding must be 'reflect' or 'valid', got {padding!r}")
    return images, kernel


def convolve_psf(images, psf, padding="reflect"):
    """Convolve images with a PSF (a true convolution, not a correlation).

    Parameters
    ----------
    images : (B, 1, H, W) tensor
        Scene on the sub-pixel grid.
    psf : (K, K) tensor
        Element [K//2, K//2] is the optical axis; a point at (r, c) lands on
        (r + i - K//2, c + j - K//2) with weight psf[i, j].
    padding : {"reflect", "valid"}
        "reflect" keeps the size (mirror the scene at its borders); "valid"
        returns (H - K + 1, W - K + 1), using only scene inside the image.
    """
    images, kernel = _padded_and_flipped(images, psf, padding)
    return F.conv2d(images, kernel)


def spad_sample(blurred, weights):
    """Return the (B, 1, H/f, W/f) pixel signals of a (B, 1, H, W) blurred image.

    Pixel (m, n) = sum_ij weights[i, j] * blurred[f m + i, f n + j]; H and W must
    be multiples of f.
    """
    w = torch.as_tensor(np.asarray(weights), dtype=blurred.dtype, device=blurred.device)
    f = w.shape[0]
    if blurred.shape[-1] % f or blurred.shape[-2] % f:
        raise ValueError(f"image size {tuple(blurred.shape[-2:])} is not a multiple of {f}")
    return F.conv2d(blurred, w.reshape(1, 1, f, f), stride=f)


def photon_noise(signal, photons, dark_counts=0.0, seeds=None, seed=0):
    """Apply exact Poisson shot noise with a straight-through gradient.

    The forward value is (Poisson(photons * signal + dark) - dark) / photons, drawn
    with numpy, one generator per batch element seeded by ``seeds[b]`` (so the
    noise of a sample does not depend on how a batch is split between
    processes); the backward pass treats the noise as additive, d out / d signal = 1
    (``torch.poisson`` alone has a zero gradient).

    Parameters
    ----------
    signal : (B, ...) tensor
        Noise-free pixel signals (scene units, white = 1); negative values count as 0.
    photons : float
        Expected counts for signal 1; <= 0 returns ``signal`` unchanged.
    seeds : sequence of int or of int tuples, length B, optional
        Per-sample seeds (default: ``seed`` plus the batch index).
    """
    if photons <= 0:
        return signal
    lam = (signal.detach().clamp_min(0).double().cpu().numpy() * photons) + dark_counts
    out = np.empty_like(lam)
    for b in range(lam.shape[0]):
        key = seeds[b] if seeds is not None else (seed, b)
        rng = np.random.default_rng(np.random.SeedSequence(key))
        out[b] = rng.poisson(lam[b])
    noisy = torch.from_numpy((out - dark_counts) / photons).to(signal.dtype).to(signal.device)
    return signal + (noisy - signal).detach()


def point_sample_blur(images, psf, cell, factor, padding="reflect"):
    """Return convolve_psf(images, psf, padding) sampled at cell (r, c) of every f x f block.

    Computes only the sampled outputs (a strided convolution), f^2 times less
    work than blurring everything and then sampling; the result is identical.
    """
    images, kernel = _padded_and_flipped(images, psf, padding)
    k = kernel.shape[-1]
    h, w = images.shape[-2] - k + 1, images.shape[-1] - k + 1
    if h % factor or w % factor:
        raise ValueError(f"image size {(h, w)} is not a multiple of {factor}")
    r, c = cell
    out = F.conv2d(images[..., r:, c:], kernel, stride=factor)
    return out[..., : h // factor, : w // factor]


def simulate_capture(images, psf, sensor, padding="reflect", seeds=None, seed=0):
    """Return the noisy (B, 1, H/f, W/f) SPAD frame of (B, 1, H, W) scenes seen through ``psf``.

    With ``padding="valid"`` the scene must be K - 1 sub-pixels larger than the
    captured area (the border supplies the light blurred into it).
    """
    w = np.asarray(sensor.weights)
    if np.count_nonzero(w) == 1:  # a point sample: blur only where it is sampled
        clean = point_sample_blur(images, psf, sensor.sample_cell, sensor.factor, padding)
    else:
        clean = spad_sample(convolve_psf(images, psf, padding), w)
    return photon_noise(clean, sensor.photons, sensor.dark_counts, seeds=seeds, seed=seed)
