"""Reading gated cubes, frame folders and IRFs; writing 16-bit frames."""

import subprocess
import sys
import types

import numpy as np
import pytest

from doe.infra.errors import InputError
from psf_learn.cubes import read_cube, write_frame_png16


@pytest.mark.parametrize(
    "name",
    ["shift_{k:03d}.png", "shift_{k}.png", "gate_{t:g}ns.png", "t_{s}ps.png", "frame-{k}.png"],
)
def test_frame_folder_is_read_as_uint16_in_name_order(tmp_path, name):
    # Unpadded numbers count as numbers: shift_2 comes before shift_10, and a gate delay
    # written as a decimal is one number: gate_0.02ns before gate_0.1ns before gate_0.12ns.
    # A delay's sign counts where the names differ by it (t_-20ps before t_0ps; they were
    # sorted 0, 20, ..., -20, -40), and a dash every name has is no sign (frame-10).
    rng = np.random.default_rng(13)
    cube = rng.integers(0, 4000, size=(5, 7, 12)).astype(np.uint16)
    folder = tmp_path / "frames"
    folder.mkdir()
    for k in range(cube.shape[-1]):
        write_frame_png16(
            folder / name.format(k=k, t=0.02 * k, s=20 * (k - 5)), cube[..., k] / 65535.0
        )
    (folder / "._shift_000.png").write_bytes(b"\x00\x05\x16\x07 macOS metadata")
    np.testing.assert_array_equal(read_cube(folder), cube.astype(np.float64))


def test_a_cube_needs_its_fewest_samples_and_no_negative_counts():
    from psf_learn.cubes import check_cube

    ones = np.ones((2, 3, 4))
    assert check_cube(ones, "c.npy").shape == (2, 3, 4)  # 4 samples fit a return
    with pytest.raises(InputError, match="T >= 4"):
        check_cube(ones[..., :3], "c.npy")
    assert check_cube(ones[..., :1], "c.npy", min_samples=1).shape == (2, 3, 1)
    with pytest.raises(InputError, match="negative counts"):  # integers too
        check_cube(-np.ones((2, 3, 4), np.int32), "c.npy")


def test_an_irf_is_read_as_one_row_and_needs_light(tmp_path):
    from psf_learn.cubes import read_irf

    irf = np.exp(-0.5 * (np.arange(20) - 8.0) ** 2)
    np.save(tmp_path / "row.npy", irf[None, :])  # saved as a (1, T) row: one response
    np.testing.assert_array_equal(read_irf(tmp_path / "row.npy"), irf)
    np.save(tmp_path / "dark.npy", np.zeros(20))
    with pytest.raises(InputError, match=r"dark\.npy.*no positive sample"):
        read_irf(tmp_path / "dark.npy")


def test_frames_are_written_rounded_to_the_nearest_16_bit_code(tmp_path):
    import OpenImageIO as oiio

    codes = np.array([[0.0, 0.4, 0.6, 1.5], [100.49, 100.51, 65534.6, 65535.0]])
    write_frame_png16(tmp_path / "f.png", codes / 65535)
    read = oiio.ImageInput.open(str(tmp_path / "f.png"))
    got = read.read_image(0, 0, 0, 1, "uint16")[..., 0]
    read.close()
    np.testing.assert_array_equal(got, [[0, 0, 1, 2], [100, 101, 65535, 65535]])


def write_frame(path, array, fmt):
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(array.shape[1], array.shape[0], array.shape[2], fmt)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(array)
    out.close()


def test_frame_folder_8bit_tiff_and_bad_folders(tmp_path):
    import OpenImageIO as oiio

    cube = np.random.default_rng(14).integers(0, 256, size=(3, 4, 5)).astype(np.uint8)
    good = tmp_path / "good"
    good.mkdir()
    for k in range(5):
        write_frame(good / f"{k}.tif", cube[..., k][:, :, None], oiio.UINT8)
    np.testing.assert_array_equal(read_cube(good), cube)
    # An RGB frame, a frame of another size, an empty folder: exit 2 naming the file.
    rgb = tmp_path / "rgb"
    rgb.mkdir()
    for k in range(4):
        write_frame(rgb / f"{k}.png", np.zeros((3, 4, 3), np.uint8), oiio.UINT8)
    sizes = tmp_path / "sizes"
    sizes.mkdir()
    for k in range(4):
        write_frame(sizes / f"{k}.png", np.zeros((3, 4 + (k == 2), 1), np.uint8), oiio.UINT8)
    # A float frame among 16-bit counts (once stacked as if both were counts).
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for k in range(4):
        frame = np.full((3, 4, 1), 0.5 if k == 3 else 2000, np.float32 if k == 3 else np.uint16)
        write_frame(mixed / f"{k}.tif", frame, oiio.FLOAT if k == 3 else oiio.UINT16)
    # A float frame with NaN or negative counts (the folder was named, not the frame).
    bad = {}
    for name, value in (("nan", np.nan), ("negative", -90.0)):
        bad[name] = tmp_path / name
        bad[name].mkdir()
        for k in range(4):
            frame = np.full((3, 4, 1), value if k == 1 else 5.0, np.float32)
            write_frame(bad[name] / f"s_{k}.tif", frame, oiio.FLOAT)
    empty = tmp_path / "empty"
    empty.mkdir()
    for folder, culprit in (
        (rgb, "0.png"),
        (sizes, "2.png"),
        (mixed, "3.tif"),
        (bad["nan"], "s_1.tif: frame contains 12 NaN"),
        (bad["negative"], "s_1.tif: frame has negative counts"),
        (empty, "empty"),
    ):
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "doe",
                "depth",
                str(folder),
                "--out",
                str(tmp_path / "o"),
            ],
            capture_output=True,
            text=True,
        )
        assert proc.returncode == 2 and culprit in proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_a_cube_path_must_be_an_npy_file_or_a_folder_of_frames(tmp_path):
    import OpenImageIO as oiio

    with pytest.raises(InputError, match=r"gone\.npy: no such file or folder"):
        read_cube(tmp_path / "gone.npy")
    write_frame_png16(tmp_path / "frame.png", np.zeros((3, 4)))  # one frame, not the folder
    with pytest.raises(InputError, match=r"frame\.png: a cube must be a \.npy file or a folder"):
        read_cube(tmp_path / "frame.png")
    wide = tmp_path / "uint32"
    wide.mkdir()
    for k in range(4):
        write_frame(wide / f"{k}.tif", np.zeros((3, 4, 1), np.uint32), oiio.UINT32)
    with pytest.raises(InputError, match=r"0\.tif: unsupported pixel type uint"):
        read_cube(wide)


def test_an_irf_must_be_a_finite_row_of_numbers(tmp_path):
    from psf_learn.cubes import read_irf

    for name, irf, why in (
        ("mask.npy", np.ones(8, bool), "IRF must be numeric, got dtype bool"),
        (
            "table.npy",
            np.ones((3, 8)),
            r"IRF must be 1-D with at least 4 samples, got shape \(3, 8\)",
        ),
        ("short.npy", np.ones(3), "IRF must be 1-D with at least 4 samples"),
        ("inf.npy", np.array([0.0, 1.0, np.inf, 1.0]), "IRF contains NaN or infinite values"),
    ):
        np.save(tmp_path / name, irf)
        with pytest.raises(InputError, match=rf"{name.replace('.', '[.]')}: {why}"):
            read_irf(tmp_path / name)


def test_a_frame_that_cannot_be_written_raises_an_oserror_naming_it(tmp_path, monkeypatch):
    import OpenImageIO as oiio

    with pytest.raises(OSError, match=r"cannot write .*frame\.xyz: .*could not find a format"):
        write_frame_png16(tmp_path / "frame.xyz", np.zeros((2, 2)))
    # no such folder: the reason was left out ("cannot write .../frame.png: ")
    with pytest.raises(OSError, match=r"cannot write .*gone/frame\.png: Could not open file"):
        write_frame_png16(tmp_path / "gone" / "frame.png", np.zeros((2, 2)))

    class FullDisk:  # the header written, the pixels refused
        closed = False

        def open(self, path, spec):
            return True

        def write_image(self, data):
            return False

        def geterror(self):
            return "No space left on device"

        def close(self):
            FullDisk.closed = True

    monkeypatch.setattr(oiio, "ImageOutput", types.SimpleNamespace(create=lambda p: FullDisk()))
    with pytest.raises(OSError, match=r"cannot write .*full\.png: No space left on device"):
        write_frame_png16(tmp_path / "full.png", np.zeros((2, 2)))
    assert FullDisk.closed
