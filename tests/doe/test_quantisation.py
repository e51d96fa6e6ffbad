"""The discrete stage: single-pixel updates and coordinate descent on the level map."""

import numpy as np

from doe import fraunhofer, quantisation, refinement, targets


def test_single_pixel_update_formula_matches_fft():
    # changing pixel (r, c) from level a to b adds (e^{i phi_b} - e^{i phi_a}) A_r A_c^T / N^2
    rng = np.random.default_rng(9)
    n, k, n_levels = 21, 7, 8
    levels = rng.integers(0, n_levels, (n, n))
    a = refinement.window_matrix(n, k)
    idx = fraunhofer.window_indices(n, k)
    before = fraunhofer.order_amplitudes(fraunhofer.level_phase(levels, n_levels))[np.ix_(idx, idx)]
    r, c, b = 5, 17, (levels[5, 17] + 3) % n_levels
    delta = np.exp(2j * np.pi * b / n_levels) - np.exp(2j * np.pi * levels[r, c] / n_levels)
    levels[r, c] = b
    after = fraunhofer.order_amplitudes(fraunhofer.level_phase(levels, n_levels))[np.ix_(idx, idx)]
    np.testing.assert_allclose(
        after, before + delta * np.outer(a[:, r], a[:, c]) / n**2, atol=1e-14
    )


def test_coordinate_descent_never_worsens_the_objective():
    rng = np.random.default_rng(10)
    target = targets.asymmetric(7)
    levels = rng.integers(0, 8, (25, 25)).astype(np.uint8)
    for weight in (0.0, 10.0):
        before = refinement.objective(fraunhofer.level_phase(levels, 8), target, weight)[0]
        out = quantisation.coordinate_descent(levels, target, 8, weight, sweeps=2, rng=rng)
        after = refinement.objective(fraunhofer.level_phase(out, 8), target, weight)[0]
        assert out.dtype == np.uint8 and out.max() < 8
        assert after < before
