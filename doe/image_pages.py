"""Pages of an image file and a quiet libpng, for the readers of captures (fab) and frames
(psf_learn)."""

import os
import sys
from contextlib import contextmanager


def png_bit_depth(path):
    """Return the bit depth in a PNG's header, or None for a file that is no PNG.

    OpenImageIO widens 1-, 2- and 4-bit PNGs to 8 bits and does not say so.
    """
    with open(path, "rb") as f:
        head = f.read(26)
    if head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR" or len(head) < 26:
        return None
    return head[24]


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
