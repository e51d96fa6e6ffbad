"""Compare a measured dot lattice with the design and diagnose the plate.

The dot powers measured on the camera lattice (``fab.verify.lattice``) are put into
the design's frame by the camera orientation the user states (never guessed: a
conjugate plate's PSF is the design's rotated by 180 degrees, so a search over
orientations would pass it). The zero order is found by correlating the
measured powers with the design's far field over integer offsets: it is often
not the brightest dot. Then the K x K window is the measured PSF, compared with
``doe.fraunhofer.simulate_levels`` the CONVENTIONS way, and the faults that
leave fingerprints are named: zero-order excess and a deep-etch depth error
(fitted to the window, and implied by the zero order), a point-reflected
pattern (conjugate plate: etch and glass swapped), a mirrored one, a plate of
another design, low signal, saturation. The faults' fits live in ``fab.verify.etch_fit``
and ``fab.verify.overlay``; the rules that name them, in ``fab.verify.diagnosis``.

Far-field model of a real plate: order (m, n) carries
``|DFT[m mod N, n mod N]|^2 sinc^2(m/N) sinc^2(n/N)`` of the power (square
mask pixels); the contract's PSF leaves out the sinc envelope, which inside the
K x K window of an N = 175 tile changes powers by under 0.3 %.
"""

import json
import math

import numpy as np

from doe.fraunhofer import (
    correlation,
    level_phase,
    order_amplitudes,
    pixel_envelope,
    rmse,
    simulate_levels,
    window_indices,
)
from fab.plate.model import PlateFaults, plate_phase
from fab.verify.diagnosis import (
    DECISIVE_CHI2,
    OTHER_DESIGN_MAX,
    SIGNIFICANCE,
    diagnose,
    explaining_fault,
    frame_of_explaining_fault,
    psf_fails,
    winning_reflection,
    zero_order_brightened,
)
from fab.verify.etch_fit import fit_etch_error, fit_etch_errors, implied_deep_etch_error
from fab.verify.overlay import fit_overlay_and_etch, fit_overlay_error

ORIENTATIONS = (
    "as-designed",
    "rot90",
    "rot180",
    "rot270",
    "mirror-x",
    "mirror-y",
    "transpose",
    "antitranspose",
)

# Pass/fail thresholds used when the fabrication manifest has no "acceptance"
# (fab.plate.tolerance derives them from the tolerance budget when it does).
# Efficiency and zero order are relative to the design, because absolute values
# depend on it: efficiency >= ratio * design efficiency, zero order <= design's
# zero order + excess.
DEFAULT_ACCEPTANCE = {
    "correlation_min": 0.95,
    "rmse_max": 0.08,
    "efficiency_ratio_min": 0.85,
    "zero_order_excess_max": 0.01,
}
# The window's signal must stand this far above its noise (else "low_signal").
MIN_WINDOW_SNR = 30.0
# An order carries signal when measured this many sigma above the noise (one false
# detection in ~3 million orders), or predicted by the design above PREDICTED_SIGMAS.
SIGNAL_SIGMAS = 5.0
PREDICTED_SIGMAS = 3.0
# Photometric error of every order besides the background noise (shot noise of the
# bright dots, flat field), as a fraction of its power; used for significance only.
PHOTOMETRIC_FLOOR = 0.01
# A fitted deep-etch depth error beyond this (fraction) fails the plate.
DEEP_ETCH_TOLERANCE = 0.10

# The design's order powers under each point symmetry a faulty plate can show.
_TRANSFORMS = {
    "design": lambda p: p,
    "rot180": lambda p: np.roll(p[::-1, ::-1], 1, axis=(0, 1)),
    "mirror-x": lambda p: np.roll(p[:, ::-1], 1, axis=1),
    "mirror-y": lambda p: np.roll(p[::-1, :], 1, axis=0),
}
# The tile that gives each of those order patterns (a plate made so).
_PLATE_LEVELS = {
    "design": lambda lv, n_levels: lv,
    "rot180": lambda lv, n_levels: (n_levels - 1 - lv.astype(np.int64)).astype(lv.dtype),
    "mirror-x": lambda lv, n_levels: np.ascontiguousarray(lv[:, ::-1]),
    "mirror-y": lambda lv, n_levels: np.ascontiguousarray(lv[::-1, :]),
}


def resolve_thresholds(acceptance, design_efficiency, design_zero_order):
    """Return absolute thresholds from the manifest's "acceptance" or the defaults.

    Returns
    -------
    dict
        correlation_min, rmse_max, efficiency_min, zero_order_max, min_window_snr,
        deep_etch_error_max, significance_sigmas, source.
    """
    if acceptance:
        missing = {"correlation_min", "rmse_max", "efficiency_min", "zero_order_max"} - set(
            acceptance
        )
        if missing:
            raise ValueError(f"acceptance lacks {sorted(missing)}")
        out = {
            k: _threshold(acceptance, k)
            for k in ("correlation_min", "rmse_max", "efficiency_min", "zero_order_max")
        }
        out["source"] = "fab_manifest.json acceptance"
    else:
        d = DEFAULT_ACCEPTANCE
        out = {
            "correlation_min": d["correlation_min"],
            "rmse_max": d["rmse_max"],
            "efficiency_min": d["efficiency_ratio_min"] * design_efficiency,
            "zero_order_max": float(design_zero_order) + d["zero_order_excess_max"],
            "source": "defaults (fab.verify.analysis.DEFAULT_ACCEPTANCE)",
        }
    out["min_window_snr"] = MIN_WINDOW_SNR
    out["deep_etch_error_max"] = (
        _threshold(acceptance, "deep_etch_error_max")
        if acceptance and "deep_etch_error_max" in acceptance
        else DEEP_ETCH_TOLERANCE
    )
    out["significance_sigmas"] = SIGNIFICANCE
    return out


def _threshold(acceptance, key):
    """Return acceptance[key] as a float; ValueError unless it is a finite number.

    A correlation threshold is null for a design whose PSF has no correlation (1 x 1).
    """
    v = acceptance[key]
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ValueError(f"acceptance {key} is {json.dumps(v)}, not a finite number")
    return float(v)


def to_design_frame(array, orientation):
    """Re-index a camera-lattice grid [u, v] into the design's order frame [m, n].

    ``orientation`` says how the camera sees the design: "rot90" means the image
    is the design rotated 90 degrees counter-clockwise, "mirror-x" flipped left
    to right, "transpose" reflected about its main diagonal (rows and columns
    swapped), "antitranspose" about the other diagonal; this undoes it.
    """
    if orientation not in ORIENTATIONS:
        raise ValueError(f"orientation must be one of {ORIENTATIONS}, got {orientation!r}")
    a = np.asarray(array)
    return {
        "as-designed": lambda x: x,
        "rot90": lambda x: np.rot90(x, -1),
        "rot180": lambda x: x[::-1, ::-1],
        "rot270": lambda x: np.rot90(x, 1),
        "mirror-x": lambda x: x[:, ::-1],
        "mirror-y": lambda x: x[::-1, :],
        "transpose": lambda x: x.T,
        "antitranspose": lambda x: x[::-1, ::-1].T,
    }[orientation](a)


def design_order_power(levels, n_levels):
    """Return the (N, N) order powers |DFT|^2 of the design tile (FFT index order, sum 1)."""
    return np.abs(order_amplitudes(level_phase(levels, n_levels))) ** 2


def _model(period_power, m0, n0, shape):
    """Return the model's order powers on a grid whose element [m0, n0] is the zero order."""
    n = period_power.shape[0]
    m = np.arange(shape[0]) - m0
    k = np.arange(shape[1]) - n0
    env = pixel_envelope(m, n)[:, None] * pixel_envelope(k, n)[None, :]
    return period_power[np.ix_(m % n, k % n)] * env


def _finite(x):
    return float(x) if np.isfinite(x) else None


def _scale(meas, model, detected, valid):
    """Return DN per unit beam power: least squares of the model on the detected orders.

    (The sum over every order in the frame would carry the noise of thousands of
    empty apertures.)
    """
    if detected.any():
        den = float((model[detected] ** 2).sum())
        if den > 0:
            return max(float((model[detected] * meas[detected]).sum()) / den, 0.0)
    return max(float(meas[valid].sum()), 0.0) / max(float(model[valid].sum()), 1e-30)


def _pearson(a, b):
    a, b = a - a.mean(), b - b.mean()
    den = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / den) if den > 0 else 0.0


def _model_table(period_power, shape):
    """Return the model's order powers for order offsets -(nu-1)..nu-1 by -(nv-1)..nv-1.

    Element [i, j] is order (i - nu + 1, j - nv + 1), pixel envelope included.
    """
    n = period_power.shape[0]
    m = np.arange(-(shape[0] - 1), shape[0])
    k = np.arange(-(shape[1] - 1), shape[1])
    env = pixel_envelope(m, n)[:, None] * pixel_envelope(k, n)[None, :]
    return period_power[np.ix_(m % n, k % n)] * env


def _correlate(table, grid):
    """Return C[m0, n0] = sum_uv grid[u, v] table[u - m0 + nu - 1, v - n0 + nv - 1] (FFT)."""
    from scipy.signal import fftconvolve

    return fftconvolve(table, grid[::-1, ::-1], mode="valid")[::-1, ::-1]


def offset_chi2(measured, valid, sigma, period_power):
    """Return the chi-square of the far-field model with its zero order at every grid element.

    For a zero order at [m0, n0] the model of order [u, v] is the tile's far
    field at (u - m0, v - n0) with the pixel envelope, times a free scale
    (weighted least squares, >= 0); the chi-square sums over EVERY valid order
    in the frame, each weighted by its noise, so that the weak orders outside
    the K x K window count as much as their signal warrants: they tell a
    design from its point reflection when the window alone cannot (a PSF
    nearly symmetric about a point half an order off the axis). The candidate
    zero order itself is left out (a deep-etch depth error changes it most).
    Orders with no light add the same (their noise) to every candidate.
    Three FFT cross-correlations give all offsets at once.

    Parameters
    ----------
    measured, valid, sigma : (nu, nv) arrays
        Dot powers in the design frame, which are measured, their 1-sigma noise.
    period_power : (N, N) float array
        Order powers of the tile, FFT index order.

    Returns
    -------
    (nu, nv) float array
        Chi-square per candidate zero order (inf where the candidate is not valid).
    """
    wts = np.where(valid, 1.0 / np.where(valid, sigma, 1.0) ** 2, 0.0)
    meas = np.where(valid, measured, 0.0)
    table = _model_table(period_power, measured.shape)
    zero = float(period_power[0, 0])
    a = float((wts * meas**2).sum()) - wts * meas**2
    b = _correlate(table, wts * meas) - wts * meas * zero
    d = _correlate(table**2, wts) - wts * zero**2
    with np.errstate(divide="ignore", invalid="ignore"):
        chi2 = a - np.where((b > 0) & (d > 0), b**2 / d, 0.0)
    return np.where(valid, chi2, np.inf)


def _frame_score(meas, valid, sigma, period_power, m0, n0, half):
    """Pearson correlation of measured and model powers over the orders with signal.

    The orders of the (2 half + 1)^2 window and those that carry signal
    (measured above ``SIGNAL_SIGMAS`` sigma, or predicted so by the design)
    count, the candidate zero order does not; the pixel envelope is divided
    out, so that two unrelated plates do not correlate through it.

    Returns
    -------
    (score, outside_score, outside_orders)
        The correlation (NaN when the design predicts no order but the zero
        order above the noise: nothing to correlate, a flat plate); that over
        the orders with signal outside the window alone (NaN when fewer than
        3) and their count.
    """
    shape = meas.shape
    sig = np.where(valid, sigma, np.inf)
    detected = valid & (meas > SIGNAL_SIGMAS * sig)
    model = _model(period_power, m0, n0, shape)
    scale = _scale(meas, model, detected, valid)
    predicted = valid & (model * scale > PREDICTED_SIGMAS * sig)
    predicted[m0, n0] = False
    use = detected | predicted
    # The window always counts: its dark orders are as telling as its bright ones.
    win = (slice(max(m0 - half, 0), m0 + half + 1), slice(max(n0 - half, 0), n0 + half + 1))
    use[win] |= valid[win]
    use[m0, n0] = False
    if use.sum() < 3:
        return 0.0, float("nan"), 0
    if not predicted.any():
        return float("nan"), float("nan"), 0
    env = np.maximum(_model(np.ones_like(period_power), m0, n0, shape)[use], 0.0025)
    r = _pearson(meas[use] / env, model[use] / env)
    out = use.copy()
    out[win] = False
    r_out = _pearson(meas[out], model[out]) if out.sum() >= 3 else float("nan")
    return r, r_out, int(out.sum())


def locate_zero_order(measured, valid, sigma, period_power, half=5):
    """Find where the zero order sits in a measured grid by matching the design's far field.

    The zero order is the candidate with the least chi-square over all the
    visible orders (``offset_chi2``); the runner-up offset is returned too, so
    that an ambiguous match can be reported rather than passed.

    Parameters
    ----------
    measured : (nu, nv) float array
        Dot powers in the design frame (anything where not ``valid``).
    valid : (nu, nv) bool array
    sigma : (nu, nv) float array
        1-sigma noise of ``measured``.
    period_power : (N, N) float array
        Order powers of the tile, FFT index order.
    half : int
        K // 2.

    Returns
    -------
    dict
        "m0", "n0" (grid indices of the zero order), "chi2" there, "runner_up"
        ((m, n) of the next best offset), "runner_up_chi2", "score" (Pearson
        correlation there, see ``_frame_score``), "outside_score",
        "outside_orders".
    """
    if not valid.any():
        raise ValueError("no valid dot where the zero order could sit")
    chi2 = offset_chi2(measured, valid, sigma, period_power)
    order = np.argsort(chi2, axis=None)
    m0, n0 = (int(i) for i in np.unravel_index(order[0], chi2.shape))
    second = np.unravel_index(order[1], chi2.shape) if order.size > 1 else (m0, n0)
    meas = np.where(valid, measured, 0.0)
    score, out_score, out_orders = _frame_score(meas, valid, sigma, period_power, m0, n0, half)
    return {
        "m0": m0,
        "n0": n0,
        "chi2": float(chi2[m0, n0]),
        "runner_up": (int(second[0]), int(second[1])),
        "runner_up_chi2": float(chi2[second]),
        "score": score,
        "outside_score": out_score,
        "outside_orders": out_orders,
    }


def _in_design_frame(grid, orientation):
    """Return the order powers, their validity and 1-sigma errors in the design frame."""
    power = to_design_frame(grid.power, orientation)
    sigma = to_design_frame(grid.sigma, orientation)
    sigma = np.sqrt(sigma**2 + (PHOTOMETRIC_FLOOR * np.nan_to_num(power)) ** 2)
    return power, to_design_frame(grid.valid, orientation), sigma


def orientations_matching(grid, levels, n_levels, kernel_size):
    """Return the orientations under which the measured orders match the design.

    Matching: the design's far field explains the visible orders with a frame
    correlation of at least ``OTHER_DESIGN_MAX`` (what keeps a plate from being
    "other_design"). A hint for a capture that fails as another design under
    the flag given; it cannot tell a camera mounted otherwise from a mirrored or
    conjugate plate, so it never decides a verdict.
    """
    searches = _searches_by_orientation(grid, levels, n_levels, kernel_size)
    return [o for o, search in searches.items() if search["score"] >= OTHER_DESIGN_MAX]


def orientations_fitting_better(grid, levels, n_levels, kernel_size, chi2, inflation):
    """Return the orientations under which the design fits decisively better than ``chi2``.

    ``chi2`` is the best fit of the hypotheses weighed (the design and its
    reflections under the flag given; ``inflation`` their reduced chi-square
    scale, see ``_search_summary``). A camera or plate turned by 90 degrees is
    none of them: its capture can fit a reflection better than the design and
    pass for a mirrored plate, while the design seen turned fits far better
    still. Best first; a hint, never a verdict.
    """
    searches = _searches_by_orientation(grid, levels, n_levels, kernel_size)
    fits = {o: search["chi2"] for o, search in searches.items()}
    better = [o for o, c in fits.items() if (chi2 - c) / inflation > DECISIVE_CHI2]
    return sorted(better, key=fits.get)


def _searches_by_orientation(grid, levels, n_levels, kernel_size):
    """Return {orientation: locate_zero_order of the design's far field seen so}."""
    period = design_order_power(levels, n_levels)
    searches = {}
    for orientation in ORIENTATIONS:
        power, valid, sigma = _in_design_frame(grid, orientation)
        searches[orientation] = locate_zero_order(power, valid, sigma, period, kernel_size // 2)
    return searches


def analyse(grid, levels, n_levels, kernel_size, orientation, thresholds):
    """Measure the PSF in a registered order grid, compare it with the design and diagnose.

    A plate that a reflection of the design fits better than the bare design does is
    measured as that reflection, unless the design with a fitted fault (an etch or an
    overlay) explains the window and fits the frame better still
    (``result["reflection_set_aside"]`` then names the reflection).

    Parameters
    ----------
    grid : fab.verify.lattice.OrderGrid
        Photometry of the capture (camera frame).
    levels : (N, N) uint8 array
        The design tile.
    n_levels : int
    kernel_size : int
        K.
    orientation : str
        Camera orientation (see ``to_design_frame``).
    thresholds : dict
        From ``resolve_thresholds``.

    Returns
    -------
    (result, measured_psf)
        ``result`` the JSON-ready figures and diagnosis; ``measured_psf`` (K, K)
        float64, >= 0, sum 1, or None when the window runs off the frame
        (``result["window_in_frame"]`` False) or holds no light.
    """
    args = (grid, levels, n_levels, kernel_size, orientation, thresholds)
    result, measured_psf = _analyse_as(None, *args)
    reflection = result["measured_as"]
    if reflection == "design":
        return result, measured_psf
    # A deep etch 45 % off gave the default design's bare plate a reduced chi-square of
    # 40, a mirror fitted its frame better, and the plate was measured as mirrored.
    as_design, design_psf = _analyse_as("design", *args)
    frame = frame_of_explaining_fault(as_design, thresholds)
    if frame is None or not frame > result["frame_correlation"][reflection]:
        return result, measured_psf
    as_design["reflection_set_aside"] = reflection
    as_design["diagnosis"] = diagnose(as_design, thresholds)
    as_design["pass"] = as_design["diagnosis"] == ["ok"]
    return as_design, design_psf


def _analyse_as(plate, grid, levels, n_levels, kernel_size, orientation, thresholds):
    """``analyse`` with the plate measured as ``plate`` ("design" or a reflection; None:
    the reflection that wins, or the design)."""
    power, valid, sigma = _in_design_frame(grid, orientation)
    rows, cols = to_design_frame(grid.rows, orientation), to_design_frame(grid.cols, orientation)
    sat = to_design_frame(grid.saturated, orientation)
    period = design_order_power(levels, n_levels)
    searches = {
        name: locate_zero_order(power, valid, sigma, transform(period), kernel_size // 2)
        for name, transform in _TRANSFORMS.items()
    }
    k, half = kernel_size, kernel_size // 2
    design_psf, design_eff = simulate_levels(levels, n_levels, k)
    result = {
        "frame_correlation": {name: s["score"] for name, s in searches.items()},
        "outside_window_correlation": {
            name: _finite(s["outside_score"]) for name, s in searches.items()
        },
        "outside_window_orders": searches["design"]["outside_orders"],
        "zero_order_search": _search_summary(searches, valid, rows, cols, period, design_psf),
        "design_efficiency": design_eff,
        "design_zero_order": float(period[0, 0]),
        "pitch_px": grid.pitch_px,
    }
    # A plate that a reflection of the design explains (conjugate or mirrored) is
    # measured as what it is, at its own zero order: at the design's, three orders
    # away, its figures and measured PSF described nothing.
    plate = plate or winning_reflection(result) or "design"
    levels, period = _PLATE_LEVELS[plate](levels, n_levels), _TRANSFORMS[plate](period)
    m0, n0 = searches[plate]["m0"], searches[plate]["n0"]
    result["measured_as"] = plate
    result["reflection_set_aside"] = None
    result["zero_order_px"] = [float(rows[m0, n0]), float(cols[m0, n0])]
    sl = (slice(m0 - half, m0 + half + 1), slice(n0 - half, n0 + half + 1))
    in_frame = (
        m0 - half >= 0
        and n0 - half >= 0
        and m0 + half < power.shape[0]
        and n0 + half < power.shape[1]
        and bool(valid[sl].all())
    )
    result["window_in_frame"] = in_frame
    if not in_frame:
        return result, None
    meas = np.where(valid, power, 0.0)
    model = _model(period, m0, n0, power.shape)
    beam = beam_power(meas, sigma, valid, model, sl)
    window = power[sl]
    measured_psf = np.clip(window, 0, None)
    if not (measured_psf.sum() > 0 and beam["power"] > 0):  # no light in the window: no PSF
        return result, None
    measured_psf = measured_psf / measured_psf.sum()
    w_sum, w_var = float(window.sum()), float((sigma[sl] ** 2).sum())
    rest, rest_var = beam["signal"] - w_sum, beam["signal_var"] - w_var
    # efficiency = (W / (W + R)) * model share of the orders used: propagate W and R.
    efficiency = w_sum / beam["power"]
    eff_sigma = (
        beam["model_share"]
        * np.hypot(rest * np.sqrt(w_var), w_sum * np.sqrt(max(rest_var, 0)))
        / max(beam["signal"], 1e-30) ** 2
    )
    zero = float(power[m0, n0]) / beam["power"]
    zero_sigma = zero * np.hypot(
        sigma[m0, n0] / max(abs(power[m0, n0]), 1e-30),
        np.sqrt(beam["signal_var"]) / max(beam["signal"], 1e-30),
    )
    on_camera = float(meas[valid].sum())
    etch_fit = fit_etch_error(window, sigma[sl], levels, n_levels)
    # the deepest error fitted beside the others' (milliseconds): a mid etch 45 % off
    # moved the deepest etch's own fit to 10.3 %, past its tolerance
    joint = fit_etch_errors(window, sigma[sl], levels, n_levels)
    snr = w_sum / np.sqrt(np.nansum(to_design_frame(grid.sigma, orientation)[sl] ** 2))
    result.update(
        {
            "correlation": correlation(measured_psf, design_psf),
            # with the plate it is measured as (the design, or the reflection that won)
            "correlation_as_measured": correlation(
                measured_psf, simulate_levels(levels, n_levels, k)[0]
            ),
            "rmse": rmse(measured_psf, design_psf),
            "efficiency": efficiency,
            "efficiency_sigma": float(eff_sigma),
            # how much of the design's light outside the window lies in orders measured:
            # the rest is taken at the design's share, so near 0 (an 8-bit capture whose
            # outer orders drown in noise) the efficiency is the design's, whatever the plate
            "outside_light_measured": float(
                (beam["model_share"] - model[sl].sum()) / max(1 - model[sl].sum(), 1e-12)
            ),
            "zero_order": zero,
            "zero_order_sigma": float(zero_sigma),
            "zero_order_excess": zero - float(period[0, 0]),
            "implied_deep_etch_error": implied_deep_etch_error(
                levels, n_levels, zero, sign_hint=None if etch_fit is None else etch_fit["eps"]
            ),
            "deep_etch_error_fit": None if etch_fit is None else etch_fit["eps"],
            "deep_etch_error_fit_significance": None if etch_fit is None else etch_fit["chi2_drop"],
            "deep_etch_error_fit_psf": None if etch_fit is None else etch_fit["psf"].tolist(),
            "deep_etch_error_joint_fit": None if joint is None else float(joint["eps"][0]),
            "deep_etch_error_joint_significance": None if joint is None else joint["mask_chi2"][0],
            "correlation_with_fitted_etch": None
            if etch_fit is None
            else correlation(measured_psf, etch_fit["psf"]),
            "rmse_with_fitted_etch": None
            if etch_fit is None
            else rmse(measured_psf, etch_fit["psf"]),
            "power_outside_window": 1 - w_sum / beam["signal"],
            "power_outside_window_sigma": float(
                np.sqrt(max(beam["signal_var"] - w_var, 0)) / beam["signal"]
            ),
            "expected_power_outside_window": 1 - float(model[sl].sum()) / beam["model_share"],
            "power_outside_window_all_orders": 1 - w_sum / on_camera,
            "beam_power_dn": beam["power"],
            "orders_with_signal": beam["orders"],
            "window_snr": float(snr),
            "saturated_dots": int(sat[valid].sum()),
            "saturated_in_window": int(sat[sl].sum()),
            "orders_measured": int(valid.sum()),
            "aperture_radius_px": grid.aperture_radius_px,
            "spot_sigma_px": grid.spot_sigma_px,
            "hot_pixel_orders": grid.spike_orders,
        }
    )
    # Plate faults are fitted only to explain a PSF or a zero order that fails (a second or
    # so at N = 175): a mid etch 30 % too deep brightened a sparse design's zero order by
    # 14 sigma, its PSF still at 0.987, and verify named no etch.
    fails = psf_fails(result, thresholds) or zero_order_brightened(result, thresholds)

    def frame_score(period):
        return _frame_score(meas, valid, sigma, period, m0, n0, half)[0]

    result["overlay_error_fit"] = (
        _overlay_fit(measured_psf, (window, sigma[sl]), frame_score, levels, n_levels)
        if fails
        else None
    )
    result["etch_error_fit"] = (  # the joint fit made above for the deepest etch's rule
        _etch_fit(measured_psf, joint, frame_score, levels, n_levels) if fails else None
    )
    result["overlay_and_etch_fit"] = None
    if fails and explaining_fault(result, thresholds) is None:  # two faults at once?
        result["overlay_and_etch_fit"] = _overlay_and_etch_fit(
            result, measured_psf, (window, sigma[sl]), frame_score, levels, n_levels
        )
    result["diagnosis"] = diagnose(result, thresholds)
    result["pass"] = result["diagnosis"] == ["ok"]
    return result, measured_psf


def _overlay_fit(measured_psf, window, frame_score, levels, n_levels):
    """Return the JSON-ready overlay fit of the window, or None when no mask can shift.

    ``window`` is (powers, sigma); ``frame_score`` maps an order-power period to
    the frame correlation, which is also taken for the fitted plate: a dense
    design's every order changes with the overlay, not only the window's.
    """
    fit = fit_overlay_error(*window, levels, n_levels)
    if fit is None:
        return None
    faults = fit["faults"]
    return {
        "mask": fit["mask"],
        "shift_px": fit["shift_px"],
        "shift_sigma_px": fit["shift_sigma"],
        "significance": fit["chi2_drop"],
        "chi2": fit["chi2"],
        "reduced_chi2": fit["reduced_chi2"],
        **_fitted_plate_figures(measured_psf, fit["psf"], faults, levels, n_levels, frame_score),
    }


def _etch_fit(measured_psf, fit, frame_score, levels, n_levels):
    """Return the JSON-ready form of ``fit_etch_errors``'s ``fit``, or None for None (no
    mask etches some pixels and not others)."""
    if fit is None:
        return None
    faults = PlateFaults(etch_errors=tuple(fit["eps"]))
    return {
        **_etch_error_figures(fit["masks"], fit),
        "significance": fit["chi2_drop"],
        "chi2": fit["chi2"],
        **_fitted_plate_figures(measured_psf, fit["psf"], faults, levels, n_levels, frame_score),
    }


def _etch_error_figures(masks, fit):
    """Return the JSON-ready etch errors of a fit (one a mask, deepest first)."""
    return {
        "masks": masks,
        "errors": [float(e) for e in fit["eps"]],
        "errors_sigma": [float(e) for e in fit["eps_sigma"]],
        "mask_significance": fit["mask_chi2"],
        "reduced_chi2": fit["reduced_chi2"],
        "at_search_edge": fit["at_search_edge"],
    }


def _overlay_and_etch_fit(result, measured_psf, window, frame_score, levels, n_levels):
    """Return the JSON-ready fit of an overlay and the etch depths together, started from
    the two fits alone; None when either is missing."""
    overlay, etch = result["overlay_error_fit"], result["etch_error_fit"]
    if overlay is None or etch is None:
        return None
    mask = etch["masks"].index(overlay["mask"])
    fit = fit_overlay_and_etch(*window, levels, n_levels, mask, overlay["shift_px"], etch["errors"])
    faults = fit["faults"]
    return {
        "mask": fit["mask"],
        "shift_px": fit["shift_px"],
        "shift_sigma_px": fit["shift_sigma"],
        "shift_significance": fit["shift_chi2"],
        **_etch_error_figures(etch["masks"], fit),
        # over the better of the two fits alone: what the second fault is worth
        "significance": (min(overlay["chi2"], etch["chi2"]) - fit["chi2"])
        / max(fit["reduced_chi2"], 1.0),
        "chi2": fit["chi2"],
        **_fitted_plate_figures(measured_psf, fit["psf"], faults, levels, n_levels, frame_score),
    }


def _fitted_plate_figures(measured_psf, fitted_psf, faults, levels, n_levels, frame_score):
    """Return how the design's plate with the fitted ``faults`` meets the measurement: its
    window's correlation and rmse with the measured PSF, its frame's correlation, and
    the window itself."""
    # A shifted mask's plate cut into 8 x 8 sub-pixels (the shift rounded to 1/8 px):
    # exact orders at any distance, aliases and envelope included.
    supersample = 8 if np.any(faults.overlay) else 1
    plate = plate_phase(levels, n_levels, faults, mask_pixel_pitch=1.0, supersample=supersample)
    return {
        "correlation": correlation(measured_psf, fitted_psf),
        "rmse": rmse(measured_psf, fitted_psf),
        "frame_correlation": frame_score(np.abs(order_amplitudes(plate)) ** 2),
        "psf": fitted_psf.tolist(),
    }


def _search_summary(searches, valid, rows, cols, period, design_psf):
    """Return the JSON-ready evidence of the zero-order search.

    The chi-squares are compared after dividing by the reduced chi-square of
    the best hypothesis when it exceeds 1 (a plate with fabrication errors
    fits no model to the noise; its misfit must not pass for evidence).
    "delta_chi2" > 0 means the transform explains the capture better than
    the design; "runner_up_margin" is how much worse the design fits with its
    zero order at the next best place. "transform_psf_correlation" is how
    well each transform of the design's PSF matches the design's PSF: near 1
    when telling them apart does not matter.
    """
    dof = max(int(valid.sum()) - 2, 1)
    best = min(s["chi2"] for s in searches.values())
    inflation = max(1.0, best / dof)
    d = searches["design"]
    k = design_psf.shape[0]
    idx = window_indices(period.shape[0], k)
    psf_corr = {}
    for name, transform in _TRANSFORMS.items():
        window = transform(period)[np.ix_(idx, idx)]
        psf_corr[name] = correlation(window / window.sum(), design_psf)
    r, c = d["runner_up"]
    return {
        "chi2": {name: s["chi2"] for name, s in searches.items()},
        "dof": dof,
        "inflation": inflation,
        "delta_chi2": {
            name: (d["chi2"] - s["chi2"]) / inflation
            for name, s in searches.items()
            if name != "design"
        },
        "runner_up_margin": (d["runner_up_chi2"] - d["chi2"]) / inflation,
        "runner_up_px": [float(rows[r, c]), float(cols[r, c])],
        "transform_psf_correlation": psf_corr,
    }


def beam_power(meas, sigma, valid, model, window):
    """Estimate the whole beam's power (DN) from the orders that carry signal.

    Summing every order in the frame adds the noise of thousands of empty
    apertures; instead the orders of the window, those measured above
    ``SIGNAL_SIGMAS`` sigma and those the design puts above it are summed, and
    divided by the design's share of the beam in those orders (the design's
    far field sums to 1 over all orders).

    The same orders give the on-camera power outside the window: the share of
    their light outside it (the empty apertures would add only noise).

    Returns
    -------
    dict
        "power" (DN), "signal" (DN in the orders used), "signal_var", "model_share",
        "orders" (count).
    """
    detected = valid & (meas > SIGNAL_SIGMAS * sigma)
    scale = _scale(meas, model, detected, valid)
    use = detected | (valid & (model * scale > PREDICTED_SIGMAS * sigma))
    use[window] = True
    signal = float(meas[use].sum())
    share = float(model[use].sum())
    return {
        "power": signal / share,
        "signal": signal,
        "signal_var": float((sigma[use] ** 2).sum()),
        "model_share": share,
        "orders": int(use.sum()),
    }
