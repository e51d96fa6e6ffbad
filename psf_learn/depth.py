"""Gated-SPAD time profiles: the gate response model and a vectorised per-pixel fit.

A gated SPAD scans a gate across the returning laser pulse in steps of
``shift``: gate k opens ``t_k = k * shift`` after the laser pulse, and a photon
arriving at time t is counted with the gate's sensitivity Pi(t - t_k). The
expected count of sample k of a pixel whose light arrives at ``mu`` is (see
docs/depth.md)::

    m_k = A * h(t_k - mu) + b,    h(x) = integral G(t) Pi(t - x) dt, peak 1,

with G the laser pulse centred at 0 and Pi the gate's sensitivity against the
time since it opened: an RC-distorted rectangle on [0, width] (rise
``1 - exp(-t/rise)`` inside it, exponential decay with ``fall`` after it)
blurred by a band-limit Gaussian. h is G convolved with Pi reversed in time:
over the scan, the profile climbs with the gate's fall and drops to 0 along its
rise as the gate opens after the light has come (t_k > mu). ``mu`` is the arrival
time; the round-trip depth is ``c * mu / 2``.

The fit of (A, mu, b) runs on all pixels at once: a coarse grid search over mu
(matched filter with intercept) picks the global optimum, then Levenberg-
Marquardt iterations on the Poisson likelihood (Fisher scoring) refine it.
numpy/scipy only: this module must not import torch.
"""

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

SPEED_OF_LIGHT = 299_792_458.0  # m/s
FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))

# The fit works in picoseconds: A, mu and b then have comparable magnitudes in the
# 3 x 3 normal equations, which keeps the batched solves well conditioned.
_PS = 1e-12
# Below this fraction of the peak the response is treated as zero (grid extent).
_TAIL = 1e-9
# The fine grid of a gate response holds at most this many samples (10 us at 1 ps).
MAX_RESPONSE_SAMPLES = 10_000_000


@dataclass(frozen=True)
class GateModel:
    """Parametric gate and pulse model of a gated SPAD (all times in seconds).

    Attributes
    ----------
    width : float
        Length of the undistorted gate rectangle [0, width] (s).
    rise, fall : float
        RC time constants of the gate's rising edge (inside the rectangle) and of
        its decay after the rectangle (s).
    band_sigma : float
        Standard deviation of the Gaussian that band-limits the gate (s).
    pulse_fwhm : float
        Full width at half maximum of the Gaussian laser pulse (s).
    pulse : {"gaussian", "emg"}
        Pulse shape; "emg" convolves the Gaussian with a one-sided exponential.
    tau : float
        Decay constant of the exponential tail of an "emg" pulse (s).
    """

    width: float = 200e-12
    rise: float = 40e-12
    fall: float = 60e-12
    band_sigma: float = 100e-12
    pulse_fwhm: float = 80e-12
    pulse: Literal["gaussian", "emg"] = "gaussian"
    tau: float = 0.0

    def __post_init__(self):
        for name in ("width", "pulse_fwhm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("rise", "fall", "band_sigma", "tau"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.pulse not in ("gaussian", "emg"):
            raise ValueError(f"pulse must be 'gaussian' or 'emg', got {self.pulse!r}")
        if self.pulse == "emg" and not self.tau > 0:
            raise ValueError("an 'emg' pulse needs tau > 0")


@dataclass(frozen=True, eq=False)
class Response:
    """The temporal response h (peak 1) sampled on a fine uniform grid.

    Attributes
    ----------
    start : float
        Time of the first sample (s).
    step : float
        Grid spacing (s).
    values : (n,) float64 array
        h at ``start + i * step``; zero is assumed outside the grid.
    """

    start: float
    step: float
    values: np.ndarray = field(repr=False)

    @property
    def times(self):
        """Return the (n,) grid times (s)."""
        return self.start + self.step * np.arange(self.values.size)

    @property
    def peak_time(self):
        """Return the time (s) at which h peaks."""
        return float(self.times[np.argmax(self.values)])

    @property
    def support(self):
        """Return (first, last) grid times (s) where h is not negligible."""
        idx = np.flatnonzero(self.values > _TAIL)
        return float(self.times[idx[0]]), float(self.times[idx[-1]])

    @property
    def fwhm(self):
        """Return the full width at half maximum of h (s)."""
        idx = np.flatnonzero(self.values >= 0.5)
        return float((idx[-1] - idx[0]) * self.step)

    def __call__(self, t, derivative=False):
        """Evaluate h (and dh/dt, 1/s) at times ``t`` (s) by linear interpolation.

        Parameters
        ----------
        t : array
            Times in seconds, any shape.
        derivative : bool
            Also return the derivative.
        """
        table = _Table(self.values, self.start, self.step)
        h, dh = table(np.asarray(t, dtype=np.float64), derivative=True)
        return (h, dh) if derivative else h


class _Table:
    """h and dh/dt on a uniform grid, zero-padded at both ends, for fast interpolation.

    One (n, 4) table (h, its increment, dh/dt, its increment) makes each lookup a
    single gather of a contiguous row; the zero pads make times outside the grid
    read 0 after a clip instead of a mask.
    """

    def __init__(self, values, start, step):
        v = np.concatenate([[0.0], values, [0.0]])
        s = np.gradient(v, step)
        self.tab = np.stack([v, np.diff(v, append=0.0), s, np.diff(s, append=0.0)], axis=-1)
        self.start, self.step = start - step, step
        self.last = v.size - 1

    def __call__(self, t, derivative=False):
        """Return h(t) (and dh/dt if ``derivative``) for times ``t`` in the grid's unit."""
        x = (t - self.start) / self.step
        x = np.clip(x, 0.0, self.last)
        i = x.astype(np.intp)  # x >= 0: truncation is the floor
        frac = x - i
        row = self.tab[i]
        h = row[..., 0] + frac * row[..., 1]
        if not derivative:
            return h
        return h, row[..., 2] + frac * row[..., 3]


def gate_response(model=None, step=1e-12):
    """Return the response h(x) = integral G(t) Pi(t - x) dt of a gate model, peak 1.

    x = t_k - mu is the gate's opening time less the light's arrival: h is the
    pulse G convolved with the gate Pi reversed in time (see the module docstring).

    Parameters
    ----------
    model : GateModel or None
        Gate and pulse parameters (defaults: the seed paper's 200 ps gate).
    step : float
        Fine grid spacing (s); 1 ps keeps interpolation errors far below the
        timing precision.

    Returns
    -------
    Response
    """
    model = model or GateModel()
    sigma_pulse = model.pulse_fwhm / FWHM_PER_SIGMA
    blur = np.hypot(sigma_pulse, model.band_sigma)
    lo = -8 * blur - step
    hi = model.width + 25 * max(model.fall, step) + 8 * blur + 25 * model.tau
    if not (hi - lo) / step <= MAX_RESPONSE_SAMPLES:
        raise ValueError(
            f"the response would span {(hi - lo) / 1e-9:.3g} ns, more than the "
            f"{MAX_RESPONSE_SAMPLES * step / 1e-9:.3g} ns its {step / 1e-12:g} ps grid holds"
        )
    t = np.arange(np.floor(lo / step), np.ceil(hi / step) + 1) * step

    gate = np.zeros_like(t)
    inside = (t >= 0) & (t <= model.width)
    after = t > model.width
    rise_edge = _rise(t[inside], model.rise)
    end_value = _rise(np.array([model.width]), model.rise)[0]
    gate[inside] = rise_edge
    gate[after] = end_value * _decay(t[after] - model.width, model.fall)
    # A sample on a jump carries the mean of its two limits (the trapezoid rule), so that
    # the gate does not gain half a sample of width at each edge.
    right_after_end = end_value * _decay(np.array([0.0]), model.fall)[0]
    gate[np.isclose(t, 0.0, atol=step / 4)] = 0.5 * _rise(np.array([0.0]), model.rise)[0]
    gate[np.isclose(t, model.width, atol=step / 4)] = 0.5 * (end_value + right_after_end)
    # A gate opening x after the light sees it at time -x of its own: reverse Pi.
    gate, t = gate[::-1], -t[::-1]

    # Kernels centred on the grid so that the convolution keeps the time origin.
    kt = np.arange(-np.ceil(10 * blur / step), np.ceil(10 * blur / step) + 1) * step
    kernel = _gauss(kt, sigma_pulse)
    if model.band_sigma > 0:
        kernel = np.convolve(kernel, _gauss(kt, model.band_sigma), mode="same")
    if model.pulse == "emg":
        n_tau = int(np.ceil(25 * model.tau / step))
        tail = np.concatenate([np.zeros(n_tau), np.exp(-np.arange(n_tau + 1) * step / model.tau)])
        # The jump at 0 carries the mean of its limits: the tail's mean is then tau,
        # not tau - step / 2.
        tail[n_tau] *= 0.5
        kernel = np.convolve(kernel, tail / tail.sum(), mode="full")
        pad = (kernel.size - kt.size) // 2
        kt = np.arange(-(kt.size // 2) - pad, kt.size // 2 + pad + 1) * step
    h = np.convolve(gate, kernel, mode="full")
    # 'full' output sample j sits at time t[0] + kt[0] + j * step.
    start = t[0] + kt[0]
    h = np.clip(h, 0.0, None)
    keep = np.flatnonzero(h > _TAIL * h.max())
    h = h[keep[0] : keep[-1] + 1]
    return Response(start=start + keep[0] * step, step=step, values=h / h.max())


def _gauss(t, sigma):
    """A Gaussian sampled at ``t``, normalised to sum 1 (a pulse far shorter than the
    grid step becomes a single sample instead of 0 * inf)."""
    with np.errstate(over="ignore"):
        g = np.exp(-0.5 * (t / sigma) ** 2)
    return g / g.sum()


def _rise(t, rise):
    if rise == 0:
        return np.ones_like(t)
    return -np.expm1(-t / rise)


def _decay(t, fall):
    if fall == 0:
        return np.zeros_like(t)
    return np.exp(-t / fall)


def response_from_irf(irf, shift, t_ref=0.0, step=1e-12):
    """Return the response h from a measured instrument response, normalised to peak 1.

    The IRF is the time profile of a reference target at arrival time ``t_ref``
    sampled on the scan axis: ``irf[k] = h(k * shift - t_ref)`` (background
    subtracted; negative noise is clipped to 0). Between samples h follows a
    cubic spline (clipped at 0). Where the IRF is cut by the start or end of the scan,
    h is extended by a Gaussian (leading edge) or exponential (trailing edge)
    matched to the first/last samples, so that arrival times later than the
    reference still see a complete leading edge.

    Parameters
    ----------
    irf : (n,) array
        Counts (any scale) of the reference profile, n >= 4.
    shift : float
        Scan step (s).
    t_ref : float
        Arrival time of the reference target (s); 0 by convention.
    step : float
        Fine grid spacing (s).
    """
    irf = np.asarray(irf, dtype=np.float64)
    if irf.ndim != 1 or irf.size < 4:
        raise ValueError(f"an IRF must be 1-D with at least 4 samples, got shape {irf.shape}")
    if not np.all(np.isfinite(irf)):
        raise ValueError("the IRF contains NaN or infinite values")
    irf = np.clip(irf, 0.0, None)
    if not irf.max() > 0:
        raise ValueError("the IRF is all zero")
    peak = int(np.argmax(irf))
    if peak in (0, irf.size - 1):  # h's scale and timing would come from an extrapolation
        raise ValueError(
            f"the IRF peaks at its {'first' if peak == 0 else 'last'} sample: the reference's "
            "peak lies outside the scan, so neither h's scale nor the timing origin is "
            "known; place the reference so that its whole profile lies in the scan"
        )
    from scipy.interpolate import CubicSpline  # slow to import; only the IRF path

    y = irf / irf.max()
    ts = np.arange(y.size) * shift - t_ref
    fine = np.arange(np.ceil(ts[0] / step), np.floor(ts[-1] / step) + 1) * step
    h = np.clip(CubicSpline(ts, y)(fine), 0.0, None)

    left = _edge_extension(ts[:4], y[:4], step, leading=True)
    right = _edge_extension(ts[-4:][::-1], y[-4:][::-1], step, leading=False)
    if left is not None:
        lt, lv = left
        fine, h = np.concatenate([lt[::-1], fine]), np.concatenate([lv[::-1], h])
    if right is not None:
        rt, rv = right
        fine, h = np.concatenate([fine, rt]), np.concatenate([h, rv])
    return Response(start=float(fine[0]), step=step, values=h / h.max())


def _edge_extension(ts, y, step, leading):
    """Extend a cut edge beyond ts[0] (ts ordered from the edge inwards), or None.

    An edge of h is a blurred step (the late edge, where the gate opens after
    the light: its RC rise blurred by the pulse), whose logarithm is concave,
    or an exponential decay (the early edge, the gate's fall; a straight line in
    log h). A parabola through log h of the four edge samples extends either: a
    Gaussian where it curves, an exponential where it does not; a straight line
    through the last two samples where the parabola opens upwards.
    """
    if y[0] <= 1e-6:
        return None
    pos = y > 0
    if pos.sum() < 2:
        return None
    ts, ly = ts[pos], np.log(y[pos])
    direction = -1.0 if leading else 1.0
    dist = np.abs(ts - ts[0])
    coef = None
    if ts.size >= 3:
        c2, c1, c0 = np.polyfit(dist, ly, 2)
        if c2 < 0 and c1 > 0:
            coef = (c2, c1, c0)
    if coef is None:
        c1, c0 = np.polyfit(dist[:2], ly[:2], 1)
        if not c1 > 0:  # the samples do not decay outwards: cannot extrapolate safely
            return None
        coef = (0.0, c1, c0)
    c2, c1, c0 = coef
    # Distance outwards d >= step; log h(d) = c0 - c1 d + c2 d^2 (d measured outwards).
    d = step * np.arange(1, 200_000)
    logv = c0 - c1 * d + c2 * d * d
    stop = np.flatnonzero(logv < np.log(_TAIL))
    n = stop[0] if stop.size else d.size
    return ts[0] + direction * d[:n], np.exp(logv[:n])


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
    """

    timing: np.ndarray
    amplitude: np.ndarray
    background: np.ndarray
    fit_quality: np.ndarray
    significance: np.ndarray
    valid: np.ndarray

    @property
    def depth(self):
        """Return the round-trip depth (m), NaN where there is no return."""
        return depth_from_timing(self.timing)


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
    table = _Table(response.values, response.start / _PS, response.step / _PS)
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
    a, mu, b, significance, deviance, mean = (np.concatenate(p) for p in zip(*parts, strict=True))
    # A fit stopped at an end of the searched range has no timing: its light came
    # before or after the scan could place it.
    inside = (mu > lo_mu) & (mu < hi_mu)
    valid = (significance >= threshold) & (a > 0) & np.isfinite(mu) & inside

    # A no-return pixel is reported as the constant background, so its quality is that
    # model's: its deviance exceeds the full fit's by exactly the likelihood ratio.
    quality = np.where(
        valid, deviance / max(n_t - 3, 1), (deviance + significance) / max(n_t - 1, 1)
    )
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
    """Fit (P, T) profiles; return per-pixel a, mu (ps), b, significance, deviance, mean."""

    def model(a, mu, b):
        h, dh = table(t[None, :] - mu[:, None], derivative=True)
        return h, dh, a[:, None] * h + b[:, None]

    a, mu, b = _grid_start(y, t, table, lo_mu, hi_mu, grid)
    a, mu, b = _poisson_lm(y, model, a, mu, b, lo_mu, hi_mu, floor, max_iter)
    m = np.maximum(model(a, mu, b)[2], floor)
    mean = y.mean(axis=1)
    nll_bg = _poisson_nll(y, np.maximum(mean[:, None], floor))
    significance = np.maximum(2 * (nll_bg - _poisson_nll(y, m)), 0.0)
    deviance = 2 * np.sum(xlogy(y, y) - xlogy(y, m) - (y - m), axis=1)
    return a, mu, b, significance, deviance, mean


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
