"""The dot lattice's pitch in camera pixels, measured from the capture alone.

``measure_pitch`` needs no pixel pitch and no lens: the dots standing out of the noise
are found at every scale down to ``MIN_MEASURED_PITCH_PX``, and the pitch is the median
of the bright dots' nearest-neighbour distances (a dense PSF's bright orders have
lit neighbours one order away). It is a start within a few per cent:
``fab.verify.lattice.register_lattice`` then fits the lattice to every dot.

``check_stated_pitch`` compares it with what the bench's flags say (camera pixel
pitch, lattice pitch on the camera): a capture contradicting them is refused with both
numbers, never read on the wrong lattice (which would fail a good plate).
``adjacent_bright_share`` says whether the design's bright orders have lit neighbours
at all (a design lighting every other order would read a multiple of the pitch).
"""

import numpy as np

from doe.infra.errors import InputError
from fab.verify.lattice import (
    DETECT_SIGMAS,
    PITCH_TOLERANCE,
    SPIKE_FRACTION,
    LatticeNotFound,
    on_lattice_share,
    pixel_noise,
    pixel_patches,
    register_lattice,
)

# Closest dots measured (px): two spots of 0.7 px sigma, smoothed by ``SMOOTH_PX``, still
# show two maxima 3 px apart (a dip needs more than twice the combined sigma).
MIN_MEASURED_PITCH_PX = 3.0
SMOOTH_PX = 0.5
# The brightest dots whose nearest neighbour gives the pitch.
PITCH_DOTS = 400
# The share of the dots' light that must lie on a stated pitch's lattice for sparse dots
# to agree with it.
ON_STATED_SHARE = 0.9
# At least half the bright dots' nearest neighbours must lie within this fraction of
# their median for it to be a lattice's pitch.
NEIGHBOUR_AGREEMENT = 0.1
# At least this share of the design's bright orders (the PITCH_DOTS brightest, at least
# BRIGHT_ORDER of the brightest) must have a bright order beside them for the
# nearest-neighbour distance to be the pitch.
BRIGHT_ORDER = 1e-3
ADJACENT_SHARE_MIN = 0.5


def measure_pitch(image, quantum=0.0):
    """Return the dot lattice's pitch in pixels (median nearest-neighbour distance of
    the brightest dots), or None when fewer than 3 dots have a neighbour.

    ``image`` is the dark-subtracted capture (DN), hot pixels repaired.
    """
    from scipy import ndimage
    from scipy.spatial import cKDTree

    x = np.asarray(image, dtype=np.float32)
    x = x - np.float32(np.median(x[::4, ::4]))
    noise = pixel_noise(x[::4, ::4], quantum)
    smooth = ndimage.gaussian_filter(x, SMOOTH_PX)
    threshold = DETECT_SIGMAS * noise / (2 * np.sqrt(np.pi) * SMOOTH_PX)
    peak = (smooth == ndimage.maximum_filter(smooth, size=3)) & (smooth > threshold)
    r, c = np.nonzero(peak)
    if r.size < 4:
        return None
    order = np.argsort(smooth[r, c])[::-1]
    r, c = r[order], c[order]
    inside = (r >= 1) & (r < x.shape[0] - 1) & (c >= 1) & (c < x.shape[1] - 1)
    r, c = r[inside], c[inside]
    if r.size < 4:
        return None
    # hot pixels (at least SPIKE_FRACTION of their 3 x 3 light in one pixel) are no dots
    raw = np.clip(pixel_patches(x, r, c, 1), 0, None)
    spot = raw.max(axis=(1, 2)) < SPIKE_FRACTION * raw.sum(axis=(1, 2))
    r, c = r[spot], c[spot]
    if r.size < 4:
        return None
    # 3 x 3 centroids: whole-pixel maxima 3.5 px apart would read 3 or 4
    patch = np.clip(pixel_patches(smooth, r, c, 1), 0, None).astype(np.float64)
    total = np.maximum(patch.sum(axis=(1, 2)), 1e-30)
    off = np.arange(-1.0, 2.0)
    dots = np.stack(
        [r + (patch.sum(axis=2) @ off) / total, c + (patch.sum(axis=1) @ off) / total], axis=1
    )
    tree = cKDTree(dots)
    bright = dots[:PITCH_DOTS]
    # a few neighbours, the first beyond the closest pitch measured (a blurred dot
    # can show two maxima a pixel or two apart)
    dist, _ = tree.query(bright, k=min(6, dots.shape[0]))
    far = np.where(dist >= MIN_MEASURED_PITCH_PX - 0.5, dist, np.inf)
    nearest = far.min(axis=1)
    nearest = nearest[np.isfinite(nearest)]
    if nearest.size < 3:
        return None
    pitch = float(np.median(nearest))
    # a lattice's dots agree on it; a few scattered dots (a dim capture) do not
    agree = np.abs(nearest / pitch - 1) <= NEIGHBOUR_AGREEMENT
    if agree.sum() < 3 or agree.mean() < 0.5:
        return None
    return pitch


def adjacent_bright_share(order_power):
    """Return the share of the design's bright orders (the ``PITCH_DOTS`` brightest, at
    least ``BRIGHT_ORDER`` of the brightest) that have a bright order one step away
    along a lattice axis (periodic (N, N) powers)."""
    p = np.asarray(order_power, float)
    # as the capture's brightest PITCH_DOTS dots, those a camera sees well above its noise
    top = np.sort(p, axis=None)[::-1][min(PITCH_DOTS, p.size) - 1]
    bright = p >= max(BRIGHT_ORDER * p.max(), top)
    beside = np.zeros_like(bright)
    for axis in (0, 1):
        for step in (1, -1):
            beside |= np.roll(bright, step, axis=axis)
    return float((bright & beside).sum() / max(bright.sum(), 1))


def capture_pitch(image, quantum, design_power, stated, source):
    """Return the lattice pitch (px) to register a capture at.

    The pitch measured from ``image`` (``measure_pitch``), checked against ``stated``
    (``check_stated_pitch``'s arguments after the measured pitch; its first, the
    stated pitch in px, None when no pixel pitch was given); the stated pitch where
    the capture cannot tell it (too few dots with neighbours, or a design whose
    bright orders are seldom adjacent, whose dots' nearest neighbours lie several
    orders apart).

    Raises
    ------
    InputError
        A capture contradicting the stated pitch (naming the flag), or one that cannot
        tell its pitch when none was stated (naming ``source``, the capture).
    """
    stated_px = stated[0]
    measured = measure_pitch(image, quantum)
    adjacent = adjacent_bright_share(design_power) >= ADJACENT_SHARE_MIN
    if measured is not None and adjacent:
        try:  # the whole lattice's pitch, for the numbers a refusal quotes
            measured = register_lattice(image, measured, refine_iterations=0, quantum=quantum)[
                0
            ].pitch_px
        except LatticeNotFound:
            pass
        if stated_px is not None and not _on_stated_lattice(image, quantum, stated_px):
            check_stated_pitch(measured, *stated)
        return measured if stated_px is None else _closer(measured, stated_px)
    if stated_px is not None:
        return stated_px
    why = (
        "too few of its dots have a neighbour to measure the lattice pitch"
        if measured is None
        else "the design's bright orders are seldom next to each other, so the "
        "dots' spacing is not the lattice pitch"
    )
    raise InputError(source, f"{why}; give --pixel-pitch-um (the camera's pixel pitch)")


def _on_stated_lattice(image, quantum, stated_px):
    """Whether the capture's dots lie on a lattice of the stated pitch (within
    ``PITCH_TOLERANCE``), ``ON_STATED_SHARE`` of their light on its sites: sparse dots
    (a dim capture, a design lighting every other order) whose nearest neighbours lie
    orders apart do not contradict it."""
    try:
        lattice, _ = register_lattice(image, stated_px, refine_iterations=1, quantum=quantum)
    except LatticeNotFound:
        return False
    share = on_lattice_share(image, lattice, stated_px, quantum)
    return share is not None and share >= ON_STATED_SHARE


def _closer(measured, stated_px):
    """Return the measured pitch where it agrees with the stated one, else the stated
    (the dots lie on its lattice, farther apart than one order)."""
    return measured if abs(measured / stated_px - 1) <= PITCH_TOLERANCE else stated_px


def check_stated_pitch(measured_px, stated_px, lattice_pitch_um, pixel_pitch_um, source):
    """Refuse a stated pitch that the capture contradicts (InputError naming ``source``).

    ``stated_px`` is the lattice pitch on the camera in pixels that the flags give
    (lattice pitch / camera pixel pitch); allowed within ``PITCH_TOLERANCE`` (a test
    lens's magnification, a focal length a few per cent off).
    """
    ratio = measured_px / stated_px
    if abs(ratio - 1) <= PITCH_TOLERANCE:
        return
    implied = lattice_pitch_um / measured_px
    raise InputError(
        source,
        f"the capture's dots are {measured_px:.4g} px apart (measured), but "
        f"--pixel-pitch-um {pixel_pitch_um:g} and a lattice pitch of {lattice_pitch_um:.4g} um "
        f"give {stated_px:.4g} px ({ratio - 1:+.0%}, allowed ±{PITCH_TOLERANCE:.0%}): "
        f"the camera's pixels would be {implied:.3g} um at that lattice pitch; correct "
        "--pixel-pitch-um or --lattice-pitch-um, or leave --pixel-pitch-um out",
    )
