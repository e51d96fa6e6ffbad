"""Tolerance of a fabricated multi-level plate to etch-depth, overlay and CD-bias errors.

Each plate of the table is one faulty plate of ``fab.plate.model`` (the error models
and the axes are stated there), evaluated exactly in its K x K window: one error kind
and value at a time, on each mask, with both signs (and, for the overlay, along x and
along y). The budget is bisected with the same model; the acceptance thresholds come
from random plates with every error within its budget at once.
"""

from dataclasses import dataclass

import numpy as np

from doe.fraunhofer import correlation, rmse, simulate_levels
from fab.plate import budget as one_budget
from fab.plate.model import PlateFaults, cd_bias_in_reach, plate_model, window_amplitudes


@dataclass(frozen=True)
class ToleranceSpec:
    """The error values the table explores and the limits derived from it (SI units).

    Attributes
    ----------
    etch_fractions : tuple of float
        Fractional etch-depth errors per mask; each is tried with both signs.
    overlay : tuple of float
        Overlay errors (m) of each later mask relative to the first, along +x and +y.
    cd_bias : tuple of float
        Edge displacement (m) applied to all masks at once, with both signs; only
        the values below half the mask pixel pitch are tabulated.
    rmse_allowance : float
        How much peak-normalised RMS a fabrication error may add to the nominal
        plate's rmse before it is out of budget. 0.01 is ~1 % of the peak per PSF
        entry: below what a captured PSF resolves (shot noise of ~1e4 photons in
        the peak, background subtraction), so a plate within budget cannot be told
        from the nominal one, while the budget still allows typical process spreads
        (a few % etch depth, a few hundred nm overlay).
    monte_carlo_plates : int
        Random plates (every error drawn uniformly within its budget at once) that
        set the acceptance thresholds.
    correlation_margin, rmse_margin, efficiency_margin, zero_order_margin : float
        Allowance for measurement error when the verification stage compares a
        captured PSF with the thresholds: correlation -0.02, rmse +0.01,
        efficiency x (1 - 0.05), zero order +0.005 of the incident power.
    """

    etch_fractions: tuple[float, ...] = (0.02, 0.05, 0.10)
    overlay: tuple[float, ...] = (0.25e-6, 0.5e-6, 1e-6, 2e-6)
    cd_bias: tuple[float, ...] = (0.1e-6, 0.25e-6)
    rmse_allowance: float = one_budget.RMSE_ALLOWANCE
    monte_carlo_plates: int = 16
    correlation_margin: float = one_budget.CORRELATION_MARGIN
    rmse_margin: float = one_budget.RMSE_MARGIN
    efficiency_margin: float = one_budget.EFFICIENCY_MARGIN
    zero_order_margin: float = one_budget.ZERO_ORDER_MARGIN


TOLERANCES = ToleranceSpec()


def plate_quality(model, target, faults=PlateFaults(), reference=None):
    """Return correlation, rmse, efficiency and zero_order of a fabricated plate.

    ``efficiency`` and ``zero_order`` are fractions of the incident power;
    correlation and rmse compare the normalised window with ``target`` (K, K) as
    in CONVENTIONS.md. With a ``reference`` PSF (K, K), also
    "correlation_vs_reference" and "rmse_vs_reference".
    """
    power = np.abs(window_amplitudes(model, faults)) ** 2
    eff = float(power.sum())
    psf = power / eff
    c = model.k // 2
    out = {
        "correlation": correlation(psf, target),
        "rmse": rmse(psf, target),
        "efficiency": eff,
        "zero_order": float(power[c, c]),
    }
    if reference is not None:
        out["correlation_vs_reference"] = correlation(psf, reference)
        out["rmse_vs_reference"] = rmse(psf, reference)
    return out


def zero_order_power_analytic(eps, phase, bitmap, mask_phase):
    """Return the zero-order power of a tile after one mask's depth is scaled by 1 + eps.

    The mask's pixels lose mask_phase * eps of phase (more etch, less glass), so
    with c0 = mean(exp(i phase)) and A = mean(bitmap * exp(i phase))

        P0(eps) = |c0 + (exp(-i mask_phase eps) - 1) A|^2.

    For a well-optimised tile c0 ~ 0 and P0 = 4 sin^2(mask_phase eps / 2) |A|^2;
    see :func:`zero_order_power_balanced` for the 1.05 eps^2 of an 8-level deep etch.

    Parameters
    ----------
    eps : float or array
        Fractional depth error of the mask.
    phase : (N, N) array
        Nominal phase of the tile (rad).
    bitmap : (N, N) bool array
        Pixels the mask etches.
    mask_phase : float
        Phase (rad) of the mask's nominal depth, 2 pi (n - 1) depth / lambda.
    """
    t = np.exp(1j * np.asarray(phase, dtype=float))
    c0 = t.mean()
    a = (t * np.asarray(bitmap, dtype=bool)).mean()
    eps = np.asarray(eps, dtype=float)
    return np.abs(c0 + (np.exp(-1j * mask_phase * eps) - 1) * a) ** 2


def zero_order_power_balanced(eps, n_levels, steps):
    """Return P0(eps) of a tile that uses every level equally often (so c0 = 0).

    A mask that etches ``steps`` level steps covers the levels l whose code
    L - 1 - l has that bit, half of the tile; its phase is 2 pi steps / L, so

        P0 = 4 sin^2(pi steps eps / L) |A|^2,  A = (1/L) sum_{l covered} exp(2 pi i l / L).

    For L = 8 and the deep mask (steps = 4): |A|^2 = (1 + (1 + sqrt 2)^2) / 64 =
    0.1067, and P0 = 4 sin^2(pi eps / 2) 0.1067 ~ 1.053 eps^2.
    """
    lv = np.arange(n_levels)
    covered = ((n_levels - 1 - lv) & steps) != 0
    a = np.exp(2j * np.pi * lv[covered] / n_levels).sum() / n_levels
    eps = np.asarray(eps, dtype=float)
    return 4 * np.sin(np.pi * steps * eps / n_levels) ** 2 * abs(a) ** 2


_UNITS = {"etch": "%", "overlay": "um", "cd_bias": "um"}
_SCALE = {"etch": 100.0, "overlay": 1e6, "cd_bias": 1e6}  # SI value -> table unit


def tolerance_analysis(
    levels,
    n_levels,
    target_psf,
    masks,
    pixel_pitch,
    level_step,
    wavelength,
    refractive_index,
    seed=0,
    rmse_limit=None,
    supersample=None,
    spec=TOLERANCES,
    on_plate=None,
):
    """Tabulate how etch, overlay and CD-bias errors degrade the plate; derive budget and limits.

    The rmse limit (unless given) is the nominal plate's rmse plus
    ``spec.rmse_allowance`` (0.01): relative to the nominal, because the design
    already differs from its target by its quantisation and the fabrication should
    add no more than a captured PSF can resolve (see :class:`ToleranceSpec`). The
    budget of an error kind (per mask; CD bias for all masks together) is the
    largest value whose worse sign or axis keeps rmse <= limit, bisected with the
    model between the last passing and the first failing table value; if every
    table value passes, the budget is the largest tested one
    (``limited_by_rmse`` False). The acceptance thresholds are the worst figures
    of ``spec.monte_carlo_plates`` random plates with every error drawn uniformly
    within its budget at once (seeded), widened by the measurement margins; their
    correlation and rmse are taken against the levels' contract PSF
    (``simulate_levels``), which is what ``fab.verify.analysis`` compares a capture with,
    while the table and the budget compare with ``target_psf``.

    Parameters
    ----------
    levels : (N, N) uint8 array
        Level map (CONVENTIONS.md); checked against the masks.
    n_levels : int
        L.
    target_psf : (K, K) array
        Target PSF, sum 1.
    masks : sequence of fab.package.masks.Mask
        Masks with ``name``, ``bitmap``, ``etch_depth`` (m), ``exposure_order``.
    pixel_pitch, level_step, wavelength : float
        Metres.
    refractive_index : float
        Substrate index at ``wavelength``.
    seed : int
        Seed of the Monte Carlo plates.
    rmse_limit : float or None
        Absolute rmse limit; None for nominal + ``spec.rmse_allowance``.
    supersample : int or None
        Sub-samples per pixel, None for the exact continuous plate.
    spec : ToleranceSpec
        The error values and margins.
    on_plate : callable or None
        Called with no argument after each simulated plate (a progress bar's update).

    Returns
    -------
    dict
        JSON-ready: "rows" (kind, mask, axis, value, unit, correlation, rmse,
        efficiency, zero_order, zero_order_excess), "budget" (kind, mask, value,
        unit, limited_by_rmse, rmse), "acceptance" (correlation_min, rmse_max,
        efficiency_min, zero_order_max), "nominal", "rmse_limit", "monte_carlo",
        "model" (the stated assumptions).
    """

    masks = list(masks)
    target = np.asarray(target_psf, dtype=float)
    _check_masks_match_levels(levels, n_levels, masks, level_step)
    optics = (pixel_pitch, level_step, n_levels, wavelength, refractive_index)
    model = plate_model(masks, *optics, target.shape[0], supersample)
    names = [str(mk.name) for mk in masks]
    order = [getattr(mk, "exposure_order", i + 1) for i, mk in enumerate(masks)]
    ref = int(np.argmin(order))
    deepest = int(np.argmax([mk.etch_depth for mk in masks]))
    plates = _Plates(model, target, on_plate)
    nominal = plates.quality()
    limit = nominal["rmse"] + spec.rmse_allowance if rmse_limit is None else float(rmse_limit)
    # An edge moved by half a pixel or more closes the one-pixel gaps: another plate, not an error.
    cd_values = tuple(v for v in spec.cd_bias if cd_bias_in_reach(model, v))
    rows, budget = _table(plates, names, ref, spec, cd_values, nominal, limit)
    # fab.verify.analysis compares a captured PSF with the levels' contract PSF, not with the
    # target, so the correlation and rmse thresholds are taken against that PSF.
    design_psf = simulate_levels(levels, n_levels, target.shape[0])[0]
    mc = _monte_carlo(design_psf, budget, names, ref, spec, seed, plates.simulate)
    return {
        "model": _assumptions(
            names[ref], pixel_pitch, supersample, cd_values, rmse_limit, spec, seed
        ),
        "reference_mask": names[ref],
        "nominal": nominal,
        "rmse_limit": limit,
        "rows": rows,
        "budget": budget,
        "monte_carlo": {"plates": spec.monte_carlo_plates, "seed": seed, **mc},
        "acceptance": one_budget.acceptance(mc, budget, names[deepest], _margins(spec)),
    }


def _margins(spec):
    """Return ``spec``'s measurement margins in ``fab.plate.budget.acceptance``'s order."""
    return (spec.correlation_margin, spec.rmse_margin, spec.efficiency_margin,
            spec.zero_order_margin)  # fmt: skip


class _Plates:
    """The plates of one analysis, each evaluated by ``plate_quality`` and counted."""

    def __init__(self, model, target, on_plate):
        self.model, self.target, self.on_plate = model, target, on_plate
        self.n_masks = len(model.bitmaps)

    def simulate(self, faults, reference=None):
        """Return the figures of one faulty plate (``plate_quality``)."""
        q = plate_quality(self.model, self.target, faults, reference)
        if self.on_plate is not None:
            self.on_plate()
        return q

    def quality(self, etch=None, shift=None, cd=0.0):
        """Return the figures of a plate with per-mask etch errors, (dx, dy) shifts, CD bias."""
        faults = PlateFaults(
            etch_errors=tuple(etch) if etch is not None else (),
            overlay=tuple(shift) if shift is not None else (),
            cd_bias=cd,
        )
        return self.simulate(faults)

    def variants(self, kind, i, v):
        """Return (axis, signed value, quality) of each plate of one table entry."""
        n_masks = self.n_masks
        if kind == "etch":
            return [
                ("", s * v, self.quality(etch=[s * v if j == i else 0.0 for j in range(n_masks)]))
                for s in (1, -1)
            ]
        if kind == "overlay":
            # A phase plate's PSF changes differently for a shift one way and the
            # other, so both signs of both axes are tabulated and budgeted.
            shifts = (("x", v, (v, 0.0)), ("x", -v, (-v, 0.0)))
            shifts += (("y", v, (0.0, v)), ("y", -v, (0.0, -v)))
            return [
                (ax, sv, self.quality(shift=[d if j == i else (0.0, 0.0) for j in range(n_masks)]))
                for ax, sv, d in shifts
            ]
        return [("", s * v, self.quality(cd=s * v)) for s in (1, -1)]

    def worst_rmse(self, kind, i, v):
        """Return the worse rmse of the signs (and axes) of one table entry."""
        return max(q["rmse"] for _, _, q in self.variants(kind, i, v))


def _table(plates, names, ref, spec, cd_values, nominal, limit):
    """Return the table's rows and the budget of each error kind (per mask; CD bias for all)."""
    rows = [_row("nominal", "all", "", 0.0, "", nominal, nominal)]
    entries = [("etch", i, spec.etch_fractions) for i in range(len(names))]
    entries += [("overlay", i, spec.overlay) for i in range(len(names)) if i != ref]
    if cd_values:
        entries += [("cd_bias", None, cd_values)]
    budget = []
    for kind, i, values in entries:
        mask = "all" if i is None else names[i]
        worst = {}
        for v in sorted(values):
            table = plates.variants(kind, i, v)
            rows += [_row(kind, mask, ax, sv, _UNITS[kind], q, nominal) for ax, sv, q in table]
            worst[v] = max(q["rmse"] for _, _, q in table)
        budget.append(
            _budget(
                kind, mask, worst, limit, lambda v, kind=kind, i=i: plates.worst_rmse(kind, i, v)
            )
        )
    return rows, budget


def _assumptions(reference, pixel_pitch, supersample, cd_values, rmse_limit, spec, seed):
    """Return the stated assumptions of an analysis (its JSON "model")."""
    return {
        "sampling": "continuous plate (exact sub-cell Fourier sums)"
        if supersample is None
        else f"{supersample} x {supersample} sub-samples per pixel",
        "supersample": supersample,
        "etch": "mask depth x (1 + error); + is too deep; both signs tabulated",
        "overlay": f"each mask after {reference} (first exposed) shifted relative to it "
        "along x and along y, both signs (separate rows), periodic",
        "cd_bias": "every edge of every mask's etched region moved outwards by the value "
        "(+ grows the etched area, width changes by twice it); square corners; "
        "only values below half the mask pixel pitch "
        f"({0.5 * pixel_pitch * 1e6:.4g} um) are tabulated" + ("" if cd_values else ", so none is"),
        "rmse_limit_rule": "given"
        if rmse_limit is not None
        else f"nominal rmse + {spec.rmse_allowance}",
        "acceptance_rule": f"worst of {spec.monte_carlo_plates} random plates within the "
        f"budget (seed {seed}); correlation and rmse against the levels' simulated PSF "
        "(simulate_levels, what verification compares a capture with), efficiency and "
        "zero order as fractions of the incident power; margins correlation -"
        f"{spec.correlation_margin}, rmse +{spec.rmse_margin}, "
        f"efficiency x(1-{spec.efficiency_margin}), zero order +"
        f"{spec.zero_order_margin}",
    }


def _row(kind, mask, axis, value, unit, q, nominal):
    scale = _SCALE.get(kind, 1.0)
    return {
        "kind": kind,
        "mask": mask,
        "axis": axis,
        "value": value * scale,
        "unit": unit,
        **q,
        "zero_order_excess": q["zero_order"] - nominal["zero_order"],
    }


def _budget(kind, mask, worst, limit, worst_rmse, iterations=10):
    """Return the largest value (table unit) with worst rmse <= limit, bisected with the model."""
    lo, hi = 0.0, None
    for v in sorted(worst):
        if worst[v] > limit:
            hi = v
            break
        lo = v
    if hi is not None:
        for _ in range(iterations):  # 2**-10 of the bracketing table interval
            mid = 0.5 * (lo + hi)
            if worst_rmse(mid) <= limit:
                lo = mid
            else:
                hi = mid
    return {
        "kind": kind,
        "mask": mask,
        "value": lo * _SCALE[kind],
        "unit": _UNITS[kind],
        "si_value": lo,
        "limited_by_rmse": hi is not None,
        "rmse": worst_rmse(lo),
    }


def _monte_carlo(reference, budget, names, ref, spec, seed, simulate):
    """Return lists of the quality figures of random plates with all errors within budget.

    ``simulate(faults, reference)`` returns a plate's figures (``plate_quality``).
    """
    rng = np.random.default_rng(seed)
    etch_b = np.zeros(len(names))
    overlay_b = np.zeros(len(names))
    cd_b = 0.0
    for b in budget:
        if b["kind"] == "cd_bias":
            cd_b = b["si_value"]
        elif b["kind"] == "etch":
            etch_b[names.index(b["mask"])] = b["si_value"]
        else:
            overlay_b[names.index(b["mask"])] = b["si_value"]
    keys = ("correlation", "rmse", "efficiency", "zero_order", "correlation_vs_reference",
            "rmse_vs_reference")  # fmt: skip
    out = {key: [] for key in keys}
    for _ in range(spec.monte_carlo_plates):
        etch = rng.uniform(-1, 1, len(names)) * etch_b
        shift = rng.uniform(-1, 1, (len(names), 2)) * overlay_b[:, None]
        shift[ref] = 0.0
        cd = float(rng.uniform(-1, 1) * cd_b)
        faults = PlateFaults(etch_errors=tuple(etch), overlay=tuple(map(tuple, shift)), cd_bias=cd)
        q = simulate(faults, reference)
        for key in out:
            out[key].append(q[key])
    return out


def _check_masks_match_levels(levels, n_levels, masks, level_step):
    """Refuse masks whose summed etch depths do not give the level map (a wrong split)."""
    levels = np.asarray(levels)
    depth = sum(np.asarray(mk.bitmap, dtype=float) * mk.etch_depth for mk in masks)
    expected = (n_levels - 1 - levels.astype(float)) * level_step
    if np.shape(depth) != levels.shape or not np.allclose(
        depth, expected, rtol=0, atol=1e-3 * level_step
    ):
        raise ValueError("the masks' summed etch depths do not reproduce the level map")
