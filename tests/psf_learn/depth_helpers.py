"""Shared scan constants and scenes of the depth tests (importable: pytest pythonpath)."""

import numpy as np

from psf_learn.depth_sim import random_scene

PS = 1e-12
SHIFT = 20 * PS
T = 120  # 2.4 ns scan: room for a complete profile anywhere in [0.62, 0.82] ns


def scene(shape, amplitude, background, response, seed, margin=None):
    """Return a random scene of the scan (depth_sim.random_scene with the tests' scan)."""
    rng = np.random.default_rng(seed)
    return random_scene(shape, amplitude, background, SHIFT, T, response, rng, margin)
