"""Fit of an overlay error: one mask of the plate printed off its place.

A mask exposed (dx, dy) off its alignment etches its pattern there; the tile the plate
repeats is then the design's with that mask's bitmap shifted (periodically). The plate
model is ``fab.plate.basis.ShiftedMaskWindows`` (``fab.plate.model``'s continuous plate
with one mask shifted, its parts precomputed): exact for any shift, sub-pixel ones
included, and K^2 operations a shift, so a grid search over thousands takes a fraction
of a second. This module searches it and takes the fit's sigmas.

Shifts are in mask pixels, x right and y up as ``fab.plate.model.PlateFaults`` states
them; a fit reports them as ``shift_px`` = [dy, dx], the order verify.json records.
"""

import numpy as np

from fab.package.masks import mask_name
from fab.plate.basis import ShiftedMaskWindows
from fab.plate.model import PlateFaults, level_plate_model

# Fitted shifts are named this far each way (10 um at the default 4.99 um pixel):
# farther, the plate is not this design aligned by any lab's process.
REACH_PX = 2.0
# and searched a little farther, so that a shift past the reach lands past it (a
# search that ends at the reach stops a shift just past it inside, named short).
SEARCH_PX = 2.5
# The search: a grid at COARSE_PX, then one at FINE_PX around its best point.
COARSE_PX = 0.1
FINE_PX = 0.01


def fit_overlay_error(window, sigma, levels, n_levels):
    """Fit the mask and shift that best explain the measured window.

    Weighted least squares with a free overall scale, over every mask and
    shifts within ``SEARCH_PX`` each way (grid search, then a finer grid).

    Parameters
    ----------
    window : (K, K) float array
        Measured order powers in the design frame (any units).
    sigma : (K, K) float array or None
        Their 1-sigma errors (None: equal weights).
    levels : (N, N) integer array
    n_levels : int

    Returns
    -------
    dict or None
        "mask" (name, e.g. "M2_mid"), "mask_index" (0 = deepest), "shift_px"
        ([dy, dx], mask pixels, +y up), "shift_sigma" (their 1-sigma errors, None at
        the edge of the search), "chi2" (the fit's), "chi2_drop" (how much
        better than no shift, in chi-square units when ``sigma`` is given, over
        the fit's reduced chi-square where that passes 1), "reduced_chi2", "psf"
        (the fitted window, sum 1) and "faults" (the fitted plate's PlateFaults, overlay
        in mask pixels); None when fewer than two masks have both etched and unetched
        pixels: the shift of the one mask then moves the whole pattern, which the order
        powers do not see.
    """
    plate = level_plate_model(levels, n_levels, window.shape[0])
    used = _structured(plate)
    if len(used) < 2:
        return None
    shifted = {j: ShiftedMaskWindows(plate, j, SEARCH_PX, etch_errors=()) for j in used}
    wts = np.ones(window.shape) if sigma is None else 1 / np.maximum(np.asarray(sigma), 1e-30)
    meas = np.asarray(window, float) * wts

    def chi2(mask, dy, dx):
        p = shifted[mask].power(dx=dx, dy=dy) * wts
        scale = (p * meas).sum(axis=(-2, -1)) / (p * p).sum(axis=(-2, -1))
        return ((p * scale[..., None, None] - meas) ** 2).sum(axis=(-2, -1))

    def best_on(offsets, mask, centre):
        dy, dx = (
            np.clip(c + g, -SEARCH_PX, SEARCH_PX)
            for c, g in zip(centre, np.meshgrid(offsets, offsets, indexing="ij"), strict=True)
        )
        values = chi2(mask, dy, dx)
        best = np.unravel_index(np.argmin(values), values.shape)
        return float(values[best]), (float(dy[best]), float(dx[best]))

    def grid(reach, step):  # whole multiples of the step, so no shift reads 1e-15 for 0
        n = round(reach / step)
        return step * np.arange(-n, n + 1)

    coarse, fine = grid(SEARCH_PX, COARSE_PX), grid(COARSE_PX, FINE_PX)
    fits = []
    for j in used:
        _, centre = best_on(coarse, j, (0.0, 0.0))
        value, shift = best_on(fine, j, centre)
        fits.append((value, j, shift))
    value, j, (dy, dx) = min(fits)
    fitted = shifted[j].power(dx=dx, dy=dy)
    dof = window.size - 3  # the scale and the shift
    # The gain is taken in units of the fit's reduced chi-square where that passes 1:
    # photometric sigmas run short, and the noise of a perfect plate must not pass for a
    # shift.
    reduced = value / max(dof, 1)
    return {
        "mask": mask_name(j, len(plate.bitmaps)),
        "mask_index": j,
        "shift_px": [dy, dx],
        "faults": _one_mask_shifted(len(plate.bitmaps), j, dx, dy),
        "shift_sigma": _shift_sigma(lambda y, x: chi2(j, y, x), dy, dx, value, dof),
        "chi2": float(value),
        "chi2_drop": (float(chi2(j, 0.0, 0.0)) - value) / max(reduced, 1.0),
        "reduced_chi2": float(reduced),
        "psf": fitted / fitted.sum(),
    }


def _shift_sigma(chi2, dy, dx, best, dof, h=FINE_PX):
    """Return the 1-sigma errors [dy, dx] of a fitted shift from the chi-square's curvature
    (finite differences of step ``h``, in units of its reduced chi-square where that
    passes 1), or None at the edge of the search, where the curvature is not there to take.

    A sparse design's few bright orders leave the valley flat: its shift wanders with
    the noise by tenths of a pixel, which the sigmas say.
    """
    if max(abs(dy), abs(dx)) + h > SEARCH_PX:
        return None
    o = np.array([-h, 0.0, h])
    grid = chi2(dy + o[:, None], dx + o[None, :])  # rows: dy, columns: dx
    hessian = (
        np.array(
            [
                [
                    grid[2, 1] - 2 * grid[1, 1] + grid[0, 1],
                    (grid[2, 2] - grid[2, 0] - grid[0, 2] + grid[0, 0]) / 4,
                ],
                [0.0, grid[1, 2] - 2 * grid[1, 1] + grid[1, 0]],
            ]
        )
        / h**2
    )
    hessian[1, 0] = hessian[0, 1]
    cov = 2 * np.linalg.pinv(hessian) * max(best / max(dof, 1), 1.0)
    return np.sqrt(np.maximum(np.diag(cov), 0.0)).tolist()


def fit_overlay_and_etch(window, sigma, levels, n_levels, mask, shift, etch_errors):
    """Fit one mask's shift and every mask's etch depth error together, from a start.

    For a plate with two faults at once, which each fit alone explains only in part:
    weighted least squares with a free scale from ``shift`` (dy, dx, mask pixels) of
    mask index ``mask`` and ``etch_errors`` (deepest first), within ``SEARCH_PX`` and
    +-50 %. Each etch error's significance is the chi-square rise with it held at 0
    and the rest refitted; the shift's, the quadratic form of the pair in the fit's
    curvature; both over the fit's reduced chi-square where that passes 1.

    Returns
    -------
    dict
        "mask", "mask_index", "shift_px", "eps" (deepest first), "chi2",
        "chi2_drop" (against no fault, over the fit's reduced chi-square where that
        passes 1, as are the others), "shift_chi2", "mask_chi2" (one a mask; 0 for
        a mask that etches all pixels or none), "shift_sigma" and "eps_sigma" (1-sigma
        errors from the fit's curvature, in the same units), "reduced_chi2",
        "at_search_edge", "psf" (the fitted window, sum 1) and "faults" (the fitted
        plate's PlateFaults, overlay in mask pixels).
    """
    from scipy.optimize import least_squares

    plate = level_plate_model(levels, n_levels, window.shape[0])
    probe = ShiftedMaskWindows(plate, mask, SEARCH_PX)
    n_masks, free = len(plate.bitmaps), _structured(plate)
    wts = np.ones(window.shape) if sigma is None else 1 / np.maximum(np.asarray(sigma), 1e-30)
    meas = np.asarray(window, float) * wts

    def power(x):  # x: dy, dx, then the free masks' etch errors
        errors = np.zeros(n_masks)
        errors[free] = x[2:]
        probe.set_etch_errors(errors)
        return probe.power(dx=x[1], dy=x[0])

    def residuals(x, held=None):  # held: a parameter kept at 0, left out of x
        x = x if held is None else np.insert(x, held, 0.0)
        p = power(x) * wts
        return (p * ((p * meas).sum() / (p * p).sum()) - meas).ravel()

    reach = np.array([SEARCH_PX, SEARCH_PX] + [0.5] * len(free))
    inside = reach * (1 - 1e-6)  # least_squares wants its start inside the bounds
    x0 = np.clip(np.r_[shift, np.asarray(etch_errors, float)[free]], -inside, inside)
    fit = least_squares(residuals, x0, bounds=(-reach, reach))
    cov = np.linalg.pinv(fit.jac.T @ fit.jac)
    # significances in units of the fit's own residual variance, where it passes 1
    reduced = 2 * fit.cost / max(window.size - len(x0) - 1, 1)
    scale = max(reduced, 1.0)
    mask_chi2 = np.zeros(n_masks)
    for i, j in enumerate(free, start=2):  # each error held at 0, the rest refitted
        rest = np.delete(reach, i)
        held = least_squares(residuals, np.delete(fit.x, i), bounds=(-rest, rest), args=(i,))
        mask_chi2[j] = 2 * (held.cost - fit.cost) / scale
    eps = np.zeros(n_masks)
    eps[free] = fit.x[2:]
    eps_sigma = np.zeros(n_masks)
    eps_sigma[free] = np.sqrt(np.maximum(np.diag(cov)[2:], 0.0) * scale)
    fitted = power(fit.x)
    dy, dx = float(fit.x[0]), float(fit.x[1])
    return {
        "mask": mask_name(mask, n_masks),
        "mask_index": int(mask),
        "shift_px": [dy, dx],
        "faults": _one_mask_shifted(n_masks, mask, dx, dy, etch_errors=tuple(eps)),
        "eps": eps,
        "chi2": float(2 * fit.cost),
        "chi2_drop": float((residuals(np.zeros_like(x0)) ** 2).sum() - 2 * fit.cost) / scale,
        "shift_chi2": float(fit.x[:2] @ np.linalg.pinv(cov[:2, :2]) @ fit.x[:2] / scale),
        "shift_sigma": np.sqrt(np.maximum(np.diag(cov)[:2], 0.0) * scale).tolist(),
        "eps_sigma": eps_sigma,
        "reduced_chi2": float(reduced),
        "mask_chi2": mask_chi2.tolist(),
        "at_search_edge": bool(np.any(np.abs(fit.x) > reach - 1e-3)),
        "psf": fitted / fitted.sum(),
    }


def _structured(plate):
    """Return the indices of the masks that etch some pixels and not others."""
    return [j for j, bm in enumerate(plate.bitmaps) if 0 < bm.mean() < 1]


def _one_mask_shifted(n_masks, mask, dx, dy, etch_errors=()):
    """Return the PlateFaults of a plate with one mask shifted by (dx, dy) mask pixels."""
    overlay = tuple((dx, dy) if j == mask else (0.0, 0.0) for j in range(n_masks))
    return PlateFaults(etch_errors=etch_errors, overlay=overlay)
