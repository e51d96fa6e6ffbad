"""The window of a faulty plate as a sum of precomputed parts, for fits.

:func:`fab.plate.model.window_amplitudes` builds the tile at every call: right for a
table of plates, ~10 ms at N = 175. A fit varies a few faults over thousands of values,
and the window is linear in what they change: in the transmission of each code (the
pixels etched by the same masks), and, for one mask shifted, in the Fourier weights of
the two parts of a pixel its shifted edge cuts. So the windows of those parts are
computed once from the model's own masks, DFT and pixel weights, and an evaluation only
weighs them. Both are tested equal to ``window_amplitudes``.

A shift of p + f pixels along an axis (p whole, 0 <= f < 1) cuts every pixel into a
part [0, f) that the mask's pixel i - p - 1 covers and a part [f, 1) that its pixel
i - p covers, so each order is a sum of four whole-pixel shifts weighted by the
Fourier integrals over those parts (``fab.plate.cells.interval_weight``).
"""

import math

import numpy as np

from fab.plate.cells import interval_weight, pixel_shifts
from fab.plate.model import code_phases


def _bare_windows(model, fields):
    """Return the window DFT (..., K, K) of (..., N, N) fields, no pixel weights."""
    return model.dft @ fields @ model.dft.T


def _pixel_weight(model):
    """Return g(m) of a whole pixel [0, 1): the continuous plate's pixel (its envelope)."""
    return interval_weight(model.orders, 0.0, 1.0, model.bitmaps.shape[-1], None)


def code_windows(model):
    """Return the window (2**M, K, K) of the design's pixels of each code, as the
    continuous plate gives it (code c: the pixels mask i etches where bit i is set).

    The window of the plate with etch errors ``e`` is then
    ``np.tensordot(np.exp(1j * code_phases(model, e)), code_windows(model), axes=1)``.
    """
    code = sum(bm.astype(np.int64) << i for i, bm in enumerate(model.bitmaps))
    fields = np.array([code == c for c in range(2 ** len(model.bitmaps))], dtype=float)
    g = _pixel_weight(model)
    return g[:, None] * g[None, :] * _bare_windows(model, fields)


class ShiftedMaskWindows:
    """The window of the design's continuous plate with one mask shifted, for any shift
    within ``reach_px`` mask pixels each way (and any etch errors).

    Parameters
    ----------
    model : fab.plate.model.PlateModel
        The design (its ``supersample`` is not used: the plate is continuous).
    mask : int
        The mask shifted (0 = deepest).
    reach_px : float
        The largest shift along either axis, in mask pixels.
    etch_errors : sequence of float or None
        The etch errors (deepest first), fixed; None to set them with
        :meth:`set_etch_errors` (a part is then precomputed for each code of the
        other masks, 2**(M-1) times the work).
    """

    def __init__(self, model, mask, reach_px, etch_errors=None):
        self.model, self.mask, self.reach_px = model, int(mask), float(reach_px)
        self.whole = np.arange(math.floor(-reach_px), math.ceil(reach_px) + 2)
        n_masks, n = len(model.bitmaps), model.bitmaps.shape[-1]
        others = [k for k in range(n_masks) if k != mask]
        others_code = np.zeros((n, n), dtype=np.int64)
        for i, k in enumerate(others):
            others_code |= model.bitmaps[k].astype(np.int64) << i
        # codes[c, b]: the full code of the pixels of the other masks' code c, etched (b = 1)
        # or not (b = 0) by the shifted mask
        classes = np.arange(2 ** len(others))
        spread = np.zeros_like(classes)
        for i, k in enumerate(others):
            spread |= ((classes >> i) & 1) << k
        self.codes = np.stack([spread, spread | (1 << self.mask)], axis=1)
        self.free_etch = etch_errors is None
        if self.free_etch:  # the pixels of each code of the other masks
            parts = np.array([others_code == c for c in classes], dtype=float)
        else:  # the plate with the shifted mask's pixels left unetched
            lut = self._transmission(etch_errors)
            parts = lut[others_code, 0][None]
        bitmap = model.bitmaps[self.mask]
        rolled = np.array(
            [[np.roll(bitmap, (p, q), axis=(0, 1)) for q in self.whole] for p in self.whole],
            dtype=float,
        )
        # The plate is those parts, each with the shifted mask etched or not on it: the
        # window of a part alone, and of its pixels the mask etches at each whole shift.
        self.plain = _bare_windows(model, parts)
        self.etched = np.array([_bare_windows(model, rolled * part) for part in parts])
        if self.free_etch:
            self.set_etch_errors(None)
        else:  # every code's transmission changes alike where the mask etches it
            self._rest = self.plain[0]
            self._contrast = (lut[0, 1] / lut[0, 0] - 1) * self.etched[0]

    def _transmission(self, etch_errors):
        """Return the transmission (C, 2) of each code of the other masks, the shifted
        mask's pixels unetched (0) and etched (1)."""
        return np.exp(1j * code_phases(self.model, etch_errors))[self.codes]

    def set_etch_errors(self, etch_errors):
        """Take the plate's etches as off by ``etch_errors`` (fractions, deepest first;
        None for none)."""
        if not self.free_etch:
            raise ValueError("these windows were built for fixed etch errors")
        lut = self._transmission(etch_errors)
        # einsum, not a BLAS call: a fit sets these hundreds of times, and OpenBLAS
        # threads cost more than the sum on a busy machine
        self._rest = np.einsum("c,c...->...", lut[:, 0], self.plain)
        self._contrast = np.einsum("c,c...->...", lut[:, 1] - lut[:, 0], self.etched)

    def amplitudes(self, dx, dy):
        """Return the complex window orders with the mask shifted by (dx, dy).

        In the model's unit (mask pixels for a pitch of 1), x right and y up as in
        ``fab.plate.model.PlateFaults``; ``dx`` and ``dy`` of one shape S (scalars
        too), the result S + (K, K).
        """
        rows, cols = pixel_shifts(dx, dy, self.model.pixel_pitch)
        reach = self.reach_px
        if not (np.abs(rows).max(initial=0) <= reach and np.abs(cols).max(initial=0) <= reach):
            raise ValueError(f"a shift beyond the model's reach of {reach} px")
        n, orders = self.model.bitmaps.shape[-1], self.model.orders
        p, q = np.floor(rows).astype(int), np.floor(cols).astype(int)
        r0, r1 = (interval_weight(orders, a, b, n, None)[..., :, None]
                  for a, b in ((0.0, rows - p), (rows - p, 1.0)))  # fmt: skip
        c0, c1 = (interval_weight(orders, a, b, n, None)[..., None, :]
                  for a, b in ((0.0, cols - q), (cols - q, 1.0)))  # fmt: skip
        i, j = p - self.whole[0], q - self.whole[0]
        g = self._contrast
        # Part [0, f) of a pixel sees the mask pixel one further back: the shift p + 1.
        etched = (
            r0 * c0 * g[i + 1, j + 1]
            + r0 * c1 * g[i + 1, j]
            + r1 * c0 * g[i, j + 1]
            + r1 * c1 * g[i, j]
        )
        return (r0 + r1) * (c0 + c1) * self._rest + etched

    def power(self, dx, dy):
        """Return the order powers (fractions of the beam) of that plate, S + (K, K)."""
        return np.abs(self.amplitudes(dx, dy)) ** 2
