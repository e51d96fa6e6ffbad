"""Camera captures of a plate's dot lattice: the one module that opens image files.

Reading goes through OpenImageIO: 8- and 16-bit TIFF/PNG (16-bit data from a
12-bit sensor may be MSB-aligned, i.e. all four low bits zero; from a 13- to
15-bit one, 1 to 3 low bits zero) and float
TIFF/EXR. Integer data is read as integers (OIIO would convert to float unless
asked), so the saturation code of the file is known exactly. The conditioning
steps (dark subtraction, hot-pixel repair, noise estimate) are plain functions
on arrays.
"""

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from doe.infra.errors import InputError

# A dark-frame pixel this many robust sigmas above the dark median is hot.
HOT_PIXEL_SIGMAS = 10.0
# This many pixels at exactly the image's maximum mark clipping when the
# sensor's full scale is not known.
PLATEAU_PIXELS = 3
# Exposure times (from the files' metadata) may differ by this fraction.
EXPOSURE_RTOL = 0.02
# A dark frame with more than this share of its pixels at full scale saw light (a
# frame saturated everywhere passed as a dark and every figure stayed the same).
DARK_SATURATED_MAX = 0.01
# The formats CONVENTIONS names for captures (OpenImageIO's names). JPEG and WebP
# were read too, their compression moving the weak orders' counts, and GIF's palette.
CAPTURE_FORMATS = {"tiff": "TIFF", "png": "PNG", "openexr": "EXR"}
LOSSY_COMPRESSIONS = {"jpeg", "webp", "dwaa", "dwab", "b44", "b44a"}
# Float pixels beyond this are refused: the analysis sums pixels times squared
# distances in float32 (largest 3.4e38); a capture at 2e38 overflowed there, printed
# numpy's warnings and read no signal. No camera counts within 1e20 of it.
FLOAT_PIXEL_MAX = 1e30


@dataclass(frozen=True)
class RawImage:
    """One single-channel image as stored.

    Attributes
    ----------
    data : (H, W) array
        uint8/uint16 as stored (MSB-aligned 12-bit data already shifted down),
        or float32 for float files.
    full_scale : float or None
        Largest code the sensor can report (255, 4095, 65532 for 14 bits MSB-aligned,
        65535); None for float files.
    exposure : float or None
        Exposure time in seconds from the file's metadata, when present.
    notes : tuple of str
        What the reader noticed (bit alignment, channels).
    encoding : str
        "uint8", "uint16", "uint16-msb12" or "float": how the codes are stored.
    quantum : float
        Step between two codes in the units of ``data`` (1 for integer data, 4 for
        10-bit data MSB-aligned, as its codes read in 12-bit DN, 4 for 14-bit data
        MSB-aligned, whose codes are kept as stored); 0 for float data.
    """

    data: np.ndarray
    full_scale: float | None
    exposure: float | None
    notes: tuple[str, ...] = ()
    encoding: str = ""
    quantum: float = 1.0


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
        ``fab.verify.lattice.repair_hot_pixels`` does, once the dots are known).
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


def read_raw_image(path):
    """Read a single-channel capture through OpenImageIO.

    Raises
    ------
    InputError
        Missing, truncated or corrupt files, colour images whose channels
        differ, unsupported pixel formats, multi-page files; the message names
        the file.
    """
    import OpenImageIO as oiio

    from doe.infra.image_pages import (
        check_file_kind,
        has_more_pages,
        native_stderr_quiet,
        stored_bits,
        stored_codes,
    )

    path = Path(path)
    check_file_kind(path)
    if not path.is_file():
        raise InputError(path, "no such image file")
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # counts as stored, not multiplied by alpha
    with native_stderr_quiet():  # libpng's own "libpng error: ..." line; geterror() has it
        inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise InputError(path, f"not a readable image ({_one_line(oiio.geterror())})")
    try:
        spec = inp.spec()
        kind = inp.format_name()
        compression = spec.get_string_attribute("compression").split(":")[0]
        if kind not in CAPTURE_FORMATS or compression in LOSSY_COMPRESSIONS:
            what = (
                f"{kind.upper()} image"
                if kind not in CAPTURE_FORMATS
                else f"{CAPTURE_FORMATS[kind]} compressed with loss ({compression})"
            )
            raise InputError(path, f"{what}; give the capture as TIFF, PNG or EXR without loss")
        base = spec.format.basetype
        if base in (oiio.UINT8, oiio.UINT16):
            fmt, full = ("uint8", 255.0) if base == oiio.UINT8 else ("uint16", 65535.0)
        elif base in (oiio.HALF, oiio.FLOAT, oiio.DOUBLE):
            fmt, full = "float", None
        else:
            raise InputError(path, f"unsupported pixel format {spec.format}; use 8/16-bit or float")
        try:
            with native_stderr_quiet():
                pixels = inp.read_image(0, 0, 0, spec.nchannels, fmt)
        except MemoryError:
            raise InputError(
                path, f"{spec.width} x {spec.height} pixels do not fit in this machine's memory"
            ) from None
        alpha = spec.alpha_channel
        if pixels is None or inp.has_error:
            raise InputError(path, f"truncated or corrupt image ({_one_line(inp.geterror())})")
        exposure = spec.get_float_attribute("ExposureTime", 0.0)
        bits = stored_bits(spec, path)
        file_orientation = spec.get_int_attribute("Orientation", 1)
        if has_more_pages(inp):  # a multi-page TIFF: which page is the capture?
            raise InputError(path, "holds several images (pages); give one capture per file")
    finally:
        inp.close()
    pixels = np.asarray(pixels)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    if 0 <= alpha < pixels.shape[2] and pixels.shape[2] > 1:  # grey or colour + alpha
        pixels = np.delete(pixels, alpha, axis=2)
    notes = []
    if not 0 < exposure < math.inf:  # unknown (0, absent) or no time at all (-0.01 s, NaN)
        if exposure != 0:
            notes.append(f"the file's ExposureTime {exposure:g} s is no exposure time: ignored")
        exposure = None
    if file_orientation != 1:
        # Viewers turn such an image; the pixels are used as stored, and
        # --orientation describes the stored image.
        notes.append(
            f"the file's Orientation tag is {file_orientation} (a viewer shows the image "
            "turned or flipped): read as stored, as verify's --orientation and mtf's "
            "edge angle describe it"
        )
    if pixels.shape[2] > 1:
        colour = pixels[..., : min(3, pixels.shape[2])]
        if not np.all(colour == colour[..., :1]):
            raise InputError(
                path,
                f"{pixels.shape[2]}-channel colour image; "
                "give a single-channel (monochrome) capture",
            )
        notes.append(f"{pixels.shape[2]} identical channels: used the first")
    data = pixels[..., 0]
    encoding = fmt
    quantum = 1.0
    if fmt != "float" and bits and bits < 8:
        # Dots of 2 or 16 grey values: verify blamed the plate for the file (CONVENTIONS
        # asks for 8 or 16 bits).
        raise InputError(path, f"{bits}-bit image; give an 8- or 16-bit or float capture")
    if fmt == "float":
        data = data.astype(np.float32)
        quantum = 0.0
        if not np.all(np.isfinite(data)):
            raise InputError(path, "image has NaN or infinite pixels")
        if np.any(np.abs(data) > FLOAT_PIXEL_MAX):
            raise InputError(
                path,
                f"float pixels reach {np.abs(data).max():.3g}, beyond {FLOAT_PIXEL_MAX:g}: "
                "the sums over a dot would overflow; scale the image down",
            )
    elif fmt == "uint16" and bits and 8 < bits < 16:
        # A 12-bit TIFF comes widened to 16 bits (4095 -> 65535, the top bits repeated
        # below): its own codes, step and full scale are taken back.
        data = stored_codes(data, bits)
        full = float((1 << bits) - 1)
        encoding = f"uint{bits}"
        notes.append(f"{bits}-bit samples: codes as stored, full scale {full:g}")
    elif fmt == "uint16" and data.any() and not np.any(data & 0xF):
        # 12-bit sensors written MSB-aligned leave the four low bits zero; a 10-bit
        # one leaves six, 8-bit data scaled by 256 eight. The codes are shifted
        # down by four bits (12-bit DN); the sensor's own top code is its full scale.
        zeros = _trailing_zero_bits(data)
        data = data >> 4
        full = float(((1 << (16 - zeros)) - 1) << (zeros - 4))
        quantum = float(1 << (zeros - 4))
        encoding = "uint16-msb12"
        notes.append(
            f"{16 - zeros}-bit data MSB-aligned in 16 bits (low {zeros} bits all zero): "
            f"shifted down by 4 bits, full scale {full:g}"
        )
    elif fmt == "uint16" and data.max() <= 4095:
        full = 4095.0  # 12-bit data stored LSB-aligned: it saturates at 4095, not 65535
        notes.append("16-bit file with values <= 4095: taken as 12-bit data (saturates at 4095)")
    elif fmt == "uint16" and not np.any(data & 1):
        # 13- to 15-bit sensors written MSB-aligned leave 1 to 3 low bits zero and clip
        # at their own top code (65532 for 14 bits): at 65535, one or two clipped pixels
        # (fewer than a plateau) went unflagged. Codes are kept as stored.
        zeros = _trailing_zero_bits(data)
        quantum = float(1 << zeros)
        full = 65536.0 - quantum
        notes.append(
            f"{16 - zeros}-bit data MSB-aligned in 16 bits (low {zeros} bits all zero): "
            f"full scale {full:g}"
        )
    return RawImage(np.ascontiguousarray(data), full, exposure, tuple(notes), encoding, quantum)


def _trailing_zero_bits(data):
    """Return how many low bits are zero in every value of non-zero integer ``data``."""
    bits = int(np.bitwise_or.reduce(data, axis=None))
    return (bits & -bits).bit_length() - 1


def write_image(path, image, exposure=None):
    """Write a single-channel uint8/uint16/float32 image through OpenImageIO.

    Parameters
    ----------
    path : path
        Output file; the extension picks the format (.png, .tif, .exr).
    image : (H, W) array
        Pixel values; the dtype picks the stored format.
    exposure : float or None
        Exposure time in seconds, written as the ``ExposureTime`` attribute.
    """
    import OpenImageIO as oiio

    image = np.asarray(image)
    fmt = {
        np.dtype(np.uint8): "uint8",
        np.dtype(np.uint16): "uint16",
        np.dtype(np.float32): "float",
    }.get(image.dtype)
    if fmt is None:
        raise ValueError(f"write_image needs uint8, uint16 or float32, got {image.dtype}")
    h, w = image.shape
    spec = oiio.ImageSpec(w, h, 1, fmt)
    if exposure is not None:
        spec.attribute("ExposureTime", float(exposure))
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise InputError(path, f"cannot write image ({_one_line(oiio.geterror())})")
    # OIIO scrambles a 2-D array: hand it (H, W, 1).
    ok = out.open(str(path), spec) and out.write_image(np.ascontiguousarray(image[..., None]))
    out.close()
    if not ok:
        raise InputError(path, f"cannot write image ({_one_line(out.geterror())})")


def read_capture(path, dark_path=None):
    """Read and condition a capture (and its optional dark frame).

    Returns
    -------
    Capture

    Raises
    ------
    InputError
        Unreadable files, or a dark frame of another size, bit depth or exposure.
    """
    raw = read_raw_image(path)
    notes = [f"{Path(path).name}: {n}" for n in raw.notes]
    dark_raw = None
    if dark_path is not None:
        dark_raw = read_raw_image(dark_path)
        notes += [f"{Path(dark_path).name}: {n}" for n in dark_raw.notes]
        check_dark(raw, dark_raw, dark_path)
    capture = condition_capture(raw, dark_raw)
    return Capture(
        capture.image,
        capture.saturated,
        capture.hot,
        capture.full_scale,
        notes + capture.notes,
        capture.quantum,
    )


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
    as such a TIFF were refused as "other camera settings"). A 16-bit file of values
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


def _one_line(message):
    text = " ".join(str(message).split())
    return text[:200] if text else "no details from the reader"
