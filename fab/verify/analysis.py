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
another design, low signal, saturation. The zero-order search lives in
``fab.verify.zero_order``; the faults' fits in ``fab.verify.etch_fit`` and
``fab.verify.overlay`` (recorded by ``fab.verify.fault_fits``); the rules that name
them, in ``fab.verify.diagnosis``.

Far-field model of a real plate: order (m, n) carries
``|DFT[m mod N, n mod N]|^2 sinc^2(m/N) sinc^2(n/N)`` of the power (square
mask pixels); the contract's PSF leaves out the sinc envelope, which inside the
K x K window of an N = 175 tile changes powers by under 0.3 %.
"""

from dataclasses import dataclass

import numpy as np

from doe.fraunhofer import (
    correlation,
    level_phase,
    order_amplitudes,
    rmse,
)
from fab.plate.budget import verify_thresholds
from fab.verify.bench_band import reference_order_power, reference_window
from fab.verify.diagnosis import (
    DECISIVE_CHI2,
    OTHER_DESIGN_MAX,
    diagnose,
    frame_of_explaining_fault,
    winning_reflection,
)
from fab.verify.etch_fit import fit_etch_error, fit_etch_errors, implied_deep_etch_error
from fab.verify.fault_fits import fit_plate_faults
from fab.verify.zero_order import (
    beam_power,
    frame_score,
    locate_zero_order,
    model_powers,
    search_summary,
)

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

# The window's signal must stand this far above its noise (else "low_signal").
MIN_WINDOW_SNR = 30.0
# Photometric error of every order besides the background noise (shot noise of the
# bright dots, flat field), as a fraction of its power; used for significance only.
PHOTOMETRIC_FLOOR = 0.01
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
    """Return absolute thresholds from the manifest's "acceptance" or the defaults: the one
    budget's (``fab.plate.budget.verify_thresholds``), with the capture's own
    ``min_window_snr``.

    Returns
    -------
    dict
        correlation_min, rmse_max, efficiency_min, zero_order_max, min_window_snr,
        deep_etch_error_max, significance_sigmas, source.
    """
    out = verify_thresholds(acceptance, design_efficiency, design_zero_order)
    out["min_window_snr"] = MIN_WINDOW_SNR
    return out


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


def _finite(x):
    return float(x) if np.isfinite(x) else None


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
    scale, see ``fab.verify.zero_order.search_summary``). A camera or plate
    turned by 90 degrees is none of them: its capture can fit a reflection better
    than the design and pass for a mirrored plate, while the design seen turned
    fits far better still. Best first; a hint, never a verdict.
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


def analyse(grid, levels, n_levels, kernel_size, orientation, thresholds, band=None):
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
    band : fab.verify.bench_band.Band or None
        The bench's light: the design's order powers are averaged over it (None: the
        design wavelength alone).

    Returns
    -------
    (result, measured_psf)
        ``result`` the JSON-ready figures and diagnosis; ``measured_psf`` (K, K)
        float64, >= 0, sum 1, or None when the window runs off the frame
        (``result["window_in_frame"]`` False) or holds no light.
    """
    args = (grid, levels, n_levels, kernel_size, orientation, thresholds, band)
    result, measured_psf = _analyse_as(None, *args)
    reflection = result["measured_as"]
    if reflection == "design":
        return result, measured_psf
    # A plate far off its design (a deep etch far off its depth) fits the bare design so
    # badly that a reflection can fit its frame better: the design with the fitted fault
    # may fit it better still.
    as_design, design_psf = _analyse_as("design", *args)
    frame = frame_of_explaining_fault(as_design, thresholds)
    if frame is None or not frame > result["frame_correlation"][reflection]:
        return result, measured_psf
    as_design["reflection_set_aside"] = reflection
    as_design["diagnosis"] = diagnose(as_design, thresholds)
    as_design["pass"] = as_design["diagnosis"] == ["ok"]
    return as_design, design_psf


@dataclass(frozen=True)
class _Frame:
    """A capture's orders in the design's frame, and the zero-order search on them."""

    power: np.ndarray  # order powers (DN)
    valid: np.ndarray  # measured
    sigma: np.ndarray  # 1-sigma errors, photometric floor included
    rows: np.ndarray  # positions on the camera (px)
    cols: np.ndarray
    saturated: np.ndarray
    period: np.ndarray  # the design's order powers, FFT index order
    searches: dict  # {transform: locate_zero_order of the design's far field so transformed}


def _frame(grid, levels, n_levels, kernel_size, orientation, band=None):
    """Return the capture's orders in the design's frame, the zero order searched for under
    the design and each of its reflections."""
    power, valid, sigma = _in_design_frame(grid, orientation)
    rows, cols = to_design_frame(grid.rows, orientation), to_design_frame(grid.cols, orientation)
    sat = to_design_frame(grid.saturated, orientation)
    period = reference_order_power(levels, n_levels, band)
    searches = {
        name: locate_zero_order(power, valid, sigma, transform(period), kernel_size // 2)
        for name, transform in _TRANSFORMS.items()
    }
    return _Frame(power, valid, sigma, rows, cols, sat, period, searches)


def _analyse_as(plate, grid, levels, n_levels, kernel_size, orientation, thresholds, band):
    """``analyse`` with the plate measured as ``plate`` ("design" or a reflection; None:
    the reflection that wins, or the design)."""
    frame = _frame(grid, levels, n_levels, kernel_size, orientation, band)
    power, valid, sigma, searches = frame.power, frame.valid, frame.sigma, frame.searches
    k, half = kernel_size, kernel_size // 2
    design_psf, design_eff = reference_window(levels, n_levels, k, band)
    result = {
        "frame_correlation": {name: s["score"] for name, s in searches.items()},
        "outside_window_correlation": {
            name: _finite(s["outside_score"]) for name, s in searches.items()
        },
        "outside_window_orders": searches["design"]["outside_orders"],
        "zero_order_search": search_summary(
            searches, valid, frame.rows, frame.cols, frame.period, design_psf, _TRANSFORMS
        ),
        "design_efficiency": design_eff,
        "design_zero_order": float(frame.period[0, 0]),
        "pitch_px": grid.pitch_px,
    }
    # A plate that a reflection of the design explains (conjugate or mirrored) is
    # measured as what it is, at its own zero order: at the design's, orders away,
    # its figures and measured PSF would describe nothing.
    plate = plate or winning_reflection(result) or "design"
    levels, period = _PLATE_LEVELS[plate](levels, n_levels), _TRANSFORMS[plate](frame.period)
    m0, n0 = searches[plate]["m0"], searches[plate]["n0"]
    result["measured_as"] = plate
    result["reflection_set_aside"] = None
    result["zero_order_px"] = [float(frame.rows[m0, n0]), float(frame.cols[m0, n0])]
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
    model = model_powers(period, m0, n0, power.shape)
    beam = beam_power(meas, sigma, valid, model, sl)
    window = power[sl]
    measured_psf = np.clip(window, 0, None)
    if not (measured_psf.sum() > 0 and beam["power"] > 0):  # no light in the window: no PSF
        return result, None
    measured_psf = measured_psf / measured_psf.sum()
    result.update(_psf_figures(measured_psf, design_psf, levels, n_levels, band))
    result.update(_power_figures(frame, (m0, n0), sl, model, beam, period))
    etch_fit = fit_etch_error(window, sigma[sl], levels, n_levels)
    # The deepest etch's error is fitted beside the others' too (milliseconds): an
    # error of another etch can pull its own fit past its tolerance.
    joint = fit_etch_errors(window, sigma[sl], levels, n_levels)
    result.update(
        _etch_figures(measured_psf, levels, n_levels, result["zero_order"], etch_fit, joint)
    )
    result.update(_window_figures(grid, frame, orientation, sl, meas, model, beam))

    def score_frame(period):
        return frame_score(meas, valid, sigma, period, m0, n0, half)[0]

    window_and_sigma = (window, sigma[sl])
    fit_plate_faults(
        result, measured_psf, window_and_sigma, score_frame, levels, n_levels, joint, thresholds
    )
    result["diagnosis"] = diagnose(result, thresholds)
    result["pass"] = result["diagnosis"] == ["ok"]
    return result, measured_psf


def _psf_figures(measured_psf, design_psf, levels, n_levels, band=None):
    """Return how the measured PSF compares with the design's and with the plate's it is
    measured as (the design, or the reflection that won)."""
    k = design_psf.shape[0]
    return {
        "correlation": correlation(measured_psf, design_psf),
        "correlation_as_measured": correlation(
            measured_psf, reference_window(levels, n_levels, k, band)[0]
        ),
        "rmse": rmse(measured_psf, design_psf),
    }


def _power_figures(frame, zero_at, sl, model, beam, period):
    """Return the efficiency and the zero order's power, with their 1-sigma errors.

    efficiency = (W / (W + R)) * the model's share of the orders used, W the window's
    signal and R the rest's: the errors of W and R are propagated.
    """
    power, sigma = frame.power, frame.sigma
    m0, n0 = zero_at
    window = power[sl]
    w_sum, w_var = float(window.sum()), float((sigma[sl] ** 2).sum())
    rest, rest_var = beam["signal"] - w_sum, beam["signal_var"] - w_var
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
    return {
        "efficiency": efficiency,
        "efficiency_sigma": float(eff_sigma),
        # How much of the design's light outside the window lies in orders measured: the
        # rest is taken at the design's share, so near 0 (an 8-bit capture whose outer
        # orders drown in noise) the efficiency is the design's, whatever the plate.
        "outside_light_measured": float(
            (beam["model_share"] - model[sl].sum()) / max(1 - model[sl].sum(), 1e-12)
        ),
        "zero_order": zero,
        "zero_order_sigma": float(zero_sigma),
        "zero_order_excess": zero - float(period[0, 0]),
    }


def _etch_figures(measured_psf, levels, n_levels, zero, etch_fit, joint):
    """Return the deepest etch's error: implied by the zero order's power ``zero``, fitted
    to the window alone (``etch_fit``) and beside the other etches (``joint``)."""
    return {
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
        "rmse_with_fitted_etch": None if etch_fit is None else rmse(measured_psf, etch_fit["psf"]),
    }


def _window_figures(grid, frame, orientation, sl, meas, model, beam):
    """Return the light outside the window, the window's signal-to-noise ratio and what
    the photometry saw (saturated dots, apertures, hot pixels)."""
    power, valid, sigma, sat = frame.power, frame.valid, frame.sigma, frame.saturated
    w_sum, w_var = float(power[sl].sum()), float((sigma[sl] ** 2).sum())
    on_camera = float(meas[valid].sum())
    # the window's noise alone, without the photometric floor of the bright orders
    snr = w_sum / np.sqrt(np.nansum(to_design_frame(grid.sigma, orientation)[sl] ** 2))
    return {
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
