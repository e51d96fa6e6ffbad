"""PSF parametrisations: a learnable softmax PSF and the fixed baselines.

Every PSF is a (K, K) array, non-negative and summing to one, element
[K//2, K//2] on the optical axis (CONVENTIONS.md). Baselines:

- ``delta``: all light on the axis; with the point-sampling SPAD this is the
  plain low fill-factor sensor.
- ``box``: a 4 x 4 box placed so that, sampled at the sensor's point-sample
  cell, it gives the mean of the pixel's own 4 x 4 block (a full fill-factor
  sensor). For the default sample cell (2, 2) the box covers axis offsets
  -1 .. +2 (rows and columns). A sensor whose active area spans several
  sub-pixels is no point sample, and no PSF turns it into the block mean: the
  box is refused there.
- ``gaussian``: sigma 0.459 sub-pixel (the best fixed PSF of Sun et al.
  2020), centred like the box on the pixel centre, so the SPAD sees a
  Gaussian-weighted mean around the centre of its own pixel, as a Gaussian
  PSF on the axis over an active area at the pixel centre does physically.
"""

import numpy as np
import torch
from torch import nn

GAUSSIAN_SIGMA = 0.459  # sub-pixels, Sun et al. 2020


def delta_psf(k):
    """Return the (k, k) float64 PSF with all light on the axis."""
    psf = np.zeros((k, k))
    psf[k // 2, k // 2] = 1.0
    return psf


def box_psf(k, factor=4, sample_cell=(2, 2)):
    """Return the (k, k) float64 box that turns a point sample into the pixel's block mean.

    A pixel sampled at cell ``s`` of its block sees blurred[f m + s] =
    sum_o psf[K//2 + o] scene[f m + s - o]; the block f m .. f m + f - 1 needs the
    offsets o = s - f + 1 .. s.
    """
    psf = np.zeros((k, k))
    lo = [k // 2 + s - factor + 1 for s in sample_cell]
    if min(lo) < 0 or max(lo) + factor > k:
        raise ValueError(
            f"a {factor} x {factor} box for sample cell {sample_cell} does not fit in K = {k}"
        )
    psf[lo[0] : lo[0] + factor, lo[1] : lo[1] + factor] = 1.0 / factor**2
    return psf


def gaussian_psf(k, sigma=GAUSSIAN_SIGMA, centre=(0.0, 0.0)):
    """Return the (k, k) float64 Gaussian PSF of ``sigma`` sub-pixels.

    ``centre`` is its (row, column) offset from the axis in sub-pixels. It is cut
    to the widest window about that centre. For whole- and half-cell centres
    (point samples, centred active areas) that window is symmetric and the
    centroid stays on the centre exactly. Elsewhere it stays only near: the window
    is one cell lopsided, and samples of a narrow Gaussian alias (0.04 sub-pixel
    off at sigma 0.459 and a centre 0.25 off a cell).
    """
    r = np.arange(k) - k // 2
    with np.errstate(over="ignore"):  # a huge sigma is a flat window: variance inf
        two_var = 2 * np.float64(sigma) ** 2

    def profile(c):
        d = np.abs(r - c)
        inside = d <= k // 2 - abs(c)
        # Measured from the nearest cell, a tiny sigma tends to its limit (the light on
        # the nearest cells); from the centre, every sample would underflow to 0 / 0.
        excess = d**2 - d[inside].min() ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            p = np.where(excess == 0, 1.0, np.exp(-excess / two_var))
        return np.where(inside, p, 0.0)

    g = profile(centre[0])[:, None] * profile(centre[1])[None, :]
    return g / g.sum()


def point_sample_weights(factor=4, sample_cell=(2, 2)):
    """Return the (f, f) weights of a point sample at ``sample_cell`` (the default sensor's)."""
    w = np.zeros((factor, factor))
    w[sample_cell] = 1.0
    return w


def pixel_centre_offset(weights):
    """Return the axis offset (sub-pixels) at which a pixel's sampling sees its own centre.

    A pixel weighting cell s of its block by W[s] sees
    sum_s W[s] sum_o psf[K//2 + o] scene[f m + s - o]: a PSF centred at offset c
    puts the response's centroid at f m + centroid(W) - c, which is the block
    centre f m + (f - 1) / 2 for c = centroid(W) - (f - 1) / 2 (+0.5 for the
    default point sample at cell (2, 2); 0 for a centred wide active area).
    """
    w = np.asarray(weights, dtype=np.float64)
    f = w.shape[0]
    idx = np.arange(f)
    rows, cols = (w.sum(axis=1) @ idx, w.sum(axis=0) @ idx) / w.sum()
    return (float(rows - (f - 1) / 2), float(cols - (f - 1) / 2))


def baseline_psf(name, k, weights=None):
    """Return a named fixed PSF: ``delta``, ``box``, ``gaussian`` or ``gaussian:SIGMA``.

    ``weights`` are the sensor's (f, f) active-area weights (default: the preset's
    point sample at cell (2, 2)). ``gaussian:SIGMA`` takes sigma in sub-pixels
    (``gaussian`` = ``gaussian:0.459``); Gaussians are centred so that each pixel
    sees its own centre, like the box.
    """
    w = point_sample_weights() if weights is None else np.asarray(weights, dtype=np.float64)
    centre = pixel_centre_offset(w)
    if name == "delta":
        return delta_psf(k)
    if name == "box":
        cells = np.argwhere(w > 0)
        if len(cells) != 1:
            raise ValueError(
                "the box baseline turns a point-sampling SPAD into a full fill-factor one; "
                f"this design's active area spans {len(cells)} sub-pixels, which no PSF "
                "undoes. For a full fill-factor baseline use --psf delta with a design "
                "whose active area fills the pixel (active_area_shape square, "
                "active_area_um = pixel_pitch_um)"
            )
        return box_psf(k, w.shape[0], tuple(int(c) for c in cells[0]))
    if name == "gaussian":
        return gaussian_psf(k, GAUSSIAN_SIGMA, centre)
    if name.startswith("gaussian:"):
        try:
            sigma = float(name.split(":", 1)[1])
        except ValueError:
            sigma = -1.0
        if not (np.isfinite(sigma) and sigma > 0):
            raise ValueError(f"gaussian:SIGMA needs a finite sigma > 0 in sub-pixels, got {name!r}")
        return gaussian_psf(k, sigma, centre)
    raise ValueError(f"unknown baseline PSF {name!r}")


START_KINDS = ("random", "dots")


def starting_psf(spec, k, weights=None, seed=0):
    """Return the (k, k) PSF a learned PSF starts from: a baseline name, ``random`` or ``dots``.

    ``random`` is uniform noise over the window; ``dots[:N]`` is N (default 6) dots of
    random weight at random cells over a faint floor (1 % of the light), so that every
    cell starts where the softmax still has a gradient. Both are drawn from ``seed``.
    """
    rng = np.random.default_rng([seed, k])
    if spec == "random":
        psf = rng.random((k, k)) + 1e-3
        return psf / psf.sum()
    if spec == "dots" or spec.startswith("dots:"):
        count = spec.partition(":")[2] or "6"
        if not count.isdigit() or not 1 <= int(count) <= k * k:
            raise ValueError(f"dots:N needs a whole N from 1 to {k * k}, got {spec!r}")
        psf = np.full((k, k), 0.01 / k**2)
        cells = rng.choice(k * k, size=int(count), replace=False)
        psf.flat[cells] += 0.99 * rng.dirichlet(np.ones(len(cells)))
        return psf / psf.sum()
    return baseline_psf(spec, k, weights)


class LearnedPSF(nn.Module):
    """A learnable PSF: softmax over K x K logits (>= 0 and sum 1 by construction).

    Parameters
    ----------
    init : (K, K) array
        Initial PSF (>= 0, sum 1); its log (floored at 1e-6 of the peak, so no
        logit starts where the softmax gradient vanishes) gives the logits.
    trainable : bool
        False freezes the PSF (a fixed baseline or a calibrated plate).
    """

    def __init__(self, init, trainable=True):
        super().__init__()
        init = np.asarray(init, dtype=np.float64)
        floor = 1e-6 * init.max() if trainable else 0.0
        with np.errstate(divide="ignore"):
            logits = np.log(np.maximum(init, floor))
        # -inf logits (exact zeros of a frozen PSF) become a large negative number
        logits = np.where(np.isfinite(logits), logits, -1e4)
        self.logits = nn.Parameter(
            torch.tensor(logits, dtype=torch.float32), requires_grad=trainable
        )

    def forward(self):
        """Return the (K, K) PSF tensor."""
        k = self.logits.shape[-1]
        return torch.softmax(self.logits.reshape(-1), dim=0).reshape(k, k)

    def numpy(self):
        """Return the PSF as float64 (K, K) summing to one exactly (the psf.npy contract)."""
        logits = self.logits.detach().double().cpu().numpy()
        p = np.exp(logits - logits.max())
        return p / p.sum()
