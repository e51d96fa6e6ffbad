"""Gerchberg-Saxton, MRAF and the flat-modulus start."""

import numpy as np

from doe import fraunhofer, targets
from doe.gerchberg_saxton import flat_modulus_start, gerchberg_saxton, mixed_region


def test_flat_modulus_start_of_two_equal_dots_is_the_binary_grating():
    # two equal dots at +-1 column: g = sqrt(2) cos(2 pi c / N + const), whose phase
    # is a 0 / pi grating; each first order then carries (2 / pi)^2 (the classic
    # 8 / pi^2 two-spot limit), the odd harmonics the rest
    k, n = 11, 175
    target = np.zeros((k, k))
    target[k // 2, k // 2 - 1] = target[k // 2, k // 2 + 1] = 0.5
    phase = flat_modulus_start(target, n, np.random.default_rng(3))
    step = np.angle(np.exp(1j * (phase - phase[0, 0])))
    assert np.allclose(np.minimum(np.abs(step), np.abs(np.abs(step) - np.pi)), 0, atol=1e-9)
    power = fraunhofer.window_power(phase, k)
    dots = power[k // 2, [k // 2 - 1, k // 2 + 1]]
    np.testing.assert_allclose(dots, 4 / np.pi**2, rtol=1e-3)
    third = power[k // 2, [k // 2 - 3, k // 2 + 3]]
    np.testing.assert_allclose(third, 4 / (9 * np.pi**2), rtol=1e-2)


def test_mixed_region_with_the_whole_window_is_weighted_gs():
    # mix = 1 keeps nothing outside the window: the GS projection, up to scale
    target = targets.asymmetric(7)
    start = np.random.default_rng(13).uniform(-np.pi, np.pi, (29, 29))
    gains = np.ones((7, 7))
    gs, gs_gains = gerchberg_saxton(target, 29, 6, phase=start, gains=gains)
    mr, mr_gains = mixed_region(target, start, gains, 6, mix=1.0)
    np.testing.assert_allclose(np.exp(1j * mr), np.exp(1j * gs), atol=1e-9)
    np.testing.assert_allclose(mr_gains, gs_gains, rtol=1e-9)
    np.testing.assert_array_equal(gains, 1.0)  # arguments are not mutated


def test_quantised_gs_lands_on_the_levels():
    target = targets.compact_blob(5)
    phase, _ = gerchberg_saxton(target, 17, 5, np.random.default_rng(0), n_levels=4)
    steps = phase / (np.pi / 2)
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-12)


def test_unweighted_gs_keeps_its_gains_and_reads_them_as_target_weights():
    # weighted=False is plain GS: the gains stay as given, and the order-plane
    # projection sqrt(target) * gains is that of plain GS towards target * gains^2
    target = targets.asymmetric(7)
    start = np.random.default_rng(17).uniform(-np.pi, np.pi, (29, 29))
    gains = np.random.default_rng(18).uniform(0.5, 2.0, (7, 7))
    phase, out_gains = gerchberg_saxton(target, 29, 4, phase=start, weighted=False, gains=gains)
    np.testing.assert_array_equal(out_gains, gains)
    reweighted = target * gains**2 / (target * gains**2).sum()
    plain, ones = gerchberg_saxton(reweighted, 29, 4, phase=start, weighted=False)
    np.testing.assert_array_equal(ones, 1.0)
    np.testing.assert_allclose(np.exp(1j * phase), np.exp(1j * plain), atol=1e-9)


def test_quantised_gs_projects_onto_the_nearest_level():
    # catches a projection that rounds down: one quantised iteration lies within half a
    # step of the plain iteration from the same start (the same first order-plane step)
    target = targets.compact_blob(5)
    start = np.random.default_rng(16).uniform(-np.pi, np.pi, (17, 17))
    plain, _ = gerchberg_saxton(target, 17, 1, phase=start)
    quantised, _ = gerchberg_saxton(target, 17, 1, phase=start, n_levels=4)
    err = np.angle(np.exp(1j * (quantised - plain)))
    assert np.abs(err).max() <= np.pi / 4 + 1e-9
    assert np.abs(err).max() > np.pi / 8  # the rounding is not a no-op
