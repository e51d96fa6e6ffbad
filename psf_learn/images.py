"""Image input for learning: folders of grayscale images, the embedded default set, raw frames.

The only module of ``psf_learn`` that opens image files. Images come back as
float32 (H, W) arrays scaled to [0, 1] (8-bit / 255, 16-bit / 65535, a TIFF of
fewer bits by its own white: 12-bit / 4095); colour
images are converted to full-range luminance (ITU-R BT.601 weights; SR benchmarks
often take MATLAB's 16-235 Y instead, whose PSNR reads 1.32 dB higher).
"""

import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from doe.infra.errors import InputError
from doe.infra.image_pages import check_file_kind, png_bit_depth, stored_codes

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
# natural photographs shipped inside scikit-image (no download on demand): trained on
_SKIMAGE_BUNDLED = (
    "coffee",
    "rocket",
    "motorcycle_left",
    "brick",
    "grass",
    "gravel",
    "coins",
    "moon",
)
# and held out: the images ``doefab learn`` scores its model on, never trained on
_SKIMAGE_HELD_OUT = ("camera", "astronaut", "chelsea")


def to_gray(image, source):
    """Return a float32 (H, W) luminance image in [0, 1] from a uint8/uint16/float array."""
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim == 3 and a.shape[2] in (2, 4):  # drop alpha
        a = a[..., : a.shape[2] - 1]
    if a.dtype == np.uint8:
        a = a.astype(np.float32) / 255.0
    elif a.dtype == np.uint16:
        a = a.astype(np.float32) / 65535.0
    elif a.dtype.kind == "f":
        a = a.astype(np.float32)
        if np.nanmin(a, initial=0) < 0 or np.nanmax(a, initial=1) > 1:
            raise InputError(
                source,
                f"float pixels must lie in [0, 1] (white = 1), got {a.min():g} .. {a.max():g}",
            )
    elif a.dtype == bool:
        a = a.astype(np.float32)
    else:
        raise InputError(source, f"unsupported pixel type {a.dtype}")
    if a.ndim == 3 and a.shape[2] == 3:
        a = a @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    elif a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim != 2:
        raise InputError(source, f"expected a grayscale or RGB image, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(source, "image contains NaN or infinite values")
    return a


def read_image(path):
    """Read one image file as float32 (H, W) in [0, 1] (raises InputError if unreadable)."""
    path = Path(path)
    a, bits = _decode(path)
    if bits and a.dtype.kind == "u" and bits < 8 * a.dtype.itemsize:
        # A 12-bit TIFF's white is 4095, not the 65535 of its uint16 container
        # (scaled by that, it would read 16 times too dark); a 4-bit one's 15, not 255.
        a = a.astype(np.float32) / ((1 << bits) - 1)
    return to_gray(a, path)


def decode(path):
    """Decode an image file as stored (uint8/uint16/float, (H, W) or (H, W, C))."""
    return _decode(path)[0]


def _decode(path):
    """Return (the image as stored, the bits per sample of a TIFF or None).

    The decoder follows the suffix: tifffile for TIFF, Pillow for everything
    else. Naming it keeps imageio from trying its other plugins (DICOM, ...)
    on a damaged file, which costs time and raises their deprecation warnings.
    16-bit PNGs go through OpenImageIO: Pillow reads 16-bit colour (and grey with
    alpha) as 8-bit, dropping the low byte without a word.
    """
    path = Path(path)
    check_file_kind(path)
    try:
        if path.suffix.lower() in (".tif", ".tiff"):
            import tifffile

            with tifffile.TiffFile(path) as tif:
                pages = sum(not page.is_reduced for page in tif.pages)  # thumbnails aside
                first = tif.pages[0]
                separated = first.photometric == tifffile.PHOTOMETRIC.SEPARATED
                white = first.photometric == tifffile.PHOTOMETRIC.MINISWHITE
                planar = first.planarconfig == tifffile.PLANARCONFIG.SEPARATE
                a = tif.series[0].asarray()
            if planar and first.samplesperpixel > 1:
                a = np.moveaxis(a, -3, -1)  # channel planes: channels last, as elsewhere
            bits = first.bitspersample
        elif png_bit_depth(path) == 16:
            separated, white, pages, a, bits = False, False, 1, _decode_oiio(path), None
        else:
            import imageio.v3 as iio
            from PIL import Image

            separated = white = False
            bits = None  # Pillow widens 1-, 2- and 4-bit PNGs to 8 bits itself
            with _pillow_quiet(Image):
                with Image.open(path) as im:  # reads the header only
                    pages = getattr(im, "n_frames", 1)
                    # imageio hands a CMYK JPEG's ink planes over as RGBA; Pillow makes light
                    a = np.asarray(im.convert("RGB")) if im.mode == "CMYK" else None
                if a is None:
                    a = iio.imread(path, plugin="pillow")
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    except Exception as e:  # the decoders raise many types on corrupt data
        raise InputError(path, f"not a readable image ({type(e).__name__}: {e})") from None
    if pages > 1:  # a stack or an animation: which page is the image?
        raise InputError(path, f"holds {pages} images (pages or frames); give one per file")
    if separated:
        a = _ink_to_rgb(a, path)
    if white:
        a = _white_to_black(a, bits, path)
    return a, bits


@contextmanager
def _pillow_quiet(Image):
    """Keep Pillow's warnings about a file off stderr: the file is read or refused anyway.

    A header past 89 Mpx (Pillow's "decompression bomb") and a palette with byte
    transparency each print two lines beside the one-line refusal or the result.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        warnings.filterwarnings("ignore", "Palette images with Transparency", UserWarning)
        yield


def _decode_oiio(path):
    """Decode an image with OpenImageIO at its stored precision, alpha left as stored."""
    import OpenImageIO as oiio

    from doe.infra.image_pages import native_stderr_quiet

    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # colour not multiplied by alpha
    with native_stderr_quiet():  # libpng's own "libpng error: ..." line; geterror() has it
        inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise ValueError(oiio.geterror().strip())
    try:
        spec = inp.spec()
        with native_stderr_quiet():
            a = inp.read_image(0, 0, 0, spec.nchannels, spec.format)
        if a is None:
            raise ValueError(inp.geterror().strip())
    finally:
        inp.close()
    return a[..., 0] if a.shape[-1] == 1 else a


def _white_to_black(a, bits, path):
    """Values of a MinIsWhite TIFF (0 = white: scans, fax) as light, 0 = black.

    tifffile hands the codes over as stored; read so, the picture and a frame's
    counts would come out as their negative.
    """
    if a.dtype != bool and a.dtype.kind != "u":  # no code is white: OpenImageIO keeps them
        raise InputError(path, f"MinIsWhite (inverted) image of {a.dtype}: give MinIsBlack")
    a = a.copy()
    grey = a if a.ndim == 2 else a[..., 0]  # an alpha channel beside it stays as stored
    grey[...] = ~grey if a.dtype == bool else (1 << bits) - 1 - grey
    return a


def _ink_to_rgb(cmyk, path):
    """RGB of CMYK ink planes without a colour profile: R = (1 - C) (1 - K), and so on."""
    if cmyk.ndim != 3 or cmyk.shape[-1] != 4 or cmyk.dtype.kind not in "uf":
        raise InputError(
            path, f"ink (separated) image of {cmyk.dtype} {cmyk.shape}: give grey or RGB"
        )
    full = np.iinfo(cmyk.dtype).max if cmyk.dtype.kind == "u" else 1.0
    ink = cmyk.astype(np.float64) / full
    rgb = (1 - ink[..., :3]) * (1 - ink[..., 3:]) * full
    return (np.round(rgb) if cmyk.dtype.kind == "u" else rgb).astype(cmyk.dtype)


def image_files(folder):
    """Return the sorted image files (PNG, JPEG, TIFF) of a folder, hidden ones aside.

    InputError if there are none.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "not a folder of images")
    files = sorted(
        p
        for p in folder.iterdir()
        # hidden files aside: macOS leaves a "._name.png" of metadata beside each image
        if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")
    )
    if not files:
        raise InputError(folder, f"no images ({', '.join(IMAGE_SUFFIXES)}) in this folder")
    return files


def read_folder(folder, min_size=0, why=""):
    """Return (names, images) of every image in a folder, float32 (H, W) in [0, 1].

    Images smaller than ``min_size`` on either side are refused with InputError,
    ``why`` (what sets the size) added to the message.
    """
    names, images = [], []
    for path in image_files(folder):
        img = read_image(path)
        if min(img.shape) < min_size:
            reason = f"image {img.shape} is smaller than {min_size} pixels"
            raise InputError(path, f"{reason} ({why})" if why else reason)
        names.append(path.name)
        images.append(img)
    return names, images


def dead_leaves(size, rng, n_disks=3000, r_min=1.5, r_max=None):
    """Return a float32 (size, size) dead-leaves image: occluding discs, power-law radii.

    Radii follow p(r) ~ r^-3 between ``r_min`` and ``r_max`` (scale invariant,
    like natural images); each disc gets a uniform grey and a faint gradient.
    """
    r_max = r_max or size / 4
    img = np.full((size, size), rng.uniform(), dtype=np.float32)
    radii = power_law_radii(rng.uniform(size=n_disks), r_min, r_max)
    for r in np.sort(radii)[::-1]:  # large discs first, small ones on top
        cy, cx = rng.uniform(-r, size + r, size=2)
        y0, y1 = max(int(cy - r), 0), min(int(cy + r) + 2, size)
        x0, x1 = max(int(cx - r), 0), min(int(cx + r) + 2, size)
        if y0 >= y1 or x0 >= x1:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1]
        inside = (yy - cy) ** 2 + (xx - cx) ** 2 <= r * r
        grey = rng.uniform() + rng.normal(0, 0.002) * ((yy - cy) + (xx - cx))
        img[y0:y1, x0:x1][inside] = np.clip(grey, 0, 1)[inside]
    return img


def power_law_radii(u, r_min, r_max):
    """Return radii with density p(r) ~ r^-3 on [r_min, r_max] from uniform ``u`` in [0, 1].

    The inverse of the CDF F(r) = (r_min^-2 - r^-2) / (r_min^-2 - r_max^-2).
    """
    return 1.0 / np.sqrt(1 / r_min**2 - np.asarray(u) * (1 / r_min**2 - 1 / r_max**2))


def default_images(seed=0, n_dead_leaves=8, size=256):
    """Return (names, images): natural photos bundled with scikit-image plus dead leaves.

    Needs no download: only images whose files ship inside scikit-image are used.
    The held-out photos (:func:`held_out_images`) are not among them.
    """
    names, images = _skimage_photos(_SKIMAGE_BUNDLED)
    rng = np.random.default_rng(seed)
    for i in range(n_dead_leaves):
        names.append(f"dead_leaves:{i}")
        images.append(dead_leaves(size, rng))
    return names, images


def held_out_images():
    """Return (names, images) of the embedded photos held out of training, to score on.

    Photographs (camera man, astronaut, cat) bundled with scikit-image, as grey.
    """
    return _skimage_photos(_SKIMAGE_HELD_OUT)


def _skimage_photos(which):
    """Return (names, images) of the named photos that ship inside scikit-image."""
    import skimage

    folder = Path(skimage.__file__).parent / "data"
    names, images = [], []
    for name in which:
        files = sorted(folder.glob(f"{name}.*"))
        if not files:
            continue  # not bundled with this scikit-image version; never download
        names.append(f"skimage:{name}")
        images.append(read_image(files[0]))
    return names, images


def read_raw(path):
    """Read raw SPAD data: .npy (H, W) or (T, H, W), or an image file (8/16 bit or float).

    Returns float64 counts: npy values as stored, integer images as their integer
    values (a 16-bit frame keeps its counts, not a [0, 1] scaling). Grey stored as
    RGB(A) or with alpha is read from its first channel; colour images and
    negative counts are refused.
    """
    path = Path(path)
    if path.suffix.lower() == ".npy":
        from doe.infra.files import load_npy

        a = load_npy(path)
        if a.dtype.kind not in "fiu" or a.ndim not in (2, 3):
            raise InputError(
                path, f"raw frames must be numeric (H, W) or (T, H, W), got {a.dtype} {a.shape}"
            )
    else:
        # Pillow widens a 4-bit grey PNG to 8 bits (1 -> 17): counts are the codes stored.
        a = stored_codes(decode(path), png_bit_depth(path))
        if a.ndim == 3 and a.shape[2] == 2:  # grey and alpha
            a = a[..., :1]
        if a.ndim == 3 and a.shape[2] in (3, 4):
            # Grey saved as RGB(A) holds the counts in each channel; colour holds no counts.
            if not np.all(a[..., :3] == a[..., :1]):
                raise InputError(
                    path, f"{a.shape[2]}-channel colour image; give the counts in grey"
                )
            a = a[..., :1]
        if a.ndim == 3 and a.shape[2] == 1:
            a = a[..., 0]
        if a.ndim != 2:
            raise InputError(path, f"expected a single-channel frame, got shape {a.shape}")
    a = np.asarray(a, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise InputError(path, "raw frames contain NaN or infinite values")
    if np.any(a < 0):
        raise InputError(path, f"raw frames contain negative counts (min {a.min():g})")
    if a.shape[-1] < 2 or a.shape[-2] < 2:
        raise InputError(path, f"frames of {a.shape} are too small")
    if a.size == 0:
        raise InputError(path, f"holds no frames (shape {a.shape})")
    return a
