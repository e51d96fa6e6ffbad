"""Tests of the overlay-error model and fit (fab.verify.overlay) against a supersampled plate."""

import numpy as np
import pytest

from doe.fraunhofer import order_amplitudes, pixel_envelope, window_indices
from fab.plate.model import PlateFaults, plate_far_field, plate_phase
from fab.verify.overlay import (
    SEARCH_PX,
    EtchedOverlayModel,
    OverlayModel,
    fit_overlay_and_etch,
    fit_overlay_error,
)

N, K, L = 24, 7, 8


@pytest.fixture(scope="module")
def levels():
    return np.random.default_rng(3).integers(0, L, (N, N)).astype(np.uint8)


@pytest.fixture(scope="module")
def model(levels):
    return OverlayModel(levels, L, K)


def supersampled_window(levels, mask, shift, supersample, etch_errors=()):
    """The window orders of a plate with ``mask`` shifted (and its etches off by
    ``etch_errors``), sampled ``supersample`` times finer."""
    faults = PlateFaults(etch_errors=etch_errors, overlay_mask=mask, overlay_shift=shift)
    orders = plate_far_field(plate_phase(levels, L, faults, 1.0, supersample))
    m = np.arange(K) - K // 2
    return orders(m[:, None], m[None, :])


@pytest.mark.parametrize("mask", [0, 1, 2])
@pytest.mark.parametrize(
    "shift", [(0.25, 0.0), (0.0, -0.5), (1.75, -1.25), (-2.0, 0.75), (1.0, 1.0), (-0.2, 0.6)]
)
def test_a_shifted_mask_gives_the_orders_of_the_supersampled_plate(levels, model, mask, shift):
    # Exact for sub-pixel shifts: the same orders as the plate cut into 20 x 20
    # sub-pixels per mask pixel, with the shift (+y up) applied to that mask's bitmap.
    expected = supersampled_window(levels, mask, (shift[0] * 1.0, shift[1] * 1.0), 20)
    assert np.allclose(model.power(mask, *shift), expected, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("mask", [0, 1, 2])
def test_the_model_is_fab_tolerance_s_plate_with_one_mask_shifted(levels, model, mask):
    # The tolerance budget's general model (continuous plate, any error), built
    # independently; this one is it restricted to a single shifted mask, made fast.
    from fab.package.masks import masks_from_levels
    from fab.plate.tolerance import PlateErrors, plate_model, window_amplitudes

    masks = masks_from_levels(levels, L, 1.0)
    general = plate_model(masks, 1.0, 1.0, L, wavelength=1.0, refractive_index=1 + 1 / L, k=K)
    for dy, dx in [(0.37, -1.91), (-1.3, 0.05), (2.0, 2.0)]:
        shift = [(0.0, 0.0)] * len(masks)
        shift[mask] = (dx, dy)  # (x, y) there
        expected = np.abs(window_amplitudes(general, PlateErrors(shift=tuple(shift)))) ** 2
        assert np.allclose(model.power(mask, dy, dx), expected, rtol=1e-9, atol=1e-15)


def square_pixel_window(levels):
    """The window orders of a level map made with square pixels (the sinc^2 envelope)."""
    amp = order_amplitudes(2 * np.pi * levels / L)
    idx = window_indices(N, K)
    env = pixel_envelope(np.arange(K) - K // 2, N)
    return np.abs(amp[np.ix_(idx, idx)]) ** 2 * np.outer(env, env)


def test_no_shift_gives_the_design_with_its_pixel_envelope(levels, model):
    design = square_pixel_window(levels)
    for mask in range(3):
        assert np.allclose(model.power(mask, 0.0, 0.0), design, rtol=1e-12)


def test_whole_pixel_shift_rolls_the_mask_bitmap_towards_row_0_for_plus_y(levels, model):
    # Independent of capture_sim: rebuild the level map with the deep mask moved one
    # row up (+y) and one column right, and compare with the design frame's FFT.
    from fab.package.masks import masks_from_levels

    masks = masks_from_levels(levels, L, 1.0)
    code = sum(
        mk.steps * np.roll(mk.bitmap, (-1, 1), axis=(0, 1)) if j == 0 else mk.steps * mk.bitmap
        for j, mk in enumerate(masks)
    )
    expected = square_pixel_window((L - 1) - code)
    assert np.allclose(model.power(0, 1.0, 1.0), expected, rtol=1e-12)
    assert not np.allclose(model.power(0, -1.0, 1.0), expected, rtol=1e-3)


def test_shifts_beyond_the_reach_are_refused(model):
    with pytest.raises(ValueError, match="reach"):
        model.power(1, SEARCH_PX + 0.1, 0.0)
    with pytest.raises(ValueError, match="reach"):
        model.power(1, 0.0, -SEARCH_PX - 0.1)


@pytest.mark.parametrize("mask, shift", [(0, (0.73, -0.41)), (1, (-1.62, 0.3)), (2, (0.0, 1.18))])
def test_the_fit_finds_the_shifted_mask_and_its_shift(levels, mask, shift):
    window = supersampled_window(levels, mask, shift, 100)  # shifts on the 0.01 px grid
    fit = fit_overlay_error(window, None, levels, L)
    assert fit["mask"] == ("M1_deep", "M2_mid", "M3_shallow")[mask]
    assert fit["shift_px"] == pytest.approx(shift, abs=0.011)
    assert fit["chi2_drop"] > 0
    assert np.allclose(fit["psf"], window / window.sum(), atol=1e-4)


def test_the_fit_of_an_aligned_plate_is_no_shift(levels):
    window = supersampled_window(levels, 0, (0.0, 0.0), 1)
    fit = fit_overlay_error(window, np.full(window.shape, 1e-6), levels, L)
    assert fit["shift_px"] == [0.0, 0.0] and fit["chi2_drop"] == pytest.approx(0.0, abs=1e-9)


def test_a_design_no_mask_structures_has_no_overlay_fit():
    # Every mask etches all pixels or none: a shift leaves no trace.
    assert fit_overlay_error(np.ones((K, K)), None, np.full((N, N), 5, np.uint8), L) is None
    # Levels 0 and 4 differ in M1 alone: its shift moves the whole pattern, no trace either
    binary = 4 * np.random.default_rng(2).integers(0, 2, (N, N)).astype(np.uint8)
    assert fit_overlay_error(np.ones((K, K)), None, binary, L) is None


@pytest.mark.parametrize("mask", [0, 1, 2])
def test_a_shifted_mask_on_a_plate_etched_off_gives_the_supersampled_plate(levels, mask):
    errors = (0.1, -0.2, 0.15)
    expected = supersampled_window(levels, mask, (1.25, -0.5), 4, errors)
    model = EtchedOverlayModel(levels, L, K, mask)
    model.set_etch_errors(errors)
    assert np.allclose(model.power(mask, 1.25, -0.5), expected, rtol=1e-9, atol=1e-15)
    model.set_etch_errors((0, 0, 0))  # and the errors undone: the plain overlay's model
    assert np.allclose(
        model.power(mask, 1.25, -0.5), OverlayModel(levels, L, K).power(mask, 1.25, -0.5)
    )


@pytest.mark.parametrize(
    "mask, shift, errors", [(0, (1.6, 0.0), (0.0, 0.3, 0.0)), (1, (1.0, -0.6), (0.2, 0.0, 0.0))]
)
def test_the_joint_fit_finds_an_overlay_and_an_etch_error_together(levels, mask, shift, errors):
    window = supersampled_window(levels, mask, shift, 5, errors)
    sigma = 1e-4 * window.max() + 0.01 * window
    # started where a lab's first fits leave it: the shift near, no etch error
    fit = fit_overlay_and_etch(window, sigma, levels, L, mask, (shift[0] - 0.2, 0.0), (0, 0, 0))
    assert fit["shift_px"] == pytest.approx(shift, abs=1e-3)
    assert fit["eps"] == pytest.approx(errors, abs=1e-3)
    # needed: the shift and the etches off; not the etches that are right
    assert fit["shift_chi2"] > 100 and fit["chi2"] < 1e-6
    assert [c > 100 for c in fit["mask_chi2"]] == [e != 0 for e in errors]
    assert fit["chi2_drop"] > 100 and not fit["at_search_edge"]


def test_the_joint_fit_s_sigmas_are_the_spread_of_its_values_over_noise(
    levels, sigmas_match_spread
):
    window = supersampled_window(levels, 1, (1.0, -0.6), 5, (0.2, 0.0, 0.1))
    sigma = 0.002 * window.max() + 0.03 * window
    sigmas_match_spread(
        lambda noisy: fit_overlay_and_etch(
            noisy, sigma, levels, L, 1, (1.0, -0.6), (0.2, 0.0, 0.1)
        ),
        window, sigma, runs=40, seed=0,
        values=lambda f: np.r_[f["shift_px"], f["eps"]],
        sigmas=lambda f: np.r_[f["shift_sigma"], f["eps_sigma"]],
    )  # fmt: skip


def test_the_overlay_fit_s_sigmas_are_the_spread_of_its_shifts_over_noise(
    levels, sigmas_match_spread
):
    window = supersampled_window(levels, 1, (1.0, -0.6), 5)
    sigma = 0.002 * window.max() + 0.03 * window
    sigmas_match_spread(
        lambda noisy: fit_overlay_error(noisy, sigma, levels, L),
        window, sigma, runs=40, seed=1,
        values=lambda f: f["shift_px"], sigmas=lambda f: f["shift_sigma"],
    )  # fmt: skip
    assert (
        fit_overlay_error(supersampled_window(levels, 1, (SEARCH_PX, 0.0), 2), sigma, levels, L)[
            "shift_sigma"
        ]
        is None
    )  # at the edge of the search: no curvature to take


def test_the_overlay_fit_s_gain_is_in_units_of_its_reduced_chi_square(levels):
    # Sigmas quoted 2x short inflate chi-square 4x; the gain must not grow with them.
    # A perfect plate's noise under short sigmas was once named a 0.19 px overlay.
    window = supersampled_window(levels, 1, (0.3, -0.2), 5)
    sigma = 0.002 * window.max() + 0.03 * window
    noisy = window + np.random.default_rng(2).normal(0, 1, window.shape) * sigma
    honest, short = (fit_overlay_error(noisy, s, levels, L) for s in (sigma, sigma / 2))
    assert short["reduced_chi2"] == pytest.approx(4 * honest["reduced_chi2"])
    assert short["reduced_chi2"] > 1 and honest["shift_px"] == short["shift_px"]
    raw = honest["chi2_drop"] * max(honest["reduced_chi2"], 1.0)
    assert short["chi2_drop"] == pytest.approx(4 * raw / short["reduced_chi2"])
    long = fit_overlay_error(noisy, 3 * sigma, levels, L)  # sigmas too long: taken as they are
    assert long["reduced_chi2"] < 1 and long["chi2_drop"] == pytest.approx(raw / 9)
