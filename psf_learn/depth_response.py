"""The temporal response of a gated SPAD: gate and pulse model, or a measured IRF.

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

This module builds h (:func:`gate_response` from a :class:`GateModel`,
:func:`response_from_irf` from a measured profile); :mod:`psf_learn.depth` fits
it to the pixels. numpy/scipy only: this module must not import torch.
"""

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))

# Below this fraction of the peak the response is treated as zero (grid extent).
_TAIL = 1e-9
# The fine grid of a gate response holds at most this many samples (10 us at 1 ps).
MAX_RESPONSE_SAMPLES = 10_000_000
# Scan directions: "gate", the gate delayed from sample to sample (h = G correlated
# with Pi); "laser", the time-reversed convention (h = G * Pi, the paper's Eq. 9).
SCANS = ("gate", "laser")


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
        table = ResponseTable(self.values, self.start, self.step)
        h, dh = table(np.asarray(t, dtype=np.float64), derivative=True)
        return (h, dh) if derivative else h


class ResponseTable:
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


def gate_response(model=None, step=1e-12, scan="gate"):
    """Return the response h(x) = integral G(t) Pi(t - x) dt of a gate model, peak 1.

    x = t_k - mu is the gate's opening time less the light's arrival: h is the
    pulse G convolved with the gate Pi reversed in time (see the module docstring).
    With ``scan="laser"`` it is the time-reversed convention, the convolution
    h(x) = integral G(t) Pi(x - t) dt (the paper's Eq. 9, I = G * Pi): for a
    symmetric pulse, the gate direction's h mirrored about x = 0.

    Parameters
    ----------
    model : GateModel or None
        Gate and pulse parameters (defaults: the seed paper's 200 ps gate).
    step : float
        Fine grid spacing (s); 1 ps keeps interpolation errors far below the
        timing precision.
    scan : {"gate", "laser"}
        Scan direction (see :data:`SCANS`).

    Returns
    -------
    Response
    """
    model = model or GateModel()
    if scan not in SCANS:
        raise ValueError(f"scan must be one of {SCANS}, got {scan!r}")
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
    if scan == "gate":  # a gate opening x after the light sees it at time -x of its own
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
