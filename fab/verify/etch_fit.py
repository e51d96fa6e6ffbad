"""Fit the etch depths of a plate's masks to its measured K x K window.

A depth error scales the phase step a mask adds. The window's far field is then a
sum of the far fields of the pixels of each code (the masks that etch them), each
turned by its code's new phase: ``fab.plate.basis.code_windows``, the plate model's
window with its parts precomputed; exact, and milliseconds a fit. Fitted here: the
deepest mask's error alone (``fit_etch_error``), every mask's together
(``fit_etch_errors``), and the deepest's implied by the zero order alone
(``implied_deep_etch_error``).
"""

import numpy as np

from fab.package.masks import mask_name
from fab.plate.basis import code_windows
from fab.plate.model import code_phases, level_plate_model
from fab.verify.diagnosis import SIGNIFICANCE


def _code_windows(levels, n_levels, k):
    """Return the plate model of a level map's masks (K-order window) and the window of
    each code's pixels (``fab.plate.basis.code_windows``)."""
    plate = level_plate_model(levels, n_levels, k)
    return plate, code_windows(plate)


def fit_etch_error(window, sigma, levels, n_levels, mask_index=0, search=0.5, step=1e-3):
    """Fit the signed depth error of one mask's etch that best explains the measured window.

    An error eps adds the phase -eps * phi to the pixels the mask etches (phi: its
    designed phase, pi for the deepest of 8 levels), so order (m, n) carries
    ``|U_mn + C_mn exp(-i phi eps)|^2`` (U, C: far fields of the pixels left and
    etched). Unlike the zero order alone, the window's orders tell a too deep etch
    from a too shallow one (unless the design is point-symmetric). Weighted least
    squares over eps with a free overall scale.

    Parameters
    ----------
    window : (K, K) float array
        Measured order powers in the design frame (any units).
    sigma : (K, K) float array or None
        Their 1-sigma errors (None: equal weights).
    mask_index : int
        The mask, 0 = deepest (exposed first).

    Returns
    -------
    dict or None
        "eps" (+0.1: the etch is 10 % too deep), "chi2_drop" (how much better the
        fit explains the window than eps = 0, in chi-square units when ``sigma`` is
        given, taken in units of the fit's reduced chi-square where that passes 1),
        "chi2" (the fit's), "reduced_chi2", "psf" (the fitted window, sum 1) and "mask"
        (its name);
        None when the mask etches all pixels or none (the error leaves no trace).
    """
    k = window.shape[0]
    plate, windows = _code_windows(levels, n_levels, k)
    bitmap = plate.bitmaps[mask_index]
    if bitmap.all() or not bitmap.any():
        return None
    # whole multiples of the step, so that +-10 % reads as exactly that either way
    eps = step * np.arange(-round(search / step), round(search / step) + 1)
    errors = np.zeros((len(eps), len(plate.bitmaps)))
    errors[:, mask_index] = eps
    amplitudes = np.einsum("ec,cmn->emn", np.exp(1j * code_phases(plate, errors)), windows)
    model = np.abs(amplitudes.reshape(len(eps), k * k)) ** 2
    wts = np.ones(k * k) if sigma is None else 1 / np.maximum(np.ravel(sigma), 1e-30)
    meas = np.asarray(window, float).ravel() * wts
    model = model * wts[None, :]
    scale = (model @ meas) / np.einsum("ij,ij->i", model, model)
    chi2 = ((model * scale[:, None] - meas[None, :]) ** 2).sum(axis=1)
    best = int(np.argmin(chi2))
    zero = int(np.argmin(np.abs(eps)))
    fitted = (model[best] / wts).reshape(k, k)
    reduced = float(chi2[best]) / max(k * k - 2, 1)  # the scale and eps
    return {
        "eps": float(eps[best]),
        "chi2": float(chi2[best]),
        "chi2_drop": float(chi2[zero] - chi2[best]) / max(reduced, 1.0),
        "reduced_chi2": reduced,
        "psf": fitted / fitted.sum(),
        "mask": mask_name(mask_index, len(plate.bitmaps)),
    }


def _best_one_mask_start(residuals, n_free, search, step=0.05):
    """Return the errors (one mask off, the rest 0) of least chi-square on a grid of
    ``step`` within ``search`` each way: a start past the local minima near 0."""
    grid = step * np.arange(-round(search / step) + 1, round(search / step))
    starts = [np.where(np.arange(n_free) == i, e, 0.0) for i in range(n_free) for e in grid]
    return min(starts, key=lambda x: float((residuals(x) ** 2).sum()))


def fit_etch_errors(window, sigma, levels, n_levels, search=0.5):
    """Fit the depth errors of every mask's etch at once.

    A plate's etches are all off by a little; one mask's error fitted alone takes up
    some of the others'. With errors eps_j, the pixels of code c (the masks j that etch
    them) carry the phase ``-sum_j b_jc phi_j (1 + eps_j)`` (phi_j: mask j's designed
    phase), so the window is ``|sum_c exp(i phase_c) F_c|^2`` with F_c the window far
    field of code c's pixels: exact, and a few K^2 operations an evaluation. Weighted
    least squares with a free scale, from no error and from the best one-mask error on
    a grid, within ``search`` each way.

    Returns
    -------
    dict or None
        "eps" (one error a mask, deepest first; 0 for a mask that etches all pixels
        or none), "chi2" (the fit's), "chi2_drop" (against no error), "mask_chi2" (for
        each mask, how much worse the fit is with its error held at 0 and the others
        refitted), both over the fit's reduced chi-square where that passes 1,
        "eps_sigma" (their 1-sigma errors, from the fit's curvature, in those units),
        "reduced_chi2",
        "at_search_edge", "psf" (the fitted window, sum 1) and "masks" (names);
        None when no mask etches some pixels and not others.
    """
    k = window.shape[0]
    plate, windows = _code_windows(levels, n_levels, k)
    n_masks = len(plate.bitmaps)
    free = [j for j, bm in enumerate(plate.bitmaps) if 0 < bm.mean() < 1]
    if not free:
        return None
    wts = np.ones((k, k)) if sigma is None else 1 / np.maximum(np.asarray(sigma), 1e-30)
    fits = _JointEtchFit(plate, windows, free, np.asarray(window, float) * wts, wts, search)
    # From no error alone the fit can stop in a local minimum near 0 when one etch is
    # far off (past 20 % on a 4-level design); a second start, the best one-mask error
    # on a grid, finds it.
    fit = fits.best_fit(np.zeros(len(free)))
    fit_from_grid = fits.best_fit(_best_one_mask_start(fits.residuals, len(free), search))
    if fit_from_grid.cost < fit.cost * (1 - 1e-6):  # not on a tie: keep the same bits
        fit = fit_from_grid
    chi2 = 2 * fit.cost
    # The photometry's sigmas run short: gains are taken in units of the fit's reduced
    # chi-square where that passes 1, so that noise does not pass for an etch error.
    reduced = chi2 / max(k * k - len(free) - 1, 1)
    mask_chi2 = [0.0] * n_masks
    for i, j in enumerate(free):
        if len(free) == 1:
            rise = (fits.residuals(np.zeros(0), (j,)) ** 2).sum() - chi2
        else:
            rise = 2 * fits.best_fit(np.delete(fit.x, i), (j,)).cost - chi2
        mask_chi2[j] = float(rise / max(reduced, 1.0))
    fit, held, eps_sigma = fits.without_unneeded(fit, mask_chi2, reduced)
    chi2 = 2 * fit.cost  # of the errors returned
    eps = fits.errors(fit.x, held)
    fitted = fits.power(eps)
    return {
        "eps": eps,
        "eps_sigma": eps_sigma,
        "chi2": float(chi2),
        "chi2_drop": float((fits.residuals(np.zeros(len(free))) ** 2).sum() - chi2)
        / max(reduced, 1.0),
        "mask_chi2": mask_chi2,
        "reduced_chi2": float(reduced),
        "at_search_edge": bool(np.any(np.abs(fit.x) > search - 1e-3)),
        "psf": fitted / fitted.sum(),
        "masks": [mask_name(j, n_masks) for j in range(n_masks)],
    }


class _JointEtchFit:
    """The least squares of every free mask's etch error with a free scale."""

    def __init__(self, plate, windows, free, meas, wts, search):
        self.plate, self.windows, self.free = plate, windows, free
        self.meas, self.wts, self.search = meas, wts, search

    def power(self, eps):
        """Return the window of the plate with etch errors ``eps`` (one a mask)."""
        phases = code_phases(self.plate, eps)
        return np.abs(np.einsum("c,cmn->mn", np.exp(1j * phases), self.windows)) ** 2

    def errors(self, x, held=()):
        """Return every mask's error: ``x`` for the free masks not ``held``, else 0."""
        eps = np.zeros(len(self.plate.bitmaps))
        eps[[j for j in self.free if j not in held]] = x
        return eps

    def residuals(self, x, held=()):
        p = self.power(self.errors(x, held)) * self.wts
        return (p * ((p * self.meas).sum() / (p * p).sum()) - self.meas).ravel()

    def best_fit(self, x0, held=()):
        from scipy.optimize import least_squares

        bounds = (-self.search, self.search)
        return least_squares(self.residuals, x0, bounds=bounds, args=(held,))

    def without_unneeded(self, fit, mask_chi2, reduced):
        """Return (fit, held, eps_sigma): the errors the window does not need held at 0
        and the rest refitted, and every mask's 1-sigma error.

        Where two masks trade off (a near-delta design's M2 and M3), the full fit
        stops anywhere along the valley; a held error's sigma is the full fit's:
        how well the window could tell it.
        """

        def sigmas(fit):  # 1-sigma errors from the fit's curvature, in the same units
            cov = np.linalg.pinv(fit.jac.T @ fit.jac) * max(reduced, 1.0)
            return np.sqrt(np.maximum(np.diag(cov), 0.0))

        eps_sigma = self.errors(sigmas(fit))
        held = tuple(j for j in self.free if mask_chi2[j] <= (SIGNIFICANCE + 1) ** 2)
        if not held or len(held) == len(self.free):
            return fit, (), eps_sigma
        kept = [i for i, j in enumerate(self.free) if j not in held]
        fit = self.best_fit(fit.x[kept], held)
        eps_sigma[[self.free[i] for i in kept]] = sigmas(fit)
        return fit, held, eps_sigma


def implied_deep_etch_error(levels, n_levels, zero_order_power, sign_hint=None):
    """Invert the zero-order power for the fractional depth error of the deepest etch.

    With U and C the zero-order amplitudes of the pixels the deepest mask leaves
    and etches, an extra phase delta on the etched pixels gives
    ``|U + C exp(i delta)|^2 = |U|^2 + |C|^2 + 2 |U| |C| cos(delta + arg C - arg U)``;
    the deepest mask's phase is pi, so delta = -pi eps. The zero order alone has
    two solutions (too deep, too shallow): the one nearer ``sign_hint`` (e.g.
    from ``fit_etch_error``) is returned, otherwise the smaller |eps|.
    Returns None when the design makes the zero order insensitive.
    """
    plate, windows = _code_windows(levels, n_levels, 1)  # the zero order alone
    fields = np.exp(1j * code_phases(plate)) * windows[:, 0, 0]
    deep = (np.arange(len(fields)) & 1) != 0  # the codes the deepest mask (bit 0) etches
    u_amp, c_amp = fields[~deep].sum(), fields[deep].sum()
    a = abs(u_amp) ** 2 + abs(c_amp) ** 2
    b = 2 * abs(u_amp) * abs(c_amp)
    if b < 1e-12:
        return None
    psi = np.angle(c_amp) - np.angle(u_amp)
    alpha = np.arccos(np.clip((zero_order_power - a) / b, -1, 1))
    deltas = np.angle(np.exp(1j * np.array([-psi + alpha, -psi - alpha])))
    eps = -deltas / np.pi
    if sign_hint is not None:
        return float(eps[np.argmin(np.abs(eps - sign_hint))])
    return float(eps[np.argmin(np.abs(eps))])
