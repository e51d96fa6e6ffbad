"""The rule-aware finish of the retrieval: a level map without corner contacts.

:func:`repair_corners` removes every corner contact (:mod:`doe.mask_rules`)
of a level map by single-pixel level changes, each the one that costs the
objective least among those that leave the changed pixel free of contacts (or,
where none does, that leave it in the fewest); the coordinate descent of
:mod:`doe.quantisation` then climbs back with moves that make no new contact.
"""

import numpy as np

from doe import fraunhofer
from doe.fraunhofer import level_step
from doe.goals import goal_values
from doe.mask_rules import checker_bits, contact_count_at, corner_blocks, popcount
from doe.refinement import window_fft, window_matrix

MAX_PASSES = 50
"""Passes over the remaining contacts before :func:`repair_corners` gives up (a guard)."""


def repair_corners(levels, target, goal, n_levels, weight, cap, mode="exact"):
    """Return ``levels`` with no corner contact in any mask (periodic), changed least.

    Each pass visits the blocks with a contact in raster order; for a block that
    still has one, every other level of each of its four pixels is a candidate.
    A candidate must lower the count of contacts the pixel is part of (its four
    blocks, each mask counted); among those that leave the pixel with none the
    one of least :func:`doe.goals.goal_values` (``weight``, ``cap``, ``mode``) is
    taken, else the one leaving the fewest. Every change lowers the total, so the
    passes end; RuntimeError if contacts remain after :data:`MAX_PASSES`.

    Parameters
    ----------
    levels : (N, N) integer array
        Level map, values 0 .. L-1.
    target : (K, K) array
        Target PSF, sum 1.
    goal : doe.goals.Goal
        Its constants.
    n_levels : int
        Number of levels L.
    weight, cap : float
        Efficiency weight and fidelity cap of the objective the changes are scored on.
    mode : {"exact", "smooth"}
        Peak normalisation of the rmse term (see :func:`doe.quantisation.coordinate_descent`).

    Returns
    -------
    (N, N) uint8
    """
    q = np.asarray(levels).astype(np.int64)
    n, k = q.shape[0], target.shape[0]
    a = window_matrix(n, k)
    phasors = np.exp(1j * level_step(n_levels) * np.arange(n_levels))
    w = window_fft(phasors[q], fraunhofer.window_indices(n, k))
    others = np.arange(1, n_levels)
    for _ in range(MAX_PASSES):
        bad = np.argwhere(corner_blocks(q, n_levels).any(axis=0))
        if bad.size == 0:
            return q.astype(np.uint8)
        for r0, c0 in bad:
            r = np.array([r0, r0, r0 + 1, r0 + 1]) % n
            c = np.array([c0, c0 + 1, c0, c0 + 1]) % n
            before = contact_count_at(q, r, c, q[r, c], n_levels)  # (4,)
            if not before.any():
                continue  # an earlier change in this pass removed it
            cand = (q[r, c][:, None] + others[None, :]) % n_levels  # (4, L-1)
            after = contact_count_at(q, r, c, cand, n_levels)
            delta = (phasors[cand] - phasors[q[r, c]][:, None]) / (n * n)
            basis = a[:, r].T[:, :, None] * a[:, c].T[:, None, :]  # (4, K, K)
            trial = w + delta[:, :, None, None] * basis[:, None]
            vals = goal_values(trial.real**2 + trial.imag**2, goal, weight, cap, mode)
            # fewest contacts left at the pixel first, then the least objective
            score = np.where(after < before[:, None], after, np.iinfo(np.int64).max)
            if score.min() == np.iinfo(np.int64).max:
                w = _block_move(q, w, r, c, phasors, basis, goal, weight, cap, mode, n_levels)
                continue
            best = np.flatnonzero(score.ravel() == score.min())
            i = best[np.argmin(vals.ravel()[best])]  # the first of equals
            p, s = divmod(int(i), n_levels - 1)
            w = w + delta[p, s] * basis[p]
            q[r[p], c[p]] = cand[p, s]
    raise RuntimeError(f"corner contacts remain after {MAX_PASSES} repair passes")


# Every non-empty subset of a block's four pixels, as a (15, 4) bool array.
_SUBSETS = np.array([[(s >> i) & 1 for i in range(4)] for s in range(1, 16)], dtype=bool)


def _block_move(q, w, r, c, phasors, basis, goal, weight, cap, mode, n_levels):
    """Change several pixels of the block at once where no single change lowers the count.

    Candidates set a subset of the block's pixels (r, c) to one level found in
    the 4 x 4 neighbourhood; they are scored on the contacts of the nine blocks
    the block's pixels belong to. The move that leaves the fewest is made (ties:
    least objective); where none leaves fewer than now, the one that frees this
    block and leaves the fewest elsewhere. ``q`` changes in place. Returns the
    updated window.
    """
    n = q.shape[0]
    rows = (r[0] + np.arange(-1, 3)) % n
    cols = (c[0] + np.arange(-1, 3)) % n
    patch = q[np.ix_(rows, cols)]
    values = np.unique(patch)
    cands = np.repeat(patch[None], len(_SUBSETS) * len(values), axis=0)  # (C, 4, 4)
    subset = np.repeat(_SUBSETS, len(values), axis=0)  # (C, 4)
    value = np.tile(values, len(_SUBSETS))  # (C,)
    inner = cands[:, 1:3, 1:3].reshape(-1, 4)
    inner[:] = np.where(subset, value[:, None], inner)
    cands[:, 1:3, 1:3] = inner.reshape(-1, 2, 2)
    count = _patch_contacts(cands, n_levels)
    if count.min() >= _patch_contacts(patch[None], n_levels)[0]:
        # a local minimum: move the contact out of this block (to be met from
        # its new place), the fewest made first
        fixed = _patch_contacts(cands[:, 1:3, 1:3], n_levels) == 0
        count = np.where(fixed, count, np.iinfo(np.int64).max)
    old = q[r, c]
    delta = (phasors[inner] - phasors[old][None]) / (n * n)  # (C, 4)
    trial = w + np.einsum("cp,pij->cij", delta, basis)
    vals = goal_values(trial.real**2 + trial.imag**2, goal, weight, cap, mode)
    best = np.flatnonzero(count == count.min())
    i = best[np.argmin(vals[best])]
    q[r, c] = inner[i]
    return trial[i]


def _patch_contacts(patches, n_levels):
    """Return the (block, mask) corner contacts inside each (P, P) patch: its (P-1)^2 blocks."""
    bits = checker_bits(
        patches[:, :-1, :-1], patches[:, :-1, 1:], patches[:, 1:, :-1], patches[:, 1:, 1:], n_levels
    )
    return popcount(bits).sum(axis=(1, 2))
