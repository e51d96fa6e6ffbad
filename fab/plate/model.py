"""The fabricated plate's phase and far field, its faults included.

One model serves the capture simulator (``fab.verify.simulate``) and verify's fits of a
faulty plate (``fab.verify.analysis``): a tile made from its binary masks, each etched to its
depth (or off it) and printed in its place (or off it), and the powers of the orders
of the tiled plate.
"""

from dataclasses import dataclass

import numpy as np

from doe.fraunhofer import order_amplitudes, pixel_envelope
from fab.package.masks import masks_from_levels


@dataclass(frozen=True)
class PlateFaults:
    """Fabrication faults of a simulated plate.

    Attributes
    ----------
    etch_errors : tuple of float
        Fractional depth error of each mask's etch, deepest first (+0.15 = 15 % too
        deep); masks beyond the tuple are etched right.
    conjugate : bool
        Etch and glass swapped (level l made as L-1-l): the PSF is point-reflected.
    overlay_mask : int
        Index (0 = deepest) of the mask that is shifted.
    overlay_shift : (float, float)
        Shift (dy, dx) in metres of that mask (y up, x right, as in the layout).
    other_levels : (N, N) array or None
        Make this level map instead (a plate of another design).
    """

    etch_errors: tuple[float, ...] = ()
    conjugate: bool = False
    overlay_mask: int = 0
    overlay_shift: tuple[float, float] = (0.0, 0.0)
    other_levels: np.ndarray | None = None


def plate_phase(levels, n_levels, faults=PlateFaults(), mask_pixel_pitch=None, supersample=1):
    """Return the supersampled phase (rad) of the fabricated tile.

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
    levels = np.asarray(faults.other_levels if faults.other_levels is not None else levels)
    if faults.conjugate:
        levels = (n_levels - 1) - levels.astype(np.int64)
    masks = masks_from_levels(levels, n_levels, level_step=1.0)
    s = int(supersample)
    phase_step = 2 * np.pi / n_levels
    full = (n_levels - 1) * phase_step
    phase = np.full((levels.shape[0] * s, levels.shape[1] * s), full)
    for j, mask in enumerate(masks):
        bitmap = np.kron(mask.bitmap, np.ones((s, s), bool)) if s > 1 else mask.bitmap
        if j == faults.overlay_mask and any(faults.overlay_shift):
            if mask_pixel_pitch is None:
                raise ValueError("an overlay shift needs mask_pixel_pitch")
            dy, dx = faults.overlay_shift
            sub = mask_pixel_pitch / s
            # Periodic: the tile repeats; +y is up, i.e. towards row 0.
            bitmap = np.roll(bitmap, (-round(dy / sub), round(dx / sub)), axis=(0, 1))
        depth = mask.steps * phase_step
        if j < len(faults.etch_errors):
            depth *= 1 + faults.etch_errors[j]
        phase = phase - depth * bitmap
    return phase


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
