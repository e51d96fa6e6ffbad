"""Pages of an image file and a quiet libpng, for the readers of captures (fab) and frames
(psf_learn)."""

import os
import sys
from contextlib import contextmanager
from pathlib import Path

from doe.infra.errors import InputError


def check_file_kind(path):
    """Raise InputError for a folder, a pipe or device, or a dangling link named as an image.

    Opening a pipe waits for a writer for ever, and "no such file" would mislead for
    /dev/zero or a link to nothing; a missing file is each reader's to name.
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(path, "is a folder, not an image file")
    if path.exists() and not path.is_file():
        raise InputError(path, "is not a regular file (a pipe or a device)")
    if path.is_symlink() and not path.exists():
        raise InputError(path, "is a symbolic link to nothing (dangling, or a loop)")


def stored_bits(spec, path):
    """Return the bits per sample a file stores (None if it does not say).

    OpenImageIO widens fewer bits to its 8 or 16: a TIFF says how many it had
    (``oiio:BitsPerSample``), a PNG only in its header.
    """
    return spec.get_int_attribute("oiio:BitsPerSample", 0) or png_bit_depth(path)


def png_bit_depth(path):
    """Return the bits per sample of a PNG from its header, or None for a file that is no PNG.

    OpenImageIO and Pillow widen 1-, 2- and 4-bit grey to 8 bits and do not say so.
    A palette image's samples are its 8-bit entries, whatever its index depth.
    """
    with open(path, "rb") as f:
        head = f.read(26)
    if head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR" or len(head) < 26:
        return None
    return 8 if head[25] == 3 else head[24]


def stored_codes(values, stored_bits):
    """Return integer ``values`` a reader widened from ``stored_bits`` bits as the codes stored.

    The readers widen 1- to 4-bit samples to 8 bits and 9- to 15-bit ones to 16 by
    repeating their bits below (15 -> 255, 4095 -> 65535): the top bits are the code.
    """
    container = 8 * values.dtype.itemsize
    if values.dtype.kind != "u" or not stored_bits or stored_bits >= container:
        return values
    return values >> (container - stored_bits)


def has_more_pages(inp):
    """Whether an open OpenImageIO ImageInput holds images after its first.

    Reduced-resolution copies of it (TIFF subfile type 1: the thumbnail some
    camera software writes) do not count; they are not another capture. Leaves
    ``inp`` on one of its later subimages.
    """
    page = 1
    while inp.seek_subimage(page, 0):
        if inp.spec().get_int_attribute("tiff:subfiletype", 0) & 1 == 0:
            return True
        page += 1
    return False


@contextmanager
def native_stderr_quiet():
    """Silence what C libraries write to file descriptor 2 while the block runs.

    libpng prints "libpng error: IHDR: CRC error" there itself on a damaged PNG, a
    second line beside the reader's one-line refusal, which quotes the same reason
    from ``OpenImageIO.geterror()``.
    """
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
