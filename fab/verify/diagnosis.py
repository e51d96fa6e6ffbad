"""Name what a verified plate's figures show: the rules of ``doefab verify``'s diagnosis.

``fab.verify.analysis.analyse`` measures a capture and fits the plate faults that could
explain it; the rules here read only that JSON-ready result and the
thresholds. A fault is named when its fit gains decisively on the design,
stays inside its search and the reach it is named in, and explains the window
within the thresholds better than any other fit; a reflection of the design
when it explains the capture decisively better and no fitted fault of the
design does; another design when nothing explains the frame or the window.
"""

import numpy as np

# Failing checks must be this many sigma beyond their threshold (noise is not a fault):
# the one budget's rule (fab.plate.budget).
from fab.plate.budget import SIGNIFICANCE, beyond, fit_sigma
from fab.verify.overlay import REACH_PX as OVERLAY_REACH_PX

# A reflection of the design (rot180: conjugate plate; mirrors) is named when it explains
# the visible orders better than the design by this chi-square (after inflation by the
# best fit's reduced chi-square) and its frame correlation reaches OTHER_DESIGN_MAX; the
# zero order is ambiguous when the runner-up offset, or a reflection whose PSF differs
# from the design's, comes within it.
DECISIVE_CHI2 = 25.0
# Below this frame correlation (design and reflections) the plate is another design ...
OTHER_DESIGN_MAX = 0.8
# ... as it is when neither the design nor the design with a fitted deep-etch error
# reaches this PSF correlation.
EXPLAINED_MIN = 0.95
# Diagnoses after which the process figures are not judged: the plate is not this
# design as oriented, or its figures cannot be trusted.
UNJUDGED_AFTER = (
    "saturated", "low_signal", "conjugate_plate", "mirrored", "other_design",
    "zero_order_ambiguous",
)  # fmt: skip


def is_judged(diagnosis):
    """Whether the plate's PSF and process figures are judged after this diagnosis.

    Not after one that the plate is not this design as oriented, or that its
    figures cannot be trusted (``UNJUDGED_AFTER``); its measured PSF is then no
    PSF to train for either.
    """
    return not set(diagnosis) & set(UNJUDGED_AFTER)


def etched_off(fit):
    """Return [(mask, error)] of the masks whose error the joint etch fit needs (chi-square
    rise over (SIGNIFICANCE + 1)^2 without it), deepest first."""
    return [
        (name, err)
        for name, err, chi2 in zip(
            fit["masks"], fit["errors"], fit["mask_significance"], strict=True
        )
        if chi2 > (SIGNIFICANCE + 1) ** 2
    ]


def explaining_fit(result):
    """Return the fit (overlay, etch depths, or both) behind the faults the diagnosis names,
    or None (none named, or the deepest etch's own fit alone)."""
    diagnosis = set(result["diagnosis"])
    if "overlay_error" in diagnosis:
        both = diagnosis & {"etch_depth_error", "deep_etch_error"}
        return result["overlay_and_etch_fit" if both else "overlay_error_fit"]
    return result["etch_error_fit"] if "etch_depth_error" in diagnosis else None


def fitted_fault(result):
    """Return (what, psf) of the plate fault the diagnosis names, or None.

    ``what`` says the fault in a few words; ``psf`` is the K x K window of the
    design's plate with that fault, fitted to the measurement (sum 1).
    """
    fit = explaining_fit(result)
    if fit is not None:
        parts = []
        if "shift_px" in fit:
            dy, dx = fit["shift_px"]
            parts.append(f"{fit['mask']} shifted y {dy:+.2f}, x {dx:+.2f} mask px")
        if "errors" in fit:
            parts += [f"{name} etch {err:+.1%}" for name, err in etched_off(fit)]
        return ", ".join(parts), np.array(fit["psf"])
    if "deep_etch_error" in result["diagnosis"]:
        what = f"the deepest mask etched {_too(result['deep_etch_error_fit'])}"
        return what, np.array(result["deep_etch_error_fit_psf"])
    return None


def _too(error):
    """'12.0 % too deep' for +0.12, 'too shallow' for a negative error."""
    return f"{abs(error):.1%} too {'deep' if error > 0 else 'shallow'}"


def psf_fails(result, thresholds):
    """Whether the measured PSF misses the design's by the correlation or rmse threshold."""
    return (
        result["correlation"] < thresholds["correlation_min"]
        or result["rmse"] > thresholds["rmse_max"]
    )


def _zero_order_fails(result, thresholds):
    """Whether the zero order is brighter than its threshold by ``SIGNIFICANCE`` sigma."""
    return (
        result["zero_order"] - thresholds["zero_order_max"]
        > SIGNIFICANCE * result["zero_order_sigma"]
    )


def zero_order_brightened(result, thresholds):
    """Whether the zero order fails and is decisively brighter than the design's own: a
    plate fault to look for (a design may miss an absolute ``zero_order_max`` itself)."""
    excess = result["zero_order_excess"] > SIGNIFICANCE * result["zero_order_sigma"]
    return excess and _zero_order_fails(result, thresholds)


def best_frame_correlation(result):
    """Return the best frame correlation of the design and its reflections (NaN if none).

    None is defined for a design with light in its zero order alone; NaN then
    compares False with any threshold, so the frame decides nothing.
    """
    scores = [s for s in result["frame_correlation"].values() if np.isfinite(s)]
    return max(scores, default=float("nan"))


def _other_design(result):
    """Whether neither the design nor the design with a fitted fault explains the plate.

    A dense design shows it in the whole frame (its speckle of weak orders is
    unrelated to another design's); a compact one only in the window, where a
    plate of this design with a depth or overlay error still matches the fitted model.
    """
    fits = list(_significant_fits(result).values())
    # and an overlay fit beyond the reach a shift is named in: a mask printed far off
    # still makes a plate of this design, which the fit at its search's edge matches
    overlay = result["overlay_error_fit"]
    if (
        overlay is not None
        and not within_reach(overlay)
        and overlay["significance"] > (SIGNIFICANCE + 1) ** 2
    ):
        fits.append(overlay)
    frame = best_frame_correlation(result)
    frames = [fit["frame_correlation"] for fit in fits]
    # The joint etch fit's plate counts for the frame even when it needs the deepest etch
    # alone (deep_etch_error's, not among the significant fits): a dense design's every
    # order changes with it, so a deep etch far off takes the bare design's frame
    # correlation below OTHER_DESIGN_MAX as another design would.
    etch = result["etch_error_fit"]
    if _decisive(etch):
        frames.append(etch["frame_correlation"])
    for value in frames:  # NaN (no frame to judge) loses to any number
        frame = float(np.fmax(frame, value))
    # but a fitted plate that lights its zero order alone leaves the frame nothing to
    # judge: the rest of the beam lies near the noise and correlates with nothing, though
    # the window may match the design closely
    flat = any(value is None or np.isnan(value) for value in frames)
    if frame < OTHER_DESIGN_MAX and not flat:
        return True
    explained = max(
        result["correlation"],
        result["correlation_with_fitted_etch"] or -1.0,
        *(fit["correlation"] for fit in fits),
    )
    return explained < EXPLAINED_MIN


def _significant_fits(result):
    """Return the fitted faults (by diagnosis code) that explain the window decisively better
    than the design does (``_decisive``)."""
    fits = {}
    overlay = result["overlay_error_fit"]
    if _decisive(overlay):
        fits["overlay_error"] = overlay
    etch = result["etch_error_fit"]
    # named for the shallower masks: the deepest alone is deep_etch_error's
    if _decisive(etch) and any(name != etch["masks"][0] for name, _ in etched_off(etch)):
        fits["etch_depth_error"] = etch
    both = result["overlay_and_etch_fit"]
    both_needed = both is not None and both["shift_significance"] > (SIGNIFICANCE + 1) ** 2
    if _decisive(both) and both_needed and etched_off(both):
        fits["overlay_and_etch"] = both
    return fits


def _decisive(fit):
    """Whether a fit gains a chi-square over (SIGNIFICANCE + 1)^2 and stops inside its search
    and the reach a shift is named in (else the fault may lie beyond, and the window's
    few orders fit a wrong value within it all too well)."""
    return (
        fit is not None
        and not fit.get("at_search_edge")
        and within_reach(fit)
        and fit["significance"] > (SIGNIFICANCE + 1) ** 2
    )


def _explains(fit, thresholds):
    """Whether a fitted plate's window meets the correlation and rmse thresholds."""
    return (
        fit["correlation"] >= thresholds["correlation_min"]
        and fit["rmse"] <= thresholds["rmse_max"]
    )


def within_reach(fit):
    """Whether a fit's shift (if it has one) lies within the reach a shift is named in;
    the search goes a little farther, so that a shift beyond it is seen to be."""
    return max(map(abs, fit.get("shift_px", [0.0]))) < OVERLAY_REACH_PX


# The fit in the result behind each explanation explaining_fault can return.
EXPLAINING_FIT = {
    "overlay_error": "overlay_error_fit",
    "etch_depth_error": "etch_error_fit",
    "overlay_and_etch": "overlay_and_etch_fit",
}


def explaining_fault(result, thresholds):
    """Return the diagnosis code of the fitted fault that explains the failing PSF: within
    the thresholds, and better than a deep-etch error and than the other fault; or None."""
    significant = _significant_fits(result)
    fits = {
        code: fit
        for code, fit in significant.items()
        if _explains(fit, thresholds)
        and fit["correlation"] > (result["correlation_with_fitted_etch"] or -1.0)
    }
    pinned = _pinned_correlation(result)
    fits = {code: fit for code, fit in fits.items() if fit["correlation"] > pinned}
    return max(fits, key=lambda code: fits[code]["correlation"], default=None)


def _pinned_correlation(result):
    """Return the window correlation of the best decisive fit left out at the edge of its
    range (-1 when none is).

    A fault named must explain the window better: it is that one, beyond its reach (a
    mask printed far off can pass for an etch error of another mask, whose fit meets the
    strict thresholds, or on a sparse design for the deepest etch a few per cent off).
    """
    overlay, etch = result["overlay_error_fit"], result["etch_error_fit"]
    pinned = [
        fit["correlation"]
        for fit, left_out in (
            (overlay, overlay is not None and not within_reach(overlay)),
            (etch, etch is not None and etch["at_search_edge"]),
        )
        if fit is not None and left_out and fit["significance"] > (SIGNIFICANCE + 1) ** 2
    ]
    return max(pinned, default=-1.0)


def _ambiguous(result, thresholds):
    """Whether the capture cannot tell where the zero order is, when it matters.

    Either the design fits nearly as well with its zero order one place
    further, or a reflection of the design (whose PSF differs from the
    design's beyond the acceptance) fits nearly as well as the design, and
    no fitted fault of the design explains the window and fits the frame better.
    """
    search = result["zero_order_search"]
    if search["runner_up_margin"] < DECISIVE_CHI2:
        return True
    # a plate with an etch far off can fit a mirror about as well as the bare design,
    # while the design with the fitted etch explains window and frame: not ambiguous
    fault = frame_of_explaining_fault(result, thresholds)
    return any(
        abs(d) <= DECISIVE_CHI2
        and search["transform_psf_correlation"][t] < thresholds["correlation_min"]
        and not (fault is not None and fault > result["frame_correlation"][t])
        for t, d in search["delta_chi2"].items()
    )


def frame_of_explaining_fault(result, thresholds):
    """Return the best frame correlation of the design's plates with a fitted fault that
    explain the window within the thresholds, decisively and within the fit's reach;
    None when none does."""
    fits = (result.get(key) for key in EXPLAINING_FIT.values())  # none off the frame
    frames = [
        fit["frame_correlation"] for fit in fits if _decisive(fit) and _explains(fit, thresholds)
    ]
    return max(frames, default=None)


def winning_reflection(result):
    """Return the reflection of the design that explains the capture decisively better, or None.

    "rot180" is a conjugate plate (etch and glass swapped), "mirror-x"/"mirror-y"
    a mirrored one.
    """
    frame = result["frame_correlation"]
    delta = result["zero_order_search"]["delta_chi2"]
    better = [t for t in delta if delta[t] > DECISIVE_CHI2 and frame[t] >= OTHER_DESIGN_MAX]
    return max(better, key=lambda t: delta[t]) if better else None


def _deep_etch_off(result, thresholds):
    """Whether the deepest etch's own fit is off decisively: beyond its tolerance, or, on a
    PSF that fails or a zero order brightened, by what brings the PSF within the thresholds.

    A deep etch off within its tolerance can still fail a design's PSF: where its fit
    explains the window, it is named rather than left a bare psf_mismatch.
    """
    fit = result["deep_etch_error_fit"]
    if fit is None or result["deep_etch_error_fit_significance"] <= (SIGNIFICANCE + 1) ** 2:
        return False
    explains = (
        result["correlation_with_fitted_etch"] >= thresholds["correlation_min"]
        and result["rmse_with_fitted_etch"] <= thresholds["rmse_max"]
    )
    tolerance = thresholds["deep_etch_error_max"]
    joint = result["deep_etch_error_joint_fit"]  # the other etches' errors fitted too
    joint_off = joint is None or (
        result["deep_etch_error_joint_significance"] > (SIGNIFICANCE + 1) ** 2
    )
    if deep_etch_beyond_budget(result, tolerance) and (
        joint is None or (abs(joint) > tolerance and joint_off)
    ):
        return True
    if psf_fails(result, thresholds):
        return explains
    # a zero order brightened, the PSF within: the deepest only where the others' fit agrees
    # (on a sparse design, another etch far off pulls the deepest's own fit off too)
    return zero_order_brightened(result, thresholds) and explains and joint_off


def deep_etch_beyond_budget(result, tolerance):
    """Whether the deepest etch's own fit lies beyond ``tolerance`` (its budget) by
    ``SIGNIFICANCE`` of its 1-sigma error (from the fit's chi-square gain)."""
    fit = result["deep_etch_error_fit"]
    if fit is None:
        return False
    return beyond(fit, fit_sigma(fit, result["deep_etch_error_fit_significance"]), tolerance)


def diagnose(result, thresholds):
    """Return the list of short diagnosis codes (["ok"] when every check holds).

    Codes: "saturated", "low_signal", "conjugate_plate", "mirrored",
    "other_design", "zero_order_ambiguous", "zero_order_excess", "overlay_error",
    "etch_depth_error" (a mask other than the deepest), "deep_etch_error", "psf_mismatch",
    "low_efficiency". A check on a noisy figure (zero order, efficiency) fails only
    when it misses its threshold by ``SIGNIFICANCE`` sigma.
    """
    codes = []
    if result["saturated_dots"]:
        codes.append("saturated")
    if result["window_snr"] < thresholds["min_window_snr"]:
        codes.append("low_signal")
    reflection = None if result["reflection_set_aside"] else winning_reflection(result)
    # The reflection must explain the window too: a plate of another design can fit the
    # conjugate of a nearly point-symmetric design better than the design itself.
    if reflection and result["correlation_as_measured"] >= EXPLAINED_MIN:
        codes.append("conjugate_plate" if reflection == "rot180" else "mirrored")
    elif not codes and (reflection or _other_design(result)):  # clipped or noisy windows
        codes.append("other_design")  # explain nothing
    elif not codes and _ambiguous(result, thresholds):
        codes.append("zero_order_ambiguous")
    process = []
    if codes:  # a plate that is not this design: its process figures mean nothing
        return codes
    if _zero_order_fails(result, thresholds):
        process.append("zero_order_excess")
    fault = explaining_fault(result, thresholds)
    if fault in ("overlay_error", "overlay_and_etch"):
        process.append("overlay_error")
    if fault in ("etch_depth_error", "overlay_and_etch"):  # deepest fitted with the others
        etch = result[EXPLAINING_FIT[fault]]
        off = etched_off(etch)
        if any(name != etch["masks"][0] for name, _ in off):
            process.append("etch_depth_error")
        deep = [err for name, err in off if name == etch["masks"][0]]
        deep_sigma = (etch.get("errors_sigma") or [None])[0]
        if deep and beyond(deep[0], deep_sigma, thresholds["deep_etch_error_max"]):
            process.append("deep_etch_error")
    elif (
        fault is None
        and _deep_etch_off(result, thresholds)
        and result["correlation_with_fitted_etch"] > _pinned_correlation(result)
    ):  # not with an overlay's
        process.append("deep_etch_error")
    codes += process
    if not codes or codes == process:
        if psf_fails(result, thresholds):
            codes.append("psf_mismatch")
        if (
            result["efficiency"] + SIGNIFICANCE * result["efficiency_sigma"]
            < thresholds["efficiency_min"]
        ):
            codes.append("low_efficiency")
    return codes or ["ok"]
