"""Sensor model: convolution orientation, SPAD sampling, photon noise, gradients."""

import numpy as np
import pytest
import torch
from scipy import ndimage
from scipy.signal import convolve2d

from doe.design import load_design
from psf_learn.psf import LearnedPSF, baseline_psf, box_psf, delta_psf, gaussian_psf
from psf_learn.sensor import (
    SensorModel,
    active_area_weights,
    convolve_psf,
    photon_noise,
    sensor_from_design,
    simulate_capture,
    spad_sample,
)

K = 11


def _t(a):
    return torch.from_numpy(np.asarray(a, dtype=np.float64))


def _design(tmp_path, sensor_toml):
    path = tmp_path / "d.toml"
    path.write_text("[sensor]\n" + sensor_toml)
    return load_design(path)


def _noise_free(weights):
    return SensorModel(tuple(map(tuple, np.asarray(weights).tolist())), photons=0.0)


def test_default_sensor_point_samples_cell_2_2():
    # a 30 um disc centred in a 150 um pixel is smaller than a 37.5 um sub-pixel; its
    # centre sits on the corner of cells 1 and 2, ties go to the lower-right cell
    sensor = sensor_from_design(load_design())
    expected = np.zeros((4, 4))
    expected[2, 2] = 1
    np.testing.assert_array_equal(np.asarray(sensor.weights), expected)
    assert sensor.sample_cell == (2, 2)
    assert sensor.photons == load_design().learning.photons_per_pixel


def test_offset_active_area_moves_the_sample_cell(tmp_path):
    # +40 um in x: centre at 115 um -> column 3; +40 um in y (up) -> centre at 35 um -> row 0
    d = _design(tmp_path, "active_offset_um = [40.0, 40.0]\n")
    w = active_area_weights(d)
    assert np.argwhere(w == 1).tolist() == [[0, 3]]


def test_full_fill_factor_is_the_block_mean(tmp_path):
    d = _design(tmp_path, 'active_area_um = 150.0\nactive_area_shape = "square"\n')
    w = active_area_weights(d)
    np.testing.assert_allclose(w, np.full((4, 4), 1 / 16), atol=1e-12)
    img = np.random.default_rng(0).uniform(size=(16, 24))
    out = spad_sample(_t(img)[None, None], w)[0, 0].numpy()
    np.testing.assert_allclose(out, img.reshape(4, 4, 6, 4).mean(axis=(1, 3)), atol=1e-12)


def test_large_circle_weights_are_symmetric_and_cover_the_centre_most(tmp_path):
    d = _design(tmp_path, "active_area_um = 100.0\n")
    w = active_area_weights(d)
    np.testing.assert_allclose(w, w.T, atol=1e-12)
    np.testing.assert_allclose(w, w[::-1, ::-1], atol=1e-12)
    assert w.sum() == pytest.approx(1)
    assert w[1, 1] > w[0, 1] > w[0, 0]


@pytest.mark.parametrize("named", [False, True])  # True: --psf delta
def test_delta_psf_is_a_point_sample(named):
    psf = baseline_psf("delta", K) if named else delta_psf(K)
    img = np.random.default_rng(1).uniform(size=(20, 28))
    frame = simulate_capture(
        _t(img)[None, None], _t(psf), _noise_free(np.eye(4)[2:3].T @ np.eye(4)[2:3])
    )
    np.testing.assert_array_equal(frame[0, 0].numpy(), img[2::4, 2::4])


def test_box_psf_with_point_sample_is_the_block_mean():
    img = np.random.default_rng(2).uniform(size=(24, 32))
    w = np.zeros((4, 4))
    w[2, 2] = 1
    frame = simulate_capture(_t(img)[None, None], _t(box_psf(K)), _noise_free(w))
    np.testing.assert_allclose(
        frame[0, 0].numpy(), img.reshape(6, 4, 8, 4).mean(axis=(1, 3)), atol=1e-12
    )


@pytest.mark.parametrize(
    "sensor_toml",
    [
        "",
        "active_area_um = 40.0\n",
        "active_area_um = 100.0\n",
        "active_offset_um = [37.5, 0.0]\n",  # samples cell (2, 3): rows and columns differ
    ],
)
def test_gaussian_baseline_shows_each_pixel_its_own_centre(tmp_path, sensor_toml):
    # The response of pixel (4, 4) to unit impulses has its centroid at the block's
    # centre, 17.5 sub-pixels; built for the argmax cell of a 40 um disc (four cells
    # of 1/4) it sat half a sub-pixel off on each axis.
    weights = active_area_weights(_design(tmp_path, sensor_toml))
    sensor = _noise_free(weights)
    psf = baseline_psf("gaussian", K, weights)
    size = 36
    impulses = torch.zeros(size * size, 1, size, size, dtype=torch.float64)
    impulses.view(size * size, -1)[torch.arange(size * size), torch.arange(size * size)] = 1
    response = simulate_capture(impulses, _t(psf), sensor)[:, 0, 4, 4].numpy()
    response = response.reshape(size, size)
    idx = np.arange(size)
    centroid = (response.sum(1) @ idx / response.sum(), response.sum(0) @ idx / response.sum())
    np.testing.assert_allclose(centroid, (17.5, 17.5), atol=1e-9)


def test_box_baseline_is_refused_for_an_active_area_wider_than_a_sub_pixel(tmp_path):
    # no PSF turns a 40 um disc's four-cell average into the block mean; it gave a tent
    weights = active_area_weights(_design(tmp_path, "active_area_um = 40.0\n"))
    with pytest.raises(ValueError, match="spans 4 sub-pixels"):
        baseline_psf("box", K, weights)


@pytest.mark.parametrize("cell", [(0, 0), (1, 3), (3, 2)])
def test_box_psf_matches_any_sample_cell(cell):
    img = np.random.default_rng(3).uniform(size=(16, 16))
    w = np.zeros((4, 4))
    w[cell] = 1
    for psf in (box_psf(K, 4, cell), baseline_psf("box", K, w)):  # --psf box: the same box
        frame = simulate_capture(_t(img)[None, None], _t(psf), _noise_free(w))
        np.testing.assert_allclose(
            frame[0, 0].numpy(), img.reshape(4, 4, 4, 4).mean(axis=(1, 3)), atol=1e-12
        )


def test_convolution_orientation_with_an_asymmetric_kernel():
    # a single PSF element at (axis + (2, -3)) moves a point 2 rows down and 3 columns left
    psf = np.zeros((K, K))
    psf[K // 2 + 2, K // 2 - 3] = 1
    img = np.zeros((21, 21))
    img[10, 10] = 1
    out = convolve_psf(_t(img)[None, None], _t(psf))[0, 0].numpy()
    assert np.argwhere(out == 1).tolist() == [[12, 7]]


def test_convolution_equals_scipy_true_convolution():
    rng = np.random.default_rng(4)
    psf = rng.uniform(size=(5, 5))
    psf /= psf.sum()
    img = rng.uniform(size=(17, 23))
    out = convolve_psf(_t(img)[None, None], _t(psf), padding="valid")[0, 0].numpy()
    np.testing.assert_allclose(out, convolve2d(img, psf, mode="valid"), atol=1e-12)


def test_convolution_conserves_energy():
    rng = np.random.default_rng(5)
    psf = rng.uniform(size=(K, K))
    psf /= psf.sum()
    img = np.zeros((40, 40))
    img[12:28, 14:26] = rng.uniform(size=(16, 12))  # light far from the borders
    out = convolve_psf(_t(img)[None, None], _t(psf))[0, 0].numpy()
    assert out.sum() == pytest.approx(img.sum(), rel=1e-12)
    assert out.min() >= 0


def test_convolution_gradcheck():
    rng = np.random.default_rng(6)
    img = _t(rng.uniform(size=(1, 1, 9, 9))).requires_grad_()
    psf = _t(rng.uniform(size=(3, 3))).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: convolve_psf(a, b), (img, psf))


def test_poisson_noise_statistics_and_determinism():
    photons = 50.0
    signal = torch.full((2000, 1, 4, 4), 0.4, dtype=torch.float64)
    noisy = photon_noise(signal, photons, seed=7)
    counts = noisy.numpy() * photons
    np.testing.assert_allclose(counts, np.round(counts), atol=1e-9)  # integer counts
    mean, var = counts.mean(), counts.var()
    n = counts.size
    assert abs(mean - 20.0) < 5 * np.sqrt(20.0 / n)
    assert abs(var - 20.0) < 5 * 20.0 * np.sqrt(2 / n)
    again = photon_noise(signal, photons, seed=7)
    assert torch.equal(noisy, again)
    assert not torch.equal(noisy, photon_noise(signal, photons, seed=8))
    assert torch.equal(photon_noise(signal, 0.0), signal)


def test_noise_of_a_sample_does_not_depend_on_the_batch_split():
    signal = torch.rand(4, 1, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    seeds = [(1, i) for i in range(4)]
    whole = photon_noise(signal, 100.0, seeds=seeds)
    halves = torch.cat(
        [
            photon_noise(signal[:2], 100.0, seeds=seeds[:2]),
            photon_noise(signal[2:], 100.0, seeds=seeds[2:]),
        ]
    )
    assert torch.equal(whole, halves)


def test_dark_counts_are_subtracted_on_average():
    signal = torch.full((4000, 1, 2, 2), 0.2, dtype=torch.float64)
    noisy = photon_noise(signal, 100.0, dark_counts=30.0, seed=3)
    # mean stays 0.2; variance is (20 + 30) / 100^2
    n = noisy.numel()
    assert abs(noisy.mean().item() - 0.2) < 5 * np.sqrt(50 / n) / 100
    assert noisy.var().item() == pytest.approx(50 / 100**2, rel=0.1)


def test_straight_through_gradient_is_identity():
    signal = torch.rand(3, 1, 4, 4, dtype=torch.float64).requires_grad_()
    weights = torch.rand(3, 1, 4, 4, dtype=torch.float64)
    (photon_noise(signal, 20.0, seed=1) * weights).sum().backward()
    assert torch.equal(signal.grad, weights)


def test_psf_gradient_flows_through_the_noise():
    # for a loss linear in the frame, the straight-through gradient equals the
    # gradient of the noise-free capture exactly, and it is not zero
    rng = np.random.default_rng(8)
    img = torch.from_numpy(rng.uniform(size=(2, 1, 26, 26)))
    weights = torch.from_numpy(rng.normal(size=(2, 1, 4, 4)))
    grads = []
    for photons in (30.0, 0.0):
        psf = LearnedPSF(gaussian_psf(K, 1.5))
        psf.logits.data = psf.logits.data.double()
        sensor = SensorModel(tuple(map(tuple, np.eye(4)[[2]].T @ np.eye(4)[[2]])), photons)
        frame = simulate_capture(img, psf(), sensor, padding="valid", seed=2)
        (frame * weights).sum().backward()
        grads.append(psf.logits.grad.clone())
    noisy, clean = grads
    assert torch.isfinite(noisy).all()
    assert noisy.abs().max() > 1e-6
    torch.testing.assert_close(noisy, clean)


@pytest.mark.parametrize("padding", ["reflect", "valid"])
@pytest.mark.parametrize("cell", [(2, 2), (0, 3)])
def test_point_sample_fast_path_equals_blur_then_sample(padding, cell):
    rng = np.random.default_rng(9)
    img = _t(rng.uniform(size=(2, 1, 26, 30) if padding == "valid" else (2, 1, 16, 20)))
    psf = _t(rng.uniform(size=(K, K)))
    psf = psf / psf.sum()
    w = np.zeros((4, 4))
    w[cell] = 1
    fast = simulate_capture(img, psf, _noise_free(w), padding=padding)
    slow = spad_sample(convolve_psf(img, psf, padding), w)
    assert fast.shape == slow.shape
    torch.testing.assert_close(fast, slow, atol=1e-12, rtol=0)


def test_photons_argument_overrides_the_design():
    # psf-learn --photons is passed as sensor_from_design(design, photons=...):
    # it must set the shot-noise level, not be replaced by the design's default
    design = load_design()
    assert design.learning.photons_per_pixel != 123.0
    sensor = sensor_from_design(design, photons=123.0, dark_counts=4.0)
    assert sensor.photons == 123.0
    assert sensor.dark_counts == 4.0


def test_reflect_padding_mirrors_the_scene_without_repeating_the_edge():
    # "reflect" mirrors the scene about its border pixel (torch reflect = scipy "mirror"):
    # with a kernel that moves light 3 columns right and 2 rows up, every output pixel
    # is the input at (r + 2, c - 3), reflected at the borders.
    k = 9
    psf = np.zeros((k, k))
    psf[k // 2 - 2, k // 2 + 3] = 1.0
    img = np.random.default_rng(0).uniform(size=(13, 17))
    out = convolve_psf(torch.from_numpy(img)[None, None], torch.from_numpy(psf))[0, 0].numpy()
    np.testing.assert_allclose(out, ndimage.convolve(img, psf, mode="mirror"), atol=1e-12)
    # explicitly, at the left border: column c - 3 < 0 mirrors to 3 - c
    np.testing.assert_allclose(out[2:11, 0], img[4:13, 3], atol=1e-12)
    np.testing.assert_allclose(out[2:11, 1], img[4:13, 2], atol=1e-12)


def test_sampling_refuses_a_padding_or_size_it_cannot_take():
    # Each once returned a frame of the wrong size or a shifted sample without a word.
    from psf_learn.sensor import point_sample_blur

    img, psf = torch.zeros(1, 1, 16, 16, dtype=torch.float64), _t(delta_psf(3))
    with pytest.raises(ValueError, match="padding must be 'reflect' or 'valid', got 'same'"):
        convolve_psf(img, psf, padding="same")
    with pytest.raises(ValueError, match=r"image size \(16, 18\) is not a multiple of 4"):
        spad_sample(torch.zeros(1, 1, 16, 18, dtype=torch.float64), np.eye(4) / 4)
    # "valid" leaves 16 - 3 + 1 = 14 sub-pixels a side: no whole 4 x 4 pixels
    with pytest.raises(ValueError, match=r"image size \(14, 14\) is not a multiple of 4"):
        point_sample_blur(img, psf, (2, 2), 4, padding="valid")
    assert point_sample_blur(img, psf, (2, 2), 4).shape == (1, 1, 4, 4)
