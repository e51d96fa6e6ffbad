"""Per-pixel gate calibration of a gated SPAD array from a scan of a flat target.

The gates of a real array do not open together: pixel p opens gate k at
``k * shift + d_p``, with a skew of 100 - 200 ps std across the array. A gate
opened ``d_p`` late sees the light as if it had come ``d_p`` early: the profile
is ``A h(t_k + d_p - mu) + b``, the whole profile moved, its shape unchanged. A
fit with the common response therefore returns ``mu - d_p``, and adding ``d_p``
back is exact.

A calibration scan of a flat target at a known distance D gives every pixel the
same arrival time ``2 D / c`` (plus a fixed system offset s: trigger and cable
delays). The fit of each pixel's profile gives ``mu_p = 2 D / c + s - d_p``, so

    gate_delay_p = 2 D / c - mu_p = d_p - s,

which holds the skew and the system offset together. A scene fitted with the
calibration reports ``mu + gate_delay_p``: the round-trip time from the
laser, the offset s removed, whatever each pixel's gate.

What the data support: the delay, to the profile's timing precision (about
1 ps at 1000 peak counts). A gate-width change moves the profile's early edge
(gates closing before the light) but not its late edge; its first-order effect
on the fitted timing is a constant per pixel, which the delay absorbs, so a
width is not fitted (docs/depth.md, "Gate calibration").

numpy only (matplotlib for the figure); no torch.
"""

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from doe.infra.errors import InputError
from doe.infra.files import load_npy, read_json, save_npy, staged_output, write_json
from psf_learn.depth import FWHM_PER_SIGMA, SPEED_OF_LIGHT, fit_profiles

CALIBRATION_JSON = "calibration.json"
GATE_DELAY_NPY = "gate_delay_ps.npy"
DELAY_SIGMA_NPY = "gate_delay_sigma_ps.npy"
SKEW_FIGURE = "gate_skew.png"
CALIBRATION_FILES = (GATE_DELAY_NPY, DELAY_SIGMA_NPY, SKEW_FIGURE, CALIBRATION_JSON)
CONVENTION = (
    "pixel p opens gate k at k * shift + d_p; gate_delay_ps = 2 D / c - mu_p of the flat "
    "target = d_p less the system offset; depth --calibration reports mu + gate_delay_ps"
)
_PS = 1e-12


@dataclass(frozen=True, eq=False)
class GateCalibration:
    """Each pixel's gate delay, fitted from a scan of a flat target.

    Attributes
    ----------
    gate_delay : (H, W) float64 array
        Gate delay (s) less the system offset; NaN where the pixel had no return.
    delay_sigma : (H, W) float64 array
        1-sigma of each delay (s), the Cramer-Rao bound at the fit; NaN where no return.
    shift : float
        Scan step (s) of the calibration scan.
    n_samples : int
        Number of gate positions T of the scan.
    distance : float
        Distance of the flat target (m).
    gate : dict
        The response's settings (as ``depth.json``'s "gate").
    median_fit_quality : float
        Median Poisson deviance per dof of the returns (about 1 where the
        profiles follow the response; NaN when not known).
    """

    gate_delay: np.ndarray = field(repr=False)
    delay_sigma: np.ndarray = field(repr=False)
    shift: float
    n_samples: int
    distance: float
    gate: dict = field(default_factory=dict)
    median_fit_quality: float = float("nan")

    @property
    def shape(self):
        """Return the array's (H, W)."""
        return tuple(self.gate_delay.shape)

    def summary(self):
        """Return the skew's figures in ps: mean, std, FWHM (2.355 std), noise, pixels."""
        d = self.gate_delay[np.isfinite(self.gate_delay)] / _PS
        noise = float(np.median(self.delay_sigma[np.isfinite(self.delay_sigma)] / _PS))
        std = float(np.std(d))
        return {
            "mean_ps": float(np.mean(d)),
            "std_ps": std,
            "fwhm_ps": float(FWHM_PER_SIGMA * std),
            "median_sigma_ps": noise,
            # the skew's own spread: the measured one less the fits' noise
            "std_beyond_noise_ps": float(np.sqrt(max(std**2 - noise**2, 0.0))),
            "calibrated_pixels": int(d.size),
            "pixels": int(self.gate_delay.size),
        }


def calibrate_gates(cube, shift, response, distance, gate=None, threshold=20.0):
    """Fit each pixel's gate delay from a gate scan of a flat target at ``distance`` (m).

    Parameters
    ----------
    cube : (H, W, T) array
        Counts of the calibration scan (sample k at ``k * shift``).
    shift : float
        Scan step (s).
    response : Response
        The common response h (a gate model or an IRF), as ``depth`` uses.
    distance : float
        Distance of the flat target (m); every pixel's light arrives at ``2 D / c``.
    gate : dict or None
        The response's settings, kept in the record.
    threshold : float
        Detection threshold of the fit; a pixel without a return gets NaN.

    Returns
    -------
    GateCalibration

    Raises
    ------
    ValueError
        When no pixel has a return.
    """
    cube = np.asarray(cube, dtype=np.float64)
    fit = fit_profiles(cube, shift, response, threshold=threshold)
    if not fit.valid.any():
        raise ValueError("no pixel of the calibration scan has a return: no delay to fit")
    round_trip = 2 * float(distance) / SPEED_OF_LIGHT
    return GateCalibration(
        gate_delay=np.where(fit.valid, round_trip - fit.timing, np.nan),
        delay_sigma=np.where(fit.valid, fit.timing_sigma, np.nan),
        shift=float(shift),
        n_samples=int(cube.shape[-1]),
        distance=float(distance),
        gate=dict(gate or {}),
        median_fit_quality=float(np.median(fit.fit_quality[fit.valid])),
    )


def apply_calibration(fit, calibration):
    """Return ``fit`` with each pixel's gate delay added to its timing.

    A pixel the calibration has no delay for reports no return (NaN timing,
    amplitude 0): its timing would carry its whole gate skew.
    """
    delay = calibration.gate_delay
    if delay.shape != fit.timing.shape:
        raise ValueError(f"the calibration is for {delay.shape} pixels, the fit {fit.timing.shape}")
    ok = fit.valid & np.isfinite(delay)
    return dataclasses.replace(
        fit,
        timing=np.where(ok, fit.timing + np.nan_to_num(delay), np.nan),
        amplitude=np.where(ok, fit.amplitude, 0.0),
        valid=ok,
        timing_sigma=np.where(ok, fit.timing_sigma, np.nan),
    )


def scan_mismatch(calibration, shape, shift, gate=None):
    """Return what differs between a cube's scan and the calibration's, or None.

    ``shape``: the cube's (H, W, T); ``shift`` in s; ``gate``: the response's
    settings (compared when given, its "warnings" aside).
    """
    problems = []
    if tuple(shape[:2]) != calibration.shape:
        problems.append(f"array {shape[0]} x {shape[1]} against {calibration.shape[0]} x "
                        f"{calibration.shape[1]}")  # fmt: skip
    if shape[2] != calibration.n_samples:
        problems.append(f"{shape[2]} frames against {calibration.n_samples}")
    if not np.isclose(shift, calibration.shift, rtol=1e-9, atol=0.0):
        problems.append(f"--shift-ps {shift / _PS:g} against {calibration.shift / _PS:g}")
    if gate is not None:
        ours = {k: v for k, v in gate.items() if k != "warnings"}
        theirs = calibration.gate
        problems += [
            f"gate {k} {ours.get(k)} against {theirs.get(k)}"
            for k in sorted(set(ours) | set(theirs))
            if ours.get(k) != theirs.get(k)
        ]
    return "; ".join(problems) or None


def write_calibration(out, calibration, cube_name="", warnings=(), force=False):
    """Write a calibration folder (all files or none); return the files' names.

    ``calibration.json`` (scan settings, skew summary), ``gate_delay_ps.npy``,
    ``gate_delay_sigma_ps.npy`` and ``gate_skew.png`` (map and histogram).
    Existing files are refused (InputError) unless ``force``.
    """
    with staged_output(out, force, names=CALIBRATION_FILES) as stage:
        save_npy(stage / GATE_DELAY_NPY, calibration.gate_delay / _PS)
        save_npy(stage / DELAY_SIGMA_NPY, calibration.delay_sigma / _PS)
        save_skew_figure(stage / SKEW_FIGURE, calibration.gate_delay / _PS, calibration.summary())
        write_json(stage / CALIBRATION_JSON, _record(calibration, cube_name, warnings))
    return CALIBRATION_FILES


def _record(calibration, cube_name, warnings):
    h, w = calibration.shape
    return {
        "cube": str(cube_name),
        "shape": [h, w, calibration.n_samples],
        "frames": calibration.n_samples,
        "shift_ps": calibration.shift / _PS,
        "distance_m": calibration.distance,
        "round_trip_ps": 2 * calibration.distance / SPEED_OF_LIGHT / _PS,
        "gate": calibration.gate,
        "gate_delay": calibration.summary(),
        "median_fit_quality_of_returns": calibration.median_fit_quality,
        "convention": CONVENTION,
        "files": list(CALIBRATION_FILES[:-1]),
        "warnings": list(warnings),
    }


def read_calibration(folder):
    """Read a calibration folder written by :func:`write_calibration`.

    Raises
    ------
    InputError
        Naming the file that is missing or malformed.
    """
    folder = Path(folder)
    path = folder / CALIBRATION_JSON
    if not folder.is_dir():
        raise InputError(
            folder, "no such calibration folder (write one with 'doefab depth-calibrate')"
        )
    if not path.is_file():
        raise InputError(path, "no such file: not a calibration folder")
    record = read_json(path)
    try:
        shape = [int(v) for v in record["shape"]]
        shift, distance = float(record["shift_ps"]) * _PS, float(record["distance_m"])
        gate = dict(record["gate"])
        if len(shape) != 3 or min(shape) < 1 or not shift > 0:
            raise ValueError(f"shape {shape} and shift_ps {shift / _PS} are not a scan")
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(path, f"not a calibration record ({type(e).__name__}: {e})") from None
    arrays = [_read_map(folder / name, shape[:2]) for name in (GATE_DELAY_NPY, DELAY_SIGMA_NPY)]
    quality = record.get("median_fit_quality_of_returns")
    return GateCalibration(
        gate_delay=arrays[0] * _PS,
        delay_sigma=arrays[1] * _PS,
        shift=shift,
        n_samples=shape[2],
        distance=distance,
        gate=gate,
        median_fit_quality=float("nan") if quality is None else float(quality),
    )


def _read_map(path, shape):
    if not path.is_file():
        raise InputError(path, "no such file: the calibration is incomplete")
    data = load_npy(path)
    if data.dtype.kind != "f" or list(data.shape) != list(shape):
        raise InputError(
            path, f"must be a float ({shape[0]}, {shape[1]}) map, got {data.dtype} {data.shape}"
        )
    if np.isinf(data).any():
        raise InputError(path, "holds infinite values")
    return data.astype(np.float64)


def save_skew_figure(path, delay_ps, summary):
    """Save the skew map (colour bar in ps; no return: grey) beside its histogram."""
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from doe.infra.png import save_png

    data = np.ma.masked_invalid(np.asarray(delay_ps, dtype=np.float64))
    fig = Figure(figsize=(12, 4.5))
    FigureCanvasAgg(fig)
    ax_map, ax_hist = fig.subplots(1, 2, width_ratios=(1.4, 1))
    im = ax_map.imshow(data, cmap=colormaps["coolwarm"].with_extremes(bad="0.6"),
                       interpolation="nearest")  # fmt: skip
    ax_map.set_title("gate delay per pixel (grey: no return)", fontsize=10)
    ax_map.set_xlabel("column")
    ax_map.set_ylabel("row")
    fig.colorbar(im, ax=ax_map, label="gate delay (ps)", shrink=0.8)
    values = data.compressed()
    ax_hist.hist(values, bins=max(10, min(60, int(np.sqrt(values.size)))), color="C0")
    ax_hist.axvline(summary["mean_ps"], color="C3", label=f"mean {summary['mean_ps']:.1f} ps")
    ax_hist.set_title(
        f"skew: std {summary['std_ps']:.1f} ps, FWHM {summary['fwhm_ps']:.1f} ps "
        f"(fit noise {summary['median_sigma_ps']:.2f} ps)",
        fontsize=9,
    )
    ax_hist.set_xlabel("gate delay (ps)")
    ax_hist.set_ylabel("pixels")
    ax_hist.legend(fontsize=8)
    fig.subplots_adjust(left=0.06, right=0.98, bottom=0.12, top=0.9, wspace=0.25)
    save_png(fig, path, dpi=100)
