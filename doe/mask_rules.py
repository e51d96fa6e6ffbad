"""Corner contacts: etched pixels of one mask that touch only at a corner.

A level map of L levels is cut into log2(L) binary masks
(:func:`fab.package.masks.masks_from_levels`: code = L - 1 - l, mask j covers
the pixels whose code has bit 2**(m-1-j)). Two etched pixels of one mask that
meet only at a corner -- a 2 x 2 block whose mask bits form a checkerboard,
``1 0 / 0 1`` or ``0 1 / 1 0`` -- are a width or space of 0 nm to a Euclidean
design-rule check. The tile repeats on the plate, so blocks that wrap around
its edges count too (``periodic``).

Since L - 1 - l = (L - 1) XOR l for L a power of two, two pixels' codes differ
in exactly the bits in which their levels differ: the checks here work on the
levels themselves. A block p a / b d (p, d on one diagonal) is a checkerboard in
every bit of ``~(p ^ d) & ~(a ^ b) & (p ^ a)``.
"""

import numpy as np

from doe.infra.files import LEVEL_COUNT_RULE, is_level_count


def _bits(n_levels):
    """Return L - 1: the mask bits of a level, all set (refuses a level count L that is not one)."""
    if not is_level_count(n_levels):
        raise ValueError(f"n_levels must be {LEVEL_COUNT_RULE}, got {n_levels}")
    return int(n_levels) - 1


def checker_bits(p, a, b, d, n_levels):
    """Return the bits (as levels, any int shape) in which block ``p a / b d`` is a checkerboard.

    Nonzero means a corner contact in the mask of each set bit (bit 2**(m-1-j)
    is mask j, j = 0 the deepest).
    """
    p, a, b, d = (np.asarray(v, dtype=np.int64) for v in (p, a, b, d))
    return ~(p ^ d) & ~(a ^ b) & (p ^ a) & _bits(n_levels)


def corner_blocks(levels, n_levels, periodic=True):
    """Return a (m, R, C) bool array: mask j has a corner contact in the block at (r, c).

    The block at (r, c) holds pixels (r, c), (r, c+1), (r+1, c), (r+1, c+1),
    wrapped around the tile when ``periodic`` (R, C = N) or inside it only
    (R, C = N - 1).
    """
    q = np.asarray(levels, dtype=np.int64)
    if q.ndim != 2:
        raise ValueError(f"levels must be 2-D, got shape {q.shape}")
    m = _bits(n_levels).bit_length()
    if periodic:
        right, down = np.roll(q, -1, axis=1), np.roll(q, -1, axis=0)
        diag = np.roll(down, -1, axis=1)
        bits = checker_bits(q, right, down, diag, n_levels)
    else:
        bits = checker_bits(q[:-1, :-1], q[:-1, 1:], q[1:, :-1], q[1:, 1:], n_levels)
    return np.stack([(bits & (1 << (m - 1 - j))) != 0 for j in range(m)])


def corner_contacts(levels, n_levels, periodic=True):
    """Return the number of corner contacts per mask, deepest (M1) first, as a tuple of ints.

    Parameters
    ----------
    levels : (N, N) integer array
        Level map, values 0 .. L-1.
    n_levels : int
        L, a power of two.
    periodic : bool
        Count the blocks that wrap around the tile's edges (the tile repeats on
        the plate).
    """
    return tuple(int(v) for v in corner_blocks(levels, n_levels, periodic).sum(axis=(1, 2)))


# The four blocks that hold a pixel: (row step, column step) to its diagonal partner.
_BLOCKS = ((-1, -1), (-1, 1), (1, -1), (1, 1))


def contacts_at(q, r, c, values, n_levels):
    """Return the corner-contact bits that pixel (r, c) at each of ``values`` would make.

    ``q`` is the (N, N) int64 level map (periodic); ``r``, ``c`` are index arrays of
    one shape S and ``values`` has shape S or S + (V,). The result has the shape
    of ``values`` + (4,): one entry per block holding the pixel, the bits of the
    masks with a checkerboard there (0: none).
    """
    n = q.shape[0]
    values = np.asarray(values, dtype=np.int64)
    extra = values.ndim - np.ndim(r)
    out = []
    for dr, dc in _BLOCKS:
        rr, cc = (r + dr) % n, (c + dc) % n
        a, b, d = q[r, cc], q[rr, c], q[rr, cc]
        a, b, d = (
            np.expand_dims(v, tuple(range(np.ndim(r), np.ndim(r) + extra))) for v in (a, b, d)
        )
        out.append(checker_bits(values, a, b, d, n_levels))
    return np.stack(out, axis=-1)


def contact_count_at(q, r, c, values, n_levels):
    """Return how many (block, mask) corner contacts pixel (r, c) at ``values`` would be part of."""
    bits = contacts_at(q, r, c, values, n_levels)
    return popcount(bits).sum(axis=-1)


def popcount(bits):
    """Return the number of set bits of each element of an int64 array."""
    count = np.zeros(bits.shape, dtype=np.int64)
    bits = bits.copy()
    while np.any(bits):
        count += bits & 1
        bits >>= 1
    return count


def pixel_is_clean(q, r, c, value, n_levels):
    """Whether pixel (r, c) of the periodic level map ``q`` at ``value`` makes no corner contact.

    The scalar form of :func:`contacts_at` (plain ints: the greedy inner loop).
    """
    n, bits, value = q.shape[0], int(n_levels) - 1, int(value)
    for dr, dc in _BLOCKS:
        rr, cc = (r + dr) % n, (c + dc) % n
        a, b, d = int(q[r, cc]), int(q[rr, c]), int(q[rr, cc])
        if ~(value ^ d) & ~(a ^ b) & (value ^ a) & bits:
            return False
    return True
