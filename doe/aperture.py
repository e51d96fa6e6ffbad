"""The plate as built: the window powers of its whole clear aperture, edge tiles and glass.

The tile model (:mod:`doe.fraunhofer`; ``fab.plate.model`` with faults) repeats the
tile without end. A plate repeats it over its clear aperture only: whole tiles, the clipped edge
tiles that complete the aperture, and plain glass (no etch, level L - 1) wherever
the pattern stops short (whole tiles only inside the design's frame). Here the
plate's level map is taken at its mask pixels over the clear aperture (a pixel
belongs to the aperture when its centre does; nothing passes outside it) and the
power of each diffraction order is its amplitude squared: the plate's far field in
the order's direction over the number of pixels (the order's coefficient over the
aperture), with the square pixel's sinc^2 envelope, as a fraction of the light
through the aperture. How the aperture (or the lens's stop) spreads each order
into a dot of finite size, whose tails reach the neighbouring sub-pixels, is the
camera's part, not the plate's. The K x K window of these powers is the plate's
own PSF. For whole tiles filling the aperture it is the tile model's window; the
clipped edge tiles (part of a period) perturb every order a little, and plain glass
adds its light to the zero order.
"""

from dataclasses import dataclass

import numpy as np

from doe import fraunhofer
from doe.goals import missed_goals
from layouts.plate_plan import array_origin_nm, plan_pattern


@dataclass(frozen=True)
class AsBuilt:
    """The plate's own far field (its figures against the target).

    Attributes
    ----------
    psf : (K, K) array or None
        The window normalised to sum 1, rows towards -y as the PSF contract.
    efficiency : float
        Fraction of the light through the clear aperture in the window.
    zero_order : float
        Fraction of the light through the clear aperture in the zero order's cell.
    correlation, rmse : float
        Against the target.
    missed : tuple of str
        The goals the plate misses (:func:`doe.goals.missed_goals`); empty when met.
    pixels : int
        Mask pixels across the clear aperture.
    patterned_fraction : float
        Fraction of the clear aperture the pattern covers (the rest is plain glass).
    cell_correlation, cell_rmse : float
        The same from each order's cell of the far field with the clear aperture as
        the stop (:func:`order_window` with points > 1): the aperture's diffraction
        spreads every dot into its neighbours' cells; informative, not the goals'.
    """

    psf: object
    efficiency: float
    zero_order: float
    correlation: float
    rmse: float
    missed: tuple
    pixels: int
    patterned_fraction: float
    cell_correlation: float
    cell_rmse: float


def design_plate(design, tile_pixels, tiles=None, mode="fill"):
    """Return the :class:`layouts.plate_plan.PlatePattern` ``doefab fab`` lays out for a
    tile of N = ``tile_pixels`` of ``design``: the whole tiles that fit the aperture (or
    ``tiles``) and, by default, the clipped edge tiles that fill it."""
    from doe.derived import derive

    der = derive(design, tile_pixels=tile_pixels)
    pitch = round(der.mask_pixel_pitch * 1e9)
    grid = round(design.fabrication.grid * 1e9)
    t = der.tiles if tiles is None else int(tiles)
    origin = array_origin_nm((t, t), der.tile_pixels, pitch, grid)
    aperture = round(design.fabrication.aperture * 1e9)
    return plan_pattern(der.tile_pixels, pitch, (t, t), origin, aperture, mode)


def aperture_pixels(plate):
    """Return (columns, rows, patterned columns, patterned rows) of the clear aperture.

    The pixels of the array's grid whose centres lie inside the clear aperture
    (``plate.aperture_nm`` wide, centred on 0), columns from the array's left edge and
    rows down from its top (:mod:`layouts.plate_plan`), and which of them the pattern
    covers (bool arrays); the rest of the aperture is plain glass.
    """
    p = plate.pixel_pitch_nm
    x0, y0 = plate.array_origin_nm
    ytop = y0 + plate.tiles[1] * plate.tile_nm
    a = plate.aperture_nm / 2
    c0, c1 = int(np.ceil((-a - x0) / p - 0.5)), int(np.floor((a - x0) / p - 0.5)) + 1
    r0, r1 = int(np.ceil((ytop - a) / p - 0.5)), int(np.floor((ytop + a) / p - 0.5)) + 1
    cols, rows = np.arange(c0, c1), np.arange(r0, r1)
    (pc0, pc1), (pr0, pr1) = plate.pixel_span()
    return cols, rows, (cols >= pc0) & (cols < pc1), (rows >= pr0) & (rows < pr1)


def aperture_levels(levels, n_levels, plate):
    """Return the plate's level map over the pixels of its clear aperture (row 0 at the
    top): the tile repeated where the pattern lies, plain glass (L - 1) elsewhere."""
    n = plate.tile_pixels
    cols, rows, pcols, prows = aperture_pixels(plate)
    out = np.asarray(levels)[np.ix_(rows % n, cols % n)].copy()
    out[~np.outer(prows, pcols)] = n_levels - 1
    return out


def _sums(indices, n, freqs):
    """Return (N, F): sum over the plate's pixels ``indices`` (a contiguous run) showing
    tile index b (i mod N) of exp(-2 pi i f i), for every frequency f (cycles per pixel).

    The pixels of index b are first_b + N j, j = 0 .. count_b - 1: a geometric series.
    """
    out = np.zeros((n, len(freqs)), np.complex128)
    if len(indices) == 0:
        return out
    start, stop = int(indices[0]), int(indices[-1]) + 1
    b = np.arange(n)
    first = start + (b - start) % n
    count = np.maximum(0, -(-(stop - first) // n))
    z = np.exp(-2j * np.pi * np.asarray(freqs) * n)
    whole = np.abs(1 - z) < 1e-12  # at an order the series sums to its count
    zc = z[None, :] ** count[:, None]
    series = np.where(whole[None, :], count[:, None], (1 - zc) / np.where(whole, 1, 1 - z))
    return np.exp(-2j * np.pi * np.outer(first, freqs)) * series


def order_window(levels, n_levels, plate, k, points=1):
    """Return the K x K window of the plate over its clear aperture (fractions of its light).

    ``points=1``: the order powers. The amplitude of order (m, n) is the plate's far
    field in the order's direction (m / N, n / N cycles per pixel) over the number of
    pixels: the tile's transform through the sums of the pixels that show each tile
    index, plus the glass rectangle's, times the square pixel's sinc. For whole tiles
    filling the aperture it is the tile model's order exactly; partial tiles and glass
    change it.

    ``points=B`` (odd): the far field's power integrated over each order's cell (one
    order spacing wide, B midpoints per axis): what a sub-pixel collects when the clear
    aperture is the stop, its dots spread by the aperture's diffraction.

    Window index i holds order i - K//2, rows towards -y, as the tile model.
    """
    n = int(plate.tile_pixels)
    cols, rows, pcols, prows = aperture_pixels(plate)
    orders = np.arange(k) - k // 2
    freqs = ((orders[:, None] - 0.5 + (np.arange(points)[None, :] + 0.5) / points) / n).ravel()
    pr, pc = rows[prows], cols[pcols]
    tile = np.exp(2j * np.pi * np.asarray(levels, float) / n_levels)
    field = _sums(pr, n, freqs).T @ tile @ _sums(pc, n, freqs)
    glass = np.exp(2j * np.pi * (n_levels - 1) / n_levels)
    field += glass * (
        np.outer(_dirichlet(rows, freqs, n), _dirichlet(cols, freqs, n))
        - np.outer(_dirichlet(pr, freqs, n), _dirichlet(pc, freqs, n))
    )
    env = np.sinc(freqs) ** 2
    size = float(len(rows) * len(cols))
    power = (
        np.abs(field) ** 2
        * np.outer(env, env)
        / (size * (size if points == 1 else (n * points) ** 2))
    )
    return power.reshape(k, points, k, points).sum(axis=(1, 3))


def _dirichlet(indices, freqs, n):
    """Sum over the pixels ``indices`` (a contiguous run) of exp(-2 pi i f i), every f."""
    return _sums(indices, n, freqs).sum(axis=0)


def as_built(levels, n_levels, plate, target):
    """Return the :class:`AsBuilt` figures of the plate ``plate`` against ``target``."""
    k = target.shape[0]
    window = order_window(levels, n_levels, plate, k)
    eff = float(window.sum())
    psf = window / eff
    quality = {
        "correlation": fraunhofer.correlation(psf, target),
        "rmse": fraunhofer.rmse(psf, target),
    }
    missed = tuple(missed_goals(quality))
    cols, rows, _, _ = aperture_pixels(plate)
    across = -(-max(len(cols), len(rows)) // plate.tile_pixels)
    cells = order_window(levels, n_levels, plate, k, points=3 * across + 1 - (3 * across) % 2)
    cell_psf = cells / cells.sum()
    return AsBuilt(
        psf, eff, float(window[k // 2, k // 2]), quality["correlation"], quality["rmse"],
        missed, len(cols), plate.patterned_fraction(),
        fraunhofer.correlation(cell_psf, target), fraunhofer.rmse(cell_psf, target),
    )  # fmt: skip


def as_built_record(figures):
    """The JSON-ready record of :class:`AsBuilt` figures (retrieval.json, fab_manifest.json)."""
    return {
        "correlation": figures.correlation,
        "rmse": figures.rmse,
        "efficiency": figures.efficiency,
        "zero_order": figures.zero_order,
        "patterned_fraction": figures.patterned_fraction,
        "pixels_across": figures.pixels,
        "cell_correlation": figures.cell_correlation,
        "cell_rmse": figures.cell_rmse,
        "goals_met": not figures.missed,
        "missed": list(figures.missed),
    }
