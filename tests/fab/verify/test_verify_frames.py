"""verify's frames: orientation undo, reflected plates, the window at the frame edge.

Each test states an analytic expectation; none depends on a simulated camera.
"""

import dataclasses

import numpy as np
import pytest

from doe.fraunhofer import pixel_envelope, simulate_levels
from fab.verify.analysis import (
    _PLATE_LEVELS,
    _TRANSFORMS,
    ORIENTATIONS,
    analyse,
    design_order_power,
    resolve_thresholds,
    to_design_frame,
)
from fab.verify.lattice import Lattice
from fab.verify.photometry import OrderGrid
from fab.verify.simulate import ORIENTATION_MAPS
from fab.verify.zero_order import locate_zero_order

N, K, L = 35, 11, 8


@pytest.mark.parametrize("orientation", ORIENTATIONS)
def test_to_design_frame_undoes_every_camera_orientation(orientation):
    # Design order (m, n) lands at camera offset ORIENTATION_MAPS[o](m, n) (the
    # simulator's statement of the convention, independent of to_design_frame).
    # Undoing it must give the design grid back, element for element, for every
    # orientation (mirror-x and rot270 are not exercised by the end-to-end tests).
    a, b = 3, 5  # a non-square design grid, zero order at [a, b]
    design = np.arange((2 * a + 1) * (2 * b + 1), dtype=float).reshape(2 * a + 1, 2 * b + 1)
    fwd = ORIENTATION_MAPS[orientation]
    offsets = [fwd(m, n) for m in range(-a, a + 1) for n in range(-b, b + 1)]
    su = max(abs(du) for du, _ in offsets)
    sv = max(abs(dv) for _, dv in offsets)
    camera = np.full((2 * su + 1, 2 * sv + 1), np.nan)
    for m in range(-a, a + 1):
        for n in range(-b, b + 1):
            du, dv = fwd(m, n)
            camera[su + du, sv + dv] = design[a + m, b + n]
    assert np.array_equal(to_design_frame(camera, orientation), design)


def test_an_orientation_not_in_the_list_is_refused():
    with pytest.raises(ValueError, match="orientation must be one of"):
        to_design_frame(np.zeros((3, 3)), "rot45")


@pytest.mark.parametrize("name", sorted(_TRANSFORMS))
def test_each_reflected_plate_tile_makes_its_transformed_far_field(name):
    # _PLATE_LEVELS[t] is "the tile that gives" the order pattern _TRANSFORMS[t]:
    # the plate verify measures a reflected capture against must be that plate.
    levels = np.random.default_rng(11).integers(0, L, (N, N)).astype(np.uint8)
    plate = _PLATE_LEVELS[name](levels, L)
    want = _TRANSFORMS[name](design_order_power(levels, L))
    np.testing.assert_allclose(design_order_power(plate, L), want, rtol=0, atol=1e-15)


def _grid(levels, shape, zero):
    """A noiseless order grid: every order measured, its power the plate's far field."""
    period = design_order_power(levels, L)
    m = np.arange(shape[0]) - zero[0]
    n = np.arange(shape[1]) - zero[1]
    power = period[np.ix_(m % N, n % N)] * np.outer(pixel_envelope(m, N), pixel_envelope(n, N))
    power = power * 1e6  # DN
    sigma = np.full(shape, 1e-6)
    u, v = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    return OrderGrid(
        u=np.arange(shape[0]), v=np.arange(shape[1]), power=power,
        valid=np.ones(shape, bool), rows=u * 10.0, cols=v * 10.0,
        saturated=np.zeros(shape, bool), noise_px=1e-6, aperture_pixels=20, sigma=sigma,
        aperture_radius_px=2.0, pitch_px=10.0,
    )  # fmt: skip


def _random_design():
    """A random 8-level tile and the default thresholds of its own figures."""
    levels = np.random.default_rng(7).integers(0, L, (N, N)).astype(np.uint8)
    _, efficiency = simulate_levels(levels, L, K)
    return levels, resolve_thresholds(None, efficiency, design_order_power(levels, L)[0, 0])


@pytest.mark.parametrize("axis", [0, 1])
def test_window_that_touches_the_frame_edge_is_measured_and_one_past_it_is_not(axis):
    levels, thresholds = _random_design()
    half = K // 2
    zero = [10, 12]
    # last window row (or column) is the frame's last one: in frame, a K x K PSF
    shape = [21, 25]
    shape[axis] = zero[axis] + half + 1
    result, psf = analyse(_grid(levels, shape, zero), levels, L, K, "as-designed", thresholds)
    assert result["window_in_frame"] and psf.shape == (K, K)
    assert [result["zero_order_px"][0] / 10, result["zero_order_px"][1] / 10] == zero
    # every order outside the K x K window carries light and counts as such
    assert result["outside_window_orders"] == shape[0] * shape[1] - K * K
    # one row (column) fewer: the window runs off the frame, no PSF
    shape[axis] -= 1
    result, psf = analyse(_grid(levels, shape, zero), levels, L, K, "as-designed", thresholds)
    assert result["window_in_frame"] is False and psf is None


def test_locating_the_zero_order_needs_a_valid_order_and_three_to_score():
    period = design_order_power(_random_design()[0], L)
    power, sigma = np.arange(25.0).reshape(5, 5), np.full((5, 5), 0.01)
    with pytest.raises(ValueError, match="no valid dot"):
        locate_zero_order(power, np.zeros((5, 5), bool), sigma, period)
    # the zero order and two orders beside it: two points always correlate perfectly,
    # so fewer than three orders give no score
    valid = np.zeros((5, 5), bool)
    valid[2, 1:4] = True
    search = locate_zero_order(power, valid, sigma, period)
    assert (search["score"], search["outside_orders"]) == (0.0, 0)
    assert np.isnan(search["outside_score"])


# Each reflected plate, made independently of the analysis: conjugate = etch and glass swapped.
REFLECTED_PLATES = {
    "mirror-x": (lambda lv: lv[:, ::-1], "mirrored"),
    "mirror-y": (lambda lv: lv[::-1, :], "mirrored"),
    "conjugate": (lambda lv: (L - 1 - lv).astype(np.uint8), "conjugate_plate"),
}


@pytest.mark.parametrize("fault", sorted(REFLECTED_PLATES))
def test_every_reflected_plate_is_named_for_its_fault(fault):
    # catches naming a plate flipped top to bottom (mirror-y) a conjugate plate
    levels, t = _random_design()
    make, code = REFLECTED_PLATES[fault]
    plate = np.ascontiguousarray(make(levels))
    result, _ = analyse(_grid(plate, (21, 25), (10, 12)), levels, L, K, "as-designed", t)
    assert result["diagnosis"] == [code]


def test_a_clipped_dot_outside_the_window_marks_the_capture_saturated():
    # catches counting clipped dots in the K x K window only: one outside it takes light
    # from the beam power, and the efficiency reads high
    levels, t = _random_design()
    grid = _grid(levels, (21, 25), (10, 12))
    saturated = np.zeros(grid.power.shape, bool)
    saturated[1, 2] = True  # order (-9, -10), outside the window
    grid = dataclasses.replace(grid, saturated=saturated)
    result, _ = analyse(grid, levels, L, K, "as-designed", t)
    assert result["saturated_in_window"] == 0 and result["diagnosis"] == ["saturated"]


def test_lattice_pitch_and_rotation_are_those_of_its_two_step_vectors():
    # A sheared lattice (a camera tilted about one axis): the step vectors, the basis's
    # columns, are 10 and hypot(4, 8) long; the basis's rows are hypot(10, 4) and 8.
    lattice = Lattice(np.array([5.0, 7.0]), np.array([[10.0, 4.0], [0.0, 8.0]]))
    origin = np.array(lattice.positions(0, 0))
    steps = [np.array(lattice.positions(u, v)) - origin for u, v in ((1, 0), (0, 1))]
    assert lattice.pitch_px == pytest.approx(np.mean([np.hypot(*d) for d in steps]))
    assert lattice.pitch_px == pytest.approx((10 + np.hypot(4, 8)) / 2)
    # +v steps 8 right and 4 down: clockwise as displayed, by atan(4 / 8)
    assert lattice.rotation_deg == pytest.approx(-np.degrees(np.arctan2(4, 8)))
