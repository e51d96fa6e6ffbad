"""PNG figures whose bytes depend only on what they show, and their text chunks.

matplotlib stamps its version into a PNG's ``Software`` text chunk, so the same
figure saved by two installations would differ. Every figure of the project is
saved through :func:`save_png`, which leaves that stamp out and can state what the
figure shows (its polarity, say) in a ``Description`` text chunk; :func:`png_text`
reads such chunks back.
"""

import struct

PNG_METADATA = {"Software": None}
"""savefig metadata for PNG: a key set to None is left out of the file."""

_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def save_png(fig, target, *, dpi=None, description=None):
    """Save a matplotlib figure as PNG with no version stamp.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure to save.
    target : path or binary file object
        Where the PNG goes.
    dpi : float, optional
        Resolution; None keeps matplotlib's ``savefig.dpi`` (by default the figure's own).
    description : str, optional
        Written as the PNG's ``Description`` text chunk (e.g. "white = etched").
    """
    metadata = dict(PNG_METADATA)
    if description:
        metadata["Description"] = description
    fig.savefig(target, format="png", dpi=dpi, metadata=metadata)


def png_text(path):
    """Return the uncompressed text chunks (``tEXt``) of a PNG file as {keyword: text}.

    Returns {} for a file that is not a PNG.
    """
    with open(path, "rb") as f:
        data = f.read()
    if not data.startswith(_SIGNATURE):
        return {}
    out, pos = {}, len(_SIGNATURE)
    while pos + 8 <= len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        if kind == b"tEXt":
            key, _, text = data[pos + 8 : pos + 8 + length].partition(b"\0")
            out[key.decode("latin-1")] = text.decode("latin-1")
        elif kind == b"IEND":
            break
        pos += 12 + length
    return out
