"""The plate in a camera: the effective PSF that the SPAD's active areas sample.

:func:`effective_psf` images a point source at infinity through the tiled plate
and the lens (:mod:`doe.camera_optics`: scalar, paraxial, thin element) for a
spectrum (:mod:`doe.spectrum`), a stop, a defocus and a rotation of the plate, and
integrates the sensor-plane intensity over an active area (the design's shape and
size) centred on each sub-pixel offset of the K x K window:

    E[i, j] = fraction of the light through the stop that an active area centred at
              ((j - K//2) p, -(i - K//2) p) from the point's geometric image collects,
              averaged over the spectrum's weights (rows grow towards -y).

At the design wavelength, in focus and unrotated, E tends to the window powers of
the plate of square pixels (``doe.fraunhofer.plate_quality``) as the stop grows.

Conventions: ``defocus`` Z > 0 puts the sensor Z behind the image plane (further
from the lens); ``rotation`` R > 0 turns the plate counter-clockwise as the PSF is
viewed (x right, y up), which turns the dot lattice the same way. The tiled area is
centred on the axis (a tile corner at -tiles T / 2), and the pattern fills the clear
aperture periodically.
"""

import math
import time
from dataclasses import dataclass, field

import numpy as np

from doe.camera_optics import (
    integrate_areas,
    plan_grid,
    rotate,
    sensor_intensity,
    stop_extent,
    tile_coefficients,
)
from doe.derived import derive
from doe.fraunhofer import correlation, rmse
from doe.infra.errors import InputError
from doe.spectrum import gaussian_band, monochromatic

# Orders are kept whose dots land within a margin of the window's reach (the window
# plus an active area): at least MARGIN_SUBPIXELS sub-pixel pitches, and for a round
# stop (whose tails wrap around the sensor grid's period) MARGIN_DOTS dot radii
# lambda N. bench/camera.py measures the convergence against a whole-aperture FFT.
MARGIN_SUBPIXELS = 6.0
MARGIN_DOTS = 200.0
# A band is sampled so that the window's outermost dot moves at most this fraction
# of the dot's radius (lambda N) between two wavelengths.
SPECTRAL_STEP_DOTS = 1.0


@dataclass(frozen=True)
class CameraOptics:
    """The lens and the plate's geometry (SI units; ``stop_diameter`` None: the square)."""

    focal_length: float
    tile_period: float
    aperture: float
    stop_diameter: float | None
    defocus: float
    rotation: float
    tiles: int


@dataclass(frozen=True)
class CameraResult:
    """The effective PSF and how it was computed.

    ``psf`` is E normalised to sum 1 (the PSF contract); ``collected`` is E itself
    (the fraction of the light through the stop each active area collects) and
    ``collected_fraction`` its sum. ``sensor`` is the spectrum-averaged intensity
    around the window (per unit power through the stop, per m^2) on a grid ``dx``
    apart in the plate's frame, point n // 2 on the axis; ``settings`` every input.
    """

    psf: np.ndarray
    collected: np.ndarray
    collected_fraction: float
    settings: dict
    seconds: float
    sensor: np.ndarray = field(repr=False)
    sensor_dx: float = 0.0


def camera_optics(design, n_pixels, *, f_number=None, defocus=0.0, rotation=0.0):
    """Return the :class:`CameraOptics` of ``design``'s tile of N = ``n_pixels`` in a lens.

    ``f_number`` None leaves the plate's square clear aperture as the stop; a round
    stop of f / N lets through what lies within it and the clear aperture (the
    square alone when the disc holds it, at f / N >= the aperture's diagonal).
    """
    der = derive(design, tile_pixels=n_pixels)
    f = design.optics.focal_length
    if f_number is not None and not (math.isfinite(f_number) and f_number > 0):
        raise InputError("--f-number", f"must be > 0, got {f_number:g}")
    if not math.isfinite(defocus) or abs(defocus) >= f / 2:
        raise InputError("--defocus-um", f"must be finite and under f/2, got {defocus * 1e6:g}")
    if not math.isfinite(rotation):
        raise InputError("--rotation-deg", "must be finite")
    aperture = design.fabrication.aperture
    diameter = None if f_number is None else f / f_number
    if diameter is not None and diameter >= aperture * math.sqrt(2):
        diameter = None  # the square clear aperture lies within the round stop
    return CameraOptics(f, der.tile_size, aperture, diameter, defocus, rotation, der.tiles)


def design_heights(design, levels):
    """Return the glass height (m) of each mask pixel of a nominal level map: l steps."""
    return np.asarray(levels, dtype=float) * derive(design, levels.shape[0]).level_step


def band_spectrum(design, bandwidth, optics, kernel):
    """Return the Gaussian band of FWHM ``bandwidth`` (m) sampled as the model needs it.

    The step moves the window's outermost dot (order K//2 + 1) by at most
    ``SPECTRAL_STEP_DOTS`` of the dot's radius lambda N between two wavelengths.
    """
    wl = design.optics.wavelength
    if bandwidth == 0:
        return monochromatic(wl)
    extent = stop_extent(optics.aperture, optics.stop_diameter)
    dot = wl * optics.focal_length / extent
    subpixel = wl * optics.focal_length / optics.tile_period
    step = SPECTRAL_STEP_DOTS * dot * wl / ((kernel // 2 + 1) * subpixel)
    return gaussian_band(wl, bandwidth, step)


def effective_psf(
    design,
    levels,
    *,
    bandwidth_nm=0.0,
    spectrum=None,
    f_number=None,
    defocus_um=0.0,
    rotation_deg=0.0,
    heights=None,
    supersample=1,
    margin_subpixels=None,
    kernel_size=None,
):
    """Return the :class:`CameraResult` of ``levels`` (N x N) made for ``design``.

    Parameters
    ----------
    design : doe.design.Design
    levels : (N, N) uint8
        The tile (CONVENTIONS.md).
    bandwidth_nm : float
        FWHM of a Gaussian band-pass centred on the design wavelength (0: monochromatic).
    spectrum : doe.spectrum.Spectrum or None
        Any spectrum instead (``doe.spectrum.read_spectrum``).
    f_number : float or None
        A round stop of diameter f / N; the light passes within it and the plate's
        square clear aperture. None: the square clear aperture.
    defocus_um : float
        Sensor distance behind the image plane (um; > 0 further from the lens).
    rotation_deg : float
        Plate rotation about the axis (deg; > 0 counter-clockwise as the PSF is viewed).
    heights : (N S, N S) array or None
        The glass height (m) of every cell of a faulty plate, S x S cells per mask
        pixel (``fab.plate.model.tile_height``); None: the nominal levels.
    supersample : int
        S of ``heights``.
    margin_subpixels : float or None
        Orders kept beyond the window, in sub-pixel pitches (the model's sampling);
        None: :func:`default_margin`.
    kernel_size : int or None
        K (default the design's).
    """
    start = time.perf_counter()
    levels = np.asarray(levels)
    n = levels.shape[0]
    k = kernel_size or design.kernel_size
    optics = camera_optics(
        design, n, f_number=f_number, defocus=defocus_um * 1e-6, rotation=rotation_deg
    )
    if spectrum is not None and bandwidth_nm:
        raise InputError("--spectrum", "give either a spectrum file or --bandwidth-nm")
    spectrum = spectrum or band_spectrum(design, bandwidth_nm * 1e-9, optics, k)
    if heights is None:
        heights, supersample = design_heights(design, levels), 1
    if margin_subpixels is None:
        margin_subpixels = default_margin(design, optics)
    ((collected, sensor, dx),) = collect(design, heights, optics, [spectrum], k, margin_subpixels)
    settings = {
        "bandwidth_nm": float(bandwidth_nm),
        "spectrum": spectrum.as_dict(),
        "f_number": None if f_number is None else float(f_number),
        "stop": _stop_name(optics),
        "stop_diameter_mm": None if optics.stop_diameter is None else optics.stop_diameter * 1e3,
        "aperture_mm": optics.aperture * 1e3,
        "defocus_um": float(defocus_um),
        "rotation_deg": float(rotation_deg),
        "kernel_size": k,
        "margin_subpixels": float(margin_subpixels),
        "supersample": int(supersample),
    }
    total = float(collected.sum())
    return CameraResult(
        psf=collected / total,
        collected=collected,
        collected_fraction=total,
        settings=settings,
        seconds=time.perf_counter() - start,
        sensor=sensor,
        sensor_dx=dx,
    )


def plate_orders(design, heights, wavelength):
    """Return the plate's Fourier coefficients (M, M) at ``wavelength`` (m).

    ``heights`` (M, M) are the glass heights of the tile's cells (M = N S for S x S
    cells per mask pixel), each cell a square.

    A cell of glass height h delays 2 pi (n(lambda) - 1) h / lambda, n from the
    design's glass; :func:`doe.camera_optics.tile_coefficients` gives the orders.
    """
    index = design.material.dispersion.index(wavelength)
    return tile_coefficients(heights, 2 * np.pi * (index - 1) / wavelength)


def default_margin(design, optics):
    """Return the margin (sub-pixel pitches) that keeps the model within ~1e-3 of the peak."""
    sensor = design.sensor
    subpixel = sensor.pixel_pitch / sensor.superres_factor
    if optics.stop_diameter is None:  # exact tails: only the orders' own reach
        return MARGIN_SUBPIXELS
    dot = design.optics.wavelength * optics.focal_length / optics.stop_diameter
    return max(MARGIN_SUBPIXELS, MARGIN_DOTS * dot / subpixel)


def _stop_name(optics):
    if optics.stop_diameter is None:
        return "square clear aperture"
    if optics.stop_diameter > optics.aperture:
        return "round, clipped by the square clear aperture"
    return "round"


def window_centres(kernel, subpixel, rotation_deg):
    """Return the K*K active-area centres (x, y) in the plate's frame, row-major.

    Centre [i, j] is ((j - K//2) p, -(i - K//2) p) on the sensor, turned by
    -rotation into the frame of the rotated plate.
    """
    offsets = (np.arange(kernel) - kernel // 2) * subpixel
    x = np.tile(offsets, kernel)
    y = -np.repeat(offsets, kernel)
    return rotate(np.stack([x, y], axis=-1), -math.radians(rotation_deg))


def collect(design, heights, optics, spectra, k, margin_subpixels):
    """Return [(E (K, K), the averaged sensor intensity, its grid step)] for each spectrum.

    The spectra share the sensor grid (planned for the shortest wavelength of all)
    and each wavelength's intensity is computed once, whichever spectra hold it: a
    set of band-passes sampled on one wavelength grid (:func:`band_spectrum`) costs
    the widest alone.
    """
    sensor = design.sensor
    subpixel = sensor.pixel_pitch / sensor.superres_factor
    centres = window_centres(k, subpixel, optics.rotation)
    half_area = sensor.active_area / 2 * (1 if sensor.active_area_shape == "circle" else 2**0.5)
    reach = float(np.abs(centres).max()) + half_area
    margin = margin_subpixels * subpixel
    f_image = optics.focal_length + optics.defocus
    extent = stop_extent(optics.aperture, optics.stop_diameter)
    shortest = min(min(s.wavelengths) for s in spectra)
    grid = plan_grid(reach, margin, shortest, f_image, extent)
    origin = ((-optics.tiles / 2) % 1.0, (-optics.tiles / 2) % 1.0)
    weights = [dict(zip(s.wavelengths, s.weights, strict=True)) for s in spectra]
    totals = [np.zeros((grid.n, grid.n)) for _ in spectra]
    for wl in sorted({w for s in spectra for w in s.wavelengths}):
        coeffs = plate_orders(design, heights, wl)
        intensity, _ = sensor_intensity(coeffs, origin, optics, grid, wl, reach + margin)
        for total, weight in zip(totals, weights, strict=True):
            if wl in weight:
                total += weight[wl] * intensity
    angle = -math.radians(optics.rotation)
    out = []
    for total in totals:
        e = integrate_areas(
            total, grid, centres, sensor.active_area_shape, sensor.active_area, angle
        )
        out.append((np.clip(e.reshape(k, k), 0.0, None), _crop(total, grid, reach), grid.dx))
    return out


def _crop(intensity, grid, reach):
    """The intensity within ``reach`` of the axis (the figure's field)."""
    half = min(grid.n // 2, math.ceil(reach / grid.dx))
    c = grid.n // 2
    return intensity[c - half : c + half + 1, c - half : c + half + 1]


def psf_figures(psf, target):
    """Return {"correlation", "rmse"} of a PSF against a target (CONVENTIONS.md)."""
    return {"correlation": correlation(psf, target), "rmse": rmse(psf, target)}
