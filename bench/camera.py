"""The camera model's cost and convergence (doe.camera), on the default design.

    python bench/camera.py [--quick | --budget]

Prints
1. seconds for one effective PSF: a 40 nm band at f/2 (the goal: <= 2 s), and the
   default camera;
2. seconds for the budget curves (doe.camera_budget.BUDGET_AXES) and for the fab
   report's budget (doe.camera_budget.camera_budget, bisected range ends, and its
   figure); with --budget only this, and the budget's range ends against those of
   finely sampled curves (--budget-fine: every 10 um, 0.05 deg, 1 nm, 2 % in N);
3. convergence in the model's sampling: the order margin and the spectral step,
   each halved and doubled, as the largest change of E over its peak and of the
   collected fraction;
4. the model against an independent whole-aperture calculation: the plate, stop and
   defocus sampled 1 x 1 or 2 x 2 per mask pixel over the whole pupil, one FFT, the
   intensity integrated over each active area as an exact Fourier sum (a period of
   6.5 mm or more leaves no tail to wrap). One sample per pixel is the point-pixel
   model, whose window orders differ from square pixels' by up to (pi m / N)^2 / 3,
   2.7e-3 at the window's edge for N = 175.
"""

import argparse
import math
import time
from pathlib import Path

import numpy as np
import scipy.fft

import doe.camera as camera
from doe.camera import effective_psf
from doe.camera_budget import budget_settings, camera_figures
from doe.camera_optics import Grid, integrate_areas, stop_area
from doe.derived import derive
from doe.design import load_design
from doe.fraunhofer import simulate_levels

LEVELS = Path(__file__).resolve().parents[1] / "tests" / "data" / "default_levels.npy"


def seconds(fn, repeat=3):
    """Return the least wall and CPU seconds of ``repeat`` calls (on a shared machine the
    CPU time of this process says more: BLAS threads wait on the other loads)."""
    wall, cpu = [], []
    for _ in range(repeat):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return min(wall), min(cpu)


def whole_aperture(d, levels, f_number, defocus, samples=2, n_fft=4096):
    """E by an FFT of the whole pupil sampled ``samples`` x ``samples`` per mask pixel."""
    n = levels.shape[0]
    der = derive(d, n)
    q, period, a_side = der.mask_pixel_pitch, der.tile_size, d.fabrication.aperture
    f, wl = d.optics.focal_length, d.optics.wavelength
    diameter = math.inf if f_number is None else f / f_number
    du = q / samples
    m = math.ceil(min(diameter, a_side) / du) + 2
    m += m % 2
    u = (np.arange(m) - m // 2 + 0.5) * du  # between the pixel edges
    corner = -der.tiles * period / 2
    col = np.floor((u - corner) / q).astype(int) % n
    row = np.floor((corner - u) / q).astype(int) % n
    phase = 2 * np.pi * levels[np.ix_(row, col)] / d.fabrication.levels
    r2 = u[:, None] ** 2 + u[None, :] ** 2
    stop = (np.abs(u)[:, None] < a_side / 2) & (np.abs(u)[None, :] < a_side / 2)
    stop &= r2 < diameter**2 / 4  # the square clear aperture within the round stop
    area = stop_area(a_side, None if f_number is None else diameter)
    f_image = f + defocus
    pupil = np.exp(1j * (phase - np.pi * defocus * r2 / (wl * f * f_image))) * stop
    big = np.zeros((n_fft, n_fft), np.complex64)
    o = n_fft // 2 - m // 2
    big[o : o + m, o : o + m] = pupil
    field = scipy.fft.fftshift(scipy.fft.fft2(scipy.fft.ifftshift(big))) * du**2 / (wl * f_image)
    dx = wl * f_image / (n_fft * du)
    if dx >= wl * f_image / (2 * min(diameter, a_side)):
        raise ValueError("the FFT is too small to sample the intensity without aliasing")
    intensity = np.abs(field.astype(complex)) ** 2 / area
    k, s = d.kernel_size, d.sensor
    centres = camera.window_centres(k, s.pixel_pitch / s.superres_factor, 0.0)
    e = integrate_areas(intensity, Grid(n_fft, dx), centres, s.active_area_shape, s.active_area, 0)
    return e.reshape(k, k)


def change(a, b):
    return np.abs(a.collected - b.collected).max() / b.collected.max(), abs(
        a.collected_fraction - b.collected_fraction
    )


def convergence(d, levels, quick):
    cases = [{}, {"f_number": 4.0}, {"f_number": 16.0, "defocus_um": 200.0}]
    if not quick:
        cases += [{"defocus_um": 200.0, "rotation_deg": 4.0}, {"f_number": 8.0, "bandwidth_nm": 20}]
    print("\norder margin (sub-pixels): E change / peak, collected-fraction change, vs 2x")
    for kw in cases:
        base = effective_psf(d, levels, **kw)
        m = base.settings["margin_subpixels"]
        finer = effective_psf(d, levels, margin_subpixels=2 * m, **kw)
        coarser = effective_psf(d, levels, margin_subpixels=m / 2, **kw)
        print(
            f"  {kw}: margin {m:.1f}: {change(base, finer)[0]:.1e} / {change(base, finer)[1]:.1e}"
            f"; margin {m / 2:.1f}: {change(coarser, finer)[0]:.1e} / "
            f"{change(coarser, finer)[1]:.1e}  ({base.seconds:.2f} s)"
        )
    print("\nspectral step (dot radii per outermost order): change vs a step 4x finer")
    default = camera.SPECTRAL_STEP_DOTS
    for kw in ({"bandwidth_nm": 40.0}, {"bandwidth_nm": 20.0, "f_number": 8.0}):
        results = {}
        for factor in (0.25, 0.5, 1.0, 2.0):
            camera.SPECTRAL_STEP_DOTS = default * factor
            results[factor] = effective_psf(d, levels, **kw)
        camera.SPECTRAL_STEP_DOTS = default
        for factor in (0.5, 1.0, 2.0):
            r = results[factor]
            e, cf = change(r, results[0.25])
            n = len(r.settings["spectrum"]["wavelengths_nm"])
            print(f"  {kw} step x{factor:g} ({n} wavelengths): {e:.1e} / {cf:.1e}")


def independent(d, levels):
    print("\nagainst the whole-aperture FFT (E change / peak, collected fraction model - FFT)")
    cases = ((16.0, 200e-6, 2, 4096), (8.0, 0.0, 1, 4096), (4.0, 100e-6, 1, 8192))
    cases += ((3.0, 0.0, 1, 8192),)  # a disc the square clear aperture clips
    for f_number, defocus, samples, n_fft in cases:
        start = time.perf_counter()
        ref = whole_aperture(d, levels, f_number, defocus, samples, n_fft)
        spent = time.perf_counter() - start
        got = effective_psf(d, levels, f_number=f_number, defocus_um=defocus * 1e6)
        diff = np.abs(got.collected - ref).max() / ref.max()
        print(
            f"  f/{f_number:g}, defocus {defocus * 1e6:g} um ({samples} x {samples} samples "
            f"per pixel): {diff:.1e}, {got.collected_fraction - ref.sum():+.1e} "
            f"(model {got.seconds:.2f} s, FFT {spent:.1f} s)"
        )


GREEN = (
    "name = 'green'\n[optics]\nwavelength_nm = 532.0\n[material]\nname = 'bk7'\n"
    "[fabrication]\nlevels = 4\naperture_mm = 12.7\n"
)


def green_design(tmp):
    """A 532 nm / BK7 / 4-level / 12.7 mm design (N = 142, 17 tiles) and a tile that puts
    its light into the window (random window orders, quantised)."""
    path = Path(tmp) / "green.toml"
    path.write_text(GREEN)
    d = load_design(path)
    n, k, n_levels = derive(d).tile_pixels, d.kernel_size, d.fabrication.levels
    rng = np.random.default_rng(5)
    spectrum = np.zeros((n, n), complex)
    idx = (np.arange(k) - k // 2) % n
    spectrum[np.ix_(idx, idx)] = rng.normal(size=(k, k)) + 1j * rng.normal(size=(k, k))
    phase = np.angle(np.fft.ifft2(spectrum))
    return d, (np.round(phase / (2 * np.pi) * n_levels) % n_levels).astype(np.uint8)


def independent_green():
    import tempfile

    print("\n532 nm / BK7 / 4 levels / 12.7 mm against the whole-aperture FFT (samples/pixel)")
    with tempfile.TemporaryDirectory() as tmp:
        d, levels = green_design(tmp)
    for f_number, defocus, samples in ((16.0, 0.0, 1), (16.0, 0.0, 2), (16.0, 0.0, 3),
                                       (16.0, 200e-6, 3)):  # fmt: skip
        ref = whole_aperture(d, levels, f_number, defocus, samples, 4096)
        got = effective_psf(d, levels, f_number=f_number, defocus_um=defocus * 1e6)
        diff = np.abs(got.collected - ref).max() / ref.max()
        print(
            f"  f/{f_number:g}, defocus {defocus * 1e6:g} um, {samples} x {samples}: {diff:.1e}, "
            f"{got.collected_fraction - ref.sum():+.1e}"
        )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer convergence cases, no FFT")
    parser.add_argument(
        "--budget", action="store_true", help="only the report budget against fine curves"
    )
    args = parser.parse_args()
    d = load_design()
    levels = np.load(LEVELS)
    target = simulate_levels(levels, d.fabrication.levels, d.kernel_size)[0]
    if args.budget:
        budget_against_fine(d, levels, target)
        return
    for name, kw in (
        ("40 nm band at f/2", {"bandwidth_nm": 40.0, "f_number": 2.0}),
        ("the default camera", {}),
        ("20 nm band at f/4, 100 um defocus", {"bandwidth_nm": 20.0, "f_number": 4.0,
                                               "defocus_um": 100.0}),
    ):  # fmt: skip
        wall, cpu = seconds(lambda kw=kw: effective_psf(d, levels, **kw))
        print(f"one effective PSF, {name}: {wall:.2f} s wall, {cpu:.2f} s CPU (best of 3)")
    points = budget_settings()
    wall, cpu = seconds(lambda: camera_figures(d, levels, target, [s for _, s in points]), 1)
    figures = camera_figures(d, levels, target, [s for _, s in points])
    print(f"budget curves, {len(points)} settings: {wall:.1f} s wall, {cpu:.1f} s CPU")
    for (axis, s), f in zip(points, figures, strict=True):
        print(
            f"  {axis} {s[axis]:g}: correlation {f['correlation']:.4f} rmse {f['rmse']:.4f} "
            f"collected {f['collected_fraction']:.4f}"
        )
    convergence(d, levels, args.quick)
    if not args.quick:
        independent(d, levels)
        independent_green()


FINE_AXES = {
    "bandwidth_nm": tuple(np.arange(0.0, 40.5, 1.0)),
    "f_number": tuple(np.round(1.8 * 1.02 ** np.arange(0, 112), 4)),
    "defocus_um": tuple(np.arange(-500.0, 501.0, 10.0)),
    "rotation_deg": tuple(np.arange(0.0, 5.01, 0.05)),
}


def budget_against_fine(d, levels, target):
    """The fab report's budget: its cost, and its range ends against finely sampled curves."""
    import tempfile

    from doe.camera_budget import budget_range, camera_budget
    from doe.camera_figure import save_budget_figure

    wall, cpu = seconds(lambda: camera_budget(d, levels, target), 1)
    budget = camera_budget(d, levels, target)
    with tempfile.TemporaryDirectory() as tmp:
        f_wall, f_cpu = seconds(lambda: save_budget_figure(Path(tmp) / "b.png", budget), 1)
    points = sum(len(c["values"]) for c in budget["axes"].values())
    print(
        f"report budget, {points} points: {wall:.1f} s wall, {cpu:.2f} s CPU; "
        f"its figure {f_wall:.1f} s wall, {f_cpu:.2f} s CPU"
    )
    nominal, limit = budget["nominal"], budget["limit"]["rmse_max"]
    print(
        f"  nominal camera: correlation {nominal['correlation']:.5f} rmse {nominal['rmse']:.4f} "
        f"collected {nominal['collected_fraction']:.4f}; limit rmse {limit:.4f}"
    )
    for axis, values in FINE_AXES.items():
        figures = camera_figures(d, levels, target, [{axis: float(v)} for v in values])
        fine = budget_range(axis, [float(v) for v in values], [f["rmse"] for f in figures], limit)
        mine = budget["axes"][axis]["within_budget"]
        print(f"  {axis}: report {_ends(mine)}, fine ({len(values)} points) {_ends(fine)}")


def _ends(within):
    if within["range"] is None:
        return within["why"]
    lo, hi = within["range"]
    return f"{lo:.4g} .. {hi:.4g} ({', '.join(within['ends'])})"


if __name__ == "__main__":
    main()
