"""The etch-depth fits of a measured window: the deepest etch alone, every etch jointly, the
error implied by the zero order."""

import numpy as np
import pytest
from verify_helpers import K, L, N

from fab.plate.model import PlateFaults, plate_far_field, plate_phase
from fab.verify.analysis import design_order_power
from fab.verify.etch_fit import fit_etch_error, fit_etch_errors, implied_deep_etch_error


@pytest.mark.parametrize("errors", [(-0.15, 0.25, 0.0), (0.0, -0.2, 0.3), (0.3, -0.3, 0.2)])
def test_the_joint_etch_fit_inverts_a_plate_with_every_etch_off(levels, errors):
    orders = np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij")
    window = plate_far_field(plate_phase(levels, L, PlateFaults(etch_errors=errors)))(*orders)
    sigma = 1e-4 * window.max() + 0.01 * window
    fit = fit_etch_errors(window, sigma, levels, L)
    assert fit["eps"] == pytest.approx(errors, abs=2e-3)
    assert fit["masks"] == ["M1_deep", "M2_mid", "M3_shallow"] and not fit["at_search_edge"]
    # a mask whose error is 0 is not needed: holding it at 0 costs (almost) nothing
    for err, chi2 in zip(errors, fit["mask_chi2"], strict=True):
        assert (chi2 > 100) if err else (chi2 < 1e-3)
    assert fit["psf"] == pytest.approx(window / window.sum(), abs=1e-6)


def test_the_joint_etch_fit_finds_a_big_error_past_the_local_minimum_near_0():
    # Started from no error alone, the fit stopped at M1 -9 % on this 4-level design's
    # window of M1 +40 % (a helper's 4-level plate: +25 % read +8 %, and the plate passed).
    from doe.retrieval import retrieve_phase
    from doe.targets import make_target

    levels = retrieve_phase(make_target("asymmetric", K), N, 4, seed=0).levels
    orders = np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij")
    for errors in ((0.4, 0.0), (-0.4, 0.0), (0.1, 0.0)):
        window = plate_far_field(plate_phase(levels, 4, PlateFaults(etch_errors=errors)))(*orders)
        assert fit_etch_errors(window, None, levels, 4)["eps"] == pytest.approx(errors, abs=1e-3)


def test_the_joint_etch_fit_s_sigmas_are_the_spread_of_its_errors_over_noise(
    levels, sigmas_match_spread
):
    orders = np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij")
    errors = (0.1, -0.2, 0.15)
    window = plate_far_field(plate_phase(levels, L, PlateFaults(etch_errors=errors)))(*orders)
    sigma = 0.002 * window.max() + 0.03 * window
    sigmas_match_spread(
        lambda noisy: fit_etch_errors(noisy, sigma, levels, L),
        window, sigma, runs=60, seed=0,
        values=lambda f: f["eps"], sigmas=lambda f: f["eps_sigma"],
    )  # fmt: skip


@pytest.mark.parametrize("joint", [False, True])
def test_the_etch_fits_gains_are_in_units_of_their_reduced_chi_square(levels, joint):
    # Sigmas quoted 2x short inflate chi-square 4x; the gains must not grow with them
    # (the deepest etch's own fit and the joint fit's total were taken as they came).
    orders = np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij")
    window = plate_far_field(plate_phase(levels, L, PlateFaults(etch_errors=(0.1, 0.1, 0.0))))(
        *orders
    )
    sigma = 0.002 * window.max() + 0.03 * window
    noisy = window + np.random.default_rng(4).normal(0, 1, window.shape) * sigma

    def fit(s):
        return (fit_etch_errors if joint else fit_etch_error)(noisy, s, levels, L)

    honest, short, long = fit(sigma), fit(sigma / 2), fit(3 * sigma)
    assert short["chi2"] == pytest.approx(4 * honest["chi2"], rel=1e-3)
    assert short["reduced_chi2"] > 1 > long["reduced_chi2"]
    raw = honest["chi2_drop"] * max(honest["reduced_chi2"], 1.0)
    assert short["chi2_drop"] == pytest.approx(4 * raw / short["reduced_chi2"], rel=1e-3)
    assert long["chi2_drop"] == pytest.approx(raw / 9, rel=1e-3)  # too long: as they are


@pytest.mark.parametrize("eps", [-0.4, 0.3])
def test_the_joint_etch_fit_holds_an_unneeded_error_at_0_where_two_masks_trade_off(eps):
    # Levels 5 and 6 only (a near-delta design's): the window sees 2 eps_M2 - eps_M3
    # alone. M2 40 % too shallow read as M2 -26.7 % with M3 +26.7 %, a point anywhere
    # along the valley; M3 alone cannot explain it within +-50 %, M2 alone can.
    two = np.random.default_rng(9).choice(np.array([5, 6], np.uint8), (N, N), p=[0.75, 0.25])
    orders = np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij")
    window = plate_far_field(plate_phase(two, L, PlateFaults(etch_errors=(0, eps, 0))))(*orders)
    fit = fit_etch_errors(window, 1e-4 * window.max() + 0.01 * window, two, L)
    assert fit["mask_chi2"][1] > 9 > fit["mask_chi2"][2]
    assert fit["eps"] == pytest.approx([0.0, eps, 0.0], abs=0.005)
    assert fit["psf"] == pytest.approx(window / window.sum(), abs=1e-6)


def test_the_joint_etch_fit_of_a_design_using_one_mask():
    # levels 3 and 7 only: the deepest mask alone etches some pixels and not others
    two = np.random.default_rng(5).choice(np.array([3, 7], np.uint8), (N, N))
    orders = np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij")
    window = plate_far_field(plate_phase(two, L, PlateFaults(etch_errors=(0.2, 0.0, 0.0))))(*orders)
    fit = fit_etch_errors(window, 1e-4 * window.max() + 0.01 * window, two, L)
    assert fit["eps"] == pytest.approx([0.2, 0.0, 0.0], abs=2e-3)
    assert fit["mask_chi2"][0] == pytest.approx(fit["chi2_drop"]) and fit["chi2_drop"] > 100
    assert fit_etch_errors(window, None, np.full((N, N), 7, np.uint8), L) is None  # flat
    far = plate_far_field(plate_phase(two, L, PlateFaults(etch_errors=(0.7, 0.0, 0.0))))(*orders)
    assert fit_etch_errors(far, None, two, L)["at_search_edge"]  # beyond the +-50 % searched


@pytest.mark.parametrize("mask", [1, 2])
def test_the_etch_fit_of_each_shallower_mask_inverts_the_simulated_plate(levels, mask):
    orders = np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij")
    for eps in (-0.3, -0.1, 0.05, 0.25):
        errors = tuple(eps if j == mask else 0.0 for j in range(3))
        window = plate_far_field(plate_phase(levels, L, PlateFaults(etch_errors=errors)))(*orders)
        fits = [fit_etch_error(window, None, levels, L, j) for j in range(3)]
        assert fits[mask]["eps"] == pytest.approx(eps, abs=2e-3)
        assert fits[mask]["mask"] == ("M1_deep", "M2_mid", "M3_shallow")[mask]
        # the other masks' fits explain the window worse (an exact fit drops chi2 the most)
        assert max(fits, key=lambda f: f["chi2_drop"]) is fits[mask]


def test_implied_deep_etch_error_inverts_the_simulated_plate(levels):
    for eps in (-0.2, -0.1, 0.05, 0.15):
        far = plate_far_field(plate_phase(levels, L, PlateFaults(etch_errors=(eps, 0.0, 0.0))))
        window = far(*np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij"))
        fit = fit_etch_error(window, None, levels, L)
        assert fit["eps"] == pytest.approx(eps, abs=2e-3)
        assert implied_deep_etch_error(levels, L, float(far(0, 0)), fit["eps"]) == pytest.approx(
            eps, abs=1e-6
        )


def test_deep_etch_fit_is_none_when_the_deep_mask_is_unused():
    upper = np.random.default_rng(4).integers(L // 2, L, (N, N)).astype(np.uint8)
    assert fit_etch_error(np.ones((K, K)), None, upper, L) is None
    # nor does the zero order tell an etch error of a mask that etches nothing
    assert implied_deep_etch_error(upper, L, 0.01) is None


def test_zero_order_follows_the_analytic_deep_etch_law():
    """A balanced random 8-level tile has no zero order; the deep mask etches the pixels
    of levels 0..3 (a quarter of the tile each... half in all), so an error eps leaves
    |C|^2 |exp(-i pi eps) - 1|^2 = 4 |C|^2 sin^2(pi eps / 2) with
    |C| = |sum_{l<4} exp(i pi l / 4)| / 8, i.e. about 1.05 eps^2."""
    n = 64
    lv = np.random.default_rng(3).permutation(np.arange(n * n) % L).reshape(n, n)
    lv = lv.astype(np.uint8)
    c = abs(np.exp(1j * np.pi * np.arange(4) / 4).sum()) / 8
    assert design_order_power(lv, L)[0, 0] == pytest.approx(0, abs=1e-20)
    for eps in (0.02, 0.05, 0.15):
        far = plate_far_field(plate_phase(lv, L, PlateFaults(etch_errors=(eps, 0.0, 0.0))))
        z = float(far(0, 0))
        assert z == pytest.approx(4 * c**2 * np.sin(np.pi * eps / 2) ** 2, rel=1e-9)
        # The zero order alone cannot tell too deep from too shallow here.
        assert abs(implied_deep_etch_error(lv, L, z)) == pytest.approx(eps, rel=1e-6)
    assert c**2 * np.pi**2 == pytest.approx(1.05, abs=0.01)
