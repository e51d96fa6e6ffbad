"""Fit of an overlay error: one mask of the plate printed off its place.

A mask exposed (dy, dx) off its alignment etches its pattern there; the tile
the plate repeats is then the design's with that mask's bitmap shifted
(periodically). Its orders are exact for any shift, sub-pixel ones included:
a shift of p + f pixels along an axis (p whole, 0 <= f < 1) cuts every pixel
into a part of width f that the mask's pixel i - p - 1 covers and a part of
width 1 - f that its pixel i - p covers, so each order is a sum of four
whole-pixel shifts weighted by the Fourier integrals over those parts.

This is ``fab.plate.tolerance``'s continuous plate (tested equal) restricted to one
mask shifted: the whole-pixel shifts are computed once, so a shift then costs
K^2 operations, and a grid search over thousands takes a fraction of a second
where the general model takes ~10 ms a shift at N = 175.

Shifts are in mask pixels in the layout's axes (+y up, +x right; row 0 of a
level map is the top edge), as ``fab.plate.model.PlateFaults`` states them.
"""

import numpy as np

from fab.package.masks import mask_name, masks_from_levels

# Fitted shifts are named this far each way (10 um at the default 4.99 um pixel):
# farther, the plate is not this design aligned by any lab's process.
REACH_PX = 2.0
# and searched a little farther, so that a shift past the reach lands past it: on
# a search that ended at the reach, an overlay of 2.25 px stopped at 1.83-1.98 px,
# inside, and was named short.
SEARCH_PX = 2.5
# The search: a grid at COARSE_PX, then one at FINE_PX around its best point.
COARSE_PX = 0.1
FINE_PX = 0.01


def _part_integrals(orders, n, frac):
    """Return the integrals of exp(-2 pi i m t / N) over t in [0, f) and [f, 1).

    ``frac`` of any shape S; each integral has the shape S + (len(orders),).
    """
    m = np.asarray(orders, float)
    f = np.asarray(frac, float)[..., None]

    def integral(t0, t1):
        k = -2j * np.pi * m / n
        with np.errstate(divide="ignore", invalid="ignore"):
            value = (np.exp(k * t1) - np.exp(k * t0)) / k
        return np.where(m == 0, t1 - t0, value)

    return integral(0.0, f), integral(f, 1.0)


def _window_arrays(dft, field, bitmap, whole):
    """Return the window orders of ``field``, and of ``field`` times ``bitmap`` rolled by each
    whole shift (p, q) in ``whole`` x ``whole``."""
    return dft @ field @ dft.T, np.array(
        [[dft @ (field * np.roll(bitmap, (p, q), axis=(0, 1))) @ dft.T for q in whole]
         for p in whole]
    )  # fmt: skip


class OverlayModel:
    """Window orders of the design with one mask shifted, for any shift within ``SEARCH_PX``."""

    def __init__(self, levels, n_levels, kernel_size, masks_modelled=None):
        levels = np.asarray(levels)
        n = levels.shape[0]
        self.n, self.orders = n, np.arange(kernel_size) - kernel_size // 2
        self.masks = masks_from_levels(levels, n_levels, level_step=1.0)
        self.names = [mask_name(j, len(self.masks)) for j in range(len(self.masks))]
        self.used = [0 < mk.bitmap.mean() < 1 for mk in self.masks]
        self.phi = np.array([2 * np.pi * mk.steps / n_levels for mk in self.masks])
        phase = -sum(d * mk.bitmap for d, mk in zip(self.phi, self.masks, strict=True))
        self.dft = np.exp(-2j * np.pi * np.outer(self.orders, np.arange(n)) / n) / n
        self.whole = np.arange(int(np.floor(-SEARCH_PX)), int(np.ceil(SEARCH_PX)) + 2)
        self.rest, self.etched, self.contrast = {}, {}, {}
        for j in range(len(self.masks)) if masks_modelled is None else masks_modelled:
            d, mk = self.phi[j], self.masks[j]
            # The plate is A (1 + c M): A the other masks' transmission, c what this one adds.
            rest = np.exp(1j * (phase + d * mk.bitmap))
            self.rest[j], self.etched[j] = _window_arrays(self.dft, rest, mk.bitmap, self.whole)
            self.contrast[j] = np.exp(-1j * d) - 1

    def amplitudes(self, mask, dy, dx):
        """Return the complex window orders with mask ``mask`` shifted by (dy, dx) px.

        ``dy`` and ``dx`` of one shape S (scalars too); the result has S + (K, K).
        """
        rows, cols = -np.asarray(dy, float), np.asarray(dx, float)  # +y is up: towards row 0
        if not (
            np.abs(rows).max(initial=0) <= SEARCH_PX and np.abs(cols).max(initial=0) <= SEARCH_PX
        ):
            raise ValueError(f"a shift beyond the model's reach of {SEARCH_PX} px")
        p, q = np.floor(rows).astype(int), np.floor(cols).astype(int)
        r0, r1 = (r[..., :, None] for r in _part_integrals(self.orders, self.n, rows - p))
        c0, c1 = (c[..., None, :] for c in _part_integrals(self.orders, self.n, cols - q))
        i, j = p - self.whole[0], q - self.whole[0]
        g = self.etched[mask]
        # Part [0, f) of a pixel sees the mask pixel one further back: the shift p + 1.
        etched = (
            r0 * c0 * g[i + 1, j + 1]
            + r0 * c1 * g[i + 1, j]
            + r1 * c0 * g[i, j + 1]
            + r1 * c1 * g[i, j]
        )
        return (r0 + r1) * (c0 + c1) * self.rest[mask] + self.contrast[mask] * etched

    def power(self, mask, dy, dx):
        """Return the order powers (fractions of the beam) of that plate, S + (K, K)."""
        return np.abs(self.amplitudes(mask, dy, dx)) ** 2


class EtchedOverlayModel(OverlayModel):
    """The model of one mask's shift on a plate whose etches are off their depths, where the
    errors change at no cost: the other masks' transmission A is a sum over the classes
    of their bits (4 for 8 levels), each with its phase, so each class's window arrays
    are computed once and an evaluation only weighs them."""

    def __init__(self, levels, n_levels, kernel_size, mask):
        super().__init__(levels, n_levels, kernel_size, masks_modelled=())
        self.mask = mask
        self.others = [k for k in range(len(self.masks)) if k != mask]
        code = sum(self.masks[k].bitmap.astype(int) << i for i, k in enumerate(self.others))
        # bits[c, i]: whether class c's pixels are etched by the i-th other mask
        self.bits = (np.arange(2 ** len(self.others))[:, None] >> np.arange(len(self.others))) & 1
        self.classes = [
            _window_arrays(
                self.dft, (code == c).astype(complex), self.masks[mask].bitmap, self.whole
            )
            for c in range(len(self.bits))
        ]

    def set_etch_errors(self, errors):
        """Take the plate's etches as off by ``errors`` (fractions, deepest mask first)."""
        errors = np.asarray(errors, float)
        depth = self.phi * (1 + errors)
        weights = np.exp(-1j * self.bits @ depth[self.others])
        self.rest[self.mask] = sum(w * r for w, (r, _) in zip(weights, self.classes, strict=True))
        self.etched[self.mask] = sum(w * g for w, (_, g) in zip(weights, self.classes, strict=True))
        self.contrast[self.mask] = np.exp(-1j * depth[self.mask]) - 1


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
        the fit's reduced chi-square where that passes 1), "reduced_chi2" and
        "psf" (the fitted window, sum 1); None when fewer than two masks have both
        etched and unetched pixels: the shift of the one mask then moves the whole
        pattern, which the order powers do not see (a 2-level plate's failing capture
        crashed the overlay-and-etch fit).
    """
    model = OverlayModel(levels, n_levels, window.shape[0])
    if np.count_nonzero(model.used) < 2:
        return None
    wts = np.ones(window.shape) if sigma is None else 1 / np.maximum(np.asarray(sigma), 1e-30)
    meas = np.asarray(window, float) * wts

    def chi2(mask, dy, dx):
        p = model.power(mask, dy, dx) * wts
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
    for j in np.flatnonzero(model.used):
        _, centre = best_on(coarse, j, (0.0, 0.0))
        value, shift = best_on(fine, j, centre)
        fits.append((value, int(j), shift))
    value, j, (dy, dx) = min(fits)
    fitted = model.power(j, dy, dx)
    dof = window.size - 3  # the scale and the shift
    # Photometric sigmas ran 1.2-1.5 times short, and every gain read 1.4-2.3 times too
    # big: a perfect plate's noise fitted as 0.19 px of M2 was worth 14 in chi-square,
    # 10.9 over the fit's reduced chi-square of 1.29.
    reduced = value / max(dof, 1)
    return {
        "mask": model.names[j],
        "mask_index": j,
        "shift_px": [dy, dx],
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

    A sparse design's few bright orders leave the valley flat: its shift wandered by
    0.1-0.4 px over noise, with nothing said of it.
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
        "at_search_edge" and "psf" (the fitted window, sum 1).
    """
    from scipy.optimize import least_squares

    probe = EtchedOverlayModel(levels, n_levels, window.shape[0], mask)
    free = np.flatnonzero(probe.used)
    wts = np.ones(window.shape) if sigma is None else 1 / np.maximum(np.asarray(sigma), 1e-30)
    meas = np.asarray(window, float) * wts

    def power(x):
        errors = np.zeros(len(probe.used))
        errors[free] = x[2:]
        probe.set_etch_errors(errors)
        return probe.power(mask, x[0], x[1])

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
    mask_chi2 = np.zeros(len(probe.used))
    for i, j in enumerate(free, start=2):  # each error held at 0, the rest refitted
        rest = np.delete(reach, i)
        held = least_squares(residuals, np.delete(fit.x, i), bounds=(-rest, rest), args=(i,))
        mask_chi2[j] = 2 * (held.cost - fit.cost) / scale
    eps = np.zeros(len(probe.used))
    eps[free] = fit.x[2:]
    eps_sigma = np.zeros(len(probe.used))
    eps_sigma[free] = np.sqrt(np.maximum(np.diag(cov)[2:], 0.0) * scale)
    fitted = power(fit.x)
    return {
        "mask": probe.names[mask],
        "mask_index": int(mask),
        "shift_px": [float(fit.x[0]), float(fit.x[1])],
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
