"""The camera model (doe.camera): against hcipy's propagation and closed forms.

Small designs (tiles of 28-35 mask pixels, a few tiles across a 3-3.5 mm
aperture, K = 5) keep each evaluation well under a second.
"""

import math

import numpy as np
import pytest
import scipy.special

from doe.camera import effective_psf, plate_orders
from doe.camera_figure import sensor_view
from doe.derived import derive
from doe.design import load_design
from doe.fraunhofer import level_phase, pixel_envelope, rmse, window_power
from doe.spectrum import Spectrum

DESIGNS = {
    # the default preset with 25 um mask pixels (N = 35), four tiles across 3.5 mm
    "fs655": "[psf]\nkernel_size = 5\n[fabrication]\nfeature_size_um = 25.0\naperture_mm = 3.5\n",
    # 532 nm, BK7, 4 levels (N = 28)
    "bk7532": (
        "[optics]\nwavelength_nm = 532.0\n[material]\nname = 'bk7'\n[psf]\nkernel_size = 5\n"
        "[fabrication]\nlevels = 4\nfeature_size_um = 25.0\naperture_mm = 3.0\n"
    ),
}


def design(tmp_path, name, aperture_mm=None):
    path = tmp_path / f"{name}.toml"
    text = DESIGNS[name]
    if aperture_mm is not None:
        text = text.replace("aperture_mm = 3.5", f"aperture_mm = {aperture_mm}")
    path.write_text(text)
    return load_design(path)


def window_tile(d, seed=0):
    """A level map that puts most of its light into the K x K window (as a designed one does)."""
    n, k, n_levels = derive(d).tile_pixels, d.kernel_size, d.fabrication.levels
    rng = np.random.default_rng(seed)
    spectrum = np.zeros((n, n), complex)
    idx = (np.arange(k) - k // 2) % n
    spectrum[np.ix_(idx, idx)] = rng.normal(size=(k, k)) + 1j * rng.normal(size=(k, k))
    phase = np.angle(np.fft.ifft2(spectrum))
    return (np.round(phase / (2 * np.pi) * n_levels) % n_levels).astype(np.uint8)


def hcipy_psf(d, levels, spectrum, f_number=None, defocus=0.0, rotation_deg=0.0, samples=6):
    """E from hcipy: the whole pupil sampled ``samples`` x ``samples`` per mask pixel (whose
    point samples dim order m by (pi m / N)^2 / (3 samples^2) against square pixels), a
    Fraunhofer propagator to a 1 um focal grid, the intensity summed over each active
    area's cells."""
    hcipy = pytest.importorskip("hcipy")
    n = levels.shape[0]
    der = derive(d, n)
    f, q, a_side = d.optics.focal_length, der.mask_pixel_pitch, d.fabrication.aperture
    diameter = 2 * a_side if f_number is None else f / f_number
    du = q / samples
    turn = math.radians(rotation_deg)  # the plate turned counter-clockwise
    reach = a_side * (abs(math.cos(turn)) + abs(math.sin(turn)))  # the turned square's width
    m = math.ceil(min(reach, diameter) / du) + 2
    m += m % 2  # the samples sit between the pixel edges, never on one
    pupil = hcipy.make_uniform_grid([m, m], [m * du, m * du])
    x, y = pupil.x, pupil.y
    xp, yp = math.cos(turn) * x + math.sin(turn) * y, -math.sin(turn) * x + math.cos(turn) * y
    corner = -der.tiles * der.tile_size / 2
    col = np.floor((xp - corner) / q).astype(int) % n
    row = np.floor((corner - yp) / q).astype(int) % n  # row 0 at a tile's top edge
    inside = (np.abs(xp) < a_side / 2) & (np.abs(yp) < a_side / 2) & (np.hypot(x, y) < diameter / 2)
    k, s = d.kernel_size, d.sensor
    p, r = s.pixel_pitch / s.superres_factor, s.active_area / 2
    dx = 1e-6
    nf = math.ceil(2 * (k // 2 * p + r + 2e-6) / dx)
    focal = hcipy.make_uniform_grid([nf, nf], [nf * dx, nf * dx])
    prop = hcipy.FraunhoferPropagator(pupil, focal, focal_length=f + defocus)
    intensity = 0.0
    for wl, weight in zip(spectrum.wavelengths, spectrum.weights, strict=True):
        n_glass = d.material.dispersion.index(wl)
        phase = 2 * np.pi * (n_glass - 1) * levels[row, col] * der.level_step / wl
        phase -= np.pi * defocus * (x**2 + y**2) / (wl * f * (f + defocus))
        wf = prop(hcipy.Wavefront(hcipy.Field(inside * np.exp(1j * phase), pupil), wl))
        intensity = intensity + weight * np.abs(np.asarray(wf.electric_field)) ** 2
    sub = (np.arange(4) + 0.5) / 4 - 0.5
    e = np.zeros((k, k))
    for i in range(k):
        for j in range(k):
            cx, cy = (j - k // 2) * p, -(i - k // 2) * p
            near = np.hypot(focal.x - cx, focal.y - cy) < r + dx
            frac = sum(
                np.hypot(focal.x[near] + sx * dx - cx, focal.y[near] + sy * dx - cy) < r
                for sx in sub
                for sy in sub
            )
            e[i, j] = np.sum(intensity[near] * frac / 16) * dx**2
    return e / (inside.sum() * du**2)


@pytest.mark.parametrize(
    "name, settings",
    [
        ("fs655", {"f_number": 16, "defocus": 200e-6, "band": (-6, 6)}),
        ("fs655", {"defocus": 100e-6}),
        ("bk7532", {"f_number": 12, "rotation_deg": 4.0}),  # a disc the square clips
        ("bk7532", {"band": (-5, 0, 5)}),
    ],
)
def test_the_effective_psf_agrees_with_hcipy(tmp_path, name, settings):
    d = design(tmp_path, name)
    levels = window_tile(d)
    wl = d.optics.wavelength
    offsets = settings.get("band", (0,))
    weights = np.exp(-0.5 * (np.array(offsets) / 4.0) ** 2)
    spectrum = Spectrum(
        tuple(wl + o * 1e-9 for o in offsets), tuple(weights / weights.sum()), "test lines"
    )
    f_number, defocus = settings.get("f_number"), settings.get("defocus", 0.0)
    rotation = settings.get("rotation_deg", 0.0)
    got = effective_psf(
        d, levels, spectrum=spectrum, f_number=f_number, defocus_um=defocus * 1e6,
        rotation_deg=rotation,
    )  # fmt: skip
    ref = hcipy_psf(d, levels, spectrum, f_number, defocus, rotation)
    assert np.abs(got.collected - ref).max() <= 2e-3 * ref.max()
    assert got.collected_fraction == pytest.approx(ref.sum(), abs=2e-3)
    assert got.psf.sum() == pytest.approx(1.0) and got.psf.min() >= 0


def test_a_lone_dot_collects_the_airy_encircled_energy(tmp_path):
    # a flat plate has one order: a round stop's Airy dot; a disc of radius a about its
    # centre holds 1 - J0(v)^2 - J1(v)^2, v = pi a / (lambda N)
    d = design(tmp_path, "fs655")
    n = derive(d).tile_pixels
    for f_number in (16.0, 24.0):
        e = effective_psf(d, np.zeros((n, n), np.uint8), f_number=f_number).collected
        v = math.pi * d.sensor.active_area / 2 / (d.optics.wavelength * f_number)
        closed = 1 - scipy.special.j0(v) ** 2 - scipy.special.j1(v) ** 2
        assert e[2, 2] == pytest.approx(closed, abs=1.5e-3)


def test_the_zero_order_of_a_staircase_off_its_wavelength(tmp_path):
    # an L-level staircase delays 2 pi beta l / L at lambda, beta = (n - 1) lambda0 /
    # ((n0 - 1) lambda): its zero order carries |sin(pi beta) / (L sin(pi beta / L))|^2
    d = design(tmp_path, "bk7532")
    n_levels, der = d.fabrication.levels, derive(d)
    n = 4 * n_levels * 3
    levels = np.tile(np.repeat(np.arange(n_levels, dtype=np.uint8), 3), (n, 4))
    glass, wl0 = d.material.dispersion, d.optics.wavelength
    for wl in (450e-9, 532e-9, 633e-9):
        c = plate_orders(d, levels * der.level_step, wl)
        beta = (glass.index(wl) - 1) * wl0 / ((glass.index(wl0) - 1) * wl)
        closed = (math.sin(math.pi * beta) / (n_levels * math.sin(math.pi * beta / n_levels))) ** 2
        assert abs(c[0, 0]) ** 2 == pytest.approx(closed, abs=1e-12)
    assert abs(plate_orders(d, levels * der.level_step, wl0)[0, 0]) < 1e-12


def blazed(d, periods):
    """A staircase of ``periods`` periods across the tile: its light goes to order (0, periods)."""
    n, n_levels = derive(d).tile_pixels, d.fabrication.levels
    cols = np.arange(n) * periods * n_levels // n % n_levels
    return np.tile(cols.astype(np.uint8), (n, 1))


def centroid(image, dx, centre, half):
    """Intensity centroid (x, y) of ``image`` (rows towards +y, point n // 2 on the axis)
    within ``half`` of ``centre``."""
    n = image.shape[0]
    xs = (np.arange(n) - n // 2) * dx
    x, y = np.meshgrid(xs, xs)
    box = (np.abs(x - centre[0]) < half) & (np.abs(y - centre[1]) < half)
    w = image * box
    return np.array([np.sum(w * x), np.sum(w * y)]) / w.sum()


def test_the_lattice_pitch_grows_with_the_wavelength(tmp_path):
    d = design(tmp_path, "fs655")
    der = derive(d)
    for scale in (0.9, 1.0, 1.1):
        wl = d.optics.wavelength * scale
        r = effective_psf(d, blazed(d, 2), spectrum=Spectrum((wl,), (1.0,), "line"))
        x = 2 * wl * d.optics.focal_length / der.tile_size
        got = centroid(r.sensor, r.sensor_dx, (x, 0.0), 12e-6)
        assert got == pytest.approx([x, 0.0], abs=0.3e-6)


def test_rotation_turns_the_lattice_counter_clockwise(tmp_path):
    d = design(tmp_path, "bk7532")
    levels = window_tile(d, seed=3)
    for f_number in (None, 20.0):
        still = effective_psf(d, levels, f_number=f_number).collected
        turned = effective_psf(d, levels, f_number=f_number, rotation_deg=90.0).collected
        # rows grow towards -y: the array as printed is the sensor as viewed
        assert turned == pytest.approx(np.rot90(still), abs=1e-9 * still.max())
    r = effective_psf(d, blazed(d, 2), rotation_deg=4.0)
    view, _ = sensor_view(r, 4.0)
    x = 2 * d.optics.wavelength * d.optics.focal_length / derive(d).tile_size
    expected = x * np.array([math.cos(math.radians(4)), math.sin(math.radians(4))])
    assert centroid(view, r.sensor_dx, expected, 12e-6) == pytest.approx(expected, abs=0.3e-6)


def test_the_effective_psf_tends_to_the_window_powers_as_the_stop_grows(tmp_path):
    errors = []
    for aperture in (3.5, 7.0, 14.0):
        d = design(tmp_path, "fs655", aperture)
        levels = window_tile(d, seed=1)
        n, k = levels.shape[0], d.kernel_size
        env = pixel_envelope(np.arange(k) - k // 2, n)
        window = window_power(level_phase(levels, 8), k) * np.outer(env, env)
        e = effective_psf(d, levels).collected
        errors.append(np.abs(e - window).max() / window.max())
    # the square stop's sinc^2 dot spills ~ lambda f / D beyond an active area: the
    # error halves with each doubling of the stop
    assert errors[1] == pytest.approx(errors[0] / 2, rel=0.15)
    assert errors[2] == pytest.approx(errors[1] / 2, rel=0.15)


def test_the_budget_curves_are_the_effective_psfs_and_end_where_they_cross_the_limit(tmp_path):
    from doe.camera_budget import RESOLUTION, camera_budget

    d = design(tmp_path, "bk7532")
    levels = window_tile(d, seed=2)
    target = effective_psf(d, levels).psf  # the default camera meets its own PSF exactly
    axes = {"bandwidth_nm": (0.0, 10.0, 40.0), "defocus_um": (-300.0, 0.0, 20.0, 300.0)}
    budget = camera_budget(d, levels, target, axes)
    assert budget["nominal"]["rmse"] == pytest.approx(0.0, abs=1e-5)  # its grid: the band's
    limit = budget["limit"]["rmse_max"]
    assert limit == budget["nominal"]["rmse"] + 0.01
    for axis, values in axes.items():
        curve = budget["axes"][axis]
        assert set(values) <= set(curve["values"]) and curve["values"] == sorted(curve["values"])
        figures = list(
            zip(curve["values"], curve["correlation"], curve["collected_fraction"], strict=True)
        )
        for value, corr, cf in figures[:: max(1, len(figures) // 3)]:
            alone = effective_psf(d, levels, **{axis: value})
            assert cf == pytest.approx(alone.collected_fraction, abs=1e-5)
            assert corr == pytest.approx(np.corrcoef(alone.psf.ravel(), target.ravel())[0, 1])
        lo, hi = curve["within_budget"]["range"]
        rows = zip(curve["values"], curve["rmse"], strict=True)
        assert all(r <= limit for v, r in rows if lo <= v <= hi)
    # the design goals hold around the nominal camera (its own PSF is the target) and
    # nowhere else: the run's ends part the points that meet them from those that miss
    curve = budget["axes"]["defocus_um"]
    goals = curve["within_goals"]
    assert goals["nominal"] and len(goals["runs"]) == 1
    lo, hi = goals["runs"][0]
    assert -300 < lo < 0 < hi < 300
    for v, c, r in zip(curve["values"], curve["correlation"], curve["rmse"], strict=True):
        assert (lo <= v <= hi) == (c >= 0.9999 and r <= 0.005)
    # defocus: 300 um misses the limit both ways; each end lies within a bisected interval
    within = budget["axes"]["defocus_um"]["within_budget"]
    assert within["ends"] == ["limit", "limit"] and -300 < within["range"][0] < 0
    for end, out in zip(within["range"], (-1, 1), strict=True):
        step = RESOLUTION["defocus_um"]
        inside = effective_psf(d, levels, defocus_um=end - out * step).psf
        outside = effective_psf(d, levels, defocus_um=end + out * step).psf
        assert rmse(inside, target) <= limit < rmse(outside, target)
