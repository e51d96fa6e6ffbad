"""The plate's budget in a camera: its figures against band-pass, stop, defocus and rotation.

:func:`camera_figures` evaluates the effective PSF (:mod:`doe.camera`) for a list of
camera settings and returns, for each, the correlation and rmse against the
design's PSF and the collected fraction. Settings that differ only in their
band-pass share the wavelengths of one grid (:func:`doe.camera.band_spectrum`), so
a band-pass curve costs about its widest band. :data:`BUDGET_AXES` holds the
curves a budget plots (each setting varied alone from the default camera), and
:func:`camera_budget` computes them with the range of each that keeps the budget.

The budget is the fabrication budget's rule (``fab.plate.budget``): a setting may
go as far as keeps the effective PSF's rmse against the design's PSF within the
nominal camera's rmse + ``allowance`` (0.01 of the peak). The nominal camera (the
design wavelength, the plate's square clear aperture as the stop, in focus,
unrotated) is the reference, not the design goals: its finite dots spill past the
active areas, so its rmse may already exceed the goals' (the budget says so). A
range end is where the curve crosses the limit: the coarse points are refined by
bisection in the interval that brackets the crossing, down to :data:`RESOLUTION`,
and the end is interpolated linearly within that interval.
"""

import math
import time

import numpy as np

from doe.camera import band_spectrum, camera_optics, collect, default_margin, design_heights
from doe.fraunhofer import correlation, level_phase, plate_quality, rmse
from doe.goals import CORRELATION_GOAL, RMSE_GOAL

# The curves of a camera budget: one setting varied from the default camera (the
# design wavelength, the square clear aperture, in focus, unrotated). The band-passes
# share one wavelength grid (each costs one area integral more than the widest);
# the others are refined where they cross the limit (RESOLUTION).
BUDGET_AXES = {
    "bandwidth_nm": (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0),
    "f_number": (1.8, 4.0, 8.0, 16.0),
    "defocus_um": (-500.0, -250.0, -100.0, 0.0, 100.0, 250.0, 500.0),
    "rotation_deg": (0.0, 1.0, 2.0, 3.0, 4.0, 5.0),
}
# How finely a range end is bisected: the interval that brackets the crossing is
# halved until it is this narrow (the f-number: this fraction of its value).
RESOLUTION = {"bandwidth_nm": 5.0, "f_number": 0.1, "defocus_um": 20.0, "rotation_deg": 0.25}
# The rmse a camera setting may add to the nominal camera's: the one tolerance budget's
# (fab.plate.budget.RMSE_ALLOWANCE), which the fab report passes in itself.
RMSE_ALLOWANCE = 0.01
_LENS_KEYS = ("f_number", "defocus_um", "rotation_deg")
_FIGURES = ("correlation", "rmse", "collected_fraction")


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


def camera_budget(design, levels, target, axes=None, *, heights=None, allowance=RMSE_ALLOWANCE):
    """Return the camera budget: the nominal camera, the limit, and per axis its curve.

    ``axes`` maps a setting (``bandwidth_nm``, ``f_number``, ``defocus_um``,
    ``rotation_deg``) to its coarse values (default :data:`BUDGET_AXES`), each varied
    alone from the nominal camera.

    Returns
    -------
    dict
        ``nominal``: the nominal camera's correlation, rmse and collected_fraction;
        ``window``: the same figures and the efficiency of the plate of square pixels
        at the design wavelength (its window powers: infinitely small dots);
        ``dots``: the nominal dot's ``width_um`` (between the first zeros of the
        square stop's sinc) beside the ``active_area_um`` that samples it;
        ``limit``: ``rmse_max`` (the nominal's rmse + ``allowance``) and
        ``allowance``; ``goals``: the design goals and whether the nominal camera
        meets them (``met``); ``axes``: per axis ``values`` (the coarse points and
        those the refinement added, sorted) with their ``correlation``, ``rmse``,
        ``collected_fraction``, ``within_budget`` (:func:`budget_range`'s dict) and
        ``within_goals`` (``runs``: each [lo, hi] of the values where the design goals
        hold, interpolated between the points sampled, not bisected; ``nominal``:
        whether the nominal camera's point is one of them);
        ``seconds``.
    """
    start = time.perf_counter()
    axes = BUDGET_AXES if axes is None else axes
    n = np.asarray(levels).shape[0]
    memo = {}

    def evaluate(settings_list):
        todo = {}
        for s in settings_list:  # each setting once, however many curves hold it
            if _key(design, n, s) not in memo:
                todo.setdefault(_key(design, n, s), s)
        figures = camera_figures(design, levels, target, list(todo.values()), heights=heights)
        for key, f in zip(todo, figures, strict=True):
            memo[key] = {k: f[k] for k in _FIGURES}
        return [memo[_key(design, n, s)] for s in settings_list]

    evaluate([{}] + [s for _, s in budget_settings(axes)])
    nominal = memo[_key(design, n, {})]
    limit = nominal["rmse"] + allowance
    out_axes = {}
    for axis, values in axes.items():
        points = dict(zip(values, evaluate([{axis: v} for v in values]), strict=True))
        _refine(axis, points, limit, lambda v, a=axis: evaluate([{a: v}])[0])
        xs = sorted(points)
        curve = {"values": xs, **{k: [points[x][k] for x in xs] for k in _FIGURES}}
        curve["within_budget"] = budget_range(axis, xs, curve["rmse"], limit)
        curve["within_goals"] = _goal_range(axis, curve)
        out_axes[axis] = curve
    met = _fidelity(nominal["correlation"], nominal["rmse"]) <= 1
    wl, f = design.optics.wavelength, design.optics.focal_length
    window = plate_quality(level_phase(np.asarray(levels), design.fabrication.levels), target)
    return {
        "nominal": nominal,
        "window": {k: window[k] for k in ("correlation", "rmse", "efficiency")},
        "dots": {  # why the nominal camera's PSF is not the window's: each dot's width
            "width_um": 2 * wl * f / design.fabrication.aperture * 1e6,  # the sinc's first zeros
            "active_area_um": design.sensor.active_area * 1e6,
            "active_area_shape": design.sensor.active_area_shape,
        },
        "limit": {"rmse_max": limit, "allowance": allowance},
        "goals": {"correlation_min": CORRELATION_GOAL, "rmse_max": RMSE_GOAL, "met": met},
        "axes": out_axes,
        "seconds": time.perf_counter() - start,
    }


def _fidelity(corr, rmse_value):
    """The larger of rmse / RMSE_GOAL and (1 - correlation) / (1 - CORRELATION_GOAL): at most
    1 within the design goals (a uniform target's correlation is None or NaN: rmse alone)."""
    miss = 0.0 if corr is None or math.isnan(corr) else (1 - corr) / (1 - CORRELATION_GOAL)
    return max(rmse_value / RMSE_GOAL, miss)


def _goal_range(axis, curve):
    """Where the design goals hold: every run of the points sampled within them, each end
    interpolated between its neighbours (not bisected), the nominal camera's or not."""
    xs = curve["values"]
    fid = [_fidelity(c, r) for c, r in zip(curve["correlation"], curve["rmse"], strict=True)]
    runs, i = [], 0
    while i < len(xs):
        if not fid[i] <= 1:
            i += 1
            continue
        j = i
        while j + 1 < len(xs) and fid[j + 1] <= 1:
            j += 1
        runs.append([_crossing(xs, fid, i, i - 1), _crossing(xs, fid, j, j + 1)])
        i = j + 1
    return {"runs": runs, "nominal": fid[xs.index(_default_value(axis, xs))] <= 1}


def _crossing(xs, ys, inside, outside):
    """Where the line from an inside point to its outside neighbour crosses 1 (the point
    itself at the end of the values explored)."""
    if not 0 <= outside < len(xs):
        return xs[inside]
    t = (1 - ys[inside]) / (ys[outside] - ys[inside])
    return xs[inside] + t * (xs[outside] - xs[inside])


def _key(design, n, settings):
    """The settings as the model sees them (an f-number whose stop holds the square: none)."""
    f_number = settings.get("f_number")
    if f_number is not None and camera_optics(design, n, f_number=f_number).stop_diameter is None:
        f_number = None
    return (
        float(settings.get("bandwidth_nm") or 0.0),
        f_number,
        float(settings.get("defocus_um") or 0.0),
        float(settings.get("rotation_deg") or 0.0),
    )


def _default_value(axis, values):
    """The point of a curve nearest the nominal camera (the widest stop for the f-number)."""
    return min(values) if axis == "f_number" else min(values, key=abs)


def _refine(axis, points, limit, evaluate):
    """Bisect each interval next to the default's run that brackets the crossing of ``limit``."""
    for side in (-1, 1):
        for _ in range(12):  # the halvings an interval needs to reach RESOLUTION
            pair = _bracket(axis, sorted(points), [points[x]["rmse"] for x in sorted(points)],
                            limit, side)  # fmt: skip
            if pair is None:
                break
            a, b = pair
            if axis == "f_number":
                if b / a - 1 <= RESOLUTION[axis]:
                    break
                mid = math.sqrt(a * b)
            else:
                if b - a <= RESOLUTION[axis]:
                    break
                mid = (a + b) / 2
            points[mid] = evaluate(mid)


def _bracket(axis, xs, ys, limit, side):
    """The pair of neighbouring values (lo, hi) where the default's run ends on ``side``."""
    i = xs.index(_default_value(axis, xs))
    if not ys[i] <= limit:
        return None
    while 0 <= i + side < len(xs) and ys[i + side] <= limit:
        i += side
    j = i + side
    if not 0 <= j < len(xs):
        return None
    return (xs[min(i, j)], xs[max(i, j)])


def budget_range(axis, xs, ys, limit):
    """Return the run of values around the default where ``ys`` stays within ``limit``.

    Returns
    -------
    dict
        ``range`` [lo, hi] (None when the default's own point misses the limit), each
        end where the straight line between the neighbouring points crosses the limit;
        ``ends`` per end "limit" (a crossing), "explored" (the curve stays within to
        the last value explored) or "nominal" (the default is the axis's end, as no
        band-pass or no rotation); ``why``: a sentence when ``range`` is None.
    """
    start = xs.index(_default_value(axis, xs))
    if not ys[start] <= limit:
        return {
            "range": None,
            "ends": None,
            "why": f"{ys[start]:.4f} at {xs[start]:g} already exceeds {limit:.4f}",
        }
    ends, kinds = [], []
    for side in (-1, 1):
        i = start
        while 0 <= i + side < len(xs) and ys[i + side] <= limit:
            i += side
        j = i + side
        if not 0 <= j < len(xs):
            ends.append(xs[i])
            kinds.append("nominal" if i == start else "explored")
            continue
        t = (limit - ys[i]) / (ys[j] - ys[i])
        ends.append(xs[i] + t * (xs[j] - xs[i]))
        kinds.append("limit")
    return {"range": ends, "ends": kinds, "why": None}
