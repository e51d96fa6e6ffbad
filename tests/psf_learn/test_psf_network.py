"""The learnable PSF, the fixed baseline PSFs and the super-resolution networks."""

import numpy as np
import pytest
import torch

from doe.infra.files import check_psf
from psf_learn.network import SRNet
from psf_learn.psf import (
    LearnedPSF,
    baseline_psf,
    box_psf,
    delta_psf,
    gaussian_psf,
    starting_psf,
)

K = 11


# --- PSF ------------------------------------------------------------------------------


def test_learned_psf_is_normalised_for_any_logits():
    psf = LearnedPSF(delta_psf(K))
    psf.logits.data = torch.randn(K, K, generator=torch.Generator().manual_seed(0)) * 5
    p = psf()
    # softmax ignores a common offset, even one whose exp overflows (float32 logits
    # near 1000 are rounded to 6e-5)
    shifted = LearnedPSF(delta_psf(K))
    shifted.logits.data = psf.logits.data + 1000
    np.testing.assert_allclose(shifted.numpy(), psf.numpy(), rtol=1e-4)
    assert (p >= 0).all()
    assert p.sum().item() == pytest.approx(1, abs=1e-6)
    exact = psf.numpy()
    assert exact.dtype == np.float64 and exact.shape == (K, K)
    assert exact.sum() == pytest.approx(1, abs=1e-14)
    check_psf(exact, "learned")  # the psf.npy contract


def test_learned_psf_starts_at_its_initial_psf_and_frozen_keeps_zeros():
    g = gaussian_psf(K)
    np.testing.assert_allclose(LearnedPSF(g).numpy(), g, atol=K * K * 1e-6 * g.max())
    frozen = LearnedPSF(box_psf(K), trainable=False)
    assert not frozen.logits.requires_grad
    np.testing.assert_allclose(frozen.numpy(), box_psf(K), atol=1e-12)


def test_a_learned_psf_started_from_a_delta_can_move_light_to_any_cell():
    # Zeros of the start are floored at 1e-6 of the peak: at log 0 the softmax would
    # hold them at exactly 0, with zero gradient, for ever.
    psf = LearnedPSF(delta_psf(K))
    (-psf()[0, 0]).backward()  # a loss that wants light in the corner
    p0 = 1e-6 / (1 + (K * K - 1) * 1e-6)  # the corner's share at the start
    # d(-p_0)/dz_0 = -p_0 (1 - p_0) for a softmax
    assert psf.logits.grad[0, 0].item() == pytest.approx(-p0 * (1 - p0), rel=1e-4)


@pytest.mark.parametrize("sigma", [0.01, 1e-200])
def test_a_gaussian_narrower_than_a_cell_tends_to_its_limit(sigma):
    # Centred between cells every sample underflowed: 0 / 0, then a flat 11 x 11 PSF.
    between = gaussian_psf(K, sigma, centre=(0.5, 0.5))
    expected = np.zeros((K, K))
    expected[K // 2 : K // 2 + 2, K // 2 : K // 2 + 2] = 0.25  # the four nearest cells
    np.testing.assert_allclose(between, expected, atol=1e-12)
    on_axis = gaussian_psf(K, sigma)
    assert on_axis[K // 2, K // 2] == pytest.approx(1)


@pytest.mark.parametrize("sigma", [0.8, 1.0, 1.2])
def test_a_gaussian_psf_has_the_variance_of_its_sigma(sigma):
    # A sampled Gaussian's variance is sigma^2 but for aliasing (Poisson summation:
    # terms in exp(-2 pi^2 sigma^2), 3e-6 at sigma 0.8) and the cut at 4.5 cells from a
    # centre between cells (3.7 sigma at sigma 1.2): both well under 1e-3.
    r = np.arange(K) - K // 2
    for centre in [(0.0, 0.0), (0.5, 0.5)]:
        g = gaussian_psf(K, sigma, centre)
        for axis, c in enumerate(centre):
            marginal = g.sum(axis=1 - axis)
            mean = marginal @ r
            assert mean == pytest.approx(c, abs=1e-12)
            assert marginal @ (r - mean) ** 2 == pytest.approx(sigma**2, rel=1e-3)


@pytest.mark.parametrize("centre", [(1.5, -1.0), (-2.0, 0.5)])
def test_a_gaussian_psf_keeps_its_centroid_at_any_centre(centre):
    # The window is cut symmetric about the centre (whole or half cells: the pixel
    # centres of point samples), which a wide Gaussian's tails reach.
    g = gaussian_psf(K, 3.0, centre)
    r = np.arange(K) - K // 2
    np.testing.assert_allclose((g.sum(axis=1) @ r, g.sum(axis=0) @ r), centre, atol=1e-12)


def test_baseline_psfs():
    g = gaussian_psf(K)
    assert g.sum() == pytest.approx(1) and np.argmax(g) == (K // 2) * K + K // 2
    np.testing.assert_allclose(g, g.T)
    np.testing.assert_allclose(g, g[::-1, ::-1])
    b = box_psf(K)
    assert np.count_nonzero(b) == 16 and b.sum() == pytest.approx(1)
    # default sample cell (2, 2): offsets -1 .. +2 from the axis
    assert np.argwhere(b > 0).min(axis=0).tolist() == [K // 2 - 1] * 2
    assert np.argwhere(b > 0).max(axis=0).tolist() == [K // 2 + 2] * 2
    assert np.count_nonzero(box_psf(5)) == 16  # offsets -1 .. +2 fit in K = 5
    # the Gaussian baseline shares the box's centroid: the sampled pixel's centre
    r = np.arange(K)
    for name in ("gaussian", "gaussian:1.836"):
        p = baseline_psf(name, K)
        assert p.sum() == pytest.approx(1)
        for axis in (0, 1):
            centroid = (p.sum(axis=1 - axis) * r).sum()
            assert centroid == pytest.approx((b.sum(axis=1 - axis) * r).sum())
    with pytest.raises(ValueError):
        box_psf(5, sample_cell=(0, 0))  # offsets -3 .. 0 do not


# --- network --------------------------------------------------------------------------


@pytest.mark.parametrize("arch", ["resnet", "dbpn"])
def test_network_upsamples_by_the_factor(arch):
    net = SRNet(4, features=4, stages=2, arch=arch)
    assert net(torch.rand(2, 1, 5, 7)).shape == (2, 1, 20, 28)


def test_count_parameters_counts_the_trainable_weights_and_biases():
    from psf_learn.network import count_parameters

    # resnet, F features, S stages, factor f: a 3 x 3 head 1 -> F, S blocks of two
    # 3 x 3 F -> F convolutions and a 3 x 3 tail F -> f^2, each with its biases
    f, features, stages = 4, 6, 2
    head, block, tail = 9 * features + features, 9 * features**2 + features, 9 * features * f**2
    expected = head + stages * 2 * block + tail + f**2
    net = SRNet(f, features=features, stages=stages)
    assert count_parameters(net) == expected
    net.head.requires_grad_(False)
    assert count_parameters(net) == expected - head


@pytest.mark.parametrize("spec", ["random", "dots", "dots:3"])
def test_drawn_starting_psfs_are_psfs_drawn_from_the_seed(spec):
    a, b, other = (starting_psf(spec, 11, seed=s) for s in (0, 0, 1))
    assert a.shape == (11, 11) and np.all(a > 0) and a.sum() == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, other)
    if spec.startswith("dots"):  # N bright cells over a floor of 1 % of the light
        n = int(spec.partition(":")[2] or 6)
        floor = a.min()
        assert np.count_nonzero(a > 2 * floor) == n
        assert a.sum() - floor * a.size == pytest.approx(0.99, abs=1e-9)


def test_a_named_starting_psf_is_the_baseline_of_that_name():
    np.testing.assert_array_equal(
        starting_psf("gaussian:1.5", 11), baseline_psf("gaussian:1.5", 11)
    )
    for bad in ("dots:0", "dots:x", "dots:122", "spiral"):
        with pytest.raises(ValueError):
            starting_psf(bad, 11)
