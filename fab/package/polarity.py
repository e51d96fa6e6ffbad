"""The one polarity convention of every mask image and figure: white = etched.

A mask pixel that is etched in that mask's step (a drawn polygon, CONVENTIONS.md
"Data polarity") is white (255 in the image files), one that is not is black (0).
That is how the photomask itself looks against the light: with positive resist it
is dark-field, clear where a polygon is drawn (etched) and chrome elsewhere. Each
image and figure says so: the PNG and TIFF ``Description`` text, the figure's colour
bar and title, and the captions of the reports and of the run's index page.
"""

POLARITY = "white = etched, black = not etched"
PHOTOMASK = "clear on the dark-field photomask"


def tile_image_description(mask):
    """Return the ``Description`` of a mask's tile image (TIFF)."""
    return (
        f"{mask}: one tile at mask-pixel resolution, {POLARITY} (255 = etched = drawn "
        f"polygon, {PHOTOMASK}); row 0 = top edge, viewed onto the patterned surface"
    )


def plate_preview_description(mask):
    """Return the ``Description`` of a mask's whole-plate preview (PNG)."""
    return (
        f"{mask}: whole-plate preview, {POLARITY} (grey = etched fraction of the mask "
        f"pixels a preview pixel covers); thin grey (128) frames: plate edge and clear "
        f"aperture; viewed onto the patterned surface"
    )


def masks_figure_description():
    """Return the caption and ``Description`` of the masks figure (``fab_fig_masks.png``)."""
    return f"Mask bitmaps of one tile: {POLARITY} (etched = drawn polygon, {PHOTOMASK})."
