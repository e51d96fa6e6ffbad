"""Tight lattices (under 4.5 px): each order's power from its lattice cell, tails undone."""

import numpy as np
import pytest
from scipy.special import erf

from fab.verify.cell_photometry import measure_cells
from fab.verify.lattice import Lattice, register_lattice
from fab.verify.pitch import measure_pitch


def _dots(pitch, sigma, powers, shape=(160, 160), background=5.0, seed=0):
    """Pixel-integrated Gaussian dots of the given powers on a square lattice (closed form)."""
    h, w = shape
    rows = np.arange(h)[:, None, None, None]
    cols = np.arange(w)[None, :, None, None]
    k = powers.shape[0]
    centre = np.array([h / 2 + 0.3, w / 2 - 0.2])
    u = np.arange(k) - k // 2
    r0 = centre[0] + pitch * u[None, None, :, None]
    c0 = centre[1] + pitch * u[None, None, None, :]
    s2 = np.sqrt(2) * sigma

    def cdf(edge, c):
        return 0.5 * (1 + erf((edge - c) / s2))

    gy = cdf(rows + 0.5, r0) - cdf(rows - 0.5, r0)
    gx = cdf(cols + 0.5, c0) - cdf(cols - 0.5, c0)
    image = (powers[None, None] * gy * gx).sum(axis=(2, 3)) + background
    image += np.random.default_rng(seed).normal(0, 0.5, image.shape)
    return image, Lattice(centre - pitch * (k // 2), pitch * np.eye(2))


# every dot bright (the worst case: no faint cell to take the background from)
@pytest.mark.parametrize(("pitch", "error"), [(3.6, 0.04), (4.27, 0.005)])
def test_cell_sums_give_the_powers_and_the_pitch(pitch, error):
    powers = np.random.default_rng(1).uniform(200, 3000, (21, 21))
    image, lattice = _dots(pitch, 0.7, powers)
    # the measured start is within the lattice fit's reach, the fit within 0.5 %
    start = measure_pitch(image)
    assert start == pytest.approx(pitch, rel=0.1)
    assert register_lattice(image, start)[0].pitch_px == pytest.approx(pitch, rel=5e-3)
    grid = measure_cells(image, lattice)
    # the grid's (u, v) = (0, 0) is the lattice's origin, the first dot
    iu, iv = np.searchsorted(grid.u, 0), np.searchsorted(grid.v, 0)
    measured = grid.power[iu : iu + 21, iv : iv + 21]
    inner = (slice(1, -1), slice(1, -1))  # the edge dots lose their outer neighbours' tails
    assert grid.valid[iu : iu + 21, iv : iv + 21][inner].all()
    # sum over the cell, background taken out, each dot's tails in its neighbours' cells
    # undone: within 0.5 % of the peak at 4.27 px, 4 % at 3.6 px
    assert np.abs(measured[inner] - powers[inner]).max() < error * powers.max()
