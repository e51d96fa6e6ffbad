"""Every mask image and figure shows etched pixels white and says so (fab.package.polarity).

The report's captions are checked in test_report.py (it writes a report anyway).
"""

import json

import numpy as np
import pytest

from doe.infra.png import png_text, save_png
from fab.package import figures
from fab.package.layer_images import read_image, write_layer_images
from fab.package.masks import masks_from_levels
from fab.package.polarity import POLARITY

PITCH_NM = 5000


def etched_by(levels, n_levels, j):
    """Whether mask j (0 = deepest, exposed first) etches each pixel: bit j of L-1-level."""
    bits = int(np.log2(n_levels))
    return ((n_levels - 1 - levels.astype(int)) >> (bits - 1 - j)) & 1 == 1


def tiff_description(path):
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    try:
        return inp.spec().getattribute("ImageDescription")
    finally:
        inp.close()


@pytest.mark.parametrize("n_levels", [4, 8])
def test_layer_images_are_white_where_etched_and_say_so(tmp_path, n_levels):
    n = 8
    levels = np.random.default_rng(n_levels).integers(0, n_levels, (n, n)).astype(np.uint8)
    masks = masks_from_levels(levels, n_levels, 100e-9)
    plate_half = aperture_half = n * PITCH_NM // 2  # one tile, no margin: pixel for pixel
    write_layer_images(tmp_path, masks, (1, 1), PITCH_NM, plate_half, aperture_half)
    for j, mk in enumerate(masks):
        etched = etched_by(levels, n_levels, j)
        assert etched.any() and not etched.all()
        tile = read_image(tmp_path / f"{mk.name}_tile.tif")
        assert np.all(tile[etched] == 255) and np.all(tile[~etched] == 0)  # white = etched
        plate = read_image(tmp_path / f"{mk.name}_plate.png").astype(int)
        inner = plate[1:-1, 1:-1]  # the outermost ring carries the grey frames
        assert np.all(inner[etched[1:-1, 1:-1]] == 255) and np.all(inner[~etched[1:-1, 1:-1]] == 0)
        assert POLARITY in tiff_description(tmp_path / f"{mk.name}_tile.tif")
        assert POLARITY in png_text(tmp_path / f"{mk.name}_plate.png")["Description"]
        assert POLARITY == "white = etched, black = not etched"


def test_mask_figure_draws_etched_white_with_a_labelled_colour_bar(
    tmp_path, saved_figures, colour_at
):
    levels = np.random.default_rng(1).integers(0, 4, (6, 6)).astype(np.uint8)
    masks = masks_from_levels(levels, 4, 100e-9)
    pitch = PITCH_NM * 1e-9
    path = tmp_path / "masks.png"
    figures.mask_bitmaps(path, [m.bitmap for m in masks], [m.name for m in masks], [1, 2], pitch)
    fig = saved_figures[-1]
    assert POLARITY in fig.get_suptitle() and POLARITY in png_text(path)["Description"]
    bar = [ax for ax in fig.axes if not ax.images]  # the colour bar's axes
    assert [t.get_text() for t in bar[0].get_yticklabels()] == ["not etched", "etched"]
    for j, ax in enumerate(a for a in fig.axes if a.images):
        etched = etched_by(levels, 4, j)
        for r, c in [tuple(np.argwhere(etched)[0]), tuple(np.argwhere(~etched)[0])]:
            x, y = (c + 0.5) * PITCH_NM / 1000, (6 - r - 0.5) * PITCH_NM / 1000  # um
            want = 255 if etched[r, c] else 0
            assert np.abs(colour_at(ax, x, y) - want).max() < 40


def test_level_map_colour_bar_names_the_etched_end(tmp_path, saved_figures):
    levels = np.arange(16, dtype=np.uint8).reshape(4, 4) % 8
    figures.level_map(tmp_path / "levels.png", levels, 8, 5e-6)
    labels = [ax.get_ylabel() for ax in saved_figures[-1].axes]
    assert "level (0 = deepest etch, 7 = unetched)" in labels


def test_run_index_captions_each_figure_with_its_description(tmp_path):
    import types

    from matplotlib.figure import Figure

    from fab.run.summary import write_index

    fab = tmp_path / "fab"
    fab.mkdir()
    save_png(Figure(figsize=(1, 1)), fab / "M1_plate.png", description=f"M1: {POLARITY}")
    save_png(Figure(figsize=(1, 1)), fab / "other.png")
    files = {"M1_plate.png": "x", "other.png": "y"}
    (tmp_path / "run_state.json").write_text(json.dumps({"fab": {"files": files}}))
    write_index(tmp_path, types.SimpleNamespace(name="d", description=""), ["fab"])
    page = (tmp_path / "index.html").read_text()
    assert f"<figcaption>fab/M1_plate.png: M1: {POLARITY}</figcaption>" in page
    assert "<figcaption>fab/other.png: other.png</figcaption>" in page
