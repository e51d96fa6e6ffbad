"""The fabricated plate: its faults and the one model of its far field.

A plate repeats a tile of N x N mask pixels, made by binary masks (deepest first),
each etching its regions to its depth. :class:`PlateFaults` says how one plate was
made off its design; :class:`PlateModel` holds the design's masks and optics. The
tile is modelled as what it physically is: a piecewise-constant phase in the plane,
each mask's etched region shifted by its overlay, its edges moved by the CD bias and
its depth scaled by its etch error (``fab.plate.cells`` cuts the pixels at those
edges). Its far field:

* :func:`window_amplitudes`: the K x K window orders, exact sub-cell Fourier sums
  (the tolerance analysis; verify's fits precompute its parts, ``fab.plate.basis``);
* :func:`tile_phase` / :func:`plate_phase`: the same tile sampled S x S per mask
  pixel, whose FFT (:func:`plate_far_field`) gives every order at once (the capture
  simulator, verify's fitted plates across the frame); :func:`tile_height`, its glass
  heights, for the camera model at any wavelength (``doe.camera``).

Axes, stated once for every module: x to the right and y up, as viewed onto the
patterned surface (CONVENTIONS.md): row 0 of a level map or bitmap is the top edge,
column 0 the left edge. An overlay (dx, dy) moves a mask's etched pattern dx to the
right (towards higher columns) and dy up (towards row 0); masks are periodic, so the
shift wraps around the tile.

Order (m, n) of the tile is exactly

    F[m, n] = sum_jk g_j(m) g_k(n) DFT_N(exp(i phase_jk))[m, n] / N**2

where phase_jk is the (N, N) phase of sub-cell (j, k) of every pixel and g_j(m) the
Fourier weight of sub-cell interval j of a pixel. Two samplings:

* ``supersample=None``: continuous plate, g_j(m) = integral over the interval of
  exp(-2 pi i m t / N) dt (t in pixels). No rounding of any error value; this is the
  limit S -> infinity of a supersampled grid and carries the pixel's sinc envelope
  (sinc^2(m/N), 0.27 % at the edge of an 11-order window for N = 175).
* ``supersample=S``: the (N S)^2 grid of S x S sub-samples per pixel, shifts and biases
  rounded to whole sub-samples, g_j(m) = sum over the sub-samples s of the interval of
  exp(-2 pi i m s / (N S)) / S. Identical to the FFT of the upsampled tile; S = 1 with
  no error is exactly ``doe.fraunhofer.simulate_levels``.

Only the K x K window is evaluated (a K x N DFT matrix built once per tile, FFTs along
rows), so a nominal plate costs ~1 ms and the tolerance analysis of an N = 175 tile
about 2 s on two shared cores (bench/tolerance.py).

Error models:

* etch: mask depth -> depth * (1 + eps); eps > 0 over-etches.
* overlay: the etched region of a mask moves by (dx, dy) metres (axes above).
* CD bias: every edge of every mask's etched region moves outwards by b (b > 0:
  etched area grows, a feature of width w becomes w + 2 b). The etched region is
  dilated (eroded for b < 0) with a square structuring element, i.e. corners stay
  square; rounding them would change each corner's area by (1 - pi/4) b^2, below
  0.1 % of a 5 um pixel for b = 0.25 um. Requires |b| < pitch / 2.
* conjugate: etch and glass swapped (level l made as L - 1 - l): every mask's bitmap
  inverted.
* other levels: the masks of another level map made instead.

The phase of a point with total etch depth d is 2 pi (n - 1) (H - d) / lambda,
H = (L - 1) * level_step, which is the level model 2 pi l / L of CONVENTIONS.md when
level_step = lambda / ((n - 1) L) and nothing is in error.
"""

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import scipy.fft

from doe.fraunhofer import order_amplitudes, pixel_envelope
from fab.package.masks import masks_from_levels
from fab.plate.cells import (
    axis_cells,
    below_half_pixel,
    bias_pixels,
    interval_weight,
    pixel_shifts,
    reduce_rolls,
)


@dataclass(frozen=True)
class PlateFaults:
    """How one plate was made off its design; per-mask tuples follow the masks, deepest first.

    Axes: x to the right and y up, as viewed onto the patterned surface (row 0 of
    the tile is its top edge, column 0 its left edge: CONVENTIONS.md).

    Attributes
    ----------
    etch_errors : tuple of float
        Fractional depth error of each mask's etch (+0.15 = 15 % too deep); () for
        none, otherwise one per mask.
    overlay : tuple of (float, float)
        Overlay (dx, dy) of each mask in metres: +dx moves its etched pattern right,
        +dy up (towards row 0); () for none, otherwise one per mask.
    cd_bias : float
        Edge displacement of every mask's etched region in metres (> 0 grows it).
    conjugate : bool
        Etch and glass swapped (level l made as L-1-l): the PSF is point-reflected.
    other_levels : (N, N) array or None
        Make this level map instead (a plate of another design).
    mirrored : bool
        The masks written mirrored left to right (a chrome-down exposure of data that
        was not mirrored for it): every bitmap's columns reversed.
    """

    etch_errors: tuple[float, ...] = ()
    overlay: tuple[tuple[float, float], ...] = ()
    cd_bias: float = 0.0
    conjugate: bool = False
    other_levels: np.ndarray | None = None
    mirrored: bool = False


@dataclass(frozen=True, eq=False)
class PlateModel:
    """A tile's masks and optics, ready to evaluate its window for any faults.

    Build with :func:`plate_model` (masks and optics in metres) or
    :func:`level_plate_model` (a level map's masks, phase 2 pi l / L). ``bitmaps`` is
    (M, N, N) bool, ``depths`` (M,) in the unit of ``level_step``, ``dft`` the (K, N)
    matrix exp(-2 pi i m r / N) / N for orders m = -K//2 .. K//2.
    """

    bitmaps: np.ndarray
    depths: np.ndarray
    pixel_pitch: float
    phase_per_depth: float
    top_height: float
    k: int
    supersample: int | None
    n_levels: int
    level_step: float
    dft: np.ndarray = field(repr=False)
    orders: np.ndarray = field(repr=False)


def plate_model(
    masks, pixel_pitch, level_step, n_levels, wavelength, refractive_index, k, supersample=None
):
    """Return the :class:`PlateModel` of a tile's masks.

    Parameters
    ----------
    masks : sequence of fab.package.masks.Mask
        Anything with ``bitmap`` ((N, N) bool, True = etched) and ``etch_depth`` (m).
    pixel_pitch : float
        Mask pixel pitch (m).
    level_step, wavelength : float
        Step height and design wavelength (m).
    n_levels : int
        L; the unetched top sits (L - 1) steps above the deepest floor.
    refractive_index : float
        Substrate index at the wavelength.
    k : int
        Window size K (odd).
    supersample : int or None
        Sub-samples per pixel, or None for the continuous plate (module docstring).
    """
    return _model(
        masks,
        pixel_pitch,
        level_step,
        n_levels,
        2 * np.pi * (refractive_index - 1) / wavelength,
        k,
        supersample,
    )


def level_plate_model(levels, n_levels, k=1, mask_pixel_pitch=1.0, supersample=None):
    """Return the :class:`PlateModel` of a level map's masks (deepest first).

    Depths are in level steps and a step delays 2 pi / L, the level model of
    CONVENTIONS.md; ``mask_pixel_pitch`` is the unit of the overlay (1: mask pixels).
    """
    masks = masks_from_levels(levels, n_levels, level_step=1.0)
    return _model(masks, mask_pixel_pitch, 1.0, n_levels, 2 * np.pi / n_levels, k, supersample)


def _model(masks, pixel_pitch, level_step, n_levels, phase_per_depth, k, supersample):
    bitmaps = np.stack([np.asarray(mk.bitmap, dtype=bool) for mk in masks])
    n = bitmaps.shape[-1]
    if bitmaps.shape[1:] != (n, n):
        raise ValueError(f"mask bitmaps must be square (N, N), got {bitmaps.shape[1:]}")
    if k % 2 != 1 or k > n:
        raise ValueError(f"window K must be odd and <= N = {n}, got {k}")
    if supersample is not None and (int(supersample) != supersample or supersample < 1):
        raise ValueError(f"supersample must be a positive integer or None, got {supersample}")
    orders = np.arange(k) - k // 2
    dft = np.exp(-2j * np.pi * np.outer(orders, np.arange(n)) / n) / n
    bitmaps.setflags(write=False)
    return PlateModel(
        bitmaps=bitmaps,
        depths=np.array([float(mk.etch_depth) for mk in masks]),
        pixel_pitch=float(pixel_pitch),
        phase_per_depth=phase_per_depth,
        top_height=(n_levels - 1) * level_step,
        k=int(k),
        supersample=None if supersample is None else int(supersample),
        n_levels=int(n_levels),
        level_step=float(level_step),
        dft=dft,
        orders=orders,
    )


def code_phases(model, etch_errors=None):
    """Return the phase (rad) of a pixel etched by each combination of masks.

    Code c etches with mask i where bit i of c is set. ``etch_errors`` (M,) or a stack
    (..., M) of them (deepest first; None or () for none); the result has shape
    ``etch_errors.shape[:-1] + (2**M,)``.
    """
    n_masks = len(model.depths)
    none = etch_errors is None or np.size(etch_errors) == 0
    etch = np.zeros(n_masks) if none else np.asarray(etch_errors, dtype=float)
    codes = np.arange(2**n_masks)
    bits = (codes[:, None] >> np.arange(n_masks)) & 1
    depths = model.depths * (1 + etch)
    total = bits @ depths if depths.ndim == 1 else depths @ bits.T
    return model.phase_per_depth * (model.top_height - total)


def cd_bias_in_reach(model, cd_bias):
    """Whether the model can make a CD bias (m): below half a pixel, as it samples it.

    An edge moved by half a pixel or more closes the one-pixel gaps: another plate.
    """
    return below_half_pixel(bias_pixels(cd_bias, model.pixel_pitch, model.supersample))


class _Tile(NamedTuple):
    """A faulty tile: its masks' bitmaps, the sub-cells of a pixel along rows and columns
    (``fab.plate.cells.axis_cells``), the bias in pixels and the phase of each code."""

    bitmaps: np.ndarray
    rows: list
    cols: list
    bias: float
    code_phase: np.ndarray


def _faulty_tile(model, faults):
    """Return the :class:`_Tile` the model's masks make with ``faults``."""
    bitmaps = _made_bitmaps(model, faults)
    n_masks = bitmaps.shape[0]
    etch = np.asarray(faults.etch_errors or (0.0,) * n_masks, dtype=float)
    if faults.etch_errors and len(faults.etch_errors) != n_masks:  # no broadcast of one value
        raise ValueError(
            f"etch errors must be one per mask ({n_masks}), got {len(faults.etch_errors)}"
        )
    if faults.overlay and len(faults.overlay) != n_masks:
        raise ValueError(
            f"overlay must be one (dx, dy) per mask ({n_masks}), got {len(faults.overlay)}"
        )
    shift = np.asarray(faults.overlay or ((0.0, 0.0),) * n_masks, dtype=float)
    bias = bias_pixels(faults.cd_bias, model.pixel_pitch, model.supersample)
    row_shift, col_shift = pixel_shifts(shift[:, 0], shift[:, 1], model.pixel_pitch)
    if model.supersample is not None:
        s = model.supersample
        col_shift, row_shift = np.round(col_shift * s) / s, np.round(row_shift * s) / s
    if not below_half_pixel(bias):
        raise ValueError(f"CD bias {faults.cd_bias:.3g} m must be below half the pixel pitch")
    rows = axis_cells(row_shift, bias, model.supersample)
    cols = axis_cells(col_shift, bias, model.supersample)
    return _Tile(bitmaps, rows, cols, bias, code_phases(model, etch))


def _made_bitmaps(model, faults):
    """Return the bitmaps of the masks made: the design's, another level map's, or
    mirrored (columns reversed), either conjugated (every bitmap inverted: the binary split
    of L - 1 - l)."""
    bitmaps = model.bitmaps
    if faults.other_levels is not None:
        other = masks_from_levels(faults.other_levels, model.n_levels, model.level_step)
        bitmaps = np.stack([mk.bitmap for mk in other])
    if faults.mirrored:
        bitmaps = np.ascontiguousarray(bitmaps[..., ::-1])
    return ~bitmaps if faults.conjugate else bitmaps


def _row_codes(tile, row_offsets):
    """Yield, for each column sub-cell, the (N, N) uint8 code of the masks that etch it
    in the row sub-cell of ``row_offsets`` (bit i: mask i)."""
    n = tile.bitmaps.shape[-1]
    row_reduced = [
        reduce_rolls(bm, row_offsets[i], 0, tile.bias) for i, bm in enumerate(tile.bitmaps)
    ]
    for _, _, col_offsets in tile.cols:
        code = np.zeros((n, n), dtype=np.uint8)
        for i, bm in enumerate(row_reduced):
            code |= reduce_rolls(bm, col_offsets[i], 1, tile.bias).view(np.uint8) << i
        yield code


def window_amplitudes(model, faults=PlateFaults()):
    """Return the complex amplitudes (K, K) of the window orders of the fabricated plate.

    Element [K//2, K//2] is the zero order; |amplitude|^2 is the fraction of the
    incident power in that order. This is the far field of a faulty plate: every
    other evaluation is tested equal to it.
    """
    tile = _faulty_tile(model, faults)
    n = model.bitmaps.shape[-1]
    if tile.bitmaps.shape[-1] != n:
        raise ValueError(f"the plate made must be the model's N = {n} pixels square")
    lut = np.exp(1j * tile.code_phase)  # a pixel's transmission, looked up by its code
    # Rows: (K, N) DFT matrices; columns: an FFT along each row, then the K orders, so
    # no large BLAS call (OpenBLAS threads thrash on a busy 2-core machine).
    left = [
        interval_weight(model.orders, a, b, n, model.supersample)[:, None] * model.dft
        for a, b, _ in tile.rows
    ]
    right = [interval_weight(model.orders, a, b, n, model.supersample) / n for a, b, _ in tile.cols]
    col_idx = model.orders % n
    out = np.zeros((model.k, model.k), dtype=complex)
    for (_, _, r_off), wr in zip(tile.rows, left, strict=True):
        acc = np.zeros((n, model.k), dtype=complex)
        for code, wc in zip(_row_codes(tile, r_off), right, strict=True):
            acc += scipy.fft.fft(lut[code], axis=1)[:, col_idx] * wc
        out += wr @ acc
    return out


def tile_phase(model, faults=PlateFaults()):
    """Return the phase (rad) of the fabricated tile sampled S x S per mask pixel.

    ``model.supersample`` is S; overlay and CD bias are rounded to whole sub-samples
    (module docstring). Shape (N S, N S), row 0 the top edge.
    """
    if model.supersample is None:
        raise ValueError("a sampled tile needs a model with a supersample")
    tile = _faulty_tile(model, faults)
    s, n = model.supersample, tile.bitmaps.shape[-1]
    out = np.empty((n, s, n, s))
    for a, b, r_off in tile.rows:
        rows = slice(round(a * s), round(b * s))
        for (c, d, _), code in zip(tile.cols, _row_codes(tile, r_off), strict=True):
            out[:, rows, :, round(c * s) : round(d * s)] = tile.code_phase[code][:, None, :, None]
    return out.reshape(n * s, n * s)


def tile_height(model, faults=PlateFaults()):
    """Return the glass height of the fabricated tile above its deepest floor, S x S per pixel.

    In the unit of the model's depths (level steps for :func:`level_plate_model`:
    multiply by the step in metres for ``doe.camera.effective_psf``'s ``heights``);
    the phase at any wavelength follows from it, which the camera model needs.
    """
    return tile_phase(model, faults) / model.phase_per_depth


def plate_phase(levels, n_levels, faults=PlateFaults(), mask_pixel_pitch=None, supersample=1):
    """Return the supersampled phase (rad) of the fabricated tile of a level map.

    Parameters
    ----------
    levels : (N, N) uint8 array
        The design.
    n_levels : int
        L.
    faults : PlateFaults
    mask_pixel_pitch : float or None
        Mask pixel pitch in metres (needed for an overlay shift).
    supersample : int
        Sub-pixels per mask pixel along each axis; an overlay shift is rounded
        to whole sub-pixels.

    Returns
    -------
    (N*S, N*S) float array
    """
    if np.any(faults.overlay) and mask_pixel_pitch is None:
        raise ValueError("an overlay shift needs mask_pixel_pitch")
    pitch = 1.0 if mask_pixel_pitch is None else mask_pixel_pitch
    model = level_plate_model(levels, n_levels, mask_pixel_pitch=pitch, supersample=supersample)
    return tile_phase(model, faults)


def plate_far_field(phase):
    """Return a function (m, n) -> order power of a tiled plate with this (sub)pixel phase."""
    if phase.ndim != 2 or phase.shape[0] != phase.shape[1]:
        raise ValueError(f"the tile must be square (CONVENTIONS), got shape {phase.shape}")
    amp = order_amplitudes(phase)
    cells = phase.shape[0]
    power = np.abs(amp) ** 2

    def orders(m, n):
        m, n = np.asarray(m), np.asarray(n)
        return power[m % cells, n % cells] * pixel_envelope(m, cells) * pixel_envelope(n, cells)

    return orders
