"""The plate's budget in a camera: its figures against band-pass, stop, defocus and rotation.

:func:`camera_figures` evaluates the effective PSF (:mod:`doe.camera`) for a list of
camera settings and returns, for each, the correlation and rmse against the
design's PSF and the collected fraction. Settings that differ only in their
band-pass share the wavelengths of one grid (:func:`doe.camera.band_spectrum`), so
a band-pass curve costs about its widest band. :data:`BUDGET_AXES` holds the
curves a budget plots (each setting varied alone from the default camera), and
:func:`camera_budget` computes them with the range of each that keeps the goals.
"""

import time

import numpy as np

from doe.camera import band_spectrum, camera_optics, collect, default_margin, design_heights
from doe.fraunhofer import correlation, rmse

# The curves of a camera budget: one setting varied from the default camera (the
# design wavelength, the square clear aperture, in focus, unrotated).
BUDGET_AXES = {
    "bandwidth_nm": (0.0, 5.0, 10.0, 20.0, 30.0, 40.0),
    "f_number": (1.8, 2.8, 4.0, 5.6, 8.0, 11.0, 16.0),
    "defocus_um": (-500.0, -250.0, -100.0, 0.0, 100.0, 250.0, 500.0),
    "rotation_deg": (0.0, 1.0, 2.0, 3.0, 4.0, 5.0),
}
_LENS_KEYS = ("f_number", "defocus_um", "rotation_deg")


def budget_settings(axes=None):
    """Return [(axis, settings dict)] for each point of each curve of ``axes``."""
    axes = BUDGET_AXES if axes is None else axes
    return [(axis, {axis: value}) for axis, values in axes.items() for value in values]


def camera_figures(design, levels, target, settings, *, heights=None):
    """Return one dict per camera setting: the figures of its effective PSF.

    Parameters
    ----------
    design : doe.design.Design
    levels : (N, N) uint8
    target : (K, K) array
        The design's PSF the figures compare with.
    settings : list of dict
        Keys among ``bandwidth_nm``, ``f_number``, ``defocus_um``, ``rotation_deg``
        (as :func:`doe.camera.effective_psf`; absent: the default).
    heights : (N S, N S) array or None
        A faulty plate's glass heights, as :func:`doe.camera.effective_psf` takes them.

    Returns
    -------
    list of dict
        ``settings``, ``correlation``, ``rmse``, ``collected_fraction`` and the
        ``seconds`` its group of settings took, in the order given.
    """
    levels = np.asarray(levels)
    k = target.shape[0]
    if heights is None:
        heights = design_heights(design, levels)
    groups = {}
    for i, s in enumerate(settings):
        groups.setdefault(tuple(s.get(key) for key in _LENS_KEYS), []).append(i)
    out = [None] * len(settings)
    for lens, members in groups.items():
        start = time.perf_counter()
        f_number, defocus_um, rotation_deg = lens
        optics = camera_optics(
            design,
            levels.shape[0],
            f_number=f_number,
            defocus=(defocus_um or 0.0) * 1e-6,
            rotation=rotation_deg or 0.0,
        )
        spectra = [
            band_spectrum(design, (settings[i].get("bandwidth_nm") or 0.0) * 1e-9, optics, k)
            for i in members
        ]
        margin = default_margin(design, optics)
        results = collect(design, heights, optics, spectra, k, margin)
        seconds = time.perf_counter() - start
        for i, (e, _, _) in zip(members, results, strict=True):
            total = float(e.sum())
            psf = e / total
            out[i] = {
                "settings": dict(settings[i]),
                "correlation": correlation(psf, target),
                "rmse": rmse(psf, target),
                "collected_fraction": total,
                "seconds": seconds,
            }
    return out


def camera_budget(design, levels, target, axes=None, *, heights=None):
    """Return the budget curves: per axis its values, figures and the range within the goals.

    ``axes`` maps a setting (``bandwidth_nm``, ``f_number``, ``defocus_um``,
    ``rotation_deg``) to its values (default :data:`BUDGET_AXES`), each varied alone
    from the default camera. ``within_goals`` is [lo, hi], the values of the curve's
    contiguous run around its default (0, or the square clear aperture for the
    f-number: its widest stop) where correlation >= CORRELATION_GOAL and rmse <=
    RMSE_GOAL; None when the default itself misses them.
    """
    axes = BUDGET_AXES if axes is None else axes
    points = budget_settings(axes)
    figures = camera_figures(design, levels, target, [s for _, s in points], heights=heights)
    out = {}
    for axis, values in axes.items():
        mine = [f for (a, _), f in zip(points, figures, strict=True) if a == axis]
        out[axis] = {
            "values": list(values),
            "correlation": [f["correlation"] for f in mine],
            "rmse": [f["rmse"] for f in mine],
            "collected_fraction": [f["collected_fraction"] for f in mine],
            "within_goals": _goal_range(axis, list(values), mine),
        }
    return out


def _goal_range(axis, values, figures):
    """The run of values around the default that meets the goals, as [lo, hi], or None."""
    from doe.goals import CORRELATION_GOAL, RMSE_GOAL

    ok = [
        not (f["correlation"] < CORRELATION_GOAL) and f["rmse"] <= RMSE_GOAL for f in figures
    ]  # a uniform target's correlation is NaN: its rmse decides
    order = np.argsort(values)
    values = [values[i] for i in order]
    ok = [ok[i] for i in order]
    # the default camera: no band, in focus, unrotated, the widest stop (smallest N)
    start = 0 if axis == "f_number" else int(np.argmin(np.abs(values)))
    if not ok[start]:
        return None
    lo = hi = start
    while lo > 0 and ok[lo - 1]:
        lo -= 1
    while hi < len(values) - 1 and ok[hi + 1]:
        hi += 1
    return [values[lo], values[hi]]
