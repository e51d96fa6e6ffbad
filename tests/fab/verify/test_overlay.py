"""Tests of the overlay-error fits (fab.verify.overlay) against a supersampled plate.

The plate model they search is tested in tests/fab/plate/test_basis.py.
"""

import numpy as np
import pytest

from fab.plate.model import PlateFaults, plate_far_field, plate_phase
from fab.verify.overlay import SEARCH_PX, fit_overlay_and_etch, fit_overlay_error

N, K, L = 24, 7, 8


@pytest.fixture(scope="module")
def levels():
    return np.random.default_rng(3).integers(0, L, (N, N)).astype(np.uint8)


def supersampled_window(levels, mask, shift_px, supersample, etch_errors=()):
    """The window orders of a plate with ``mask`` shifted by ``shift_px`` ([dy, dx] mask
    pixels, as a fit reports it) and its etches off by ``etch_errors``, sampled
    ``supersample`` times finer."""
    dy, dx = shift_px
    overlay = tuple((dx, dy) if j == mask else (0.0, 0.0) for j in range(3))
    faults = PlateFaults(etch_errors=etch_errors, overlay=overlay)
    orders = plate_far_field(plate_phase(levels, L, faults, 1.0, supersample))
    m = np.arange(K) - K // 2
    return orders(m[:, None], m[None, :])


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
