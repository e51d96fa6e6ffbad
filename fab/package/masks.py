"""Binary lithography masks of an L-level phase tile (binary-weighted etch depths).

Level l keeps l glass steps above the deepest etch floor, so a pixel is etched
by ``code = L - 1 - l`` steps. Mask j (j = 0 the deepest, etching 2**(m-1-j)
steps) covers the pixels whose code has that bit set; the masks are exposed and
etched deepest first. A polygon (a True bitmap pixel) marks area to etch.
"""

from dataclasses import dataclass

import numpy as np

_SIZE_NAMES = ("deep", "mid", "shallow")


@dataclass(frozen=True, eq=False)
class Mask:
    """One binary lithography mask of a multi-level phase tile.

    Attributes
    ----------
    name : str
        Mask name, e.g. "M1_deep" (M1 is exposed first).
    gds_layer : int
        GDS layer that carries the mask's polygons.
    gds_datatype : int
        GDS datatype (0).
    etch_depth : float
        Etch depth of this step in metres.
    steps : int
        Etch depth in level steps (a power of two).
    exposure_order : int
        1 for the first exposure (deepest etch), then 2, 3, ...
    bitmap : (N, N) bool array
        True where the mask etches; row 0 is the top edge of the tile.
    """

    name: str
    gds_layer: int
    gds_datatype: int
    etch_depth: float
    steps: int
    exposure_order: int
    bitmap: np.ndarray

    @property
    def fill_fraction(self):
        """Fraction of the tile that this mask etches."""
        return float(np.mean(self.bitmap))


def mask_count(n_levels):
    """Return log2(L), refusing L that is not a power of two >= 2."""
    n_levels = int(n_levels)
    if n_levels < 2 or n_levels & (n_levels - 1):
        raise ValueError(f"n_levels must be a power of two >= 2, got {n_levels}")
    return n_levels.bit_length() - 1


def mask_name(j, m):
    """Return the name of mask j (0 = deepest) of m masks, e.g. "M1_deep"."""
    if m <= len(_SIZE_NAMES):
        label = (*_SIZE_NAMES[: m - 1], "shallow") if m > 1 else ("deep",)
        return f"M{j + 1}_{label[j]}"
    return f"M{j + 1}_{2 ** (m - 1 - j)}step"


def masks_from_levels(levels, n_levels, level_step, first_layer=1):
    """Split a level map into binary masks, deepest first.

    Parameters
    ----------
    levels : (N, N) integer array
        Level map with values 0 .. L-1 (row 0 = top edge).
    n_levels : int
        L, a power of two.
    level_step : float
        Etch depth of one level step in metres (from the Sellmeier index).
    first_layer : int
        GDS layer of the first mask; mask j sits on ``first_layer + j``.

    Returns
    -------
    list of Mask
        log2(L) masks; mask j etches 2**(m-1-j) steps and is exposed j+1-th.
    """
    m = mask_count(n_levels)
    levels = np.asarray(levels)
    if levels.ndim != 2:
        raise ValueError(f"levels must be 2-D, got shape {levels.shape}")
    if levels.size and (levels.min() < 0 or levels.max() >= n_levels):
        raise ValueError(f"levels must lie in 0..{n_levels - 1}")
    code = (n_levels - 1) - levels.astype(np.int64)
    masks = []
    for j in range(m):
        steps = 2 ** (m - 1 - j)
        bitmap = (code & steps) != 0
        bitmap.setflags(write=False)
        masks.append(
            Mask(
                name=mask_name(j, m),
                gds_layer=first_layer + j,
                gds_datatype=0,
                etch_depth=steps * level_step,
                steps=steps,
                exposure_order=j + 1,
                bitmap=bitmap,
            )
        )
    return masks


def levels_from_masks(masks, n_levels, level_step):
    """Rebuild the level map from masks via their etch depths (inverse of masks_from_levels).

    The etch depth of a pixel is the sum of the depths of the masks covering it;
    it must be a whole number of level steps.

    Returns
    -------
    (N, N) uint8 array
    """
    depth = sum(mk.bitmap.astype(np.float64) * mk.etch_depth for mk in masks)
    code = np.rint(depth / level_step).astype(np.int64)
    if not np.allclose(code * level_step, depth, rtol=0, atol=1e-3 * level_step):
        raise ValueError("mask etch depths are not whole multiples of the level step")
    levels = (n_levels - 1) - code
    if levels.min() < 0:
        raise ValueError("masks etch deeper than L-1 steps")
    return levels.astype(np.uint8)


def etch_depth_map(masks):
    """Return the total etch depth (m) of each pixel: the sum over masks covering it."""
    return sum(mk.bitmap.astype(np.float64) * mk.etch_depth for mk in masks)


def min_feature_pixels(bitmap):
    """Return the narrowest run (in pixels) of etched or unetched pixels along rows and columns.

    Runs that touch the tile edge continue into the neighbouring tile, so they
    are measured on the periodically extended tile (a 3 x 3 tiling's centre).
    A uniform bitmap has no feature and returns its size.
    """
    b = np.asarray(bitmap, dtype=bool)
    n_rows, n_cols = b.shape
    big = np.tile(b, (3, 3))
    best = max(n_rows, n_cols)
    for arr in (big, big.T):
        rows = arr.shape[0] // 3
        centre = arr[rows : 2 * rows].astype(np.int8)
        change = np.diff(centre, axis=1) != 0
        r, c = np.nonzero(change)  # a run ends after column c of row r
        if len(r) < 2:
            continue
        same_row = r[1:] == r[:-1]
        lengths = (c[1:] - c[:-1])[same_row]
        width = arr.shape[1] // 3
        # only runs that overlap the central copy of the tile
        inside = (c[1:][same_row] >= width) & (c[:-1][same_row] < 2 * width)
        if np.any(inside):
            best = min(best, int(lengths[inside].min()))
    return best
