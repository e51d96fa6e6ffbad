"""The axes of a plate fault, pinned against CONVENTIONS.md.

Row 0 of a level map is the top edge of the layout (largest y), column 0 its left edge
(smallest x), looking onto the patterned surface. So an overlay of +x must move that
mask's pattern right (towards higher columns) and +y up (towards row 0): in the tolerance
model, in the simulator's plate and in verify's fits alike, which report the shift they
find as ``shift_px`` = [dy, dx].
"""

import numpy as np
import pytest

from doe.fraunhofer import level_phase, order_amplitudes, pixel_envelope, window_indices
from fab.package.masks import masks_from_levels
from fab.plate.model import (
    PlateFaults,
    plate_far_field,
    plate_model,
    plate_phase,
    window_amplitudes,
)
from fab.verify.overlay import fit_overlay_and_etch, fit_overlay_error
from fab.verify.simulate import simulate_capture

N, K, L = 24, 7, 8
PITCH = 5e-6
N_INDEX, WAVELENGTH = 1.4564, 655e-9
STEP = WAVELENGTH / (N_INDEX - 1) / L  # the level_step that makes level l = 2 pi l / L
MID = 1  # M2_mid, etching 2 of the 7 steps


@pytest.fixture(scope="module")
def levels():
    return np.random.default_rng(7).integers(0, L, (N, N)).astype(np.uint8)


def mid_mask_shifted(dx, dy):
    return PlateFaults(overlay=((0.0, 0.0), (dx, dy), (0.0, 0.0)))


def moved(levels, right, up):
    """The level map made with the mid mask's etched pattern moved ``right`` columns and
    ``up`` rows (towards row 0), by hand."""
    code = sum(
        mk.steps * (np.roll(mk.bitmap, (-up, right), axis=(0, 1)) if j == MID else mk.bitmap)
        for j, mk in enumerate(masks_from_levels(levels, L, 1.0))
    )
    return ((L - 1) - code).astype(np.uint8)


def square_pixel_window(levels):
    """The window powers of a level map (CONVENTIONS' model) made with square pixels."""
    amp = order_amplitudes(level_phase(levels, L))
    idx = window_indices(N, K)
    env = pixel_envelope(np.arange(K) - K // 2, N)
    return np.abs(amp[np.ix_(idx, idx)]) ** 2 * np.outer(env, env)


def centre_xy(row, col):
    """The centre (x, y) of mask pixel (row, col) in metres, as CONVENTIONS places it."""
    return (col + 0.5) * PITCH, (N - row - 0.5) * PITCH


@pytest.mark.parametrize("dx, dy", [(PITCH, 0.0), (0.0, PITCH), (-2 * PITCH, 3 * PITCH)])
def test_an_overlay_moves_a_mask_s_pixel_by_dx_right_and_dy_up(dx, dy):
    # One pixel the mid mask alone etches (level 5: code 2); the rest unetched.
    lv = np.full((N, N), L - 1, np.uint8)
    lv[9, 5] = L - 1 - 2
    phase = plate_phase(lv, L, mid_mask_shifted(dx, dy), PITCH)
    etched = np.argwhere(~np.isclose(np.exp(1j * phase), np.exp(2j * np.pi * (L - 1) / L)))
    assert len(etched) == 1
    x0, y0 = centre_xy(9, 5)
    x1, y1 = centre_xy(*etched[0])
    assert (x1 - x0, y1 - y0) == pytest.approx((dx, dy))


@pytest.mark.parametrize("right, up", [(2, 1), (-1, 2), (1, -3)])
def test_the_tolerance_model_moves_the_pattern_right_for_plus_x_and_up_for_plus_y(
    levels, right, up
):
    masks = masks_from_levels(levels, L, STEP)
    model = plate_model(masks, PITCH, STEP, L, WAVELENGTH, N_INDEX, K)
    faults = mid_mask_shifted(right * PITCH, up * PITCH)
    power = np.abs(window_amplitudes(model, faults)) ** 2
    np.testing.assert_allclose(power, square_pixel_window(moved(levels, right, up)), atol=1e-14)
    for wrong in ((-right, up), (right, -up), (up, right)):  # a flipped or swapped axis
        assert not np.allclose(power, square_pixel_window(moved(levels, *wrong)), atol=1e-6)


@pytest.mark.parametrize("supersample", [1, 3])
def test_the_simulator_s_plate_moves_the_pattern_right_for_plus_x_and_up_for_plus_y(
    levels, supersample
):
    faults = mid_mask_shifted(2 * PITCH, PITCH)
    phase = plate_phase(levels, L, faults, PITCH, supersample)
    expected = np.kron(level_phase(moved(levels, 2, 1), L), np.ones((supersample,) * 2))
    np.testing.assert_allclose(np.exp(1j * phase), np.exp(1j * expected), rtol=0, atol=1e-12)
    # and the capture it simulates shows that plate's orders
    sim = simulate_capture(
        levels, L, shape=(96, 96), pitch_px=8.0, faults=faults, mask_pixel_pitch=PITCH,
        supersample=supersample,
    )  # fmt: skip
    m = np.arange(-5, 6)
    far = plate_far_field(level_phase(moved(levels, 2, 1), L))
    np.testing.assert_allclose(
        sim["order_power"](m[:, None], m[None, :]), far(m[:, None], m[None, :]), atol=1e-14
    )


def supersampled_window(levels, dx, dy, etch_errors=()):
    """The window of the plate with the mid mask shifted (dx, dy) mask pixels, sampled
    10 x 10 per pixel (shifts on the 0.1 px grid)."""
    faults = PlateFaults(etch_errors=etch_errors, overlay=mid_mask_shifted(dx, dy).overlay)
    orders = plate_far_field(plate_phase(levels, L, faults, 1.0, 10))
    m = np.arange(K) - K // 2
    return orders(m[:, None], m[None, :])


@pytest.mark.parametrize("dx, dy", [(0.4, -1.3), (-1.1, 0.7), (1.6, 0.0), (0.0, -0.9)])
def test_the_overlay_fit_returns_the_simulated_shift_with_its_sign(levels, dx, dy):
    fit = fit_overlay_error(supersampled_window(levels, dx, dy), None, levels, L)
    assert fit["mask"] == "M2_mid"
    assert fit["shift_px"] == pytest.approx([dy, dx], abs=0.011)  # verify.json's order
    assert fit["faults"].overlay[MID] == pytest.approx((dx, dy), abs=0.011)
    assert fit["faults"].overlay[0] == fit["faults"].overlay[2] == (0.0, 0.0)


def test_the_overlay_and_etch_fit_returns_the_simulated_shift_with_its_sign(levels):
    dx, dy, errors = -0.7, 1.2, (0.2, 0.0, -0.1)
    window = supersampled_window(levels, dx, dy, errors)
    sigma = 1e-4 * window.max() + 0.01 * window
    fit = fit_overlay_and_etch(window, sigma, levels, L, MID, (dy + 0.2, dx - 0.1), (0, 0, 0))
    assert fit["shift_px"] == pytest.approx([dy, dx], abs=1e-3)
    assert fit["faults"].overlay[MID] == pytest.approx((dx, dy), abs=1e-3)
    assert fit["faults"].etch_errors == pytest.approx(errors, abs=1e-3)
