"""The capture simulator and the faulty plate's far field it renders."""

import numpy as np
import pytest
from verify_helpers import PITCH_PX, K, L, N

from doe.fraunhofer import simulate_levels
from fab.plate.model import PlateFaults, plate_far_field, plate_phase
from fab.verify.simulate import simulate_capture


def test_plate_far_field_conserves_power_and_matches_the_contract(levels):
    # sum_k sinc^2(x + k) = 1: all orders together carry the whole beam; a sum
    # truncated at |m|, |n| <= M n misses about 2 / (pi^2 M) of it (sin^2 averages 1/2).
    small = np.random.default_rng(8).integers(0, L, (8, 8)).astype(np.uint8)
    far = plate_far_field(plate_phase(small, L))
    for reach in (40, 80):
        m = np.arange(-reach * 8, reach * 8 + 1)
        total = far(m[:, None], m[None, :]).sum()
        assert 1 - total == pytest.approx(2 / (np.pi**2 * reach), rel=0.05)
    psf, _ = simulate_levels(levels, L, K)
    far = plate_far_field(plate_phase(levels, L))
    window = far(*np.meshgrid(np.arange(K) - K // 2, np.arange(K) - K // 2, indexing="ij"))
    env = np.sinc((np.arange(K) - K // 2) / N) ** 2
    flat = window / np.outer(env, env)
    assert np.allclose(flat / flat.sum(), psf)


def test_capture_with_the_zero_order_far_outside_the_frame_has_every_dot(levels):
    # The orders drawn reached hypot(h, w) / pitch from the zero order, wherever it
    # was: 300 px above and left of a 201 px frame, most of the frame stayed dark.
    from scipy import ndimage

    sim = simulate_capture(
        levels, L, pitch_px=PITCH_PX, shape=(201, 201), centre=(-300.0, -300.0), bits=16,
        full_well_e=1e10, read_noise_dn=0, dark_level_dn=0, seed=0,
    )  # fmt: skip
    # Lattice sites with a whole spot inside the frame: 18 x 18 of them.
    sites = np.arange(-60, 60) * PITCH_PX - 300.0
    inside = np.count_nonzero((sites > 1) & (sites < 199))
    _, dots = ndimage.label(sim["capture"] > 0)
    assert inside == 18 and dots >= 0.95 * inside**2


def test_plate_far_field_refuses_a_tile_that_is_not_square():
    with pytest.raises(ValueError, match="square"):
        plate_far_field(np.zeros((8, 12)))


def _same_phase(a, b):
    np.testing.assert_allclose(np.exp(1j * a), np.exp(1j * b), rtol=0, atol=1e-12)


def test_plate_phase_is_the_level_model_with_its_etch_faults():
    lv = np.random.default_rng(2).integers(0, L, (12, 12)).astype(np.uint8)
    _same_phase(plate_phase(lv, L), 2 * np.pi * lv / L)
    # etch and glass swapped: level l is made as L - 1 - l
    _same_phase(plate_phase(lv, L, PlateFaults(conjugate=True)), 2 * np.pi * (L - 1 - lv) / L)
    # the deep mask etches L/2 steps (pi) into levels 0 .. L/2 - 1; 15 % too deep takes
    # another 0.15 pi of glass off those pixels and leaves the others alone
    for eps in (0.15, -0.1):
        faulty = plate_phase(lv, L, PlateFaults(etch_errors=(eps, 0.0, 0.0)))
        _same_phase(faulty, 2 * np.pi * lv / L - eps * np.pi * (lv < L // 2))


@pytest.mark.parametrize("supersample", [1, 2, 3])
def test_plate_phase_overlay_moves_one_mask_up_and_right(supersample):
    # +y is up (towards row 0), +x to the right; a whole-pixel shift is the same at any
    # supersampling. Mask 1 etches 2 steps: bit 2 of the etch code L - 1 - level.
    lv = np.random.default_rng(3).integers(0, L, (12, 12)).astype(np.uint8)
    pitch = 5e-6
    faults = PlateFaults(overlay=((0.0, 0.0), (-2 * pitch, pitch), (0.0, 0.0)))  # left 2, up 1
    code = (L - 1) - lv.astype(int)
    moved = (code & ~2) | np.roll(code & 2, (-1, -2), axis=(0, 1))
    expected = np.kron(2 * np.pi * ((L - 1) - moved) / L, np.ones((supersample, supersample)))
    _same_phase(plate_phase(lv, L, faults, pitch, supersample), expected)


def test_plate_phase_needs_the_pixel_pitch_to_shift_a_mask():
    lv = np.zeros((4, 4), np.uint8)
    faults = PlateFaults(overlay=((0.0, 0.0), (0.0, 1e-6), (0.0, 0.0)))
    with pytest.raises(ValueError, match="an overlay shift needs mask_pixel_pitch"):
        plate_phase(lv, L, faults)


def _blazed():
    """Levels 0..7 along each row: a phase ramp that sends all light into order (0, +1)."""
    return np.tile(np.arange(L, dtype=np.uint8), (L, 1))


@pytest.mark.parametrize(
    "orientation, step, centre",
    [
        ("as-designed", (0, 1), (30.3, 29.6)),
        ("rot90", (-1, 0), (30.3, 29.6)),  # design right is camera up
        ("mirror-x", (0, -1), None),  # default centre: the middle of the frame
    ],
)
def test_a_single_order_lands_where_the_rotated_scaled_lattice_puts_it(orientation, step, centre):
    # Order (0, 1) of a blazed grating is the only one in the frame. Its dot is a Gaussian
    # of sigma^2 = spot^2 + blur^2 integrated over the pixels: its centroid is the lattice
    # site and its variance sigma^2 + 1/12 along each axis (to exp(-2 pi^2 sigma^2)).
    shape, pitch, scale, theta = (61, 61), 10.0, 1.1, np.radians(20.0)
    sim = simulate_capture(
        _blazed(), L, shape=shape, pitch_px=pitch, scale=scale, rotation_deg=20.0,
        orientation=orientation, centre=centre, spot_sigma_px=1.0, blur_sigma_px=1.5,
        full_well_e=1e9, read_noise_dn=0.0, dark_level_dn=0.0, bits=16,
    )  # fmt: skip
    zero = np.array(centre if centre is not None else ((shape[0] - 1) / 2, (shape[1] - 1) / 2))
    assert np.allclose(sim["zero_order_px"], zero)
    down = scale * pitch * np.array([np.cos(theta), np.sin(theta)])  # (row, col), CCW shown
    right = scale * pitch * np.array([-np.sin(theta), np.cos(theta)])
    site = zero + step[0] * down + step[1] * right
    img = sim["capture"].astype(float)
    rows, cols = np.indices(shape)
    total = img.sum()
    centroid = np.array([(img * rows).sum(), (img * cols).sum()]) / total
    assert np.allclose(centroid, site, atol=0.01)
    var = [(img * (rows - centroid[0]) ** 2).sum() / total,
           (img * (cols - centroid[1]) ** 2).sum() / total]  # fmt: skip
    assert np.allclose(var, 1.0**2 + 1.5**2 + 1 / 12, rtol=0.01)
    # exposure: the brightest pixel at peak_fraction (0.7) of full scale
    assert img.max() == pytest.approx(0.7 * 65535, rel=1e-3)


def test_a_capture_that_no_order_reaches_is_refused():
    # orders 1000 px apart, the zero order 500 px left of a 61 px frame: its neighbour
    # to the right lands at column 500, 440 px past the frame's last column
    with pytest.raises(ValueError, match="no order lands in the frame"):
        simulate_capture(_blazed(), L, shape=(61, 61), pitch_px=1000.0, centre=(30.0, -500.0))


def test_every_order_that_reaches_the_frame_is_drawn_even_past_its_far_edge():
    # Levels 0, 2, 4, 6 along each row send all light into order (0, +2), here the lattice
    # site two pitches right of a zero order on the left edge: column 199.5, the frame's
    # right edge, 199.01 px from the farthest corner. Columns 199 and 198 hold the 0..1 and
    # 1..2 sigma slices of its dot.
    from scipy.special import erf

    grating = np.tile((2 * np.arange(L) % L).astype(np.uint8), (L, 1))
    sim = simulate_capture(
        grating, L, shape=(5, 200), pitch_px=99.75, centre=(2.0, 0.0), spot_sigma_px=1.0,
        full_well_e=1e9, read_noise_dn=0.0, dark_level_dn=0.0, bits=16,
    )  # fmt: skip
    cap = sim["capture"].astype(float)
    assert cap[2, 199] == cap.max() > 0
    phi = 0.5 * (1 + erf(np.array([0.0, 1.0, 2.0]) / np.sqrt(2)))
    expected = (phi[2] - phi[1]) / (phi[1] - phi[0])
    assert cap[2, 198] / cap[2, 199] == pytest.approx(expected, rel=0.01)


def test_capture_noise_is_poisson_electrons_and_read_noise_in_dn():
    # A uniform plate: one dot. Across seeds a pixel of mean S electrons reads, in DN,
    # S / g + pedestal with variance S / g^2 + read^2 + 1/12 (g electrons per DN);
    # the dark frame reads the pedestal with read^2 + 1/12.
    flat = np.zeros((8, 8), np.uint8)
    full_well, read, pedestal = 20000.0, 3.0, 100.0
    gain = full_well / 4095
    caps, darks = [], []
    for seed in range(60):
        sim = simulate_capture(
            flat, L, shape=(15, 15), pitch_px=60.0, spot_sigma_px=2.0, full_well_e=full_well,
            read_noise_dn=read, dark_level_dn=pedestal, seed=seed,
        )  # fmt: skip
        caps.append(sim["capture"] >> 4)  # 12-bit data MSB-aligned in 16 bits
        darks.append(sim["dark"] >> 4)
    assert sim["capture"].dtype == np.uint16 and not np.any(sim["capture"] & 0xF)
    caps, darks = np.array(caps, float), np.array(darks, float)
    assert darks.mean() == pytest.approx(pedestal, abs=0.15)
    assert darks.std() == pytest.approx(np.sqrt(read**2 + 1 / 12), rel=0.05)
    lit = caps.mean(axis=0) > pedestal + 200  # the dot's core, S > 500 electrons
    assert lit.sum() >= 20
    signal = (caps.mean(axis=0)[lit] - pedestal) * gain
    expected = signal / gain**2 + read**2 + 1 / 12
    assert caps.var(axis=0, ddof=1)[lit].sum() / expected.sum() == pytest.approx(1, abs=0.1)
    # seeded: the same seed makes the same frames, another seed others
    again = simulate_capture(flat, L, shape=(15, 15), pitch_px=60.0, spot_sigma_px=2.0,
                             full_well_e=full_well, read_noise_dn=read, dark_level_dn=pedestal,
                             seed=59)  # fmt: skip
    assert np.array_equal(again["capture"] >> 4, caps[-1])
    assert np.array_equal(again["dark"] >> 4, darks[-1])
    assert not np.array_equal(caps[-1], caps[-2])


def test_hot_pixels_are_the_same_in_capture_and_dark_at_a_fifth_to_nine_tenths_of_full_scale():
    flat = np.zeros((8, 8), np.uint8)
    sim = simulate_capture(
        flat, L, shape=(40, 40), pitch_px=200.0, centre=(5.0, 5.0), hot_pixels=12,
        read_noise_dn=1.0, dark_level_dn=50.0, seed=4,
    )  # fmt: skip
    cap, dark = sim["capture"] >> 4, sim["dark"] >> 4
    hot = dark > 50 + 0.1 * 4095
    assert hot.sum() == 12
    away = hot.copy()
    away[:15, :15] = False  # off the dot
    assert away.sum() >= 8
    # the same hot electrons drawn twice: Poisson of <= 9000 e, sigma < 100 e = 41 DN each
    assert np.all(np.abs(cap[away].astype(float) - dark[away]) < 6 * np.sqrt(2) * 41)
    level = dark[hot] - 50.0
    assert np.all(level > 0.2 * 4095 - 150) and np.all(level < 0.9 * 4095 + 150)
