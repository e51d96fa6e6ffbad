"""The plate as built (doe.aperture) against closed forms and an independent FFT of the
plate as KLayout reads it back from the GDS."""

import numpy as np
import pytest

from doe import fraunhofer
from doe.aperture import aperture_levels, as_built, order_window
from fab.package.masks import masks_from_levels
from layouts.gds import build_library, write_gds
from layouts.plate_plan import array_origin_nm, plan_pattern
from layouts.plate_raster import aperture_match

L, N, K, PITCH = 4, 12, 5, 5000
TILE = N * PITCH


def _plate(tiles, aperture, mode):
    origin = array_origin_nm((tiles, tiles), N, PITCH)
    return plan_pattern(N, PITCH, (tiles, tiles), origin, aperture, mode)


def _levels(seed=0):
    return np.random.default_rng(seed).integers(0, L, (N, N)).astype(np.uint8)


def test_whole_tiles_filling_the_aperture_give_the_tile_model():
    levels = _levels()
    target, _ = fraunhofer.simulate_levels(levels, L, K)
    got = as_built(levels, L, _plate(3, 3 * TILE, "fill"), target)
    want = fraunhofer.plate_quality(fraunhofer.level_phase(levels, L), target)
    assert got.efficiency == pytest.approx(want["efficiency"], rel=1e-12)
    assert got.correlation == pytest.approx(want["correlation"], rel=1e-12)
    assert got.rmse == pytest.approx(want["rmse"], rel=1e-9, abs=1e-14)
    assert got.patterned_fraction == 1.0 and got.pixels == 36


def test_plain_glass_adds_its_light_to_the_zero_order():
    # an unetched tile (level 0 everywhere) amid glass (level L - 1): only the zero order
    # is lit, with amplitude f + (1 - f) exp(2 pi i (L - 1) / L) over an aperture that is
    # a fraction f pattern
    levels = np.zeros((N, N), np.uint8)
    plate = _plate(3, round(3.3 * TILE), "glass")
    window = order_window(levels, L, plate, K)
    rows = cols = 40  # pixel centres inside 3.3 tiles of 12 pixels
    f = 36 * 36 / (rows * cols)
    glass = np.exp(2j * np.pi * (L - 1) / L)
    assert window[K // 2, K // 2] == pytest.approx(abs(f + (1 - f) * glass) ** 2, rel=1e-12)


def _fft_window(level_map, points, spacing=None):
    """Independent: zero-pad the plate to N x C pixels (C bins per order spacing, C = B
    by default, B odd), FFT, sum each order's B x B bins around it (B = 1: the bin on the
    order), with the square pixel's sinc^2."""
    h, w = level_map.shape
    spacing = spacing or points
    m = N * spacing
    field = np.zeros((m, m), complex)
    field[:h, :w] = np.exp(2j * np.pi * level_map / L)
    power = np.abs(np.fft.fft2(field)) ** 2
    env = np.sinc(np.fft.fftfreq(m)) ** 2
    power *= np.outer(env, env)
    half = points // 2
    orders = (np.arange(K) - K // 2) * spacing
    idx = (orders[:, None] + np.arange(-half, half + 1)[None, :]).ravel() % m
    cells = power[np.ix_(idx, idx)].reshape(K, points, K, points).sum(axis=(1, 3))
    # Parseval: the light through the aperture is h w; an order's point power is its
    # amplitude over h w squared, a cell's power its bins over h w (N B)^2
    return cells / (h * w) / (h * w if points == 1 else (N * points) ** 2)


@pytest.mark.parametrize("mode", ["fill", "glass"])
def test_an_fft_of_the_klayout_rasterised_plate_agrees(tmp_path, mode):
    levels = _levels(seed=4)
    aperture = round(3.3 * TILE)
    masks = masks_from_levels(levels, L, 100e-9)
    lib, info = build_library(masks, PITCH, (3, 3), "ab", aperture, marks=False, mode=mode)
    write_gds(lib, tmp_path / "p.gds")
    _, written, _ = aperture_match(tmp_path / "p.gds", info.plate_cell, masks, levels, info.plate)
    assert np.array_equal(written, aperture_levels(levels, L, info.plate))
    target, _ = fraunhofer.simulate_levels(levels, L, K)
    got = as_built(levels, L, info.plate, target)
    fft = _fft_window(written.astype(float), 1, spacing=7)
    assert np.allclose(got.psf, fft / fft.sum(), rtol=0, atol=1e-12)
    assert got.efficiency == pytest.approx(fft.sum(), rel=1e-10)
    assert got.zero_order == pytest.approx(fft[K // 2, K // 2], rel=1e-10)
    points = 13  # the cells' midpoints fall on the bins of an N x 13 FFT
    cells = order_window(levels, L, info.plate, K, points=points)
    assert np.allclose(cells, _fft_window(written.astype(float), points), rtol=1e-9, atol=1e-15)
    if mode == "glass":  # plain glass dims the pattern's orders and feeds the zero order
        tile = fraunhofer.plate_quality(fraunhofer.level_phase(levels, L), target)
        assert got.correlation < tile["correlation"] and got.missed
