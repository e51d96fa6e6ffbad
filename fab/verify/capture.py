"""Camera captures of a plate's dot lattice: the one module that opens image files.

Reading goes through OpenImageIO: 8- and 16-bit TIFF/PNG (16-bit data from a
12-bit sensor may be MSB-aligned, i.e. all four low bits zero; from a 13- to
15-bit one, 1 to 3 low bits zero) and float
TIFF/EXR. Integer data is read as integers (OIIO would convert to float unless
asked), so the saturation code of the file is known exactly. ``read_capture``
reads a capture and its dark frame and conditions them (``fab.verify.conditioning``:
dark subtraction, saturation and hot pixels).
"""

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from doe.infra.errors import InputError
from doe.infra.image_pages import (
    check_file_kind,
    has_more_pages,
    native_stderr_quiet,
    stored_bits,
    stored_codes,
)
from fab.verify.conditioning import Capture, check_dark, condition_capture

# The formats CONVENTIONS names for captures (OpenImageIO's names). Lossy compression
# moves the weak orders' counts; a palette image (GIF) holds no camera counts.
CAPTURE_FORMATS = {"tiff": "TIFF", "png": "PNG", "openexr": "EXR"}
LOSSY_COMPRESSIONS = {"jpeg", "webp", "dwaa", "dwab", "b44", "b44a"}
# Float pixels beyond this are refused: the analysis sums pixels times squared
# distances in float32 (largest 3.4e38), which would overflow. No camera counts
# within 1e20 of it.
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


def read_raw_image(path):
    """Read a single-channel capture through OpenImageIO.

    Raises
    ------
    InputError
        Missing, truncated or corrupt files, colour images whose channels
        differ, unsupported pixel formats, multi-page files; the message names
        the file.
    """
    path = Path(path)
    check_file_kind(path)
    if not path.is_file():
        raise InputError(path, "no such image file")
    stored = _read_stored(path)
    pixels = np.asarray(stored.pixels)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    if 0 <= stored.alpha < pixels.shape[2] and pixels.shape[2] > 1:  # grey or colour + alpha
        pixels = np.delete(pixels, stored.alpha, axis=2)
    notes = []
    exposure = stored.exposure
    if not 0 < exposure < math.inf:  # unknown (0, absent) or no time at all (-0.01 s, NaN)
        if exposure != 0:
            notes.append(f"the file's ExposureTime {exposure:g} s is no exposure time: ignored")
        exposure = None
    if stored.orientation != 1:
        # Viewers turn such an image; the pixels are used as stored, and
        # --orientation describes the stored image.
        notes.append(
            f"the file's Orientation tag is {stored.orientation} (a viewer shows the image "
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
    data, full, encoding, quantum = _codes(pixels[..., 0], stored, path, notes)
    return RawImage(np.ascontiguousarray(data), full, exposure, tuple(notes), encoding, quantum)


@dataclass(frozen=True)
class _Stored:
    """An image file's pixels as OpenImageIO reads them ("uint8", "uint16" or "float"
    ``fmt``, whose top code is ``full``) and what its header says (alpha channel or -1,
    exposure in s or 0, bits per sample or 0, Orientation tag)."""

    pixels: object
    fmt: str
    full: float | None
    alpha: int
    exposure: float
    bits: int
    orientation: int


def _read_stored(path):
    """Return a capture file's pixels as stored (integers kept integers, so that the
    file's saturation code is known exactly) and its header.

    Raises
    ------
    InputError
        A file OpenImageIO cannot read, a format other than ``CAPTURE_FORMATS``,
        lossy compression, an unsupported pixel format, several pages.
    """
    import OpenImageIO as oiio

    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # counts as stored, not multiplied by alpha
    with native_stderr_quiet():  # libpng's own "libpng error: ..." line; geterror() has it
        inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise InputError(path, f"not a readable image ({_one_line(oiio.geterror())})")
    try:
        spec = inp.spec()
        _check_format(path, inp.format_name(), spec)
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
        if pixels is None or inp.has_error:
            raise InputError(path, f"truncated or corrupt image ({_one_line(inp.geterror())})")
        stored = _Stored(
            pixels,
            fmt,
            full,
            spec.alpha_channel,
            spec.get_float_attribute("ExposureTime", 0.0),
            stored_bits(spec, path),
            spec.get_int_attribute("Orientation", 1),
        )
        if has_more_pages(inp):  # a multi-page TIFF: which page is the capture?
            raise InputError(path, "holds several images (pages); give one capture per file")
    finally:
        inp.close()
    return stored


def _check_format(path, kind, spec):
    """Refuse a file format other than ``CAPTURE_FORMATS``, or one compressed with loss."""
    compression = spec.get_string_attribute("compression").split(":")[0]
    if kind not in CAPTURE_FORMATS or compression in LOSSY_COMPRESSIONS:
        what = (
            f"{kind.upper()} image"
            if kind not in CAPTURE_FORMATS
            else f"{CAPTURE_FORMATS[kind]} compressed with loss ({compression})"
        )
        raise InputError(path, f"{what}; give the capture as TIFF, PNG or EXR without loss")


def _codes(data, stored, path, notes):
    """Return (data, full scale, encoding, quantum) of a file's single channel ``data``.

    Integer samples of fewer than 16 bits are taken back to the sensor's own codes,
    step and full scale; ``notes`` gets what was assumed.
    """
    fmt, full, bits = stored.fmt, stored.full, stored.bits
    encoding = fmt
    quantum = 1.0
    if fmt != "float" and bits and bits < 8:
        # Dots of 2 or 16 grey values would be blamed on the plate (CONVENTIONS asks
        # for 8 or 16 bits).
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
        # at their own top code (65532 for 14 bits), not at 65535. Codes are kept as stored.
        zeros = _trailing_zero_bits(data)
        quantum = float(1 << zeros)
        full = 65536.0 - quantum
        notes.append(
            f"{16 - zeros}-bit data MSB-aligned in 16 bits (low {zeros} bits all zero): "
            f"full scale {full:g}"
        )
    return data, full, encoding, quantum


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


def _one_line(message):
    text = " ".join(str(message).split())
    return text[:200] if text else "no details from the reader"
