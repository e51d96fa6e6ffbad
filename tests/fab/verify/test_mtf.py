"""Slanted-edge MTF against the analytic MTF of a Gaussian-blurred edge."""

import json

import numpy as np
import pytest
from scipy.special import erf

from doe.infra.cli import main
from fab.verify.capture import write_image
from fab.verify.mtf import EdgeNotFound, slanted_edge_mtf


def gaussian_edge(sigma, angle_deg, shape=(200, 160), low=20.0, high=220.0, noise=0.0, seed=0):
    """An edge blurred by a Gaussian of ``sigma`` px, sampled at pixel centres.

    Its MTF across the edge is exp(-2 pi^2 sigma^2 f^2) (f in cycles/pixel).
    """
    h, w = shape
    y, x = np.mgrid[0:h, 0:w].astype(float)
    t = np.tan(np.radians(angle_deg))
    d = (x - (w / 2 + 0.3) - t * (y - h / 2)) / np.hypot(1, t)
    img = low + (high - low) * 0.5 * (1 + erf(d / (np.sqrt(2) * sigma)))
    return img + np.random.default_rng(seed).normal(0, noise, img.shape)


def analytic_mtf(f, sigma):
    return np.exp(-2 * np.pi**2 * sigma**2 * f**2)


@pytest.mark.parametrize(
    "sigma, angle, transpose",
    [(1.0, 5.0, False), (2.0, -4.0, False), (0.7, 6.0, True), (1.5, 3.5, True)],
)
def test_mtf_of_gaussian_edge_matches_analytic(sigma, angle, transpose):
    img = gaussian_edge(sigma, angle, noise=0.3)
    if transpose:
        img = img.T[::-1]  # horizontal edge, dark side below
    r = slanted_edge_mtf(img, oversample=4)
    f = np.array(r["frequencies_cycles_per_pixel"])
    m = np.array(r["mtf"])
    sel = f <= 0.5
    assert np.max(np.abs(m[sel] - analytic_mtf(f[sel], sigma))) < 0.02
    mtf50 = np.sqrt(np.log(2) / (2 * np.pi**2)) / sigma
    assert r["mtf50_cycles_per_pixel"] == pytest.approx(mtf50, rel=0.03)
    assert r["edge_orientation"] == ("horizontal" if transpose else "vertical")
    assert abs(r["edge_angle_deg"]) == pytest.approx(abs(angle), abs=0.1)


def test_a_wide_region_does_not_read_a_lower_mtf50():
    # The line spread was windowed over the whole region: its noise roughened the MTF
    # until a dip crossed 0.5 early (mean -9 % over 480 px at a signal-to-noise of 20).
    sigma = 1.0
    mtf50 = np.sqrt(np.log(2) / (2 * np.pi**2)) / sigma
    for width in (120, 480, 960):
        found = [
            slanted_edge_mtf(gaussian_edge(sigma, 5, (100, width), 20, 220, 10, seed))[
                "mtf50_cycles_per_pixel"
            ]
            for seed in range(8)
        ]
        assert np.mean(found) == pytest.approx(mtf50, rel=0.03), width


def test_sharper_edge_has_higher_mtf50():
    a = slanted_edge_mtf(gaussian_edge(0.8, 5))["mtf50_cycles_per_pixel"]
    b = slanted_edge_mtf(gaussian_edge(1.6, 5))["mtf50_cycles_per_pixel"]
    assert a == pytest.approx(2 * b, rel=0.05)


def test_flat_image_has_no_edge():
    with pytest.raises(EdgeNotFound):
        slanted_edge_mtf(np.full((50, 50), 7.0))


@pytest.mark.parametrize("shape", [(7, 50), (50, 7), (8,)])
def test_a_region_smaller_than_8x8_is_refused(shape):
    with pytest.raises(EdgeNotFound, match="at least 8x8 pixels"):
        slanted_edge_mtf(np.zeros(shape))


@pytest.mark.parametrize("crop", [66, 67, 68])
def test_an_edge_nearer_than_4_px_to_the_border_is_refused(crop):
    # The edge of gaussian_edge(..., 5 deg) crosses row 0 at x = 80.3 - 100 tan(5 deg)
    # = 71.55, its point nearest the left border; cropped, it lies 71.55 - crop px from
    # column 0 along the row, cos(5 deg) times that across the edge.
    img = gaussian_edge(1.0, 5, noise=0.3)[:, crop:]
    reach = (80.3 - 100 * np.tan(np.radians(5)) - crop) * np.cos(np.radians(5))
    if reach < 4:
        with pytest.raises(EdgeNotFound, match="too close to the image border"):
            slanted_edge_mtf(img)
    else:
        assert slanted_edge_mtf(img)["edge_reach_px"] == pytest.approx(reach, abs=0.02)


def test_an_edge_seen_in_fewer_than_4_rows_is_refused():
    img = np.full((8, 16), 220.0)
    img[:3, 0] = 20.0  # the corner of a chart: the edge shows in rows 0 to 2 only
    with pytest.raises(EdgeNotFound, match="fewer than 4 rows show the edge"):
        slanted_edge_mtf(img)


def test_mtf_cli_writes_json_and_plot(tmp_path):
    img = np.clip(gaussian_edge(1.2, 5, high=3000, noise=2.0), 0, 65535).astype(np.uint16)
    write_image(tmp_path / "edge.png", img)
    assert main(["mtf", str(tmp_path / "edge.png"), "--out", str(tmp_path / "o")]) == 0
    result = json.loads((tmp_path / "o" / "mtf.json").read_text())
    assert result["mtf"][0] == pytest.approx(1.0)
    assert result["mtf50_cycles_per_pixel"] == pytest.approx(
        np.sqrt(np.log(2) / (2 * np.pi**2)) / 1.2, rel=0.05
    )
    assert (tmp_path / "o" / "mtf.png").stat().st_size > 0
    # Refuses to overwrite without --force.
    assert main(["mtf", str(tmp_path / "edge.png"), "--out", str(tmp_path / "o")]) == 2


def test_mtf_cli_reports_how_the_file_was_read(tmp_path, capsys):
    # 12-bit data MSB-aligned in 16 bits is shifted down: mtf once said nothing of it.
    img = np.clip(gaussian_edge(1.2, 5, high=3000, noise=2.0), 0, 4095).astype(np.uint16) << 4
    write_image(tmp_path / "edge.png", img)
    assert main(["mtf", str(tmp_path / "edge.png"), "--out", str(tmp_path / "o")]) == 0
    notes = json.loads((tmp_path / "o" / "mtf.json").read_text())["notes"]
    assert len(notes) == 1 and "MSB-aligned" in notes[0]
    assert notes[0] in capsys.readouterr().err


@pytest.mark.parametrize("oversample", ["0", "17"])
def test_mtf_cli_refuses_an_oversampling_out_of_range(tmp_path, capsys, oversample):
    write_image(tmp_path / "edge.png", gaussian_edge(1.2, 5).astype(np.uint8))
    out = tmp_path / "o"
    argv = ["mtf", str(tmp_path / "edge.png"), "--out", str(out), "--oversample", oversample]
    assert main(argv) == 2
    assert f"--oversample: must be 1..16, got {oversample}" in capsys.readouterr().err
    assert not out.exists()


def test_mtf_cli_flat_image_exits_2(tmp_path, capsys):
    write_image(tmp_path / "flat.tif", np.full((40, 40), 100, np.uint16))
    assert main(["mtf", str(tmp_path / "flat.tif"), "--out", str(tmp_path / "o")]) == 2
    assert "flat.tif" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_edge_sharper_than_the_grid_has_mtf50_beyond_the_range(tmp_path, capsys):
    # Analytic MTF50 of sigma 0.15 px is 1.25 cycles/pixel, beyond the measured 1.0:
    # MTF50 is None (this once crashed the plot title), never NaN.
    r = slanted_edge_mtf(gaussian_edge(0.15, 5))
    f, m = np.array(r["frequencies_cycles_per_pixel"]), np.array(r["mtf"])
    measured = np.isfinite(m)
    assert r["mtf50_cycles_per_pixel"] is None
    assert np.all(m[measured] >= 0.5) and f[measured].max() > 0.9
    img = np.clip(gaussian_edge(0.15, 5, high=3000), 0, 65535).astype(np.uint16)
    write_image(tmp_path / "sharp.png", img)
    assert main(["mtf", str(tmp_path / "sharp.png"), "--out", str(tmp_path / "o")]) == 0
    assert "MTF50 >" in capsys.readouterr().out
    assert json.loads((tmp_path / "o" / "mtf.json").read_text())["mtf50_cycles_per_pixel"] is None


@pytest.mark.parametrize("noise", [4.0, 8.0])
def test_noise_does_not_bias_the_edge_angle_or_the_mtf(noise):
    # Clipped at zero, the row derivative's noise pulled every centroid to the middle:
    # at 8 DN on a 200 DN step the angle read 3.4 deg (5 true) and MTF50 72 % low.
    true50 = np.sqrt(np.log(2) / 2) / np.pi  # exp(-2 pi^2 f^2) = 1/2 at sigma 1
    angles, mtf50 = [], []
    for seed in range(4):
        r = slanted_edge_mtf(gaussian_edge(1.0, 5, shape=(400, 400), noise=noise, seed=seed))
        angles.append(r["edge_angle_deg"])
        mtf50.append(r["mtf50_cycles_per_pixel"])
    assert np.mean(angles) == pytest.approx(5.0, abs=0.02)
    assert np.mean(mtf50) == pytest.approx(true50, rel=0.03)


def test_a_region_with_two_opposite_edges_is_refused_as_such():
    # A bar or a chart's whole square once read "the image is flat: no edge".
    edge = gaussian_edge(1.0, 5, shape=(200, 240))
    bar = 100 + edge[:, 40:200] - edge[:, 0:160]  # rises at column 80, falls at 120
    with pytest.raises(EdgeNotFound, match="edges of both signs"):
        slanted_edge_mtf(bar)


@pytest.mark.parametrize("size, small", [(16, True), (24, True), (96, False)])
def test_a_region_too_small_for_the_blur_is_flagged(size, small, tmp_path, capsys):
    # sigma 2 px: MTF50 reads 27 % high in 16 x 16, 10 % in 24 x 24, 0.4 % in 96 x 96.
    img = gaussian_edge(2.0, 5, shape=(size, size))
    r = slanted_edge_mtf(img)
    assert r["region_too_small"] is small
    assert r["edge_rise_px"] == pytest.approx(2.563 * 2.0, rel=0.15)  # 10-90 % of erf
    write_image(tmp_path / "edge.tif", img.astype(np.float32) / 255)
    assert main(["mtf", str(tmp_path / "edge.tif"), "--out", str(tmp_path / "o")]) == 0
    assert ("overstates the MTF; give a larger region" in capsys.readouterr().err) is small


# 8: above MIN_EDGE_SNR (5) times the noise; catches the two sides' noises summed, not averaged
@pytest.mark.parametrize("contrast, found", [(0.0, False), (4.0, False), (8.0, True), (30.0, True)])
def test_edge_must_stand_out_of_the_noise(contrast, found):
    # Pixel noise 1: a pure-noise image once passed as an edge with MTF50 NaN.
    img = gaussian_edge(1.0, 5, low=100.0, high=100.0 + contrast, noise=1.0, seed=3)
    if found:
        assert slanted_edge_mtf(img)["mtf50_cycles_per_pixel"] > 0
    else:
        with pytest.raises(EdgeNotFound, match="noise"):
            slanted_edge_mtf(img)


@pytest.mark.parametrize("angle", [0.0, 45.0])
def test_edge_without_sub_pixel_phases_is_refused_with_its_angle(angle):
    # A 45 deg edge once got "too little slant": every row then crosses the grid
    # at the same phase, as an axis-aligned edge does.
    with pytest.raises(EdgeNotFound, match=f"{angle:.1f} deg off the pixel axis"):
        slanted_edge_mtf(gaussian_edge(1.0, angle, shape=(120, 240)))


@pytest.mark.parametrize(
    "name, scale, offset, dark, bright",
    [
        ("black.png", 1.0, -100.0, True, False),  # offset subtracted: dark side cut at 0
        ("white.tif", 1 / 200, 0.0, False, True),  # float, clipped at 1.0
        ("noisy.tif", 1 / 300, 0.0, False, False),  # float, unclipped
        ("both.tif", 1 / 200, -0.35, True, True),  # float, clipped at 0.15 and 1.0
        ("noisy.png", 1.0, 0.0, False, False),
    ],
)
def test_an_edge_clipped_on_either_side_is_flagged(
    tmp_path, capsys, name, scale, offset, dark, bright
):
    # A dark side cut at code 0, or a float file clipped at 1.0, read MTF50 45 % high
    # and silently: only the full-scale code counted. A float file clipped on both
    # sides named only the side with more pixels at its extreme.
    edge = (gaussian_edge(1.0, 5, noise=2.0, seed=3) + offset) * scale
    if name.endswith(".png"):
        edge = np.clip(np.round(edge), 0, 255).astype(np.uint8)
        at_dark, at_bright = edge == 0, edge == 255
    else:
        floor = 0.15 if dark else -np.inf
        edge = np.clip(edge, floor, 1.0).astype(np.float32)
        at_dark, at_bright = edge == np.float32(floor), edge == 1.0
    write_image(tmp_path / name, edge)
    assert main(["mtf", str(tmp_path / name), "--out", str(tmp_path / "out")]) == 0
    result = json.loads((tmp_path / "out" / "mtf.json").read_text())
    assert result["clipped_dark_pixels"] == (np.count_nonzero(at_dark) if dark else 0)
    assert result["saturated_pixels"] == (np.count_nonzero(at_bright) if bright else 0)
    assert (result["clipped_dark_pixels"] > 1000) == dark
    assert (result["saturated_pixels"] > 1000) == bright
    err = capsys.readouterr().err
    assert ("keep the camera's black level" in err) == dark
    assert ("shorten the exposure" in err) == bright


def test_clipped_edge_is_flagged(tmp_path, capsys):
    # Clipping flattens the bright side of the edge and overstates the MTF; the
    # command says so and records the clipped pixels.
    edge = gaussian_edge(1.2, 5, high=300.0)
    for name, image, clipped in (
        ("clean.png", edge * 0.8, 0),
        ("clipped.png", edge, int(np.count_nonzero(np.round(edge) >= 255))),
    ):
        write_image(tmp_path / name, np.clip(np.round(image), 0, 255).astype(np.uint8))
        out = tmp_path / name.replace(".png", "")
        assert main(["mtf", str(tmp_path / name), "--out", str(out)]) == 0
        assert json.loads((out / "mtf.json").read_text())["saturated_pixels"] == clipped
        err = capsys.readouterr().err
        assert ("shorten the exposure" in err) == bool(clipped)
    assert clipped > 1000


@pytest.mark.parametrize("slope", [1 / 10, 1 / 4])
@pytest.mark.parametrize("sigma", [0.7, 1.0])
def test_an_edge_at_a_simple_fraction_slope_reads_its_mtf50(slope, sigma):
    # Such an edge puts its samples at a few fixed places in each bin; read at the bins'
    # centres, MTF50 was 2.7 % high at slope 1/10 and 2.4 % low at 1/4 (sigma 0.7 px).
    r = slanted_edge_mtf(gaussian_edge(sigma, np.degrees(np.arctan(slope))))
    mtf50 = np.sqrt(np.log(2) / (2 * np.pi**2)) / sigma
    assert r["mtf50_cycles_per_pixel"] == pytest.approx(mtf50, rel=0.012)


def test_a_falling_edge_reads_the_mtf_of_the_rising_one():
    # catches a line spread left negative for a bright-to-dark edge: noiseless, it read
    # "no contrast"; the edge mirrored left to right has the same MTF
    sigma = 1.0
    r = slanted_edge_mtf(gaussian_edge(sigma, 5)[:, ::-1])
    f, m = np.array(r["frequencies_cycles_per_pixel"]), np.array(r["mtf"])
    sel = f <= 0.5
    assert np.max(np.abs(m[sel] - analytic_mtf(f[sel], sigma))) < 0.02
    assert r["mtf50_cycles_per_pixel"] == pytest.approx(
        np.sqrt(np.log(2) / (2 * np.pi**2)) / sigma, rel=0.03
    )


def test_rows_where_the_edge_is_hidden_are_left_out_of_the_line_fit():
    # catches fitting every row: the noise centroids of rows above the chart's corner
    # (here 40 rows of flat bright field) pulled the line off the edge
    img = gaussian_edge(1.0, 5, noise=1.0, seed=2)
    img[:40] = 220.0 + np.random.default_rng(5).normal(0, 1.0, (40, img.shape[1]))
    r = slanted_edge_mtf(img)
    assert r["rows_used"] == img.shape[0] - 40
    assert r["edge_angle_deg"] == pytest.approx(5.0, abs=0.1)
    assert r["mtf50_cycles_per_pixel"] == pytest.approx(
        np.sqrt(np.log(2) / (2 * np.pi**2)), rel=0.03
    )


def test_mtf_refuses_an_edge_stored_with_loss(tmp_path, capsys):
    # JPEG's 8 x 8 blocks ring along an edge: its MTF is the codec's as much as the lens's.
    from PIL import Image

    img = np.clip(gaussian_edge(1.2, 5, high=220, noise=2.0), 0, 255).astype(np.uint8)
    Image.fromarray(img).save(tmp_path / "edge.jpg", quality=90)
    assert main(["mtf", str(tmp_path / "edge.jpg"), "--out", str(tmp_path / "o")]) == 2
    assert "edge.jpg: JPEG image; give the capture as" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_measure_mtf_as_a_library_returns_the_record_and_writes_it_when_asked(tmp_path):
    from doe.infra.errors import InputError
    from fab.verify.mtf_check import MTF_FILES, measure_mtf, save_mtf

    img = np.clip(gaussian_edge(1.2, 5, high=300.0), 0, 255).astype(np.uint8)
    write_image(tmp_path / "edge.png", img)
    result = measure_mtf(tmp_path / "edge.png")
    assert result.out is None and result.files == () and not (tmp_path / "o").exists()
    assert result.mtf50 == slanted_edge_mtf(img)["mtf50_cycles_per_pixel"]  # clipped: high
    assert result.mtf50_text == f"{result.mtf50:.4f} cycles/pixel"
    assert result.record["image"] == "edge.png" and result.record["saturated_pixels"] > 1000
    (clipped,) = result.messages  # said, never printed by the library
    assert clipped.startswith(f"warning: {tmp_path / 'edge.png'}: ") and "shorten" in clipped
    saved = save_mtf(result, tmp_path / "o")
    assert saved.files == tuple(tmp_path / "o" / name for name in MTF_FILES)
    assert json.loads((tmp_path / "o" / "mtf.json").read_text())["mtf"] == result.record["mtf"]
    with pytest.raises(InputError) as refused:
        measure_mtf(tmp_path / "edge.png", out=tmp_path / "o")  # exists: not overwritten
    assert "mtf.json" in str(refused.value)
    write_image(tmp_path / "flat.tif", np.full((40, 40), 100, np.uint16))
    with pytest.raises(InputError) as refused:
        measure_mtf(tmp_path / "flat.tif")
    assert refused.value.source == str(tmp_path / "flat.tif")
