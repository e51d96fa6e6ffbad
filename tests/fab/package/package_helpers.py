"""The fab package tests' design folder (importable: on pytest's pythonpath)."""

import numpy as np

from doe.fraunhofer import simulate_levels


def make_design_dir(path, n=35, n_levels=8, seed=0, target=True, k=11):
    """Write a random N x N level map (and its target PSF) as a retrieve folder; return it."""
    path.mkdir(parents=True, exist_ok=True)
    levels = np.random.default_rng(seed).integers(0, n_levels, (n, n)).astype(np.uint8)
    np.save(path / "levels.npy", levels)
    if target:
        np.save(path / "target_psf.npy", simulate_levels(levels, n_levels, k)[0])
    return levels
