"""Gated-SPAD time profiles: a vectorised per-pixel fit of arrival time, amplitude, background.

The expected count of sample k (gate opening ``t_k = k * shift`` after the laser
pulse) of a pixel whose light arrives at ``mu`` is ``m_k = A * h(t_k - mu) + b``,
with h the temporal response of :mod:`psf_learn.depth_response` (peak 1; see
docs/depth.md). The round-trip depth is ``c * mu / 2``.

The fit of (A, mu, b) runs on all pixels at once: a coarse grid search over mu
(matched filter with intercept) picks the global optimum, then Levenberg-
Marquardt iterations on the Poisson likelihood (Fisher scoring) refine it.
numpy/scipy only: this module must not import torch.

The response model's names (:class:`GateModel`, :func:`gate_response`,
:func:`response_from_irf`, ...) are importable from here too.
"""

from dataclasses import dataclass

import numpy as np

from psf_learn.depth_response import (
    FWHM_PER_SIGMA,
    MAX_RESPONSE_SAMPLES,
    SCANS,
    GateModel,
    Response,
    ResponseTable,
    gate_response,
    response_from_irf,
)

__all__ = [
    "FWHM_PER_SIGMA",
    "MAX_RESPONSE_SAMPLES",
    "SCANS",
    "SPEED_OF_LIGHT",
    "GateModel",
    "ProfileFit",
    "Response",
    "ResponseTable",
    "check_scan",
    "cramer_rao_timing",
    "depth_from_timing",
    "expected_counts",
    "fit_profiles",
    "gate_response",
    "response_from_irf",
    "scan_times",
    "xlogy",
]

SPEED_OF_LIGHT = 299_792_458.0  # m/s

# The fit works in picoseconds: A, mu and b then have comparable magnitudes in the
# 3 x 3 normal equations, which keeps the batched solves well conditioned.
_PS = 1e-12


def expected_counts(response, times, amplitude, timing, background):
    """Return the expected counts ``A h(t - mu) + b`` of every pixel at every scan time.

    Parameters
    ----------
    response : Response
    times : (T,) array
        Scan times (s).
    amplitude, timing, background : (...) arrays
        Peak counts A, arrival time mu (s) and background counts b per pixel.

    Returns
    -------
    (..., T) float64 array
    """
    amplitude, timing, background = np.broadcast_arrays(
        *(np.asarray(v, dtype=np.float64) for v in (amplitude, timing, background))
    )
    h = response(np.asarray(times)[None, :] - timing.reshape(-1, 1))
    m = amplitude.reshape(-1, 1) * h + background.reshape(-1, 1)
    return m.reshape((*amplitude.shape, len(times)))


def cramer_rao_timing(response, times, amplitude, timing, background):
    """Return the Cramer-Rao bound on the std of mu (s) of every pixel, Poisson counts.

    The same bound as :attr:`ProfileFit.timing_sigma` (the full (A, mu, b) Fisher
    matrix inverted), at the given parameters instead of the fitted ones.

    Parameters
    ----------
    response : Response
    times : (T,) array
        Scan times (s).
    amplitude, timing, background : (...) arrays
        Peak counts A, arrival time mu (s) and background counts b per pixel.

    Returns
    -------
    (...) float64 array
    """
    amplitude, timing, background = np.broadcast_arrays(
        *(np.asarray(v, dtype=np.float64) for v in (amplitude, timing, background))
    )
    x = np.asarray(times)[None, :] - timing.reshape(-1, 1)
    h, dh = response(x, derivative=True)
    a = amplitude.reshape(-1, 1)
    m = np.maximum(a * h + background.reshape(-1, 1), 1e-300)
    return _timing_sigma(h, -a * dh, m).reshape(amplitude.shape)


def depth_from_timing(timing):
    """Return the round-trip depth (m), ``c * mu / 2``, of arrival times mu (s)."""
    return SPEED_OF_LIGHT * np.asarray(timing, dtype=np.float64) / 2


@dataclass(frozen=True, eq=False)
class ProfileFit:
    """Per-pixel fit of gated time profiles; arrays have the cube's (H, W) shape.

    Attributes
    ----------
    timing : float64 array
        Arrival time mu (s); NaN where there is no return.
    amplitude : float64 array
        Peak signal counts A; 0 where there is no return.
    background : float64 array
        Background counts per sample b.
    fit_quality : float64 array
        Poisson deviance per degree of freedom (about 1 for a good fit) of the
        reported model (the constant background where there is no return).
    significance : float64 array
        Likelihood-ratio statistic 2 (log L_fit - log L_background-only).
    valid : bool array
        True where a return was detected (significance >= threshold).
    timing_sigma : float64 array
        1-sigma of the timing (s) from the Poisson likelihood's curvature at the
        fit: the Cramer-Rao bound of the fitted model, amplitude and background
        as nuisance parameters (the full 3 x 3 Fisher matrix inverted); NaN
        where there is no return.
    log_likelihood : float64 array
        Poisson log-likelihood of the reported model (the fit where a return,
        the constant background elsewhere) less that of the saturated model:
        minus half its deviance.
    """

    timing: np.ndarray
    amplitude: np.ndarray
    background: np.ndarray
    fit_quality: np.ndarray
    significance: np.ndarray
    valid: np.ndarray
    timing_sigma: np.ndarray
    log_likelihood: np.ndarray

    @property
    def depth(self):
        """Return the round-trip depth (m), NaN where there is no return."""
        return depth_from_timing(self.timing)

    @property
    def depth_sigma(self):
        """Return the 1-sigma of the depth (m), ``c * timing_sigma / 2``; NaN: no return."""
        return depth_from_timing(self.timing_sigma)


def scan_times(n_samples, shift):
    """Return the (T,) scan times ``k * shift`` (s)."""
    return np.arange(n_samples) * float(shift)


def fit_profiles(
    cube, shift, response, threshold=20.0, max_iter=60, grid_step=None, chunk=4096, progress=False
):
    """Fit amplitude, arrival time and background of every pixel of a gated cube.

    Maximises the Poisson likelihood of ``A h(t_k - mu) + b`` for all pixels at
    once: a grid search over mu (matched filter with intercept) picks the
    global optimum, Levenberg-Marquardt (Fisher scoring) steps refine it. A pixel
    is a return only if the likelihood ratio against a constant background is at
    least ``threshold``; otherwise its timing is NaN.

    Parameters
    ----------
    cube : (..., T) array
        Non-negative counts; sample k is taken at scan time ``k * shift``.
    shift : float
        Scan step (s).
    response : Response
        Temporal response h (peak 1).
    threshold : float
        Detection threshold on 2 (log L_fit - log L_background); the default 20
        lets through about 1e-4 of pure-background pixels (measured: the maximum
        over mu makes the null distribution wider than chi^2 with one dof).
    max_iter : int
        Maximum number of Levenberg-Marquardt iterations.
    grid_step : float or None
        Spacing of the initial mu grid (s); default a 1/25 of h's FWHM.
    chunk : int
        Pixels fitted together (memory: about 200 * chunk * T bytes, bench/depth.py).
    progress : bool
        Show a tqdm bar over the chunks on stderr (when it is a terminal).

    Returns
    -------
    ProfileFit
    """
    cube = np.asarray(cube, dtype=np.float64)
    shape, n_t = cube.shape[:-1], cube.shape[-1]
    check_scan(n_t, shift, response)
    y = cube.reshape(-1, n_t)
    if y.shape[0] == 0:
        raise ValueError("the cube has no pixels")
    t = scan_times(n_t, shift) / _PS
    table = ResponseTable(response.values, response.start / _PS, response.step / _PS)
    step = response.step / _PS

    lo_mu, hi_mu = _timing_range(t, response)
    grid = grid_step / _PS if grid_step else max(response.fwhm / _PS / 25, step)
    # The smallest expected count (keeps log m finite), per pixel: one bright pixel
    # must not raise the floor of the dim ones.
    floor = 1e-9 * np.maximum(y.max(axis=1, initial=0.0), 1.0)[:, None]
    # Chunks of pixels bound the (pixels, T, 3) work arrays of a super-resolved cube.
    starts = range(0, y.shape[0], chunk)
    if progress and len(starts) > 1:
        from tqdm import tqdm

        starts = tqdm(starts, desc="fit", unit="chunk", disable=None)
    parts = [
        _fit_chunk(y[i : i + chunk], t, table, lo_mu, hi_mu, grid, floor[i : i + chunk], max_iter)
        for i in starts
    ]
    a, mu, b, significance, deviance, mean, sigma = (
        np.concatenate(p) for p in zip(*parts, strict=True)
    )
    # A fit stopped at an end of the searched range has no timing: its light came
    # before or after the scan could place it.
    inside = (mu > lo_mu) & (mu < hi_mu)
    valid = (significance >= threshold) & (a > 0) & np.isfinite(mu) & inside

    # A no-return pixel is reported as the constant background, so its quality is that
    # model's: its deviance exceeds the full fit's by exactly the likelihood ratio.
    reported = np.where(valid, deviance, deviance + significance)
    quality = reported / np.where(valid, max(n_t - 3, 1), max(n_t - 1, 1))
    timing = np.where(valid, mu * _PS, np.nan)
    amplitude = np.where(valid, a, 0.0)
    background = np.where(valid, b, mean)
    return ProfileFit(
        timing=timing.reshape(shape),
        amplitude=amplitude.reshape(shape),
        background=background.reshape(shape),
        fit_quality=quality.reshape(shape),
        significance=significance.reshape(shape),
        valid=valid.reshape(shape),
        timing_sigma=np.where(valid, sigma * _PS, np.nan).reshape(shape),
        log_likelihood=(-0.5 * reported).reshape(shape),
    )


def check_scan(n_samples, shift, response):
    """Raise ValueError unless a scan of ``n_samples`` at ``shift`` (s) can time ``response``.

    It needs 4 samples, at least one per FWHM of the response (a pulse between two
    farther samples has no timing), and must cover one FWHM (a shorter scan sees a
    nearly flat slice of h, where amplitude and background are one unknown).
    """
    fwhm = response.fwhm
    if n_samples < 4:
        raise ValueError(f"a profile needs at least 4 samples, got {n_samples}")
    if not shift <= fwhm:
        raise ValueError(
            f"the scan step {shift / _PS:.3g} ps exceeds the response's FWHM "
            f"{fwhm / _PS:.3g} ps: a return between two samples has no timing"
        )
    if (n_samples - 1) * shift < fwhm:
        raise ValueError(
            f"the scan covers {(n_samples - 1) * shift / _PS:.3g} ps, less than the "
            f"response's FWHM {fwhm / _PS:.3g} ps"
        )


def _fit_chunk(y, t, table, lo_mu, hi_mu, grid, floor, max_iter):
    """Fit (P, T) profiles; per pixel a, mu (ps), b, significance, deviance, mean, sigma (ps)."""

    def model(a, mu, b):
        h, dh = table(t[None, :] - mu[:, None], derivative=True)
        return h, dh, a[:, None] * h + b[:, None]

    a, mu, b = _grid_start(y, t, table, lo_mu, hi_mu, grid)
    a, mu, b = _poisson_lm(y, model, a, mu, b, lo_mu, hi_mu, floor, max_iter)
    h, dh, m = model(a, mu, b)
    m = np.maximum(m, floor)
    mean = y.mean(axis=1)
    nll_bg = _poisson_nll(y, np.maximum(mean[:, None], floor))
    significance = np.maximum(2 * (nll_bg - _poisson_nll(y, m)), 0.0)
    deviance = 2 * np.sum(xlogy(y, y) - xlogy(y, m) - (y - m), axis=1)
    sigma = _timing_sigma(h, -a[:, None] * dh, m)
    return a, mu, b, significance, deviance, mean, sigma


def _timing_sigma(h, dmu, m):
    """The Cramer-Rao std of mu: sqrt of [F^-1]_11, F the (A, mu, b) Fisher information.

    ``h``, ``dmu`` (dm/dmu) and ``m`` are (P, T); dm/db = 1. The inverse's middle
    element is a cofactor over the determinant, written out (no batched inverse of
    singular matrices where A = 0).
    """
    w = 1.0 / m
    wh, wd = w * h, w * dmu
    f00, f01, f02 = (wh * h).sum(1), (wh * dmu).sum(1), wh.sum(1)
    f11, f12, f22 = (wd * dmu).sum(1), wd.sum(1), w.sum(1)
    cof = f00 * f22 - f02 * f02
    det = (
        f00 * (f11 * f22 - f12 * f12)
        - f01 * (f01 * f22 - f12 * f02)
        + f02 * (f01 * f12 - f11 * f02)
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        var = np.where(det > 0, cof / np.where(det > 0, det, 1.0), np.nan)
    return np.sqrt(np.where(var >= 0, var, np.nan))


def _timing_range(t, response):
    """Arrival times (ps) whose response peak falls within the scan, plus half a FWHM."""
    peak, half = response.peak_time / _PS, response.fwhm / _PS / 2
    return t[0] - peak - half, t[-1] - peak + half


def _grid_start(y, t, table, lo_mu, hi_mu, grid_step):
    """Initial (A, mu, b) per pixel from a least-squares matched filter over a mu grid.

    The grid is scanned in blocks of at most max(16, min(P, T)) points (each with
    its two neighbours, for the refinement), so that its work arrays stay within
    those of the fit: the grid grows with T, and all of it at once would take
    memory growing as T^2.
    """
    mus = np.arange(lo_mu, hi_mu + grid_step, grid_step)
    yc = y - y.mean(axis=1, keepdims=True)
    n = y.shape[0]
    rows = np.arange(n)
    best, j = np.full(n, -np.inf), np.zeros(n, dtype=np.intp)
    s_left, s_right, edge = np.zeros(n), np.zeros(n), np.zeros(n, dtype=bool)
    slope, h_mean = np.zeros(n), np.zeros(n)
    block = max(16, min(n, t.size))
    for first in range(0, mus.size, block):
        lo, hi = max(first - 1, 0), min(first + block + 1, mus.size)
        hg = table(t[None, :] - mus[lo:hi, None])  # (B + 2, T)
        hc = hg - hg.mean(axis=1, keepdims=True)
        var = np.maximum(np.sum(hc * hc, axis=1), 1e-30)
        cov = yc @ hc.T  # (P, B + 2)
        score = np.where(cov > 0, cov * cov / var, 0.0)
        inner = score[:, first - lo : min(first + block, mus.size) - lo]
        k = np.argmax(inner, axis=1) + (first - lo)
        better = score[rows, k] > best
        kl, kr = np.maximum(k - 1, 0), np.minimum(k + 1, hi - lo - 1)
        best[better], j[better] = score[rows, k][better], lo + k[better]
        s_left[better], s_right[better] = score[rows, kl][better], score[rows, kr][better]
        edge[better] = ((kl == k) | (kr == k))[better]
        slope[better] = (cov[rows, k] / var[k])[better]
        h_mean[better] = hg.mean(axis=1)[k][better]
    # Sub-grid refinement: vertex of the parabola through the three scores around the peak.
    curv = s_left - 2 * best + s_right
    offset = np.where(
        (curv < 0) & ~edge, 0.5 * (s_left - s_right) / np.where(curv < 0, curv, -1.0), 0.0
    )
    mu = mus[j] + np.clip(offset, -0.5, 0.5) * grid_step
    a = np.maximum(slope, 0.0)
    b = np.maximum(y.mean(axis=1) - a * h_mean, 0.0)
    return a, mu, b


def xlogy(x, y):
    """Return x * log(y), with 0 where x == 0 (scipy.special.xlogy, without its import)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(x == 0, 0.0, x * np.log(np.where(x == 0, 1.0, y)))


def _poisson_nll(y, m):
    return np.sum(m - xlogy(y, m), axis=1)


def _poisson_lm(y, model, a, mu, b, lo_mu, hi_mu, floor, max_iter):
    """Levenberg-Marquardt on the Poisson likelihood, all pixels at once."""
    n = y.shape[0]
    lam = np.full(n, 1e-3)
    h, dh, m = model(a, mu, b)
    m = np.maximum(m, floor)
    nll = _poisson_nll(y, m)
    active = np.ones(n, dtype=bool)
    eye = np.eye(3)
    for _ in range(max_iter):
        if not active.any():
            break
        idx = np.flatnonzero(active)
        ya, ma = y[idx], m[idx]
        # Jacobian columns: dm/dA = h, dm/dmu = -A h', dm/db = 1. Gradient and Fisher
        # information of the negative log-likelihood, sums written out (faster than einsum).
        hj, dj = h[idx], -a[idx, None] * dh[idx]
        w = 1.0 / ma
        r = 1.0 - ya * w
        wh, wd = w * hj, w * dj
        grad = np.stack([(r * hj).sum(1), (r * dj).sum(1), r.sum(1)], axis=-1)
        f00, f01, f02 = (wh * hj).sum(1), (wh * dj).sum(1), wh.sum(1)
        f11, f12, f22 = (wd * dj).sum(1), wd.sum(1), w.sum(1)
        fisher = np.stack([f00, f01, f02, f01, f11, f12, f02, f12, f22], axis=-1).reshape(-1, 3, 3)
        diag = np.maximum(np.stack([f00, f11, f22], axis=-1), 1e-12)
        damped = fisher + lam[idx, None, None] * diag[:, :, None] * eye
        try:
            delta = np.linalg.solve(damped, -grad[..., None])[..., 0]
        except np.linalg.LinAlgError:
            delta = -grad / diag
        delta = np.where(np.isfinite(delta), delta, 0.0)
        na = np.maximum(a[idx] + delta[:, 0], 0.0)
        nmu = np.clip(mu[idx] + delta[:, 1], lo_mu, hi_mu)
        nb = np.maximum(b[idx] + delta[:, 2], 0.0)
        nh, ndh, nm = model(na, nmu, nb)
        nm = np.maximum(nm, floor[idx])
        new_nll = _poisson_nll(ya, nm)
        better = new_nll <= nll[idx]
        acc = idx[better]
        gain = nll[acc] - new_nll[better]
        a[acc], mu[acc], b[acc] = na[better], nmu[better], nb[better]
        h[acc], dh[acc], m[acc], nll[acc] = nh[better], ndh[better], nm[better], new_nll[better]
        lam[acc] = np.maximum(lam[acc] / 3, 1e-7)
        rej = idx[~better]
        lam[rej] *= 4
        # Converged: an accepted step that moved mu by < 0.01 ps and gained < 1e-6 in
        # log-likelihood (both far below statistical relevance), or a damping so
        # large that no step can help.
        done = np.zeros(n, dtype=bool)
        done[acc] = (np.abs(delta[better, 1]) < 1e-2) & (gain < 1e-6)
        # The undamped quadratic model promises almost nothing: at the optimum (up to
        # rounding, where every step is rejected).
        newton = -np.einsum("pk,pk->p", grad, delta)
        done[rej] = (lam[rej] > 1e8) | (newton[~better] < 1e-7)
        active &= ~done
    return a, mu, b
