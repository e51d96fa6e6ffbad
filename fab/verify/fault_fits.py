"""The JSON-ready fits of plate faults to a measured window: an overlay, the etch depths, both.

Each fit (``fab.verify.overlay``, ``fab.verify.etch_fit``) is recorded with how the
design's plate with the fitted faults meets the measurement: its window's
correlation and rmse with the measured PSF and its frame's correlation
(``fitted_plate_figures``), which ``fab.verify.diagnosis`` weighs.
"""

import numpy as np

from doe.fraunhofer import correlation, order_amplitudes, rmse
from fab.plate.model import PlateFaults, plate_phase
from fab.verify.diagnosis import explaining_fault, psf_fails, zero_order_brightened
from fab.verify.overlay import fit_overlay_and_etch, fit_overlay_error


def overlay_fit_record(measured_psf, window, frame_score, levels, n_levels):
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
        **fitted_plate_figures(measured_psf, fit["psf"], faults, levels, n_levels, frame_score),
    }


def etch_fit_record(measured_psf, fit, frame_score, levels, n_levels):
    """Return the JSON-ready form of ``fit_etch_errors``'s ``fit``, or None for None (no
    mask etches some pixels and not others)."""
    if fit is None:
        return None
    faults = PlateFaults(etch_errors=tuple(fit["eps"]))
    return {
        **etch_error_figures(fit["masks"], fit),
        "significance": fit["chi2_drop"],
        "chi2": fit["chi2"],
        **fitted_plate_figures(measured_psf, fit["psf"], faults, levels, n_levels, frame_score),
    }


def etch_error_figures(masks, fit):
    """Return the JSON-ready etch errors of a fit (one a mask, deepest first)."""
    return {
        "masks": masks,
        "errors": [float(e) for e in fit["eps"]],
        "errors_sigma": [float(e) for e in fit["eps_sigma"]],
        "mask_significance": fit["mask_chi2"],
        "reduced_chi2": fit["reduced_chi2"],
        "at_search_edge": fit["at_search_edge"],
    }


def overlay_and_etch_fit_record(result, measured_psf, window, frame_score, levels, n_levels):
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
        **etch_error_figures(etch["masks"], fit),
        # over the better of the two fits alone: what the second fault is worth
        "significance": (min(overlay["chi2"], etch["chi2"]) - fit["chi2"])
        / max(fit["reduced_chi2"], 1.0),
        "chi2": fit["chi2"],
        **fitted_plate_figures(measured_psf, fit["psf"], faults, levels, n_levels, frame_score),
    }


def fitted_plate_figures(measured_psf, fitted_psf, faults, levels, n_levels, frame_score):
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


def fit_plate_faults(
    result, measured_psf, window, frame_score, levels, n_levels, joint, thresholds
):
    """Add the fits of plate faults that may explain a failing window to ``result``.

    The faults are fitted only where the PSF or the zero order fails (a second or so
    at N = 175): "overlay_error_fit", "etch_error_fit" (the joint fit ``joint`` of
    every etch depth, already made for the deepest etch's rule) and, where neither
    fault alone explains the window, "overlay_and_etch_fit"; None where not fitted.
    A zero order brighter than the design's counts as failing though the PSF passes:
    a mid etch far off can leave a sparse design's PSF within its thresholds.

    Parameters
    ----------
    result : dict
        The analysis so far (figures of the window and zero order).
    measured_psf : (K, K) float array
    window : (powers, sigma)
        The measured window's order powers and their 1-sigma errors.
    frame_score : callable
        Maps an order-power period to the frame correlation.
    levels : (N, N) array
        The tile the plate is measured as.
    n_levels : int
    joint : dict or None
        ``fit_etch_errors`` of the window.
    thresholds : dict
    """
    fails = psf_fails(result, thresholds) or zero_order_brightened(result, thresholds)
    result["overlay_error_fit"] = (
        overlay_fit_record(measured_psf, window, frame_score, levels, n_levels) if fails else None
    )
    result["etch_error_fit"] = (
        etch_fit_record(measured_psf, joint, frame_score, levels, n_levels) if fails else None
    )
    result["overlay_and_etch_fit"] = None
    if fails and explaining_fault(result, thresholds) is None:  # two faults at once?
        result["overlay_and_etch_fit"] = overlay_and_etch_fit_record(
            result, measured_psf, window, frame_score, levels, n_levels
        )
