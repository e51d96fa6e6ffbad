"""Tests of fab.plate.basis: the plate model's window with its parts precomputed for fits,
against the model itself and against a supersampled plate."""

import numpy as np
import pytest

from doe.fraunhofer import order_amplitudes, pixel_envelope, window_indices
from fab.package.masks import masks_from_levels
from fab.plate.basis import ShiftedMaskWindows, code_windows
from fab.plate.model import (
    PlateFaults,
    code_phases,
    level_plate_model,
    plate_far_field,
    plate_model,
    plate_phase,
    window_amplitudes,
)

N, K, L = 24, 7, 8
REACH_PX = 2.5  # as far as verify's overlay fit searches


@pytest.fixture(scope="module")
def levels():
    return np.random.default_rng(3).integers(0, L, (N, N)).astype(np.uint8)


@pytest.fixture(scope="module")
def shifted(levels):
    """The plate with mask j shifted, for each mask."""
    plate = level_plate_model(levels, L, K)
    return [ShiftedMaskWindows(plate, j, REACH_PX) for j in range(3)]


def one_mask_overlay(mask, dx, dy):
    return tuple((dx, dy) if j == mask else (0.0, 0.0) for j in range(3))


def supersampled_window(levels, mask, dx, dy, supersample, etch_errors=()):
    """The window orders of a plate with ``mask`` shifted by (dx, dy) mask pixels (and its
    etches off by ``etch_errors``), sampled ``supersample`` times finer."""
    faults = PlateFaults(etch_errors=etch_errors, overlay=one_mask_overlay(mask, dx, dy))
    orders = plate_far_field(plate_phase(levels, L, faults, 1.0, supersample))
    m = np.arange(K) - K // 2
    return orders(m[:, None], m[None, :])


@pytest.mark.parametrize("mask", [0, 1, 2])
@pytest.mark.parametrize(
    "shift", [(0.25, 0.0), (0.0, -0.5), (1.75, -1.25), (-2.0, 0.75), (1.0, 1.0), (-0.2, 0.6)]
)
def test_a_shifted_mask_gives_the_orders_of_the_supersampled_plate(levels, shifted, mask, shift):
    # Exact for sub-pixel shifts: the same orders as the plate cut into 20 x 20
    # sub-pixels per mask pixel, with the shift (+y up) applied to that mask's bitmap.
    dy, dx = shift
    expected = supersampled_window(levels, mask, dx * 1.0, dy * 1.0, 20)
    assert np.allclose(shifted[mask].power(dx=dx, dy=dy), expected, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("mask", [0, 1, 2])
def test_the_model_is_fab_tolerance_s_plate_with_one_mask_shifted(levels, shifted, mask):
    # The tolerance budget's general model (continuous plate, any error), built
    # independently; this one is it restricted to a single shifted mask, made fast.
    masks = masks_from_levels(levels, L, 1.0)
    general = plate_model(masks, 1.0, 1.0, L, wavelength=1.0, refractive_index=1 + 1 / L, k=K)
    for dy, dx in [(0.37, -1.91), (-1.3, 0.05), (2.0, 2.0)]:
        faults = PlateFaults(overlay=one_mask_overlay(mask, dx, dy))
        expected = np.abs(window_amplitudes(general, faults)) ** 2
        assert np.allclose(shifted[mask].power(dx=dx, dy=dy), expected, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("mask", [0, 1, 2])
def test_with_etch_errors_too_it_is_the_plate_model(levels, mask):
    plate = level_plate_model(levels, L, K)
    windows = ShiftedMaskWindows(plate, mask, REACH_PX)
    for errors, (dx, dy) in [((0.1, -0.2, 0.15), (0.37, -1.91)), ((-0.3, 0.0, 0.2), (-2.5, 1.2))]:
        windows.set_etch_errors(errors)
        faults = PlateFaults(etch_errors=errors, overlay=one_mask_overlay(mask, dx, dy))
        np.testing.assert_allclose(
            windows.amplitudes(dx, dy), window_amplitudes(plate, faults), rtol=0, atol=1e-14
        )


def test_shifts_are_evaluated_at_once_on_any_grid(levels, shifted):
    dx, dy = np.meshgrid([-0.3, 0.0, 1.7], [0.2, -2.1], indexing="ij")
    grid = shifted[1].power(dx=dx, dy=dy)
    assert grid.shape == (3, 2, K, K)
    for i, j in np.ndindex(dx.shape):
        np.testing.assert_allclose(grid[i, j], shifted[1].power(dx=dx[i, j], dy=dy[i, j]))


def square_pixel_window(levels):
    """The window orders of a level map made with square pixels (the sinc^2 envelope)."""
    amp = order_amplitudes(2 * np.pi * levels / L)
    idx = window_indices(N, K)
    env = pixel_envelope(np.arange(K) - K // 2, N)
    return np.abs(amp[np.ix_(idx, idx)]) ** 2 * np.outer(env, env)


def test_no_shift_gives_the_design_with_its_pixel_envelope(levels, shifted):
    design = square_pixel_window(levels)
    for mask in range(3):
        assert np.allclose(shifted[mask].power(dx=0.0, dy=0.0), design, rtol=1e-12)


def test_whole_pixel_shift_rolls_the_mask_bitmap_towards_row_0_for_plus_y(levels, shifted):
    # Independent of the simulator: rebuild the level map with the deep mask moved one
    # row up (+y) and one column right, and compare with the design frame's FFT.
    masks = masks_from_levels(levels, L, 1.0)
    code = sum(
        mk.steps * np.roll(mk.bitmap, (-1, 1), axis=(0, 1)) if j == 0 else mk.steps * mk.bitmap
        for j, mk in enumerate(masks)
    )
    expected = square_pixel_window((L - 1) - code)
    assert np.allclose(shifted[0].power(dx=1.0, dy=1.0), expected, rtol=1e-12)
    assert not np.allclose(shifted[0].power(dx=1.0, dy=-1.0), expected, rtol=1e-3)


def test_shifts_beyond_the_reach_are_refused(shifted):
    with pytest.raises(ValueError, match="reach"):
        shifted[1].power(dx=0.0, dy=REACH_PX + 0.1)
    with pytest.raises(ValueError, match="reach"):
        shifted[1].power(dx=-REACH_PX - 0.1, dy=0.0)


@pytest.mark.parametrize("mask", [0, 1, 2])
def test_a_shifted_mask_on_a_plate_etched_off_gives_the_supersampled_plate(levels, mask):
    errors = (0.1, -0.2, 0.15)
    expected = supersampled_window(levels, mask, -0.5, 1.25, 4, errors)
    windows = ShiftedMaskWindows(level_plate_model(levels, L, K), mask, REACH_PX)
    windows.set_etch_errors(errors)
    assert np.allclose(windows.power(dx=-0.5, dy=1.25), expected, rtol=1e-9, atol=1e-15)
    windows.set_etch_errors((0, 0, 0))  # and the errors undone: the aligned etches' model
    aligned = ShiftedMaskWindows(level_plate_model(levels, L, K), mask, REACH_PX)
    assert np.allclose(windows.power(dx=-0.5, dy=1.25), aligned.power(dx=-0.5, dy=1.25))


def test_one_mask_plate_has_a_basis_too():
    binary = 4 * np.random.default_rng(2).integers(0, 2, (N, N)).astype(np.uint8)
    plate = level_plate_model(binary // 4, 2, K)
    windows = ShiftedMaskWindows(plate, 0, REACH_PX)
    faults = PlateFaults(overlay=((0.3, -0.6),))
    np.testing.assert_allclose(
        windows.amplitudes(0.3, -0.6), window_amplitudes(plate, faults), rtol=0, atol=1e-14
    )


@pytest.mark.parametrize("errors", [(0.0, 0.0, 0.0), (0.2, -0.1, 0.05), (-0.45, 0.3, 0.0)])
def test_code_windows_weighted_by_the_codes_phases_are_the_plate_model(levels, errors):
    plate = level_plate_model(levels, L, K)
    window = np.tensordot(np.exp(1j * code_phases(plate, errors)), code_windows(plate), axes=1)
    expected = window_amplitudes(plate, PlateFaults(etch_errors=errors))
    np.testing.assert_allclose(window, expected, rtol=0, atol=1e-14)
    # a stack of error sets gives a stack of phases
    stacked = code_phases(plate, np.array([errors, (0.0, 0.0, 0.0)]))
    np.testing.assert_allclose(stacked[0], code_phases(plate, errors), rtol=0, atol=1e-14)
