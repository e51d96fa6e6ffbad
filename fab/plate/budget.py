"""The one tolerance budget: what the fab report states and what ``doefab verify`` judges by.

The budget is the fabrication that keeps the design's goals: each error kind (a mask's
etch depth, a mask's overlay, the CD bias) may go as far as keeps the plate's rmse
against the target within the nominal plate's + ``RMSE_ALLOWANCE``
(``fab.plate.tolerance`` bisects it with the plate model). From it:

* ``acceptance``: the limits a captured PSF is held to, written into
  ``fab_manifest.json`` (``"acceptance"``) and printed by the fab report: the worst
  figures of random plates with every error within its budget at once, widened by the
  measurement margins, and ``deep_etch_error_max``, the deepest etch's own budget (the
  one error verify measures on every plate, from the window's fit);
* ``verify_thresholds``: those limits as verify applies them (``verify.json``'s
  ``"thresholds"`` quote them unchanged), or ``DEFAULT_ACCEPTANCE`` for a folder that has
  no budget (a retrieve output);
* ``beyond``: the rule verify's table and verdict share: a measured figure fails its
  limit only when it misses by ``SIGNIFICANCE`` sigma, so a good plate is not failed by
  the noise of its capture.
"""

import json
import math

# How much peak-normalised RMS a fabrication error may add to the nominal plate's rmse
# against the target before it is out of budget (see fab.plate.tolerance.ToleranceSpec).
RMSE_ALLOWANCE = 0.01
# Allowances for measurement error when a captured PSF is compared with the limits.
CORRELATION_MARGIN = 0.02
RMSE_MARGIN = 0.01
EFFICIENCY_MARGIN = 0.05
ZERO_ORDER_MARGIN = 0.005
# A measured figure fails its limit only when it misses by this many sigmas.
SIGNIFICANCE = 2.0
# A folder without a budget (a retrieve output): efficiency and zero order relative to the
# design's own (efficiency >= ratio * design efficiency, zero order <= design's + excess).
DEFAULT_ACCEPTANCE = {
    "correlation_min": 0.95,
    "rmse_max": 0.08,
    "efficiency_ratio_min": 0.85,
    "zero_order_excess_max": 0.01,
}
# The deepest etch's error allowed where the folder has no budget (fraction).
DEFAULT_DEEP_ETCH_ERROR_MAX = 0.10
# The four limits every acceptance holds.
PSF_LIMITS = ("correlation_min", "rmse_max", "efficiency_min", "zero_order_max")


MARGINS = (CORRELATION_MARGIN, RMSE_MARGIN, EFFICIENCY_MARGIN, ZERO_ORDER_MARGIN)


def acceptance(monte_carlo, budget, deepest_mask, margins=MARGINS):
    """Return the acceptance limits of a tolerance analysis.

    ``monte_carlo`` holds the random plates' "correlation_vs_reference",
    "rmse_vs_reference", "efficiency" and "zero_order" lists; ``budget`` the analysis's
    budget rows; ``deepest_mask`` the deepest mask's name; ``margins`` the measurement
    margins (correlation, rmse, efficiency fraction, zero order).
    """
    corr_m, rmse_m, eff_m, zero_m = margins
    deep = [b for b in budget if b["kind"] == "etch" and b["mask"] == deepest_mask]
    return {
        "correlation_min": min(monte_carlo["correlation_vs_reference"]) - corr_m,
        "rmse_max": max(monte_carlo["rmse_vs_reference"]) + rmse_m,
        "efficiency_min": min(monte_carlo["efficiency"]) * (1 - eff_m),
        "zero_order_max": max(monte_carlo["zero_order"]) + zero_m,
        "deep_etch_error_max": deep[0]["si_value"] if deep else DEFAULT_DEEP_ETCH_ERROR_MAX,
    }


def verify_thresholds(limits, design_efficiency, design_zero_order):
    """Return the limits verify applies: a folder's ``acceptance`` as written, or the
    defaults (relative to the design's efficiency and zero order).

    Returns
    -------
    dict
        correlation_min, rmse_max, efficiency_min, zero_order_max, deep_etch_error_max,
        significance_sigmas, source. ValueError for an acceptance that lacks one of
        the four PSF limits or holds one that is no finite number.
    """
    if limits:
        missing = set(PSF_LIMITS) - set(limits)
        if missing:
            raise ValueError(f"acceptance lacks {sorted(missing)}")
        out = {k: _number(limits, k) for k in PSF_LIMITS}
        out["source"] = "fab_manifest.json acceptance"
    else:
        d = DEFAULT_ACCEPTANCE
        out = {
            "correlation_min": d["correlation_min"],
            "rmse_max": d["rmse_max"],
            "efficiency_min": d["efficiency_ratio_min"] * design_efficiency,
            "zero_order_max": float(design_zero_order) + d["zero_order_excess_max"],
            # the name verify.json has always recorded for these defaults
            "source": "defaults (fab.verify.DEFAULT_ACCEPTANCE)",
        }
    has_deep = bool(limits) and "deep_etch_error_max" in limits
    out["deep_etch_error_max"] = (
        _number(limits, "deep_etch_error_max") if has_deep else DEFAULT_DEEP_ETCH_ERROR_MAX
    )
    out["deep_etch_error_source"] = (
        "the deepest etch's fabrication budget" if has_deep else "default (no budget)"
    )
    out["significance_sigmas"] = SIGNIFICANCE
    return out


def beyond(value, sigma, limit, sigmas=SIGNIFICANCE):
    """Whether |value| exceeds ``limit`` by more than ``sigmas`` of its 1-sigma ``sigma``
    (None or NaN: taken as 0)."""
    s = 0.0 if sigma is None or not math.isfinite(sigma) else abs(sigma)
    return abs(value) - sigmas * s > limit


def fit_sigma(value, chi2_gain):
    """Return the 1-sigma error of a fitted value from its chi-square gain over 0 (a
    quadratic chi-square: gain = (value / sigma)^2); None when the gain says nothing."""
    if value is None or chi2_gain is None or not chi2_gain > 0:
        return None
    return abs(value) / math.sqrt(chi2_gain)


def _number(limits, key):
    """Return limits[key] as a float; ValueError unless it is a finite number.

    A correlation threshold is null for a design whose PSF has no correlation (1 x 1).
    """
    v = limits[key]
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ValueError(f"acceptance {key} is {json.dumps(v)}, not a finite number")
    return float(v)
