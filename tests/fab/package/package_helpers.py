"""The fab package tests' design folder (importable: on pytest's pythonpath)."""

import numpy as np

from doe.fraunhofer import simulate_levels
from doe.goals import Goal
from doe.mask_rules import corner_contacts
from doe.rule_finish import repair_corners

# A 532 nm, bk7, 4-level design on a 12.7 mm aperture, 10 um features on a 10 nm grid:
# the tests' design beside sun2020 (17 x 17 tiles of 0.709 mm).
GREEN_FOUR_LEVELS = """
[optics]
wavelength_nm = 532.0
[material]
name = "bk7"
[fabrication]
levels = 4
aperture_mm = 12.7
feature_size_um = 10.0
grid_nm = 10
[psf]
kernel_size = 7
"""

# The diagonal partner and the two other pixels of the four 2 x 2 blocks a pixel is in,
# as offsets from it: (partner, other, other).
_BLOCKS = (
    ((-1, -1), (-1, 0), (0, -1)),  # the pixel at the block's lower right
    ((-1, 1), (-1, 0), (0, 1)),  # lower left
    ((1, -1), (0, -1), (1, 0)),  # upper right
    ((1, 1), (0, 1), (1, 0)),  # upper left
)


def corner_free_levels(n, n_levels, seed=0, k=11):
    """Return a random N x N level map whose masks have no corner contact (periodic).

    Pixels are drawn in raster order, each uniform at random, then each mask bit that
    would close a checkerboard with an already drawn 2 x 2 block is set to the value
    that does not. Where the tile wraps two blocks can ask for opposite bits; the few
    contacts left there are removed by :func:`doe.rule_finish.repair_corners` (what a
    retrieval does). A mask shop's DRC at the feature size then finds nothing in the
    tile when the pixel is at least the feature size.
    """
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, n_levels, (n, n))
    q = np.full((n, n), -1, dtype=np.int64)
    m = int(n_levels).bit_length() - 1
    for r in range(n):
        for c in range(n):
            v = int(draws[r, c])
            for bit in range(m):
                want = _wanted_bit(q, r, c, bit)
                if want is not None:
                    v = v & ~(1 << bit) | (want << bit)
            q[r, c] = v
    levels = q.astype(np.uint8)
    if any(corner_contacts(levels, n_levels)):
        target = simulate_levels(levels, n_levels, k)[0]
        levels = repair_corners(levels, target, Goal.of(target), n_levels, 10.0, 0.81)
    assert not any(corner_contacts(levels, n_levels))
    return levels


def _wanted_bit(q, r, c, bit):
    """The value of ``bit`` at (r, c) that closes no checkerboard with drawn pixels, or None."""
    n = q.shape[0]
    wanted = set()
    for partner, o1, o2 in _BLOCKS:
        px = [q[(r + dr) % n, (c + dc) % n] for dr, dc in (partner, o1, o2)]
        if min(px) < 0:
            continue
        d, a, b = ((int(v) >> bit) & 1 for v in px)
        if a == b != d:  # the pixel equal to its partner would touch it only at a corner
            wanted.add(a)
    return wanted.pop() if len(wanted) == 1 else None


def make_design_dir(path, n=35, n_levels=8, seed=0, target=True, k=11):
    """Write a random N x N level map without corner contacts (and its target PSF) as a
    retrieve folder; return it."""
    path.mkdir(parents=True, exist_ok=True)
    levels = corner_free_levels(n, n_levels, seed, k)
    np.save(path / "levels.npy", levels)
    if target:
        np.save(path / "target_psf.npy", simulate_levels(levels, n_levels, k)[0])
    return levels
