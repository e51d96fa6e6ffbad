"""Conditioning of a capture once read: dark subtraction, saturation, hot pixels, noise.

Plain functions on arrays: ``check_dark`` refuses a dark frame that does not match
its capture, ``condition_capture`` subtracts it and flags saturated and hot pixels;
``robust_sigma`` estimates noise, ``repair_pixels`` fills flagged pixels from their
neighbours.
"""

from dataclasses import dataclass, field

import numpy as np

from doe.infra.errors import InputError

# A dark-frame pixel this many robust sigmas above the dark median is hot.
HOT_PIXEL_SIGMAS = 10.0
# This many pixels at exactly the image's maximum mark clipping when the
# sensor's full scale is not known.
PLATEAU_PIXELS = 3
# Exposure times (from the files' metadata) may differ by this fraction.
EXPOSURE_RTOL = 0.02
# A dark frame with more than this share of its pixels at full scale saw light:
# subtracted, a frame clipped everywhere takes a constant off and changes no figure.
DARK_SATURATED_MAX = 0.01


@dataclass(frozen=True)
class Capture:
    """A conditioned capture, ready for lattice registration.

    Attributes
    ----------
    image : (H, W) float32 array
        Dark-subtracted signal in data numbers (DN).
    saturated : (H, W) bool array
        Pixels at the sensor's full-scale code (or a float plateau) in the raw capture.
    hot : (H, W) bool array
        Pixels flagged hot in the dark frame (not repaired in ``image``:
        ``fab.verify.hot_pixels.repair_hot_pixels`` does, once the dots are known).
    full_scale : float or None
        Saturation code in DN (None for float data without a plateau).
    notes : list of str
        Human-readable remarks for the report.
    quantum : float
        Step between two codes in DN (``RawImage.quantum``); 0 for float data.
    """

    image: np.ndarray
    saturated: np.ndarray
    hot: np.ndarray
    full_scale: float | None
    notes: list = field(default_factory=list)
    quantum: float = 1.0


def check_dark(raw, dark, dark_source):
    """Refuse a dark frame that does not match the capture (size, bit depth, exposure)
    or that saw light (a share above ``DARK_SATURATED_MAX`` of its pixels at full scale)."""
    if dark.data.shape != raw.data.shape:
        raise InputError(
            dark_source,
            f"dark frame is {dark.data.shape[1]}x{dark.data.shape[0]} "
            f"pixels but the capture is {raw.data.shape[1]}x{raw.data.shape[0]}",
        )
    if _code_kind(dark) != _code_kind(raw) and dark.data.any():
        raise InputError(
            dark_source,
            f"dark frame is stored as {dark.encoding} but the "
            f"capture as {raw.encoding}; take both with the same camera settings",
        )
    if (
        raw.exposure
        and dark.exposure
        and (abs(raw.exposure - dark.exposure) > EXPOSURE_RTOL * raw.exposure)
    ):
        raise InputError(
            dark_source,
            f"dark exposure {dark.exposure:.6g} s differs from the "
            f"capture's {raw.exposure:.6g} s; take the dark at the same exposure",
        )
    if dark.full_scale is not None:
        share = np.count_nonzero(dark.data >= dark.full_scale) / dark.data.size
        if share > DARK_SATURATED_MAX:
            raise InputError(
                dark_source,
                f"{100 * share:.3g} % of the dark frame's pixels are at full scale "
                f"({dark.full_scale:g}): it saw light; take it with the light blocked",
            )


def _code_kind(raw):
    """How a file's codes read in DN: a 12-bit sensor's codes read the same stored
    MSB-aligned in 16 bits or as a BitsPerSample-12 TIFF (a capture as PNG and its dark
    as such a TIFF are not refused as "other camera settings"). A 16-bit file of values
    <= 4095 stays apart: it may be a 16-bit mode's dark."""
    if raw.encoding in ("uint16-msb12", "uint12") and raw.full_scale == 4095.0:
        return "12-bit DN"
    return raw.encoding


def condition_capture(raw, dark=None):
    """Subtract the dark frame, flag saturation and hot pixels.

    Parameters
    ----------
    raw : RawImage
        The capture.
    dark : RawImage or None
        A dark frame of the same size and exposure.

    Returns
    -------
    Capture
        ``image`` float32 DN; without a dark frame a constant pedestal is
        left in and removed later by the local background of each dot.
    """
    data = raw.data
    notes = []
    saturated = np.zeros(data.shape, bool)
    if raw.full_scale is not None:
        saturated = data >= raw.full_scale
    if raw.encoding in ("float", "uint16") and not saturated.any():
        # A sensor of unknown depth (a 14-bit one stored LSB-aligned, float data)
        # clips to a plateau: several bright pixels at exactly the maximum.
        peak = float(data.max())
        plateau = data >= peak
        floor = float(np.median(data[::4, ::4]))
        if np.count_nonzero(plateau) >= PLATEAU_PIXELS and peak > floor + 100 * max(
            robust_sigma(data[::4, ::4]), 1e-6
        ):
            saturated = plateau
            notes.append(
                f"{int(plateau.sum())} pixels share the maximum value {peak:g}: "
                "taken as clipped (saturated)"
            )
    image = data.astype(np.float32)
    hot = np.zeros(data.shape, bool)
    if dark is not None:
        dark_f = dark.data.astype(np.float32)
        image -= dark_f
        rise = float(np.median(dark_f[::4, ::4]) - np.median(data[::4, ::4]))
        if rise > max(5 * robust_sigma(dark_f[::4, ::4]), raw.quantum):
            # Harmless to the figures (each dot's local background takes it out), but
            # a dark frame above the capture was not taken with the capture's settings.
            notes.append(
                f"the dark frame's floor is {rise:.4g} DN above the capture's: taken "
                "with other camera settings? Each dot's local background takes the offset out"
            )
        # Flagged, not repaired: on a dot, a hot pixel less its dark still holds
        # the dot's light; which pixels lie on a dot is known once the lattice is.
        hot = hot_pixels_from_dark(dark_f)
    return Capture(image, saturated, hot, raw.full_scale, notes, raw.quantum)


def robust_sigma(values):
    """Return the standard deviation of the bulk of ``values``, robust to outliers.

    Starts from 1.4826 * the median absolute deviation, then takes the standard
    deviation of the values within 4 sigma of the median (twice): the MAD alone
    is quantised on integer data (a noise of 2.1 DN can read as 1.48).
    """
    values = np.asarray(values, dtype=np.float64).ravel()
    if values.size == 0:
        return 0.0
    med = np.median(values)
    dev = np.abs(values - med)
    sigma = 1.4826 * float(np.median(dev))
    if sigma == 0:
        sigma = float(values.std())
    for _ in range(2):
        if sigma == 0:
            break
        near = values[dev <= 4 * sigma]
        # A Gaussian cut at 4 sigma keeps 99.994 % of its variance.
        sigma = float(np.sqrt(np.mean((near - med) ** 2)))
    return sigma


def hot_pixels_from_dark(dark):
    """Flag pixels of a dark frame far above its median (``HOT_PIXEL_SIGMAS`` robust sigmas)."""
    sample = dark[::3, ::3]
    sigma = max(robust_sigma(sample), 0.5)
    return dark > np.median(sample) + HOT_PIXEL_SIGMAS * sigma


def repair_pixels(image, bad):
    """Return a copy of ``image``, ``bad`` pixels replaced by the median of good neighbours.

    Parameters
    ----------
    image : (H, W) float array
    bad : (H, W) bool array
    """
    out = np.array(image, dtype=np.float32, copy=True)
    rows, cols = np.nonzero(bad)
    if rows.size == 0:
        return out
    _h, _w = image.shape
    padded = np.pad(np.where(bad, np.nan, out), 1, constant_values=np.nan)
    offsets = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc]
    neigh = np.stack([padded[rows + 1 + dr, cols + 1 + dc] for dr, dc in offsets], axis=1)
    all_bad = np.all(np.isnan(neigh), axis=1)
    fill = np.zeros(rows.size, dtype=np.float32)
    if np.any(~all_bad):
        fill[~all_bad] = np.nanmedian(neigh[~all_bad], axis=1)
    out[rows, cols] = fill
    return out
