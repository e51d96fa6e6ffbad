"""Raster images of every mask (OpenImageIO): the tile at mask-pixel resolution, a plate preview.

Pixel values: 255 (white) = etched (a drawn polygon), 0 (black) = not etched, the
project's one polarity (``fab.package.polarity``), written into each file's
``Description``; row 0 is the top edge of the layout, viewed onto the patterned
surface (right-reading). In the plate preview a pixel is the etched fraction of
the mask pixels it covers, and the plate edge and the clear-aperture frame are
drawn in grey (128).
This module and :func:`read_image` are the only places here that touch image files.
"""

import math
from pathlib import Path

import numpy as np

from fab.package.polarity import POLARITY, plate_preview_description, tile_image_description

ETCHED = 255
OUTLINE_GREY = 128
PREVIEW_MAX_PX = 1024
# TIFF writers stamp the current time; pin it so the bytes are reproducible.
PINNED_DATETIME = "2020:01:01 00:00:00"


def tile_image(bitmap):
    """Return the (N, N, 1) uint8 image of a mask bitmap: 255 where etched, row 0 at the top."""
    return (np.asarray(bitmap, dtype=bool).astype(np.uint8) * ETCHED)[:, :, None]


def preview_factor(pitch_nm, plate_half_nm, max_px=PREVIEW_MAX_PX):
    """Return how many mask pixels along x and y one plate-preview pixel covers."""
    return max(1, math.ceil(2 * plate_half_nm / pitch_nm / max_px))


def plate_preview(
    bitmap, tiles, pitch_nm, plate_half_nm, aperture_half_nm, max_px=PREVIEW_MAX_PX,
    edge_pixels=(0, 0, 0, 0),
):  # fmt: skip
    """Return a downsampled picture of the whole plate for one mask.

    Parameters
    ----------
    bitmap : (N, N) bool array
        The mask's tile.
    tiles : (int, int)
        Tiles along x and y.
    pitch_nm : int
        Mask pixel pitch.
    plate_half_nm, aperture_half_nm : int
        Half sizes of the plate and of the clear aperture (nm), centred on the array.
    max_px : int
        Upper bound of the preview's width and height.
    edge_pixels : (int, int, int, int)
        Pixel columns left and right, rows below and above the whole-tile array that
        continue the periodic pattern (the clipped edge tiles).

    Returns
    -------
    (H, W, 1) uint8 array
        Each preview pixel covers f x f mask pixels (f an integer), value = 255 x etched fraction.
    """
    b = np.asarray(bitmap, dtype=bool)
    n = b.shape[0]
    nx, ny = tiles
    e_left, e_right, e_bottom, e_top = (int(v) for v in edge_pixels)
    f = preview_factor(pitch_nm, plate_half_nm, max_px)
    s = f * pitch_nm  # preview pixel size, nm
    # The whole tiled plate can be tens of gigapixels at a fine pitch; count the etched
    # pixels of each f x f block from the tile alone: rows @ tile @ cols.T, exact integers.
    rows = _block_counts(-e_top, ny * n + e_bottom, n, f)
    small = rows @ b.astype(float) @ _block_counts(-e_left, nx * n + e_right, n, f).T / f**2
    size = math.ceil(2 * plate_half_nm / s)
    centre = size / 2
    # Row 0 of the array is its top edge: place it at y = +ny * n * p / 2.
    # blocks stay on the whole-tile array's grid; the edge tiles add blocks before it
    top = round(centre - ny * n * pitch_nm / 2 / s) + (-e_top) // f
    left = round(centre - nx * n * pitch_nm / 2 / s) + (-e_left) // f
    h, w = min(small.shape[0], size - top), min(small.shape[1], size - left)
    if top < 0 or left < 0 or h <= 0 or w <= 0:
        raise ValueError("the tiled array does not fit inside the plate")
    img = np.zeros((size, size), np.uint8)
    for half in (plate_half_nm, aperture_half_nm):
        r = half / s
        lo = int(np.clip(round(centre - r), 0, size - 1))
        hi = int(np.clip(round(centre + r) - 1, 0, size - 1))
        img[lo, lo : hi + 1] = img[hi, lo : hi + 1] = OUTLINE_GREY
        img[lo : hi + 1, lo] = img[lo : hi + 1, hi] = OUTLINE_GREY
    # The array goes over the frames: an aperture edge that rounds into its first
    # row or column must not hide the pattern there.
    img[top : top + h, left : left + w] = np.rint(small[:h, :w] * ETCHED)
    return img[:, :, None]


def _block_counts(start, stop, n, f):
    """Return (blocks, n): how often tile index k falls in block i of the line of pixels
    start <= r < stop (pixel r shows tile index r mod n), the blocks of f pixels counted
    from the block that holds pixel ``start`` on the grid of pixel 0's."""
    r = np.arange(start, stop)
    blocks = (stop - 1) // f - start // f + 1
    i = (r // f - start // f) * n + r % n
    return np.bincount(i, minlength=blocks * n).reshape(blocks, n).astype(float)


def write_image(path, image, pixel_nm=None, description=None):
    """Write an (H, W, 1) uint8 array as a single-channel TIFF or PNG with pinned metadata.

    With ``pixel_nm`` the file records its pixel size as a resolution (TIFF:
    pixels per cm; PNG: pixels per metre, to 1 part in 2e5), so that image viewers
    show the true scale; ``fab_manifest.json`` stays the exact record. ``description``
    goes into the TIFF ImageDescription tag / the PNG ``Description`` text chunk.
    """
    import OpenImageIO as oiio

    image = np.ascontiguousarray(image, dtype=np.uint8)
    if image.ndim == 2:
        image = image[:, :, None]  # OIIO scrambles pixels of a 2-D array
    h, w, c = image.shape
    spec = oiio.ImageSpec(w, h, c, "uint8")
    spec.attribute("DateTime", PINNED_DATETIME)
    if description:
        spec.attribute("ImageDescription", description)
    if pixel_nm is not None:
        spec.attribute("XResolution", 1e7 / pixel_nm)
        spec.attribute("YResolution", 1e7 / pixel_nm)
        spec.attribute("ResolutionUnit", "cm")
    if str(path).lower().endswith((".tif", ".tiff")):
        spec.attribute("compression", "lzw")
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise OSError(f"{path}: OpenImageIO cannot write this format: {oiio.geterror()}")
    try:
        if not out.open(str(path), spec) or not out.write_image(image):
            raise OSError(f"{path}: OpenImageIO write failed: {out.geterror()}")
    finally:
        out.close()


def read_image(path):
    """Read an 8-bit single-channel image back as (H, W) uint8 (for checks and tests)."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise OSError(f"{path}: OpenImageIO cannot read it: {oiio.geterror()}")
    try:
        data = inp.read_image("uint8")
    finally:
        inp.close()
    return np.asarray(data)[:, :, 0]


def layer_image_names(mask_name):
    """Return (tile TIFF, plate preview PNG) file names of a mask."""
    return f"{mask_name}_tile.tif", f"{mask_name}_plate.png"


def write_layer_images(
    out_dir, masks, tiles, pitch_nm, plate_half_nm, aperture_half_nm, edge_pixels=(0, 0, 0, 0)
):
    """Write the tile TIFF and the plate preview PNG of every mask; return the file names."""
    out_dir = Path(out_dir)
    names = []
    for mk in masks:
        tif, png = layer_image_names(mk.name)
        tile = tile_image(mk.bitmap)
        write_image(out_dir / tif, tile, pitch_nm, tile_image_description(mk.name))
        preview = plate_preview(
            mk.bitmap, tiles, pitch_nm, plate_half_nm, aperture_half_nm, edge_pixels=edge_pixels
        )
        f = preview_factor(pitch_nm, plate_half_nm)
        write_image(out_dir / png, preview, f * pitch_nm, plate_preview_description(mk.name))
        names += [tif, png]
    return names


def layer_image_blocks(mask_names):
    """Return report blocks listing each mask's layer images with what they show."""
    items = []
    for name in mask_names:
        tif, png = layer_image_names(name)
        items.append(f"{tif}: {tile_image_description(name)}.")
        items.append(f"{png}: {plate_preview_description(name)}.")
    return [("p", f"Layer images ({POLARITY} in each):"), ("ul", items)]
