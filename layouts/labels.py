"""Text labels etched on the masks, drawn as a pixel font at the process's feature size.

gdstk's font is built from unit squares (1/16 of the text size, 9 units per
character, 14 units tall with descenders): strokes and gaps of one unit, except
the diagonals ("0", "&", "/"), whose squares meet only at a corner, a zero-width
neck to a Euclidean design-rule check. Here the glyphs are sampled on their unit
grid, each corner-only contact is filled with one unit square (so no two set
pixels, and no two clear ones, meet only at a corner), and the bitmap is drawn
with a unit of at least the feature size: every stroke and gap is then at least
one unit wide, measured in any direction.
"""

import unicodedata

import numpy as np

FONT_SIZE_UNITS = 16  # gdstk's text size in font units
CHAR_ADVANCE_UNITS = 9  # each character advances by 9 units


def etchable(text):
    """Return ``text`` in the printable ASCII that gdstk's font draws.

    gdstk drops every other character without a word ("µ-plate" etched as "-plate"):
    accents go (é -> e), micro signs become u, anything else becomes "?".
    """
    text = unicodedata.normalize("NFKD", text.replace("µ", "u").replace("μ", "u"))
    text = "".join(c for c in text if not unicodedata.combining(c))
    return "".join(c if " " <= c <= "~" else "?" for c in text)


def glyph_bitmap(text):
    """Return the text as a bool bitmap of font units (row 0 = top) without corner contacts.

    The bitmap spans 14 rows (descender to ascender) and ``9 * len(text)`` columns.
    """
    import gdstk

    cols, rows = CHAR_ADVANCE_UNITS * max(len(text), 1), FONT_SIZE_UNITS - 2
    polys = gdstk.text(text, FONT_SIZE_UNITS, (0, 0))
    yy, xx = np.mgrid[rows - 1 : -1 : -1, 0:cols]  # pixel (r, c) covers x in [c, c+1]
    centres = np.stack([xx.ravel() + 0.5, yy.ravel() + 0.5], axis=1)
    bitmap = np.zeros(rows * cols, bool)
    if polys:
        bitmap = np.asarray(gdstk.inside(centres, polys), bool)
    return fill_corner_contacts(bitmap.reshape(rows, cols))


def fill_corner_contacts(bitmap):
    """Fill one pixel of every 2 x 2 window whose set pixels touch only at a corner.

    [[1, 0], [0, 1]] becomes [[1, 0], [1, 1]] and [[0, 1], [1, 0]] becomes
    [[0, 1], [1, 1]]; repeated until none is left (each pass only sets pixels).
    """
    b = np.array(bitmap, bool)
    while True:
        tl, tr, bl, br = b[:-1, :-1], b[:-1, 1:], b[1:, :-1], b[1:, 1:]
        down = tl & br & ~tr & ~bl  # "\" diagonal
        up = tr & bl & ~tl & ~br  # "/" diagonal
        if not (down.any() or up.any()):
            return b
        r, c = np.nonzero(down)
        b[r + 1, c] = True
        r, c = np.nonzero(up)
        b[r + 1, c + 1] = True


def label_size_units(text):
    """Return (columns, rows) of the text's bitmap in font units."""
    return CHAR_ADVANCE_UNITS * max(len(text), 1), FONT_SIZE_UNITS - 2


def label_polygons(text, x0, y0, unit, layer):
    """Return the text's pixels as merged polygons, lower-left corner at (x0, y0) nm.

    ``unit`` (nm) is the side of one font unit: the narrowest stroke and gap drawn.
    """
    import gdstk

    from layouts.rectangles import bitmap_rectangles, rectangle_corners_nm

    bitmap = glyph_bitmap(text)
    if not bitmap.any():
        return []
    corners = rectangle_corners_nm(bitmap_rectangles(bitmap), bitmap.shape[0], unit)
    corners = corners[:, :] + np.array([x0, y0, x0, y0])
    rects = [gdstk.rectangle((a / 1000, b / 1000), (c / 1000, d / 1000)) for a, b, c, d in corners]
    merged = gdstk.boolean(rects, [], "or", precision=1e-3)
    return [
        gdstk.Polygon(np.round(p.points * 1000) / 1000, layer=layer, datatype=0) for p in merged
    ]
