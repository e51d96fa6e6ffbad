"""Lattice registration, order photometry and hot-pixel repair on simulated captures."""

import json
import re

import numpy as np
import pytest
from verify_helpers import PITCH_PX, K, L, N, make_design_dir, run_verify

from doe.infra.cli import main
from fab.verify.capture import write_image
from fab.verify.lattice import Lattice, LatticeNotFound, register_lattice
from fab.verify.photometry import measure_orders
from fab.verify.simulate import simulate_capture


def test_hot_pixels_that_may_lie_on_dots_ask_for_a_dark_frame(tmp_path, levels, capsys):
    # 0.15 % of a default capture's pixels hot and no dark frame read a good plate as
    # conjugate_plate, without a word about hot pixels
    run_verify(tmp_path, levels, dict(seed=5, hot_pixels=300), dark=False)
    err = capsys.readouterr().err
    assert re.search(r"about \d+ more hot pixels may lie on dots, .*: give --dark", err)


def test_hot_pixels_without_a_dark_frame_do_not_fail_a_good_plate(tmp_path, designed):
    code, report, sim = run_verify(tmp_path, designed, dict(seed=28, hot_pixels=150), dark=False)
    assert code == 0, report["diagnosis"]
    assert np.allclose(report["zero_order_px"], sim["zero_order_px"], atol=0.3)
    assert any("hot pixel" in n for n in report["notes"])
    assert report["efficiency"] == pytest.approx(report["design_efficiency"], abs=0.03)


@pytest.fixture(scope="module")
def registered_capture(levels):
    """A 16-bit capture of the plate (float32, read-only) and its registered lattice."""
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=29, shape=(300, 300), bits=16)
    image = sim["capture"].astype(np.float32)
    image.flags.writeable = False  # shared: each test works on its own copy
    return image, register_lattice(image, PITCH_PX)[0]


def test_spike_repair_keeps_dots_and_removes_stray_pixels(registered_capture):
    from fab.verify.hot_pixels import repair_stray_spikes

    image, lattice = registered_capture
    spiked = image.copy()
    spiked[150 + 5, 150 + 5] += 5000  # half a pitch from every dot
    fixed, repaired = repair_stray_spikes(spiked, lattice)
    assert repaired[155, 155]
    assert abs(fixed[155, 155] - image[155, 155]) < 50
    # Real dots are untouched.
    u, v = np.meshgrid(np.arange(-5, 6), np.arange(-5, 6), indexing="ij")
    r, c = lattice.positions(u, v)
    r, c = np.rint(r).astype(int), np.rint(c).astype(int)
    assert np.array_equal(fixed[r, c], spiked[r, c])


def test_hot_pixel_of_the_dark_frame_on_a_dot_keeps_the_dot_light(tmp_path, levels):
    """Dark subtraction already takes a hot pixel's dark signal away; repairing it
    as well (median of neighbours) would take away the dot's peak."""
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=30, bits=16)
    design = make_design_dir(tmp_path / "design", levels)
    reports = []
    for name, hot in (("clean", 0), ("hot", 15000)):
        capture, dark = sim["capture"].astype(np.int64), sim["dark"].astype(np.int64)
        # the core pixel of the brightest dot in the K x K window of orders
        r0, c0 = np.rint(sim["zero_order_px"]).astype(int)
        reach = int(K // 2 * PITCH_PX) + 2
        box = capture[r0 - reach : r0 + reach + 1, c0 - reach : c0 + reach + 1]
        r, c = np.unravel_index(np.argmax(box), box.shape)
        r, c = r + r0 - reach, c + c0 - reach
        capture[r, c] += hot
        dark[r, c] += hot
        assert capture.max() < sim["full_scale"]
        write_image(tmp_path / f"{name}.tif", capture.astype(np.uint16))
        write_image(tmp_path / f"{name}_dark.tif", dark.astype(np.uint16))
        out = tmp_path / f"out_{name}"
        args = [str(tmp_path / f"{name}.tif"), "--dark", str(tmp_path / f"{name}_dark.tif")]
        assert main(["verify", str(design), *args, "--out", str(out)]) == 0
        reports.append(np.load(out / "measured_psf.npy"))
    clean, hot = reports
    assert np.abs(hot - clean).max() < 0.01 * clean.max()


def test_background_gradient_leaves_the_lattice_right(tmp_path, levels):
    """Stray light rising 400 DN across the frame (dots peak near 2900 DN)."""
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, seed=31, centre=(301.3, 297.6))
    ramp = np.linspace(0.0, 400.0, sim["capture"].shape[1])[None, :]
    capture = np.rint((sim["capture"] >> 4) + ramp).astype(np.uint16)  # 12-bit DN
    assert capture.max() < 4095
    design = make_design_dir(tmp_path / "design", levels)
    write_image(tmp_path / "cap.png", capture)
    code = main(["verify", str(design), str(tmp_path / "cap.png"), "--out", str(tmp_path / "o")])
    report = json.loads((tmp_path / "o" / "verify.json").read_text())
    assert code == 0, report["diagnosis"]
    assert np.allclose(report["zero_order_px"], sim["zero_order_px"], atol=0.2)
    assert report["lattice"]["pitch_px"] == pytest.approx(PITCH_PX, rel=1e-3)


def test_spike_repair_leaves_the_wings_of_blurred_dots_alone(levels):
    from fab.verify.hot_pixels import repair_stray_spikes

    sim = simulate_capture(
        levels, L, pitch_px=PITCH_PX, seed=32, shape=(300, 300), bits=16, blur_sigma_px=0.8
    )
    image = sim["capture"].astype(np.float32)
    lattice, _ = register_lattice(image, PITCH_PX)
    fixed, repaired = repair_stray_spikes(image, lattice)
    assert not repaired.any()
    assert np.array_equal(fixed, image)


def test_spike_repair_leaves_a_bright_scene_alone(registered_capture):
    # Stray light (2000 DN, shot noise) over 40 % of the frame: over a quarter of the
    # pixels stand out of the dark noise, a scene rather than a dot lattice, and its
    # grain (a local maximum every few pixels) is not hot pixels: nothing repaired.
    from fab.verify.hot_pixels import repair_stray_spikes

    image, lattice = registered_capture
    lit = image.copy()
    lit[:, :120] += np.random.default_rng(5).poisson(2000.0, (300, 120)).astype(np.float32)
    fixed, repaired = repair_stray_spikes(lit, lattice)
    assert not repaired.any()
    assert np.array_equal(fixed, lit)


def test_pixel_noise_is_at_least_the_rounding_noise_of_the_codes():
    from fab.verify.lattice import pixel_noise

    assert pixel_noise(np.full(100, 7.0), quantum=4.0) == pytest.approx(4.0 / np.sqrt(12))
    assert pixel_noise(np.full(100, 7.0)) > 0  # float data: never a zero sigma
    noisy = np.random.default_rng(0).normal(0.0, 3.0, 10_000)
    assert pixel_noise(noisy, quantum=1.0) == pytest.approx(3.0, rel=0.05)


def test_registered_origin_is_the_lattice_point_nearest_the_image_centre(levels):
    # catches rounding the centre's lattice coordinates down: the origin up to a pitch off
    shape = (300, 300)
    zero = (np.array(shape) - 1) / 2 - 0.7 * PITCH_PX  # the centre lies 0.7 pitch down-right
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, shape=shape, centre=tuple(zero), seed=34)
    lattice, _ = register_lattice(sim["capture"] >> 4, PITCH_PX)
    # the order one step down and right lies 0.3 pitch from the centre on each axis
    assert np.allclose(lattice.origin, zero + PITCH_PX, atol=0.3)


def test_a_frame_narrower_than_4_pitches_is_refused():
    with pytest.raises(LatticeNotFound, match="image 300x40 px holds fewer than 4 dots across"):
        register_lattice(np.zeros((40, 300)), PITCH_PX)
    with pytest.raises(LatticeNotFound, match="check --pixel-pitch-um and --lattice-pitch-um"):
        register_lattice(np.zeros((40, 300)), PITCH_PX)


@pytest.mark.parametrize("scale, off", [(1.17, "+17%"), (0.83, "-17%")])
def test_dots_17_percent_off_the_nominal_pitch_are_refused(levels, scale, off):
    # within the neighbour search (0.8 to 1.18 pitches), beyond the 15 % allowed: the
    # camera pixel pitch given is wrong
    sim = simulate_capture(levels, L, pitch_px=PITCH_PX, scale=scale, shape=(300, 300), seed=1)
    with pytest.raises(LatticeNotFound, match=re.escape(f"{off} off the nominal 10.87 px")):
        register_lattice(sim["capture"], PITCH_PX)
    # a lens of another focal length: the flag that mends it is --lattice-pitch-um
    with pytest.raises(LatticeNotFound, match="give --lattice-pitch-um for a lens of another"):
        register_lattice(sim["capture"], PITCH_PX)


def test_dots_found_closer_than_photometry_needs_are_refused(levels):
    # nominally 3.7 px apart (enough), found 3.3 px apart (within 15 %, too close)
    sim = simulate_capture(levels, L, pitch_px=3.3, shape=(300, 300), seed=1)
    with pytest.raises(
        LatticeNotFound, match=re.escape("the dots are 3.3 px apart, closer than the 3.4")
    ):
        register_lattice(sim["capture"], 3.7)


@pytest.mark.parametrize(("scale", "rotation_deg"), [(0.87, 0.0), (1.12, 0.0), (1.08, 4.0)])
def test_a_plate_lighting_every_other_order_registers_off_the_nominal_pitch(scale, rotation_deg):
    # A tile of 2 x 2 copies has period N / 2: only even orders are lit, no dot has a
    # neighbour one pitch away, and the fit starts from the design's pitch. Allowed
    # to move it by 5 % at a time, it stopped between the two: the origin 4-5 px off
    # at 8-12 % magnification error, a good plate failed as other_design.
    quarter = np.random.default_rng(5).integers(0, L, (18, 18)).astype(np.uint8)
    sim = simulate_capture(
        np.tile(quarter, (2, 2)), L, pitch_px=PITCH_PX, scale=scale,
        rotation_deg=rotation_deg, shape=(600, 600), seed=2,
    )  # fmt: skip
    lattice, notes = register_lattice(sim["capture"], PITCH_PX)
    assert any("too few neighbouring dots" in n for n in notes)  # the case under test
    assert lattice.pitch_px == pytest.approx(scale * PITCH_PX, rel=1e-3)
    assert np.allclose(lattice.origin, sim["zero_order_px"], atol=0.1)


@pytest.mark.parametrize("every_other", [True, False])
def test_only_the_first_fit_of_a_pitch_not_measured_may_move_it_by_the_tolerance(
    monkeypatch, levels, every_other
):
    # Once fitted to the dots, the pitch is as good as a measured one: later fits over
    # more dots step by MAX_BASIS_STEP, so a stray dot cannot drag the lattice 20 %.
    from fab.verify import lattice as lattice_module

    steps, fit = [], lattice_module._fit_dots

    def spy(lattice, dots, weight, reach, max_step=lattice_module.MAX_BASIS_STEP):
        steps.append(max_step)
        return fit(lattice, dots, weight, reach, max_step)

    monkeypatch.setattr(lattice_module, "_fit_dots", spy)
    plate = np.tile(levels[:18, :18], (2, 2)) if every_other else levels
    sim = simulate_capture(plate, L, pitch_px=PITCH_PX, scale=1.1, shape=(600, 600), seed=2)
    register_lattice(sim["capture"], PITCH_PX)
    small, large = lattice_module.MAX_BASIS_STEP, lattice_module.PITCH_TOLERANCE
    assert steps == [large + small if every_other else small] + [small] * 3


def test_a_fit_step_larger_than_allowed_keeps_the_basis():
    # Three dots, one a quarter pitch off its site along v: their exact fit stretches v
    # by 25 %. From a measured pitch (steps of 5 % allowed) that is a stray dot: the
    # basis stays, the origin moves by the median residual (none). From the design's
    # pitch the whole tolerance is allowed, and the fit follows the dots.
    from fab.verify.lattice import MAX_BASIS_STEP, _fit_dots

    prior = Lattice(np.array([50.0, 50.0]), 10.0 * np.eye(2))
    dots = np.array([[50.0, 50.0], [60.0, 50.0], [50.0, 62.5]])
    kept = _fit_dots(prior, dots, np.ones(3), reach=3, max_step=MAX_BASIS_STEP)
    assert np.array_equal(kept.basis, prior.basis) and np.allclose(kept.origin, prior.origin)
    followed = _fit_dots(prior, dots, np.ones(3), reach=3, max_step=0.3)
    assert np.allclose(followed.basis, [[10.0, 0.0], [0.0, 12.5]])


def test_a_grating_whose_orders_lie_on_one_line_registers_along_it():
    # levels vary along x only: every order is (0, n), one lattice row; its step along
    # the row is measured, the step across it stays the nominal one
    grating = np.tile(np.random.default_rng(3).integers(0, L, N).astype(np.uint8), (N, 1))
    sim = simulate_capture(grating, L, pitch_px=PITCH_PX, rotation_deg=3.0, shape=(300, 300))
    lattice, _ = register_lattice(sim["capture"], PITCH_PX)
    assert np.allclose(lattice.origin, sim["zero_order_px"], atol=0.1)
    along = np.array(lattice.positions(0, 1)) - lattice.origin  # (row, col) of one step
    theta = np.radians(3.0)
    assert np.allclose(along, PITCH_PX * np.array([-np.sin(theta), np.cos(theta)]), atol=0.02)


@pytest.fixture(scope="module")
def empty_orders(levels):
    """A dark frame (integer codes, pedestal between two codes) and the lattice it would hold."""
    sim = simulate_capture(
        levels, L, pitch_px=PITCH_PX, centre=(300.0, 300.0), seed=41, bits=16,
        read_noise_dn=1.0, dark_level_dn=60.3,
    )  # fmt: skip
    return sim["dark"].astype(np.float32), Lattice(np.array([300.0, 300.0]), PITCH_PX * np.eye(2))


def test_empty_orders_scatter_as_their_reported_sigma(empty_orders):
    # catches a sigma without the error of the annulus background (about 30 % too small)
    image, lattice = empty_orders
    grid = measure_orders(image, lattice, quantum=1.0)
    z = grid.power[grid.valid] / grid.sigma[grid.valid]
    assert z.size > 2000  # the std of 2000 unit normals is 1 within 0.016
    assert np.std(z) == pytest.approx(1.0, abs=0.1)


def test_empty_orders_of_integer_codes_measure_no_power(empty_orders):
    # catches a median background: on integer codes it is off by up to half a DN per
    # pixel, which summed over thousands of faint orders biases the beam power
    image, lattice = empty_orders
    power = measure_orders(image, lattice, quantum=1.0).power
    power = power[np.isfinite(power)]
    assert abs(power.mean()) < 4 * power.std() / np.sqrt(power.size)


def test_saturated_pixel_outside_the_aperture_flags_no_order(empty_orders):
    # catches flagging every order whose patch (aperture and annulus) holds a clipped pixel
    image, lattice = empty_orders
    saturated = np.zeros(image.shape, bool)
    saturated[300, 305] = True  # 5 px from order (0, 0): in its annulus, off its aperture
    r, c = np.rint(lattice.positions(2, 3)).astype(int)
    saturated[r, c] = True  # on order (2, 3)
    grid = measure_orders(image, lattice, saturated, quantum=1.0)
    assert grid.aperture_radius_px < 5
    (iu,), (iv,) = np.nonzero(grid.u == 2), np.nonzero(grid.v == 3)
    assert np.array_equal(np.argwhere(grid.saturated), [[iu[0], iv[0]]])


def test_aperture_holds_99_percent_of_a_blurred_dot_plus_a_pixel(levels):
    # catches an aperture sized for 90 % of the light, which loses 1.5 % of blurred dots
    spot, blur, pitch = 0.3, 1.5, 2 * PITCH_PX
    sim = simulate_capture(
        levels, L, pitch_px=pitch, seed=35, bits=16, spot_sigma_px=spot, blur_sigma_px=blur
    )
    image = sim["capture"].astype(np.float32) - sim["dark"]
    lattice, _ = register_lattice(image, pitch)
    grid = measure_orders(image, lattice, quantum=1.0)
    # A Gaussian dot of sigma per axis (the pixels add 1/12 px^2) holds 1 - exp(-r^2 / 2 sigma^2)
    # of its light within r; the radius is searched in 0.25 px steps on a pixel grid.
    sigma = np.sqrt(spot**2 + blur**2 + 1 / 12)
    r99 = sigma * np.sqrt(2 * np.log(100))
    assert grid.aperture_radius_px == pytest.approx(r99 + 1, abs=0.5)
