"""Property tests: the image readers accept good files and refuse damaged ones with InputError."""

import re
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from doe.infra.errors import InputError
from fab.verify.capture import read_raw_image, write_image
from psf_learn.cubes import read_frame
from psf_learn.images import read_image, read_raw

READERS = {
    "capture": lambda path: read_raw_image(path).data,
    "frame": read_frame,
    "training image": read_image,
}


@pytest.fixture(scope="module")
def good_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("images")
    rng = np.random.default_rng(0)
    files = {}
    for ext, dtype in (("png", np.uint16), ("tif", np.uint8), ("tif16", np.uint16)):
        image = rng.integers(1, np.iinfo(dtype).max, (40, 56)).astype(dtype)
        path = folder / f"good.{ext.removesuffix('16')}"
        path = path.with_stem(f"good_{ext}")
        write_image(path, image)
        files[ext] = (path, image)
    return files


@pytest.mark.parametrize("reader", READERS)
def test_readers_return_the_pixels_of_a_good_file(good_files, reader):
    for path, image in good_files.values():
        got = np.asarray(READERS[reader](path))
        assert got.shape == image.shape, (reader, path)
        if reader != "training image":  # that one scales to [0, 1] grey
            assert np.array_equal(got, image), (reader, path)


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    kind=st.sampled_from(["png", "tif", "tif16"]),
    reader=st.sampled_from(sorted(READERS)),
    cut=st.floats(0.0, 0.9),
    flips=st.lists(st.tuples(st.floats(0, 1), st.integers(1, 255)), max_size=4),
)
def test_damaged_files_are_refused_or_read_never_crash(
    good_files, tmp_path, kind, reader, cut, flips
):
    path, _ = good_files[kind]
    data = bytearray(path.read_bytes())
    for where, xor in flips:
        data[int(where * (len(data) - 1))] ^= xor
    damaged = tmp_path / f"damaged_{kind}{path.suffix}"
    damaged.write_bytes(bytes(data[: max(1, int(len(data) * (1 - cut)))]))
    try:
        READERS[reader](damaged)
    except InputError as e:
        assert str(damaged) in str(e)  # names the file
    # Anything else (a crash, a hang) fails the test.


@pytest.mark.parametrize("reader", READERS)
def test_truncated_file_is_refused(good_files, tmp_path, reader):
    path, _ = good_files["png"]
    data = path.read_bytes()
    damaged = tmp_path / "truncated.png"
    damaged.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated"):
        READERS[reader](damaged)


@pytest.mark.parametrize("reader", [*READERS, "raw frame"])
def test_damaged_signature_is_refused_plainly(good_files, tmp_path, reader):
    # A PNG whose signature is damaged: no decoder accepts it. The readers must
    # say so, naming the file, without trying every other format on it (imageio's
    # hunt left unclosed files and a DICOM-plugin deprecation warning behind).
    path, _ = good_files["png"]
    data = bytearray(path.read_bytes())
    data[1] ^= 0xFF
    damaged = tmp_path / "damaged_signature.png"
    damaged.write_bytes(bytes(data))
    read = READERS.get(reader, read_raw)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match=r"damaged_signature\.png"):
            read(damaged)


@pytest.mark.parametrize("reader", [*READERS, "raw frame"])
def test_multi_page_tiff_is_refused(tmp_path, reader):
    # Which page is the capture (or frame, or image)? Each reader once took the first
    # page silently; the training reader took a 5-page stack for one image.
    import tifffile

    path = tmp_path / "burst.tif"
    pages = np.random.default_rng(1).integers(0, 4000, (2, 24, 32)).astype(np.uint16)
    with tifffile.TiffWriter(path) as tif:
        for page in pages:
            tif.write(page)
    with pytest.raises(InputError, match=r"burst\.tif.*pages"):
        READERS.get(reader, read_raw)(path)


@pytest.mark.parametrize("reader", [*READERS, "raw frame"])
def test_a_tiff_with_a_thumbnail_is_one_image(tmp_path, reader):
    # A reduced-resolution copy (subfile type 1) is no second capture; the capture
    # and frame readers refused it as "several images" while the training one read it.
    import tifffile

    path = tmp_path / "with_thumbnail.tif"
    image = np.random.default_rng(2).integers(1, 4000, (24, 32)).astype(np.uint16)
    with tifffile.TiffWriter(path) as tif:
        tif.write(image)
        tif.write(image[::4, ::4], subfiletype=1)
    got = np.asarray(READERS.get(reader, read_raw)(path))
    assert got.shape == image.shape


def test_raw_frames_are_counts(tmp_path):
    # Grey saved as RGB keeps its counts; colour (once blended to luminance) and
    # negative values (once passed to the network) are no counts.
    from PIL import Image

    grey = np.random.default_rng(2).integers(0, 256, (12, 10)).astype(np.uint8)
    Image.fromarray(np.repeat(grey[..., None], 3, axis=2)).save(tmp_path / "grey_rgb.png")
    np.testing.assert_array_equal(read_raw(tmp_path / "grey_rgb.png"), grey)
    colour = np.stack([grey, grey, 255 - grey], axis=2)
    Image.fromarray(colour).save(tmp_path / "colour.png")
    with pytest.raises(InputError, match=r"colour\.png.*colour"):
        read_raw(tmp_path / "colour.png")
    np.save(tmp_path / "dark_subtracted.npy", grey.astype(float) - 128.0)
    with pytest.raises(InputError, match="negative"):
        read_raw(tmp_path / "dark_subtracted.npy")


def write_png16(path, image):
    """A 16-bit PNG written by hand, byte by byte as the PNG standard lays it out."""
    import struct
    import zlib

    image = np.asarray(image, dtype=">u2")
    colour_type = {1: 0, 2: 4, 3: 2, 4: 6}[1 if image.ndim == 2 else image.shape[2]]
    rows = b"".join(b"\x00" + row.tobytes() for row in image)  # filter 0 on every row

    def chunk(kind, data):
        crc = zlib.crc32(kind + data)
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    header = struct.pack(">IIBBBBB", image.shape[1], image.shape[0], 16, colour_type, 0, 0, 0)
    body = chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b"")
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + body)


def test_sixteen_bit_colour_pngs_keep_their_low_byte(tmp_path):
    # Pillow reads 16-bit RGB, RGBA and grey+alpha PNGs as 8-bit: sr took 62123
    # counts for 242, silently, while the same counts in a grey PNG read right.
    counts = (np.arange(63).reshape(9, 7) * 1000 + 123).astype(np.uint16)
    alpha = np.full_like(counts, 30000)  # partial: colour must not be multiplied by it
    for name, image in (
        ("grey", counts),
        ("grey_alpha", np.dstack([counts, alpha])),
        ("rgb", np.dstack([counts] * 3)),
        ("rgba", np.dstack([counts] * 3 + [alpha])),
    ):
        path = tmp_path / f"{name}.png"
        write_png16(path, image)
        np.testing.assert_array_equal(read_raw(path), counts, err_msg=name)
        np.testing.assert_allclose(read_image(path), counts / 65535, atol=1e-6, err_msg=name)
        # A capture too: OIIO multiplied its counts by alpha (17 read as 8), and
        # grey + alpha was refused as a 2-channel colour image.
        np.testing.assert_array_equal(read_raw_image(path).data, counts, err_msg=name)


def test_compressed_tiffs_are_read(tmp_path):
    # LZW is the usual TIFF compression of cameras and ImageJ; float TIFFs (ours
    # too) carry a floating-point predictor. Without tifffile's codecs both were
    # refused (exit 2) by the training, evaluation and sr reader.
    import OpenImageIO as oiio

    counts = (np.arange(48).reshape(6, 8) * 5).astype(np.uint8)
    spec = oiio.ImageSpec(8, 6, 1, "uint8")
    spec.attribute("compression", "lzw")
    out = oiio.ImageOutput.create(str(tmp_path / "lzw.tif"))
    assert out.open(str(tmp_path / "lzw.tif"), spec) and out.write_image(counts[..., None])
    out.close()
    np.testing.assert_array_equal(read_raw(tmp_path / "lzw.tif"), counts)
    np.testing.assert_allclose(read_image(tmp_path / "lzw.tif"), counts / 255, atol=1e-6)
    frame = np.linspace(0, 1, 48, dtype=np.float32).reshape(6, 8)
    write_image(tmp_path / "float.tif", frame)
    np.testing.assert_array_equal(read_raw(tmp_path / "float.tif"), frame)


def test_hidden_files_in_an_image_folder_are_left_aside(tmp_path):
    # One macOS "._name.png" (resource-fork metadata, no image) refused the folder.
    from psf_learn.images import read_folder

    write_image(tmp_path / "a.png", np.full((5, 6), 200, np.uint8))
    (tmp_path / "._a.png").write_bytes(b"\x00\x05\x16\x07 macOS metadata")
    names, images = read_folder(tmp_path)
    assert names == ["a.png"] and images[0].shape == (5, 6)


def test_planar_tiffs_are_told_by_their_tag_not_by_their_shape(tmp_path):
    # Channels were taken to be planes whenever the first axis had 3 or 4 entries:
    # a grey + alpha TIFF 3 rows high became a "3-channel colour image".
    import tifffile

    rng = np.random.default_rng(5)
    rgb = rng.integers(0, 65536, (3, 5, 7)).astype(np.uint16)  # planes: (S, H, W)
    tifffile.imwrite(tmp_path / "planar.tif", rgb, photometric="rgb", planarconfig="separate")
    luminance = np.moveaxis(rgb / 65535, 0, -1) @ np.array([0.299, 0.587, 0.114])
    np.testing.assert_allclose(read_image(tmp_path / "planar.tif"), luminance, atol=1e-6)
    grey_alpha = rng.integers(0, 256, (3, 8, 2)).astype(np.uint8)  # interleaved, 3 rows
    tifffile.imwrite(
        tmp_path / "la.tif", grey_alpha, photometric="minisblack", extrasamples=["unassalpha"]
    )
    np.testing.assert_allclose(read_image(tmp_path / "la.tif"), grey_alpha[..., 0] / 255, atol=1e-6)


def test_float_training_images_must_lie_in_zero_one(tmp_path):
    # Images are grey in [0, 1]; a float TIFF of [-0.5, 0.5] once went into PSNRs as is.
    import tifffile

    rng = np.random.default_rng(3)
    tifffile.imwrite(tmp_path / "ok.tif", rng.random((20, 20)).astype(np.float32))
    assert 0 <= read_image(tmp_path / "ok.tif").min() <= read_image(tmp_path / "ok.tif").max() <= 1
    tifffile.imwrite(tmp_path / "signed.tif", (rng.random((20, 20)) - 0.5).astype(np.float32))
    with pytest.raises(InputError, match=r"signed\.tif.*\[0, 1\]"):
        read_image(tmp_path / "signed.tif")


def test_nan_pixels_in_a_float_training_image_are_refused(tmp_path):
    # NaN slips past the [0, 1] range check (nanmin and nanmax skip it)
    from psf_learn.images import to_gray

    image = np.full((6, 6), 0.5, np.float32)
    image[2, 3] = np.nan
    with pytest.raises(InputError, match=r"img\.tif.*NaN"):
        to_gray(image, tmp_path / "img.tif")


def test_an_image_folder_takes_images_of_exactly_the_minimum_size(tmp_path):
    from psf_learn.images import read_folder

    write_image(tmp_path / "a.png", np.full((16, 20), 200, np.uint8))
    assert read_folder(tmp_path, min_size=16)[1][0].shape == (16, 20)
    with pytest.raises(InputError, match=r"a\.png.*smaller than 17"):
        read_folder(tmp_path, min_size=17)


def test_dead_leaves_radii_have_density_r_to_the_minus_3():
    # F(r) by integrating r^-3 numerically; the radii must invert it
    from scipy.integrate import quad

    from psf_learn.images import power_law_radii

    r_min, r_max = 1.5, 64.0
    total = quad(lambda r: r**-3, r_min, r_max)[0]
    for r in (1.5, 2.0, 3.7, 10.0, 64.0):
        cdf = quad(lambda x: x**-3, r_min, r)[0] / total
        assert power_law_radii(cdf, r_min, r_max) == pytest.approx(r, rel=1e-9)


def test_raw_stack_without_frames_is_refused(tmp_path):
    # A (0, H, W) stack once went through `sr` and left empty outputs behind.
    np.save(tmp_path / "none.npy", np.zeros((0, 8, 8)))
    with pytest.raises(InputError, match=r"none\.npy.*no frames"):
        read_raw(tmp_path / "none.npy")


def test_cmyk_images_are_read_as_light_not_as_ink(tmp_path):
    # imageio once handed a CMYK JPEG's ink planes over as RGBA: the "luminance"
    # correlated at -0.5 with the picture's. Ink becomes light: R = (1 - C)(1 - K).
    import tifffile
    from PIL import Image

    rng = np.random.default_rng(4)
    ink = rng.integers(0, 256, (24, 32, 4), dtype=np.uint8)
    Image.fromarray(ink, "CMYK").save(tmp_path / "ink.jpg", quality=100)
    expected = np.asarray(Image.open(tmp_path / "ink.jpg").convert("L"), float) / 255
    assert np.abs(read_image(tmp_path / "ink.jpg") - expected).max() < 2 / 255

    ink16 = rng.integers(0, 65536, (24, 32, 4), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "ink.tif", ink16, photometric="separated")
    c = ink16 / 65535.0
    rgb = (1 - c[..., :3]) * (1 - c[..., 3:])
    expected = rgb @ np.array([0.299, 0.587, 0.114])
    np.testing.assert_allclose(read_image(tmp_path / "ink.tif"), expected, atol=1e-5)


def test_min_is_white_tiffs_are_read_as_light_not_as_their_negative(tmp_path):
    # A MinIsWhite TIFF (scanners, fax: 0 = white) stores each code inverted; tifffile
    # hands them over as stored, so a picture came out as its negative and a frame's
    # counts as 255 - count. The capture reader (OpenImageIO) read them right.
    import tifffile

    light = np.random.default_rng(6).integers(0, 256, (24, 32), dtype=np.uint8)
    tifffile.imwrite(tmp_path / "white.tif", 255 - light, photometric="miniswhite")
    np.testing.assert_array_equal(read_raw(tmp_path / "white.tif"), light)
    np.testing.assert_allclose(read_image(tmp_path / "white.tif"), light / 255, atol=1e-7)
    assert np.array_equal(read_raw_image(tmp_path / "white.tif").data, light)
    tifffile.imwrite(tmp_path / "bits.tif", light > 127, photometric="miniswhite")
    np.testing.assert_array_equal(read_image(tmp_path / "bits.tif"), light <= 127)
    tifffile.imwrite(tmp_path / "float.tif", light / 255.0, photometric="miniswhite")
    with pytest.raises(InputError, match=r"float\.tif.*MinIsWhite"):
        read_image(tmp_path / "float.tif")


def test_a_12_bit_tiff_is_scaled_by_its_own_white(tmp_path):
    # A 12-bit TIFF holds codes up to 4095 in a uint16: divided by 65535 a training
    # image read 16 times too dark. Raw frames keep the codes as counts.
    import OpenImageIO as oiio

    codes = np.linspace(0, 4095, 24 * 32).astype(np.uint16).reshape(24, 32)
    path = str(tmp_path / "twelve.tif")
    spec = oiio.ImageSpec(32, 24, 1, "uint16")
    spec.attribute("oiio:BitsPerSample", 12)
    out = oiio.ImageOutput.create(path)
    assert out.open(path, spec) and out.write_image(codes[..., None] << 4)  # stored >> 4
    out.close()
    np.testing.assert_array_equal(read_raw(path), codes)
    np.testing.assert_allclose(read_image(path), codes / 4095, atol=1e-6)


@pytest.mark.parametrize("reader", [*READERS, "raw frames"])
def test_a_folder_is_named_as_a_folder(tmp_path, reader):
    # Readers once said "no such image file" of a folder that exists, or passed on
    # the decoders' "[Errno 21] Is a directory".
    with pytest.raises(InputError, match="is a folder, not an image file"):
        READERS.get(reader, read_raw)(tmp_path)


def test_a_tiff_orientation_tag_is_noted_and_the_pixels_kept_as_stored(tmp_path):
    import OpenImageIO as oiio

    path = tmp_path / "turned.tif"
    pixels = np.arange(12, dtype=np.uint16).reshape(3, 4)
    spec = oiio.ImageSpec(4, 3, 1, "uint16")
    spec.attribute("Orientation", 3)  # viewers show it rotated by 180 degrees
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(pixels[..., None])
    out.close()
    raw = read_raw_image(path)
    assert np.array_equal(raw.data, pixels)
    assert any("Orientation tag is 3" in n for n in raw.notes)


@pytest.mark.parametrize("reader", ["capture", "frame", "training image"])
@pytest.mark.parametrize("damage", ["header", "pixels"])
def test_a_damaged_png_is_refused_in_one_line_with_its_reason(
    good_files, tmp_path, capfd, reader, damage
):
    # libpng wrote "libpng error: IHDR: CRC error" to stderr itself, a second line
    # beside the one-line refusal; damaged pixel data was refused as "(ValueError: )"
    # or "could not read the pixels", its reason only on libpng's line.
    path, _ = good_files["png"]  # 16 bit: read through OpenImageIO
    data = bytearray(path.read_bytes())
    data[29 if damage == "header" else len(data) // 2] ^= 0xFF  # IHDR's CRC / the IDAT data
    damaged = tmp_path / "damaged.png"
    damaged.write_bytes(bytes(data))
    with pytest.raises(InputError) as refusal:
        READERS[reader](damaged)
    reason = "IHDR: CRC error" if damage == "header" else "IDAT: "
    assert str(damaged) in str(refusal.value) and reason in str(refusal.value)
    assert capfd.readouterr().err == ""


def test_a_pipe_named_like_an_image_is_refused_not_waited_on(tmp_path):
    # Opening a FIFO blocks until something writes to it: sr and evaluate hung for
    # ever on one named x.png. The capture reader refused it already.
    import os
    import signal

    os.mkfifo(tmp_path / "pipe.png")

    def hung(*args):
        raise TimeoutError("the reader waited on the pipe")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(10)
    try:
        for read in (read_image, read_raw):
            with pytest.raises(InputError, match=r"pipe\.png: is not a regular file"):
                read(tmp_path / "pipe.png")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def test_pillow_warns_of_nothing_on_stderr(tmp_path):
    # A PNG header of 100 Mpx (Pillow's "decompression bomb" warning) over a few
    # bytes, and a palette with byte transparency: Pillow's two-line warnings went
    # to stderr beside sr's and evaluate's one-line refusal, or beside the result.
    import struct
    import zlib

    from PIL import Image

    def chunk(kind, data):
        crc = struct.pack(">I", zlib.crc32(kind + data))
        return struct.pack(">I", len(data)) + kind + data + crc

    header = struct.pack(">IIBBBBB", 10000, 10000, 8, 0, 0, 0, 0)
    (tmp_path / "bomb.png").write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(bytes(100)))
        + chunk(b"IEND", b"")
    )
    grey = np.random.default_rng(7).integers(0, 256, (8, 8), dtype=np.uint8)
    Image.fromarray(grey, "L").convert("P").save(tmp_path / "clear.png", transparency=bytes(4))
    for read in (read_image, read_raw):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            with pytest.raises(InputError, match=r"bomb\.png: not a readable image.*truncated"):
                read(tmp_path / "bomb.png")
            scale = 255 if read is read_image else 1
            np.testing.assert_allclose(read(tmp_path / "clear.png"), grey / scale, atol=1e-6)
        assert [str(w.message) for w in caught] == []


def test_a_one_bit_image_is_black_and_white(tmp_path):
    from PIL import Image

    bits = np.array([[0, 255, 255], [255, 0, 0]], np.uint8)
    Image.fromarray(bits).convert("1").save(tmp_path / "bits.png")
    image = read_image(tmp_path / "bits.png")
    assert image.dtype == np.float32  # as every training image
    np.testing.assert_array_equal(image, bits / 255)


def test_images_no_reader_can_take_are_refused_naming_the_file(tmp_path):
    import tifffile

    tifffile.imwrite(tmp_path / "signed.tif", np.zeros((8, 8), np.int16))
    with pytest.raises(InputError, match=r"signed\.tif: unsupported pixel type int16"):
        read_image(tmp_path / "signed.tif")
    five = np.zeros((8, 8, 5), np.uint8)  # five samples a pixel: no grey, RGB or alpha
    tifffile.imwrite(tmp_path / "five.tif", five, photometric="minisblack", planarconfig="contig")
    with pytest.raises(InputError, match=r"five\.tif: expected a grayscale or RGB image"):
        read_image(tmp_path / "five.tif")
    with pytest.raises(InputError, match=r"five\.tif: expected a single-channel frame"):
        read_raw(tmp_path / "five.tif")
    # ink planes beside a fifth sample, or of signed integers: no R = (1 - C)(1 - K)
    tifffile.imwrite(tmp_path / "ink5.tif", five, photometric="separated", planarconfig="contig")
    tifffile.imwrite(tmp_path / "ink_signed.tif", np.zeros((8, 8, 4), np.int16),
                     photometric="separated")  # fmt: skip
    for name in ("ink5.tif", "ink_signed.tif"):
        with pytest.raises(InputError, match=rf"{name}: ink \(separated\) image"):
            read_image(tmp_path / name)
    for missing in ("gone.png", "gone.tif", "gone.jpg"):
        with pytest.raises(InputError, match=rf"{missing}: no such file"):
            read_image(tmp_path / missing)


def test_an_image_folder_must_be_a_folder(tmp_path):
    from psf_learn.images import read_folder

    write_image(tmp_path / "a.png", np.full((16, 20), 200, np.uint8))
    for path in (tmp_path / "gone", tmp_path / "a.png"):
        with pytest.raises(InputError, match=f"{path}: not a folder of images"):
            read_folder(path)


def test_raw_frames_must_be_finite_and_two_pixels_a_side(tmp_path):
    nan = np.ones((4, 4))
    nan[1, 2] = np.nan
    np.save(tmp_path / "nan.npy", nan)
    with pytest.raises(InputError, match=r"nan\.npy: raw frames contain NaN"):
        read_raw(tmp_path / "nan.npy")
    for shape in ((1, 8), (8, 1), (3, 8, 1)):
        np.save(tmp_path / "thin.npy", np.ones(shape))
        with pytest.raises(InputError, match=r"thin\.npy: frames of .* are too small"):
            read_raw(tmp_path / "thin.npy")
    np.save(tmp_path / "two.npy", np.ones((2, 2)))
    assert read_raw(tmp_path / "two.npy").shape == (2, 2)


def test_default_images_leave_out_a_photo_this_scikit_image_lacks(monkeypatch):
    # scikit-image versions ship different photos; a missing one is never downloaded
    from psf_learn import images

    monkeypatch.setattr(images, "_SKIMAGE_BUNDLED", ("no_such_photo", "camera"))
    names, imgs = images.default_images(n_dead_leaves=1, size=16)
    assert names == ["skimage:camera", "dead_leaves:0"]
    assert imgs[0].shape == (512, 512) and imgs[1].shape == (16, 16)


def test_a_missing_capture_is_named(tmp_path):
    with pytest.raises(InputError, match=re.escape("none.png: no such image file")):
        read_raw_image(tmp_path / "none.png")


def test_a_capture_that_is_no_file_says_what_it_is(tmp_path):
    # A pipe, a device, a dangling link and a link loop were each "no such image file".
    import os

    os.mkfifo(tmp_path / "pipe.png")
    os.symlink("/dev/zero", tmp_path / "zero.png")
    os.symlink(tmp_path / "gone.png", tmp_path / "dangling.png")
    os.symlink(tmp_path / "loop.png", tmp_path / "loop.png")
    for name, problem in (
        ("pipe.png", "is not a regular file"),
        ("zero.png", "is not a regular file"),
        ("dangling.png", "is a symbolic link to nothing"),
        ("loop.png", "is a symbolic link to nothing"),
    ):
        with pytest.raises(InputError, match=re.escape(f"{name}: {problem}")):
            read_raw_image(tmp_path / name)


def _grey_png(path, codes, bits):
    """Write a 1-, 2- or 4-bit greyscale PNG by hand (Pillow writes none of them but 1-bit)."""
    import struct
    import zlib

    def chunk(kind, data):
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    rows = b""
    for row in codes:
        text = "".join(format(int(v), f"0{bits}b") for v in row)
        text += "0" * (-len(text) % 8)
        rows += b"\0" + int(text, 2).to_bytes(len(text) // 8, "big")
    header = struct.pack(">IIBBBBB", codes.shape[1], codes.shape[0], bits, 0, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows))
        + chunk(b"IEND", b"")
    )  # fmt: skip


@pytest.mark.parametrize("bits", [1, 2, 4])
def test_counts_of_a_png_of_fewer_than_8_bits_are_its_codes(tmp_path, bits):
    # The readers widen them to 8 bits (a 4-bit 1 read 17, a 1-bit 1 read 255 as a
    # depth frame): counts are the codes stored. A capture of them is refused.
    codes = (np.arange(6 * 10).reshape(6, 10) % (1 << bits)).astype(np.uint8)
    path = tmp_path / f"c{bits}.png"
    _grey_png(path, codes, bits)
    np.testing.assert_array_equal(read_raw(path), codes)
    np.testing.assert_array_equal(read_frame(path), codes)
    np.testing.assert_allclose(read_image(path), codes / ((1 << bits) - 1), atol=1e-6)
    with pytest.raises(InputError, match=re.escape(f"c{bits}.png: {bits}-bit image")):
        read_raw_image(path)


def test_a_capture_of_fewer_than_8_bits_is_refused(tmp_path):
    # Widened to 8 bits by the reader, a 1-bit capture's every dot read saturated and
    # verify failed the plate (exit 1) for what the file held; CONVENTIONS: 8 or 16 bit.
    import tifffile
    from PIL import Image

    bits = np.arange(64).reshape(8, 8) % 3 == 0
    Image.fromarray(bits).save(tmp_path / "one.png")  # mode "1": a 1-bit PNG
    tifffile.imwrite(tmp_path / "one.tif", bits)  # BitsPerSample 1
    for name in ("one.png", "one.tif"):
        with pytest.raises(InputError, match=re.escape(f"{name}: 1-bit image; give an 8-")):
            read_raw_image(tmp_path / name)


def test_a_12_bit_tiff_capture_keeps_its_codes_and_full_scale(tmp_path):
    # OpenImageIO widens 12-bit samples to 16 bits (4095 -> 65535): the codes, their
    # step and the sensor's full scale are the file's own.
    import OpenImageIO as oiio

    codes = (np.arange(64 * 64).reshape(64, 64) * 7 % 4096).astype(np.uint16)
    path = tmp_path / "twelve.tif"
    spec = oiio.ImageSpec(64, 64, 1, "uint16")
    spec.attribute("oiio:BitsPerSample", 12)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image((codes << 4)[..., None])
    out.close()
    raw = read_raw_image(path)
    assert np.array_equal(raw.data, codes)
    assert raw.full_scale == 4095 and raw.quantum == 1
    assert any("12-bit samples" in n for n in raw.notes)
    # and as a depth frame, its counts (they read 16 times too many), as sr reads them
    np.testing.assert_array_equal(read_frame(path), codes)
    np.testing.assert_array_equal(read_raw(path), codes)


def test_a_capture_of_signed_integers_is_refused(tmp_path):
    import tifffile

    tifffile.imwrite(tmp_path / "signed.tif", np.zeros((8, 8), np.int32))
    with pytest.raises(
        InputError, match=re.escape("signed.tif: unsupported pixel format int; use 8/16")
    ):
        read_raw_image(tmp_path / "signed.tif")


def test_a_capture_too_large_for_memory_is_refused_plainly(good_files, monkeypatch):
    import OpenImageIO as oiio

    def out_of_memory(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(oiio.ImageInput, "read_image", out_of_memory)
    path, _ = good_files["png"]
    with pytest.raises(InputError, match="56 x 40 pixels do not fit in this machine's memory"):
        read_raw_image(path)


def test_a_colour_capture_is_refused_unless_its_channels_agree(tmp_path):
    from PIL import Image

    grey = np.random.default_rng(5).integers(0, 256, (8, 8), dtype=np.uint8)
    Image.fromarray(np.stack([grey] * 3, axis=-1), "RGB").save(tmp_path / "grey.png")
    assert np.array_equal(read_raw_image(tmp_path / "grey.png").data, grey)
    colour = np.stack([grey, grey, 255 - grey], axis=-1)
    Image.fromarray(colour, "RGB").save(tmp_path / "colour.png")
    with pytest.raises(InputError, match=re.escape("colour.png: 3-channel colour image")):
        read_raw_image(tmp_path / "colour.png")


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_a_float_capture_with_nan_or_infinite_pixels_is_refused(tmp_path, bad):
    image = np.ones((8, 8), np.float32)
    image[3, 4] = bad
    write_image(tmp_path / "bad.exr", image)
    with pytest.raises(InputError, match=re.escape("bad.exr: image has NaN or infinite pixels")):
        read_raw_image(tmp_path / "bad.exr")


def test_a_float_capture_near_the_largest_float_is_refused(tmp_path):
    # Values of 3.4e38 (float32's largest, where some writers put a clipped pixel)
    # overflowed the sums over a dot: numpy's RuntimeWarnings on stderr beside a
    # refusal, or a pass. 1e29 is read.
    image = np.ones((8, 8), np.float32)
    write_image(tmp_path / "ok.exr", image * np.float32(1e29))
    assert read_raw_image(tmp_path / "ok.exr").data.max() == np.float32(1e29)
    image[3, 4] = np.finfo(np.float32).max
    write_image(tmp_path / "big.exr", image)
    with pytest.raises(InputError, match=re.escape("big.exr: float pixels reach 3.4e+38")):
        read_raw_image(tmp_path / "big.exr")


def test_write_image_refuses_a_dtype_or_a_path_it_cannot_write(tmp_path):
    with pytest.raises(ValueError, match="needs uint8, uint16 or float32, got int64"):
        write_image(tmp_path / "a.png", np.zeros((4, 4), np.int64))
    for name in ("a.not-an-image-format", "nowhere/a.png"):
        with pytest.raises(InputError, match=re.escape(f"{name}: cannot write image")):
            write_image(tmp_path / name, np.zeros((4, 4), np.uint8))
        assert not (tmp_path / name).exists()
