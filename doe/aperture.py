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
    """

    psf: object
    efficiency: float
    zero_order: float
    correlation: float
    rmse: float
    missed: tuple
    pixels: int
    patterned_fraction: float


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


def aperture_levels(levels, n_levels, plate):
    """Return (level map, patterned, span) of the plate over the pixels of its clear aperture.

    ``plate`` is a :class:`layouts.plate_plan.PlatePattern`; pixels of the clear
    aperture outside the pattern are plain glass (level L - 1). ``span`` is ((c0, c1),
    (r0, r1)): the columns and rows of the map on the array's pixel grid.
    """
    n, p = plate.tile_pixels, plate.pixel_pitch_nm
    x0, y0 = plate.array_origin_nm
    ytop = y0 + plate.tiles[1] * plate.tile_nm
    a = plate.aperture_nm / 2
    c0, c1 = int(np.ceil((-a - x0) / p - 0.5)), int(np.floor((a - x0) / p - 0.5)) + 1
    r0, r1 = int(np.ceil((ytop - a) / p - 0.5)), int(np.floor((ytop + a) / p - 0.5)) + 1
    cols, rows = np.arange(c0, c1), np.arange(r0, r1)
    out = np.asarray(levels)[np.ix_(rows % n, cols % n)].copy()
    (pc0, pc1), (pr0, pr1) = plate.pixel_span()
    patterned = np.outer((rows >= pr0) & (rows < pr1), (cols >= pc0) & (cols < pc1))
    out[~patterned] = n_levels - 1
    return out, patterned, ((c0, c1), (r0, r1))


def _sums(indices, n, freqs):
    """Return (N, F): sum over the plate's pixels ``indices`` showing tile index b (i mod N)
    of exp(-2 pi i f i), for every frequency f (cycles per pixel)."""
    phases = np.exp(-2j * np.pi * np.outer(indices, freqs))
    out = np.zeros((n, len(freqs)), np.complex128)
    np.add.at(out, indices % n, phases)
    return out


def order_window(level_map, patterned, n_levels, tile_pixels, k, span):
    """Return (window, zero order): the K x K order powers of the plate over its aperture.

    ``level_map`` holds the aperture's pixels (rows ``span[1]``, columns ``span[0]`` of
    the array's pixel grid, :func:`aperture_levels`), ``patterned`` where the periodic
    pattern lies (a rectangle), plain glass elsewhere. The amplitude of order (m, n) is
    the plate's far field at the order's direction (m / N, n / N cycles per pixel),
    over the number of pixels: the tile's transform through the sums of the pixels
    that show each tile index, plus the glass rectangle's, times the square pixel's
    sinc. For whole tiles filling the aperture it is the tile model's order exactly;
    partial tiles and glass change it. Window index i holds order i - K//2, rows
    towards -y, as the tile model.
    """
    n = int(tile_pixels)
    (c0, c1), (r0, r1) = span
    cols, rows = np.arange(c0, c1), np.arange(r0, r1)
    freqs = (np.arange(k) - k // 2) / n
    pr = np.flatnonzero(patterned.any(axis=1))
    pc = np.flatnonzero(patterned.any(axis=0))
    levels = np.asarray(level_map)
    tile = np.zeros((n, n), np.complex128)  # the tile, from the level map's own pixels
    if len(pr) and len(pc):
        sub = levels[np.ix_(pr, pc)]
        tile[np.ix_(rows[pr] % n, cols[pc] % n)] = np.exp(2j * np.pi * sub / n_levels)
    field = _sums(rows[pr], n, freqs).T @ tile @ _sums(cols[pc], n, freqs)
    glass = np.exp(2j * np.pi * (n_levels - 1) / n_levels)
    field += glass * (
        np.outer(_dirichlet(rows, freqs), _dirichlet(cols, freqs))
        - np.outer(_dirichlet(rows[pr], freqs), _dirichlet(cols[pc], freqs))
    )
    env = np.sinc(freqs) ** 2
    window = np.abs(field) ** 2 * np.outer(env, env) / float(levels.size) ** 2
    return window, float(window[k // 2, k // 2])


def _dirichlet(indices, freqs):
    """Sum over the pixels ``indices`` of exp(-2 pi i f i) for every frequency f."""
    return np.exp(-2j * np.pi * np.outer(indices, freqs)).sum(axis=0)


def as_built(levels, n_levels, plate, target):
    """Return the :class:`AsBuilt` figures of the plate ``plate`` against ``target``."""
    level_map, patterned, span = aperture_levels(levels, n_levels, plate)
    k = target.shape[0]
    window, zero = order_window(level_map, patterned, n_levels, plate.tile_pixels, k, span)
    eff = float(window.sum())
    psf = window / eff
    quality = {
        "correlation": fraunhofer.correlation(psf, target),
        "rmse": fraunhofer.rmse(psf, target),
    }
    missed = tuple(missed_goals(quality))
    return AsBuilt(
        psf, eff, zero, quality["correlation"], quality["rmse"], missed, level_map.shape[1],
        plate.patterned_fraction(),
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
        "goals_met": not figures.missed,
        "missed": list(figures.missed),
    }
