"""Tolerance of a fabricated multi-level plate to etch-depth, overlay and CD-bias errors.

The fabricated tile is modelled as what it physically is: a piecewise-constant
phase in the plane, with each mask's etched region shifted by its overlay error,
its edges moved by a CD bias and its depth scaled by an etch error. Every mask
edge lies at a pixel boundary of its own (shifted) grid, so within each mask
pixel the fabricated plate is constant on the sub-cells cut by the breakpoints
{overlay shift, shift +- bias} of all masks (the same offsets in every pixel).
Order (m, n) of the tile is then exactly

    F[m, n] = sum_jk g_j(m) g_k(n) DFT_N(exp(i phase_jk))[m, n] / N**2

where phase_jk is the (N, N) phase of sub-cell (j, k) of every pixel and g_j(m)
the Fourier weight of sub-cell interval j of a pixel. Two samplings:

* ``supersample=None`` (default): continuous plate, g_j(m) = integral over the
  interval of exp(-2 pi i m t / N) dt (t in pixels). No rounding of any error
  value; this is the limit S -> infinity of a supersampled grid and carries the
  pixel's sinc envelope (sinc^2(m/N), 0.27 % at the edge of an 11-order window
  for N = 175).
* ``supersample=S``: the (N S)^2 grid of S x S sub-samples per pixel, shifts and
  biases rounded to whole sub-samples, g_j(m) = sum over the sub-samples s of the
  interval of exp(-2 pi i m s / (N S)) / S. Identical to the FFT of the
  upsampled tile; S = 1 with no error is exactly ``doe.fraunhofer.simulate_levels``.

Only the K x K window is evaluated (a K x N DFT matrix built once per tile, FFTs
along rows), so a nominal plate costs ~1 ms and the whole analysis of an N = 175
tile about 2 s on two shared cores (bench/tolerance.py).

Error models (stated once, used everywhere):

* etch: mask depth -> depth * (1 + eps); eps > 0 over-etches.
* overlay: the etched region of a mask moves by (dx, dy) metres, +x right, +y up
  (towards row 0); masks are periodic, so the shift wraps around the tile. The
  first-exposed mask is the reference; the table shifts each later mask along +x
  and along +y separately and reports the worse.
* CD bias: every edge of every mask's etched region moves outwards by b (b > 0:
  etched area grows, a feature of width w becomes w + 2 b). The etched region is
  dilated (eroded for b < 0) with a square structuring element, i.e. corners stay
  square; rounding them would change each corner's area by (1 - pi/4) b^2, below
  0.1 % of a 5 um pixel for b = 0.25 um. Requires |b| < pitch / 2.

The phase of a point with total etch depth d is 2 pi (n - 1) (H - d) / lambda,
H = (L - 1) * level_step, which is the level model 2 pi l / L of CONVENTIONS.md
when level_step = lambda / ((n - 1) L) and nothing is in error.
"""

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
import scipy.fft

from doe.fraunhofer import correlation, rmse, simulate_levels


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
    rmse_allowance: float = 0.01
    monte_carlo_plates: int = 16
    correlation_margin: float = 0.02
    rmse_margin: float = 0.01
    efficiency_margin: float = 0.05
    zero_order_margin: float = 0.005


TOLERANCES = ToleranceSpec()


@dataclass(frozen=True)
class PlateErrors:
    """Fabrication errors of one plate; per-mask tuples follow the order of the masks.

    Attributes
    ----------
    etch : tuple of float
        Fractional depth error of each mask (0.05 = 5 % too deep).
    shift : tuple of (float, float)
        Overlay (dx, dy) of each mask in metres, +x right, +y up.
    cd_bias : float
        Edge displacement of every mask's etched region in metres (> 0 grows it).
    """

    etch: tuple[float, ...] = ()
    shift: tuple[tuple[float, float], ...] = ()
    cd_bias: float = 0.0


@dataclass(frozen=True, eq=False)
class PlateModel:
    """A tile's masks and optics, ready to evaluate its window for any errors.

    Build with :func:`plate_model`. ``bitmaps`` is (M, N, N) bool, ``depths`` (M,)
    metres, ``dft`` the (K, N) matrix exp(-2 pi i m r / N) / N for orders
    m = -K//2 .. K//2.
    """

    bitmaps: np.ndarray
    depths: np.ndarray
    pixel_pitch: float
    phase_per_depth: float
    top_height: float
    k: int
    supersample: int | None
    dft: np.ndarray = field(repr=False)
    orders: np.ndarray = field(repr=False)


def plate_model(
    masks, pixel_pitch, level_step, n_levels, wavelength, refractive_index, k, supersample=None
):
    """Return the :class:`PlateModel` of a tile's masks.

    Parameters
    ----------
    masks : sequence of fab.package.masks.Mask
        Anything with ``bitmap`` ((N, N) bool, True = etched) and ``etch_depth`` (m).
    pixel_pitch : float
        Mask pixel pitch (m).
    level_step, wavelength : float
        Step height and design wavelength (m).
    n_levels : int
        L; the unetched top sits (L - 1) steps above the deepest floor.
    refractive_index : float
        Substrate index at the wavelength.
    k : int
        Window size K (odd).
    supersample : int or None
        Sub-samples per pixel, or None for the continuous plate (module docstring).
    """
    bitmaps = np.stack([np.asarray(mk.bitmap, dtype=bool) for mk in masks])
    n = bitmaps.shape[-1]
    if bitmaps.shape[1:] != (n, n):
        raise ValueError(f"mask bitmaps must be square (N, N), got {bitmaps.shape[1:]}")
    if k % 2 != 1 or k > n:
        raise ValueError(f"window K must be odd and <= N = {n}, got {k}")
    if supersample is not None and (int(supersample) != supersample or supersample < 1):
        raise ValueError(f"supersample must be a positive integer or None, got {supersample}")
    orders = np.arange(k) - k // 2
    dft = np.exp(-2j * np.pi * np.outer(orders, np.arange(n)) / n) / n
    bitmaps.setflags(write=False)
    return PlateModel(
        bitmaps=bitmaps,
        depths=np.array([float(mk.etch_depth) for mk in masks]),
        pixel_pitch=float(pixel_pitch),
        phase_per_depth=2 * np.pi * (refractive_index - 1) / wavelength,
        top_height=(n_levels - 1) * level_step,
        k=int(k),
        supersample=None if supersample is None else int(supersample),
        dft=dft,
        orders=orders,
    )


def window_amplitudes(model, errors=PlateErrors()):
    """Return the complex amplitudes (K, K) of the window orders of the fabricated plate.

    Element [K//2, K//2] is the zero order; |amplitude|^2 is the fraction of the
    incident power in that order.
    """
    n_masks, n = model.bitmaps.shape[0], model.bitmaps.shape[-1]
    etch = np.asarray(errors.etch or (0.0,) * n_masks, dtype=float)
    shift = np.asarray(errors.shift or ((0.0, 0.0),) * n_masks, dtype=float).reshape(n_masks, 2)
    if errors.etch and len(errors.etch) != n_masks:  # once broadcast one value to every mask
        raise ValueError(f"etch errors must be one per mask ({n_masks}), got {len(errors.etch)}")
    bias = _bias_pixels(errors.cd_bias, model)
    # Shifts in pixels along array axes: columns follow +x, rows grow towards -y.
    col_shift, row_shift = shift[:, 0] / model.pixel_pitch, -shift[:, 1] / model.pixel_pitch
    if model.supersample is not None:
        s = model.supersample
        col_shift, row_shift = np.round(col_shift * s) / s, np.round(row_shift * s) / s
    if not _below_half_pixel(bias):
        raise ValueError(f"CD bias {errors.cd_bias:.3g} m must be below half the pixel pitch")
    rows = _axis_cells(row_shift, bias, model.supersample)
    cols = _axis_cells(col_shift, bias, model.supersample)
    depths = model.depths * (1 + etch)
    # A pixel's phase depends only on which masks etch it: look it up by that bit code.
    codes = np.arange(2**n_masks)
    bits = (codes[:, None] >> np.arange(n_masks)) & 1
    lut = np.exp(1j * model.phase_per_depth * (model.top_height - bits @ depths))
    # Rows: (K, N) DFT matrices; columns: an FFT along each row, then the K orders, so
    # no large BLAS call (OpenBLAS threads thrash on a busy 2-core machine).
    left = [
        _interval_weight(model.orders, a, b, n, model.supersample)[:, None] * model.dft
        for a, b, _ in rows
    ]
    right = [_interval_weight(model.orders, a, b, n, model.supersample) / n for a, b, _ in cols]
    col_idx = model.orders % n
    out = np.zeros((model.k, model.k), dtype=complex)
    for (_, _, r_off), wr in zip(rows, left, strict=True):
        row_reduced = [_reduce_rolls(bm, r_off[i], 0, bias) for i, bm in enumerate(model.bitmaps)]
        acc = np.zeros((n, model.k), dtype=complex)
        for (_, _, c_off), wc in zip(cols, right, strict=True):
            code = np.zeros((n, n), dtype=np.uint8)
            for i, bm in enumerate(row_reduced):
                code |= _reduce_rolls(bm, c_off[i], 1, bias).view(np.uint8) << i
            acc += scipy.fft.fft(lut[code], axis=1)[:, col_idx] * wc
        out += wr @ acc
    return out


def _axis_cells(shifts, bias, supersample):
    """Cut a pixel [0, 1) at every mask's edges; return (start, end, offsets per mask).

    ``offsets[i]`` lists the pixel offsets q whose bitmap value reaches this
    interval for mask i: the mask value at pixel c is the OR (bias > 0) or AND
    (bias < 0) of bitmap[c + q] over q.
    """
    cuts = {0.0}
    for s in shifts:
        for e in (s, s + bias, s - bias):
            cuts.add(_frac(e, supersample))
    cuts = [*sorted(cuts), 1.0]
    cells = []
    for a, b in itertools.pairwise(cuts):
        if b - a <= 1e-12:
            continue
        mid = 0.5 * (a + b)
        offsets = []
        for s in shifts:
            w = mid - s
            q = math.floor(w)
            f = w - q
            near = [q]
            if f < abs(bias):
                near.append(q - 1)
            if f > 1 - abs(bias):
                near.append(q + 1)
            offsets.append(tuple(near))
        cells.append((a, b, offsets))
    return cells


def _frac(x, supersample):
    f = x - math.floor(x)
    if supersample is not None:
        f = round(f * supersample) / supersample
    return 0.0 if f >= 1.0 - 1e-12 or f < 1e-12 else f


def _reduce_rolls(bitmap, offsets, axis, bias):
    """Return OR (bias >= 0) / AND (bias < 0) over q of bitmap[c + q] along ``axis``."""
    out = np.roll(bitmap, -offsets[0], axis=axis)
    for q in offsets[1:]:
        rolled = np.roll(bitmap, -q, axis=axis)
        out = out | rolled if bias >= 0 else out & rolled
    return out


def _interval_weight(orders, a, b, n, supersample):
    """Return g(m) of the pixel interval [a, b) (pixel units) for each order m."""
    if supersample is None:
        m = orders.astype(float)
        safe = np.where(m == 0, 1.0, m)
        w = (np.exp(-2j * np.pi * m * b / n) - np.exp(-2j * np.pi * m * a / n)) / (
            -2j * np.pi * safe / n
        )
        return np.where(m == 0, b - a, w)
    s = np.arange(round(a * supersample), round(b * supersample))
    return np.exp(-2j * np.pi * np.outer(orders, s) / (n * supersample)).sum(axis=1) / supersample


def plate_quality(model, target, errors=PlateErrors(), reference=None):
    """Return correlation, rmse, efficiency and zero_order of a fabricated plate.

    ``efficiency`` and ``zero_order`` are fractions of the incident power;
    correlation and rmse compare the normalised window with ``target`` (K, K) as
    in CONVENTIONS.md. With a ``reference`` PSF (K, K), also
    "correlation_vs_reference" and "rmse_vs_reference".
    """
    power = np.abs(window_amplitudes(model, errors)) ** 2
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
    0.1067, and P0 = 4 sin^2(pi eps / 2) 0.1067 ~ 1.053 eps^2 (the issue's 1.05 eps^2).
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
    model = plate_model(
        masks,
        pixel_pitch,
        level_step,
        n_levels,
        wavelength,
        refractive_index,
        target.shape[0],
        supersample,
    )
    names = [str(mk.name) for mk in masks]
    order = [getattr(mk, "exposure_order", i + 1) for i, mk in enumerate(masks)]
    ref = int(np.argmin(order))
    n_masks = len(masks)

    def quality(etch=None, shift=None, cd=0.0):
        errors = PlateErrors(
            etch=tuple(etch) if etch is not None else (),
            shift=tuple(shift) if shift is not None else (),
            cd_bias=cd,
        )
        return simulate(errors)

    def simulate(errors, reference=None):
        q = plate_quality(model, target, errors, reference)
        if on_plate is not None:
            on_plate()
        return q

    def variants(kind, i, v):
        """Return (axis, signed value, quality) of each plate of one table entry."""
        if kind == "etch":
            return [
                ("", s * v, quality(etch=[s * v if j == i else 0.0 for j in range(n_masks)]))
                for s in (1, -1)
            ]
        if kind == "overlay":
            # A phase plate's PSF changes differently for a shift one way and the
            # other, so both signs of both axes are tabulated and budgeted.
            shifts = (("x", v, (v, 0.0)), ("x", -v, (-v, 0.0)))
            shifts += (("y", v, (0.0, v)), ("y", -v, (0.0, -v)))
            return [
                (ax, sv, quality(shift=[d if j == i else (0.0, 0.0) for j in range(n_masks)]))
                for ax, sv, d in shifts
            ]
        return [("", s * v, quality(cd=s * v)) for s in (1, -1)]

    def worst_rmse(kind, i, v):
        return max(q["rmse"] for _, _, q in variants(kind, i, v))

    nominal = quality()
    limit = nominal["rmse"] + spec.rmse_allowance if rmse_limit is None else float(rmse_limit)
    rows = [_row("nominal", "all", "", 0.0, "", nominal, nominal)]
    entries = [("etch", i, spec.etch_fractions) for i in range(n_masks)]
    entries += [("overlay", i, spec.overlay) for i in range(n_masks) if i != ref]
    # An edge moved by half a pixel or more closes the one-pixel gaps: another plate, not an error.
    cd_values = tuple(v for v in spec.cd_bias if _below_half_pixel(_bias_pixels(v, model)))
    if cd_values:
        entries += [("cd_bias", None, cd_values)]
    budget = []
    for kind, i, values in entries:
        mask = "all" if i is None else names[i]
        worst = {}
        for v in sorted(values):
            plates = variants(kind, i, v)
            rows += [_row(kind, mask, ax, sv, _UNITS[kind], q, nominal) for ax, sv, q in plates]
            worst[v] = max(q["rmse"] for _, _, q in plates)
        budget.append(
            _budget(kind, mask, worst, limit, lambda v, kind=kind, i=i: worst_rmse(kind, i, v))
        )
    # fab.verify.analysis compares a captured PSF with the levels' contract PSF, not with the
    # target, so the correlation and rmse thresholds are taken against that PSF.
    design_psf = simulate_levels(levels, n_levels, target.shape[0])[0]
    mc = _monte_carlo(design_psf, budget, names, ref, spec, seed, simulate)
    acceptance = {
        "correlation_min": min(mc["correlation_vs_reference"]) - spec.correlation_margin,
        "rmse_max": max(mc["rmse_vs_reference"]) + spec.rmse_margin,
        "efficiency_min": min(mc["efficiency"]) * (1 - spec.efficiency_margin),
        "zero_order_max": max(mc["zero_order"]) + spec.zero_order_margin,
    }
    return {
        "model": {
            "sampling": "continuous plate (exact sub-cell Fourier sums)"
            if supersample is None
            else f"{supersample} x {supersample} sub-samples per pixel",
            "supersample": supersample,
            "etch": "mask depth x (1 + error); + is too deep; both signs tabulated",
            "overlay": f"each mask after {names[ref]} (first exposed) shifted relative to it "
            "along x and along y, both signs (separate rows), periodic",
            "cd_bias": "every edge of every mask's etched region moved outwards by the value "
            "(+ grows the etched area, width changes by twice it); square corners; "
            "only values below half the mask pixel pitch "
            f"({0.5 * pixel_pitch * 1e6:.4g} um) are tabulated"
            + ("" if cd_values else ", so none is"),
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
        },
        "reference_mask": names[ref],
        "nominal": nominal,
        "rmse_limit": limit,
        "rows": rows,
        "budget": budget,
        "monte_carlo": {"plates": spec.monte_carlo_plates, "seed": seed, **mc},
        "acceptance": acceptance,
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


def _bias_pixels(cd_bias, model):
    """Return a CD bias in pixels as the model samples it (rounded to its sub-samples)."""
    bias = cd_bias / model.pixel_pitch
    if model.supersample is not None:
        bias = round(bias * model.supersample) / model.supersample
    return bias


def _below_half_pixel(bias):
    """Whether a bias (pixels) is below half a pixel, and not half a pixel in rounding.

    The pitch is grid steps x 1e-9 m, so 0.25 um over a 500 nm pitch is 0.4999999999999999.
    """
    return abs(bias) < 0.5 - 1e-9


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

    ``simulate(errors, reference)`` returns a plate's figures (``plate_quality``).
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
        errors = PlateErrors(tuple(etch), tuple(map(tuple, shift)), cd)
        q = simulate(errors, reference)
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
