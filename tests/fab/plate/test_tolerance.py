"""Tests of fab.plate.tolerance: the fabricated-plate model against independent oracles."""

import itertools
import json
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from doe.fraunhofer import level_phase, simulate_levels, window_power
from fab.package.masks import masks_from_levels
from fab.plate.model import PlateFaults, plate_model, window_amplitudes
from fab.plate.tolerance import (
    ToleranceSpec,
    plate_quality,
    tolerance_analysis,
    zero_order_power_analytic,
    zero_order_power_balanced,
)

L = 8
N_INDEX = 1.4564
WAVELENGTH = 655e-9
STEP = WAVELENGTH / (N_INDEX - 1) / L  # level_step that makes level l = 2 pi l / L
PITCH = 5e-6
ATOL = 1e-14  # float64 round-off of a sum of ~N^2 unit phasors divided by N^2


def random_levels(n, seed=0):
    return np.random.default_rng(seed).integers(0, L, (n, n)).astype(np.uint8)


def model_of(levels, k, supersample=None, level_step=STEP):
    masks = masks_from_levels(levels, L, level_step)
    return plate_model(masks, PITCH, level_step, L, WAVELENGTH, N_INDEX, k, supersample), masks


def gs_levels(n, target, seed=0, iters=120):
    """Return a small Gerchberg-Saxton level map that sends most light into ``target``."""
    rng = np.random.default_rng(seed)
    k = target.shape[0]
    idx = np.ix_((np.arange(k) - k // 2) % n, (np.arange(k) - k // 2) % n)
    phase = rng.uniform(0, 2 * np.pi, (n, n))
    q = 2 * np.pi / L
    for it in range(iters):
        f = np.fft.fft2(np.exp(1j * phase))
        g = np.zeros_like(f)
        g[idx] = np.sqrt(target) * n * np.exp(1j * np.angle(f[idx]))
        phase = np.angle(np.fft.ifft2(g))
        if it > iters // 2:
            phase = np.round(phase / q) * q
    return (np.round(phase / q) % L).astype(np.uint8)


def brute_force_window(masks, errors, supersample, k, continuous):
    """Upsample, roll, dilate and FFT the full (N S)^2 tile: the model without its algebra."""
    s = supersample
    n = masks[0].bitmap.shape[0]
    depth = np.zeros((n * s, n * s))
    bias = round(errors.cd_bias / PITCH * s)
    for i, mk in enumerate(masks):
        up = np.kron(mk.bitmap.astype(np.uint8), np.ones((s, s), np.uint8))
        dx, dy = errors.overlay[i]
        up = np.roll(up, (round(-dy / PITCH * s), round(dx / PITCH * s)), axis=(0, 1))
        if bias > 0:
            up = ndimage.maximum_filter(up, size=2 * bias + 1, mode="wrap")
        elif bias < 0:
            up = ndimage.minimum_filter(up, size=-2 * bias + 1, mode="wrap")
        depth += up * mk.etch_depth * (1 + errors.etch_errors[i])
    field = np.exp(2j * np.pi * (N_INDEX - 1) * ((L - 1) * STEP - depth) / WAVELENGTH)
    amp = np.fft.fft2(field) / field.size
    m = np.arange(k) - k // 2
    window = amp[np.ix_(m % (n * s), m % (n * s))]
    if continuous:  # each sub-sample is a box of width 1/(N S) of the tile
        box = np.exp(-1j * np.pi * m / (n * s)) * np.sinc(m / (n * s))
        window = window * box[:, None] * box[None, :]
    return window


def test_zero_error_s1_is_simulate_levels():
    levels = random_levels(24)
    model, _ = model_of(levels, 9, supersample=1)
    power = np.abs(window_amplitudes(model)) ** 2
    np.testing.assert_allclose(power, window_power(level_phase(levels, L), 9), rtol=0, atol=ATOL)
    psf, eff = simulate_levels(levels, L, 9)
    q = plate_quality(model, psf)
    assert q["efficiency"] == pytest.approx(eff, abs=ATOL)
    assert q["correlation"] == pytest.approx(1.0, abs=1e-12)
    assert q["rmse"] == pytest.approx(0.0, abs=1e-12)


def test_continuous_nominal_is_levels_times_pixel_sinc_envelope():
    levels = random_levels(20, seed=3)
    model, _ = model_of(levels, 7)
    m = np.arange(7) - 3
    envelope = np.sinc(m / 20) ** 2
    expected = window_power(level_phase(levels, L), 7) * envelope[:, None] * envelope[None, :]
    np.testing.assert_allclose(np.abs(window_amplitudes(model)) ** 2, expected, atol=ATOL)


@pytest.mark.parametrize("continuous", [False, True])
@pytest.mark.parametrize("bias_sub", [0, 1, -1, 2, -2])
def test_model_matches_brute_force_supersampled_tile(continuous, bias_sub):
    s, k = 5, 7
    levels = random_levels(12, seed=bias_sub + 7)
    model, masks = model_of(levels, k, supersample=None if continuous else s)
    sub = PITCH / s
    errors = PlateFaults(
        etch_errors=(0.03, -0.05, 0.1),
        overlay=((0.0, 0.0), (sub, -2 * sub), (-3 * sub, 6 * sub)),
        cd_bias=bias_sub * sub,
    )
    np.testing.assert_allclose(
        window_amplitudes(model, errors),
        brute_force_window(masks, errors, s, k, continuous),
        rtol=0,
        atol=1e-13,
    )


def test_supersampled_model_rounds_errors_to_sub_samples():
    levels = random_levels(12, seed=1)
    model, _ = model_of(levels, 5, supersample=4)
    exact = PlateFaults(overlay=((0, 0), (PITCH / 4, 0), (0, 0)))
    rounded = PlateFaults(overlay=((0, 0), (PITCH / 4 * 1.2, 0), (0, 0)))
    np.testing.assert_array_equal(
        window_amplitudes(model, exact), window_amplitudes(model, rounded)
    )


@pytest.mark.parametrize("axis", ["x", "y"])
def test_whole_pixel_overlay_equals_rolled_bitmap(axis):
    levels = random_levels(16, seed=5)
    model, masks = model_of(levels, 7)
    # +x moves the pattern to larger columns; +y moves it up, to smaller rows.
    # roll = (shift, axis) of np.roll.
    shift, roll = ((PITCH, 0.0), (1, 1)) if axis == "x" else ((0.0, PITCH), (-1, 0))
    shifted = window_amplitudes(model, PlateFaults(overlay=((0, 0), shift, (0, 0))))
    rolled = [masks[0], replace(masks[1], bitmap=np.roll(masks[1].bitmap, *roll)), masks[2]]
    rolled_model = plate_model(rolled, PITCH, STEP, L, WAVELENGTH, N_INDEX, 7)
    np.testing.assert_array_equal(shifted, window_amplitudes(rolled_model))


def test_zero_cd_bias_is_a_no_op_and_the_model_is_continuous_in_it():
    levels = random_levels(16, seed=2)
    model, _ = model_of(levels, 7)
    shift = ((0, 0), (0.3e-6, -0.7e-6), (0, 0))
    base = window_amplitudes(model, PlateFaults(overlay=shift))
    np.testing.assert_array_equal(
        base, window_amplitudes(model, PlateFaults(overlay=shift, cd_bias=0.0))
    )
    for tiny in (1e-13, -1e-13):
        near = window_amplitudes(model, PlateFaults(overlay=shift, cd_bias=tiny))
        assert np.abs(near - base).max() < 1e-7


@pytest.mark.parametrize("bias", [0.3e-6, -0.3e-6, 1.1e-6])
def test_cd_bias_grows_an_isolated_pixel_by_twice_the_bias(bias):
    # One etched pixel of a pi-deep single mask: c0 = 1 - 2 * etched area / tile area.
    n = 8
    levels = np.full((n, n), L - 1, np.uint8)
    levels[3, 5] = L // 2 - 1  # etched by the deep mask only
    model, _ = model_of(levels, 3)
    c0 = window_amplitudes(model, PlateFaults(cd_bias=bias))[1, 1]
    top_phase = np.exp(2j * np.pi * (L - 1) / L)
    area = (PITCH + 2 * bias) ** 2 / (n * PITCH) ** 2
    assert c0 / top_phase == pytest.approx(1 - 2 * area, abs=1e-14)


def test_zero_order_matches_analytic_formula_for_each_mask():
    levels = random_levels(32, seed=11)
    model, masks = model_of(levels, 5)
    phase = level_phase(levels, L)
    for i, mk in enumerate(masks):
        mask_phase = 2 * np.pi * (N_INDEX - 1) * mk.etch_depth / WAVELENGTH
        for eps in (-0.1, -0.02, 0.05, 0.2):
            etch = tuple(eps if j == i else 0.0 for j in range(len(masks)))
            p0 = abs(window_amplitudes(model, PlateFaults(etch_errors=etch))[2, 2]) ** 2
            analytic = zero_order_power_analytic(eps, phase, mk.bitmap, mask_phase)
            assert p0 == pytest.approx(float(analytic), rel=1e-10, abs=1e-15)


def test_balanced_tile_deep_etch_zero_order_is_1p05_eps_squared():
    # Every level exactly equally often: c0 = 0, so P0 = 4 sin^2(pi eps / 2) |A|^2.
    n = 32
    levels = np.random.default_rng(4).permutation(np.arange(n * n) % L).reshape(n, n)
    model, _ = model_of(levels.astype(np.uint8), 3)
    assert abs(window_amplitudes(model)[1, 1]) ** 2 < 1e-28
    coeff = (1 + (1 + np.sqrt(2)) ** 2) / 64 * np.pi**2  # small-eps slope, 1.0530
    assert coeff == pytest.approx(1.053, abs=5e-4)
    for eps in (0.01, 0.02, 0.05, 0.1):
        p0 = abs(window_amplitudes(model, PlateFaults(etch_errors=(eps, 0, 0)))[1, 1]) ** 2
        assert p0 == pytest.approx(float(zero_order_power_balanced(eps, L, L // 2)), rel=1e-9)
        assert p0 == pytest.approx(coeff * eps**2, rel=0.01 * (eps / 0.1) ** 2 + 1e-3)


@pytest.fixture(scope="module")
def designed():
    """A small GS design and the analysis of it against its own nominal PSF (rmse 0)."""
    n, k = 40, 7
    rng = np.random.default_rng(1)
    target = rng.uniform(0.3, 1.0, (k, k))
    levels = gs_levels(n, target / target.sum())
    masks = masks_from_levels(levels, L, STEP)
    model = plate_model(masks, PITCH, STEP, L, WAVELENGTH, N_INDEX, k)
    power = np.abs(window_amplitudes(model)) ** 2
    own = power / power.sum()
    result = tolerance_analysis(levels, L, own, masks, PITCH, STEP, WAVELENGTH, N_INDEX, seed=3)
    return levels, masks, own, result


def test_degradation_is_monotonic_for_a_plate_against_its_own_psf(designed):
    _, _, _, result = designed
    rows = result["rows"]
    assert rows[0]["kind"] == "nominal" and rows[0]["rmse"] == pytest.approx(0.0, abs=1e-12)
    groups = {}
    for r in rows[1:]:
        sign = np.sign(r["value"])
        groups.setdefault((r["kind"], r["mask"], r["axis"], sign), []).append(r)
    assert len(groups) == 3 * 2 + 2 * 2 * 2 + 2
    for key, grp in groups.items():
        grp = sorted(grp, key=lambda r: abs(r["value"]))
        rmses = [0.0] + [r["rmse"] for r in grp]
        corrs = [1.0] + [r["correlation"] for r in grp]
        assert np.all(np.diff(rmses) > 0), key
        assert np.all(np.diff(corrs) < 0), key
    deep = sorted(
        (r for r in rows if r["kind"] == "etch" and r["mask"] == "M1_deep" and r["value"] > 0),
        key=lambda r: r["value"],
    )
    assert np.all(np.diff([r["zero_order_excess"] for r in deep]) > 0)


def test_table_layout_units_and_reference_mask(designed):
    _, masks, _, result = designed
    rows = result["rows"]
    spec = ToleranceSpec()
    assert len(rows) == 1 + 3 * 3 * 2 + 2 * 4 * 4 + 2 * 2
    assert {r["kind"] for r in rows} == {"nominal", "etch", "overlay", "cd_bias"}
    assert result["reference_mask"] == masks[0].name
    assert all(r["mask"] != masks[0].name for r in rows if r["kind"] == "overlay")
    units = {r["kind"]: r["unit"] for r in rows}
    assert units == {"nominal": "", "etch": "%", "overlay": "um", "cd_bias": "um"}
    assert sorted({abs(r["value"]) for r in rows if r["kind"] == "etch"}) == pytest.approx(
        [100 * v for v in spec.etch_fractions]
    )
    for mask in (m.name for m in masks[1:]):
        for axis in "xy":
            values = [
                r["value"]
                for r in rows
                if r["kind"] == "overlay" and (r["mask"], r["axis"]) == (mask, axis)
            ]
            assert sorted(values) == pytest.approx(
                sorted(1e6 * s * v for v in spec.overlay for s in (1, -1))
            )
    for r in rows:
        assert r["zero_order_excess"] == pytest.approx(r["zero_order"] - rows[0]["zero_order"])
    json.dumps(result)  # JSON-ready


def test_budget_is_the_largest_value_within_the_rmse_limit(designed):
    _, masks, own, result = designed
    limit = result["rmse_limit"]
    assert limit == pytest.approx(result["nominal"]["rmse"] + ToleranceSpec().rmse_allowance)
    model = plate_model(masks, PITCH, STEP, L, WAVELENGTH, N_INDEX, own.shape[0])
    names = [mk.name for mk in masks]
    for b in result["budget"]:
        v = b["si_value"]

        def worst(v, b=b):
            i = names.index(b["mask"]) if b["mask"] in names else None
            if b["kind"] == "etch":
                plates = [
                    PlateFaults(etch_errors=tuple(s * v if j == i else 0 for j in range(3)))
                    for s in (1, -1)
                ]
            elif b["kind"] == "overlay":
                plates = [
                    PlateFaults(overlay=tuple(d if j == i else (0, 0) for j in range(3)))
                    for d in ((v, 0), (-v, 0), (0, v), (0, -v))
                ]
            else:
                plates = [PlateFaults(cd_bias=s * v) for s in (1, -1)]
            return max(plate_quality(model, own, p)["rmse"] for p in plates)

        assert worst(v) <= limit
        if b["limited_by_rmse"]:
            assert worst(v * 1.02 + 1e-12) > limit, b
    acc = result["acceptance"]
    nom = result["nominal"]
    assert acc["correlation_min"] < nom["correlation"]
    assert acc["rmse_max"] > nom["rmse"]
    assert acc["efficiency_min"] < nom["efficiency"]
    assert acc["zero_order_max"] > nom["zero_order"]
    assert len(result["monte_carlo"]["rmse"]) == ToleranceSpec().monte_carlo_plates


def test_analysis_is_deterministic_for_a_seed_and_reports_every_plate(designed):
    levels, masks, own, result = designed
    plates = []
    again = tolerance_analysis(
        levels, L, own, masks, PITCH, STEP, WAVELENGTH, N_INDEX, seed=3,
        on_plate=lambda: plates.append(1),
    )  # fmt: skip
    assert json.dumps(again, sort_keys=True) == json.dumps(result, sort_keys=True)
    # every table row and random plate, and two plates (signs or axes) per bisection step
    bisected = sum(b["limited_by_rmse"] for b in result["budget"])
    assert bisected and len(plates) >= len(result["rows"]) + 16 + 2 * bisected
    assert result["monte_carlo"]["plates"] == 16


def test_masks_that_do_not_make_the_levels_are_refused():
    levels = random_levels(8)
    masks = masks_from_levels(levels, L, STEP)
    target = np.random.default_rng(0).uniform(0.5, 1, (3, 3))
    wrong = [masks[0], replace(masks[1], bitmap=~masks[1].bitmap), masks[2]]
    with pytest.raises(ValueError, match="level map"):
        tolerance_analysis(
            levels, L, target / target.sum(), wrong, PITCH, STEP, WAVELENGTH, N_INDEX
        )


def test_cd_bias_of_half_a_pixel_is_refused():
    model, _ = model_of(random_levels(8), 3)
    with pytest.raises(ValueError, match="half the pixel pitch"):
        window_amplitudes(model, PlateFaults(cd_bias=PITCH / 2))


def test_etch_errors_are_one_per_mask():
    # one value was once applied to every mask without a word
    model, _ = model_of(random_levels(8), 3)
    with pytest.raises(ValueError, match="one per mask"):
        window_amplitudes(model, PlateFaults(etch_errors=(0.05,)))


@pytest.mark.parametrize(
    "shape, k, supersample, message",
    [
        ((8, 6), 3, None, "must be square"),
        ((8, 8), 4, None, "window K must be odd"),
        ((8, 8), 9, None, "window K must be odd and <= N = 8"),
        ((8, 8), 3, 0, "supersample must be a positive integer"),
        ((8, 8), 3, 1.5, "supersample must be a positive integer"),
    ],
)
def test_plate_model_refuses_what_it_cannot_model(shape, k, supersample, message):
    levels = np.random.default_rng(0).integers(0, L, shape).astype(np.uint8)
    masks = masks_from_levels(levels, L, STEP)
    with pytest.raises(ValueError, match=message):
        plate_model(masks, PITCH, STEP, L, WAVELENGTH, N_INDEX, k, supersample)


@pytest.mark.parametrize(
    "pitch, tabulated",
    [
        (0.3e-6, [0.1e-6]),
        (0.15e-6, []),
        # pitches as the design makes them, grid steps x 1e-9: 0.25 um over 500 * 1e-9 m
        # is 0.4999999999999999 pixel, and half-pixel biases were once tabulated
        (500 * 1e-9, [0.1e-6]),
        (200 * 1e-9, []),
    ],
)
def test_fine_pitch_tabulates_only_cd_biases_below_half_a_pixel(pitch, tabulated):
    # the table's 0.25 um bias closes a 0.3 um pixel's gaps; 0.1 um does too at 0.15 um
    levels = gs_levels(16, np.full((3, 3), 1 / 9))
    masks = masks_from_levels(levels, L, STEP)
    own = simulate_levels(levels, L, 3)[0]
    result = tolerance_analysis(levels, L, own, masks, pitch, STEP, WAVELENGTH, N_INDEX)
    rows = {abs(r["value"]) * 1e-6 for r in result["rows"] if r["kind"] == "cd_bias"}
    assert sorted(rows) == pytest.approx(tabulated)
    budget = [b for b in result["budget"] if b["kind"] == "cd_bias"]
    assert len(budget) == len(tabulated)
    assert f"{pitch / 2 * 1e6:.4g} um" in result["model"]["cd_bias"]


@pytest.mark.slow
def test_full_size_tile_nominal_row_is_the_enveloped_contract_model():
    from doe.derived import derive
    from doe.design import load_design

    design = load_design()
    der = derive(design)
    n, k = der.tile_pixels, design.kernel_size
    rng = np.random.default_rng(0)
    target = rng.uniform(0.2, 1.0, (k, k))
    target /= target.sum()
    levels = gs_levels(n, target, iters=60)
    masks = masks_from_levels(levels, L, der.level_step)
    result = tolerance_analysis(
        levels,
        L,
        target,
        masks,
        der.mask_pixel_pitch,
        der.level_step,
        design.optics.wavelength,
        der.refractive_index,
    )
    m = np.arange(k) - k // 2
    env = np.sinc(m / n) ** 2
    power = window_power(level_phase(levels, L), k) * env[:, None] * env[None, :]
    nominal = result["rows"][0]
    assert nominal["efficiency"] == pytest.approx(power.sum(), rel=1e-9)
    assert nominal["zero_order"] == pytest.approx(power[k // 2, k // 2], rel=1e-9, abs=1e-15)
    assert len(result["rows"]) == 1 + 3 * 3 * 2 + 2 * 4 * 4 + 2 * 2


def test_acceptance_compares_with_the_levels_psf_like_verification():
    # With negligible errors every Monte Carlo plate is the nominal one, so the thresholds
    # are the continuous nominal plate against simulate_levels' PSF, plus the margins.
    levels = random_levels(24, seed=9)
    masks = masks_from_levels(levels, L, STEP)
    target = np.random.default_rng(2).uniform(0.5, 1.0, (5, 5))
    target /= target.sum()
    spec = ToleranceSpec(etch_fractions=(1e-12,), overlay=(1e-15,), cd_bias=(1e-15,),
                         monte_carlo_plates=3)  # fmt: skip
    result = tolerance_analysis(levels, L, target, masks, PITCH, STEP, WAVELENGTH, N_INDEX,
                                spec=spec)  # fmt: skip
    model = plate_model(masks, PITCH, STEP, L, WAVELENGTH, N_INDEX, 5)
    design_psf = simulate_levels(levels, L, 5)[0]
    nominal = plate_quality(model, target, reference=design_psf)
    acc = result["acceptance"]
    assert acc["rmse_max"] == pytest.approx(nominal["rmse_vs_reference"] + spec.rmse_margin)
    assert acc["correlation_min"] == pytest.approx(
        nominal["correlation_vs_reference"] - spec.correlation_margin
    )
    assert acc["efficiency_min"] == pytest.approx(
        nominal["efficiency"] * (1 - spec.efficiency_margin)
    )
    assert acc["zero_order_max"] == pytest.approx(nominal["zero_order"] + spec.zero_order_margin)
    # ... and not against the (here unrelated) target.
    assert nominal["rmse"] > 10 * nominal["rmse_vs_reference"]


@settings(max_examples=15, deadline=None)
@given(
    dx=st.floats(-3 * PITCH, 3 * PITCH),
    dy=st.floats(-3 * PITCH, 3 * PITCH),
    bias=st.floats(-0.4 * PITCH, 0.4 * PITCH),
)
def test_shifting_every_mask_alike_only_adds_a_phase_ramp(dx, dy, bias):
    # Translating the whole plate by (dx, dy) multiplies order (m, n) by
    # exp(-2 pi i (n dx - m dy) / T) (rows grow towards -y), for any sub-pixel shift.
    n, k = 12, 5
    model, _ = model_of(random_levels(n, seed=13), k)
    base = window_amplitudes(model, PlateFaults(cd_bias=bias))
    moved = window_amplitudes(model, PlateFaults(overlay=((dx, dy),) * 3, cd_bias=bias))
    m = np.arange(k) - k // 2
    tile = n * PITCH
    ramp = np.exp(-2j * np.pi * (m[None, :] * dx - m[:, None] * dy) / tile)
    np.testing.assert_allclose(moved, base * ramp, rtol=0, atol=1e-13)


def _flat_design(n=16):
    """A small GS level map for a flat 3 x 3 target, its masks and its own (contract) PSF."""
    levels = gs_levels(n, np.full((3, 3), 1 / 9))
    return levels, masks_from_levels(levels, L, STEP), simulate_levels(levels, L, 3)[0]


def test_rmse_limit_is_the_nominal_rmse_plus_the_allowance_or_the_given_one():
    # Against a target the plate does not make, the nominal rmse is far from 0 and the
    # limit must be relative to it (the fixture's plate meets its own PSF: rmse 0).
    levels, masks, _ = _flat_design()
    target = np.array([[1.0, 2, 1], [2, 6, 2], [1, 2, 1]])
    target /= target.sum()
    env = np.sinc((np.arange(3) - 1) / 16) ** 2  # the continuous plate's pixel envelope
    power = window_power(level_phase(levels, L), 3) * env[:, None] * env[None, :]
    psf = power / power.sum()
    nominal = np.sqrt(np.mean((psf / psf.max() - target / target.max()) ** 2))
    assert nominal > 0.1
    result = tolerance_analysis(levels, L, target, masks, PITCH, STEP, WAVELENGTH, N_INDEX)
    assert result["nominal"]["rmse"] == pytest.approx(nominal, rel=1e-9)
    assert result["rmse_limit"] == pytest.approx(nominal + 0.01, rel=1e-9)
    given = tolerance_analysis(
        levels, L, target, masks, PITCH, STEP, WAVELENGTH, N_INDEX, rmse_limit=nominal + 0.002
    )
    assert given["rmse_limit"] == nominal + 0.002
    assert all(b["rmse"] <= nominal + 0.002 for b in given["budget"])


def test_a_table_value_exactly_at_the_rmse_limit_is_within_budget():
    # "rmse <= limit": the deep mask's largest etch value, with the limit set to its own
    # worse-sign rmse, is the budget, not the start of a bisection below it.
    levels, masks, own = _flat_design()
    model = plate_model(masks, PITCH, STEP, L, WAVELENGTH, N_INDEX, 3)
    at = max(plate_quality(model, own, PlateFaults(etch_errors=(s * 0.1, 0.0, 0.0)))["rmse"]
             for s in (1, -1))  # fmt: skip
    spec = ToleranceSpec(monte_carlo_plates=1)
    result = tolerance_analysis(levels, L, own, masks, PITCH, STEP, WAVELENGTH, N_INDEX,
                                rmse_limit=at, spec=spec)  # fmt: skip
    deep = next(b for b in result["budget"] if (b["kind"], b["mask"]) == ("etch", masks[0].name))
    assert deep["si_value"] == 0.1 and not deep["limited_by_rmse"]
    assert (deep["value"], deep["unit"]) == (pytest.approx(10.0), "%")  # in the table's unit


def test_overlay_is_relative_to_the_first_exposed_mask_whichever_it_is():
    levels, masks, own = _flat_design()
    masks = [replace(mk, exposure_order=o) for mk, o in zip(masks, (2, 1, 3), strict=True)]
    result = tolerance_analysis(levels, L, own, masks, PITCH, STEP, WAVELENGTH, N_INDEX)
    assert result["reference_mask"] == masks[1].name
    others = {masks[0].name, masks[2].name}
    assert {r["mask"] for r in result["rows"] if r["kind"] == "overlay"} == others
    assert {b["mask"] for b in result["budget"] if b["kind"] == "overlay"} == others


def test_monte_carlo_plates_draw_every_error_uniformly_within_its_budget(monkeypatch):
    import fab.plate.tolerance

    drawn, figures, real = [], [], fab.plate.tolerance.plate_quality

    def spy(model, target, errors, reference=None):
        q = real(model, target, errors, reference)
        if reference is not None:  # only the Monte Carlo plates carry the reference PSF
            drawn.append(errors)
            figures.append(q)
        return q

    monkeypatch.setattr(fab.plate.tolerance, "plate_quality", spy)
    levels, masks, own = _flat_design()

    def run(seed):
        drawn.clear()
        figures.clear()
        result = tolerance_analysis(levels, L, own, masks, PITCH, STEP, WAVELENGTH, N_INDEX,
                                    seed=seed)  # fmt: skip
        return result, list(drawn)

    result, plates = run(5)
    assert len(plates) == ToleranceSpec().monte_carlo_plates
    budget = {(b["kind"], b["mask"]): b["si_value"] for b in result["budget"]}
    etch = np.array([p.etch_errors for p in plates])  # (plates, masks)
    shift = np.array([p.overlay for p in plates])  # (plates, masks, (dx, dy))
    cd = np.array([p.cd_bias for p in plates])

    def uniform_within(values, b):
        # |value| <= budget (SI units), and 16 uniform draws reach past a quarter of
        # it on both sides (each side misses with probability (5/8)**16 = 5e-4)
        assert b > 0
        assert np.all(np.abs(values) <= b)
        assert values.min() < -b / 4 and values.max() > b / 4

    for i, mk in enumerate(masks):
        uniform_within(etch[:, i], budget["etch", mk.name])
    assert np.all(shift[:, 0] == 0)  # the first exposed mask is the reference
    for i in (1, 2):
        for axis in (0, 1):
            uniform_within(shift[:, i, axis], budget["overlay", masks[i].name])
        assert np.all(shift[:, i, 0] != shift[:, i, 1])  # x and y drawn independently
    uniform_within(cd, budget["cd_bias", "all"])
    # the thresholds are the worst of these plates, widened by the margins
    spec, acc = ToleranceSpec(), result["acceptance"]
    worst = {key: [q[key] for q in figures] for key in figures[0]}
    corr, rmse = worst["correlation_vs_reference"], worst["rmse_vs_reference"]
    assert acc["correlation_min"] == min(corr) - spec.correlation_margin
    assert acc["rmse_max"] == max(rmse) + spec.rmse_margin
    assert acc["efficiency_min"] == min(worst["efficiency"]) * (1 - spec.efficiency_margin)
    assert acc["zero_order_max"] == max(worst["zero_order"]) + spec.zero_order_margin
    # seeded: the same seed draws the same plates, another seed others
    assert run(5)[1] == plates
    assert run(6)[1] != plates


def test_masks_one_step_off_on_a_single_pixel_are_refused():
    levels = random_levels(8)
    masks = masks_from_levels(levels, L, STEP)
    bitmap = masks[2].bitmap.copy()  # the shallowest mask: one level step
    bitmap[3, 4] = not bitmap[3, 4]
    wrong = [masks[0], masks[1], replace(masks[2], bitmap=bitmap)]
    target = np.full((3, 3), 1 / 9)
    with pytest.raises(ValueError, match="level map"):
        tolerance_analysis(levels, L, target, wrong, PITCH, STEP, WAVELENGTH, N_INDEX)


def test_supersampled_model_rounds_the_cd_bias_to_sub_samples():
    model, _ = model_of(random_levels(12, seed=1), 5, supersample=4)
    np.testing.assert_array_equal(
        window_amplitudes(model, PlateFaults(cd_bias=PITCH / 4)),
        window_amplitudes(model, PlateFaults(cd_bias=PITCH / 4 * 1.2)),
    )
    # 0.45 pixel is two of four sub-samples: half a pixel, which closes one-pixel gaps
    with pytest.raises(ValueError, match="half the pixel pitch"):
        window_amplitudes(model, PlateFaults(cd_bias=0.45 * PITCH))


def test_y_overlay_rows_shift_along_y():
    # Levels that vary only along x (every row alike) are blind to a shift along y, at any
    # sub-pixel value: the y rows must equal the nominal plate, the x rows must not.
    row = np.random.default_rng(6).integers(0, L, 16).astype(np.uint8)
    levels = np.tile(row, (16, 1))
    masks = masks_from_levels(levels, L, STEP)
    own = simulate_levels(levels, L, 3)[0]
    result = tolerance_analysis(levels, L, own, masks, PITCH, STEP, WAVELENGTH, N_INDEX)
    nominal = result["nominal"]["rmse"]
    overlay = [r for r in result["rows"] if r["kind"] == "overlay"]
    assert {r["axis"] for r in overlay} == {"x", "y"}
    for r in overlay:
        if r["axis"] == "y":
            assert r["rmse"] == pytest.approx(nominal, abs=1e-12), r
        else:
            assert r["rmse"] > nominal + 1e-4, r


@pytest.mark.parametrize("bias_sub", [-1, 1])
def test_shifts_half_way_between_sub_samples_round_to_one_consistent_plate(bias_sub):
    # Rounding may go either way at a tie, but the plate must be one of the supersampled
    # tiles with every shift on a whole sub-sample, not a mix of two of them.
    s, k = 5, 5
    model, masks = model_of(random_levels(12, seed=1), k, supersample=s)
    sub = PITCH / s

    def plate(shifts):  # (dx, dy) of each mask in sub-samples
        shift = tuple((x * sub, y * sub) for x, y in shifts)
        return PlateFaults(etch_errors=(0.0, 0.0, 0.0), overlay=shift, cd_bias=bias_sub * sub)

    halves = ((-2.5, 2.5), (-0.5, 0.5), (1.5, -3.5))
    got = window_amplitudes(model, plate(halves))
    roundings = itertools.product(*[(c - 0.5, c + 0.5) for xy in halves for c in xy])
    candidates = (plate(zip(r[::2], r[1::2], strict=True)) for r in roundings)
    assert any(
        np.allclose(got, brute_force_window(masks, c, s, k, False), rtol=0, atol=1e-13)
        for c in candidates
    )
