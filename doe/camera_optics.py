"""The numerics of the camera model: a tiled plate in the lens pupil, imaged onto a sensor.

Scalar, paraxial, thin element, a point source at infinity. Everything here is in
the plate's own frame (x right, y up, viewed as the PSF contract views the sensor:
order (m, n) of the tile's DFT lands at x = n P, y = -m P, P = lambda f' / T); a
rotated plate is handled by rotating the sensor's points the other way
(:func:`rotate`), since the round stop and the defocus are rotationally symmetric and
the plate's square clear aperture turns with it.

The pupil field is t(u) S(u) exp(-i pi Z |u|^2 / (lambda f f')), t the periodic
plate (the tile's Fourier series, :func:`tile_coefficients`, each mask pixel a
square), S the stop (the plate's square clear aperture, within a round stop),
Z the sensor's distance behind the image plane (Z > 0 further from the lens) and
f' = f + Z. The sensor field is U(X) = FT[pupil](X / (lambda f')) / (lambda f')
(Fresnel propagation over f', the quadratic phase outside the integral dropped).
Because t holds only the orders near the window, U = sum_mn c_mn h(X - x_mn) with h
the stop's (defocused) amplitude PSF: the dots interfere where their tails overlap.

Sampling (:func:`plan_grid`): the square stop's field is separable and computed
exactly (:func:`slit_field`: a sinc, or Fresnel integrals out of focus). A round
stop's pupil is sampled at du = lambda f' / L, so its sensor field is the exact
field made periodic over L (Poisson summation: the stop's hard edge is exact, its
far tails wrap around); L holds the window, the orders within ``margin`` of it and
as much again as guard. The
sensor step dx < lambda_min f' / (2 D) keeps |U|^2 free of aliasing on the grid,
so the intensity integrated over an active area is an exact Fourier sum
(:func:`integrate_areas`), wherever the area's centre lies.
"""

import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.fft
import scipy.special

# The sensor step is this fraction of the intensity's Nyquist step lambda f' / (2 D).
NYQUIST_FRACTION = 0.95


@dataclass(frozen=True)
class Grid:
    """The periodic sensor grid: n x n points dx apart, point n // 2 on the axis."""

    n: int
    dx: float

    @property
    def period(self):
        return self.n * self.dx


def tile_coefficients(heights, phase_per_height):
    """Return the Fourier coefficients (M, M) of a tile of square cells, M = N S.

    ``heights`` is the glass height (m) of each of the S x S cells of every mask
    pixel, row 0 at the top; the cell's transmission is exp(i phase_per_height h).
    Coefficient [m, n] (indices mod M; m along rows, towards -y) multiplies
    exp(2 pi i (n x - m y) / T) in the plate, x and y measured from the tile's
    top-left corner; it includes the square cell's envelope sinc(m/M) sinc(n/M) and
    the half-cell shift of its centre. Sum of |c|^2 over all orders is 1.
    """
    m = heights.shape[0]
    field = np.exp(1j * phase_per_height * np.asarray(heights, dtype=np.float64))
    coeffs = scipy.fft.fft2(field) / field.size
    k = np.fft.fftfreq(m, 1.0 / m)  # the signed order of each index
    cell = np.sinc(k / m) * np.exp(-1j * np.pi * k / m)
    return coeffs * cell[:, None] * cell[None, :]


def stop_area(aperture, diameter):
    """Return the area (m^2) of the square clear aperture (side ``aperture``) within
    a centred round stop of ``diameter`` (None: no round stop)."""
    h = aperture / 2
    if diameter is None:
        return aperture**2
    r = diameter / 2
    if r <= h:
        return math.pi * r**2
    if r >= h * math.sqrt(2):
        return aperture**2
    segment = r**2 * math.acos(h / r) - h * math.sqrt(r**2 - h**2)  # beyond one side
    return math.pi * r**2 - 4 * segment


def stop_extent(aperture, diameter):
    """Return the stop's width along x (or y) (m)."""
    return aperture if diameter is None else min(aperture, diameter)


def plan_grid(reach, margin, wavelength_min, focal, extent):
    """Return the :class:`Grid` for a window reaching ``reach`` (m) from the axis.

    ``margin`` (m) is how far beyond the window the orders are kept; the period
    holds twice (reach + margin), so a wrapped tail comes from at least ``margin``
    beyond the window's edge.
    """
    dx = NYQUIST_FRACTION * wavelength_min * focal / (2 * extent)
    n = scipy.fft.next_fast_len(math.ceil(2 * (reach + margin) / dx))
    return Grid(n + n % 2, dx)


def _axis(grid_n, step):
    return (np.arange(grid_n) - grid_n // 2) * step


def sensor_intensity(coeffs, origin_phase, optics, grid, wavelength, reach):
    """Return the sensor intensity (n, n) per unit power through the stop, and the orders used.

    Parameters
    ----------
    coeffs : (M, M) complex
        :func:`tile_coefficients` at this wavelength.
    origin_phase : (float, float)
        (x0, y0) / T: the top-left corner of a tile, from the axis, in tile periods.
    optics : CameraOptics
        Focal length, tile period, aperture, stop, defocus.
    grid : Grid
    wavelength : float
    reach : float
        Keep the orders whose dots land within ``reach`` (m) of the axis along x and y.
    """
    f, z, period = optics.focal_length, optics.defocus, optics.tile_period
    f_image = f + z
    pitch = wavelength * f_image / period
    half = min(int(reach // pitch), (coeffs.shape[0] - 1) // 2)
    orders = np.arange(-half, half + 1)
    x0, y0 = origin_phase
    c = coeffs[np.ix_(orders % coeffs.shape[0], orders % coeffs.shape[0])]
    # The tile's corner at (x0, y0): exp(2 pi i (n (x - x0) - m (y - y0)) / T).
    c = c * np.exp(2j * np.pi * (orders[:, None] * y0 - orders[None, :] * x0))
    c = c / math.sqrt(stop_area(optics.aperture, optics.stop_diameter))
    clipped = optics.stop_diameter is not None and optics.stop_diameter > optics.aperture
    if optics.stop_diameter is None or clipped:
        field = _square_field(c, orders * pitch, optics, grid, wavelength)
        if clipped:  # the square less its corners outside the disc (short straight edges)
            if np.isrealobj(field):
                field = field[0] + 1j * field[1]
            field -= _pupil_field(c, orders, optics, grid, wavelength, corners=True)
    else:
        field = _pupil_field(c, orders, optics, grid, wavelength, corners=False)
    if np.isrealobj(field):  # a pair of real fields: the real and imaginary parts
        return field[0] ** 2 + field[1] ** 2, half
    return field.real**2 + field.imag**2, half


def _square_field(c, positions, optics, grid, wavelength):
    """The square stop's field on the grid: separable, exact (no wrapped tails)."""
    f, z = optics.focal_length, optics.defocus
    f_image = f + z
    alpha = -np.pi * z / (wavelength * f * f_image)
    x = _axis(grid.n, grid.dx)
    bx = slit_field(x[:, None] - positions, optics.aperture, alpha, wavelength, f_image)
    by = slit_field(x[:, None] + positions, optics.aperture, alpha, wavelength, f_image)
    c = c / (wavelength * f_image)
    # single precision: the sum of a few hundred terms keeps ~1e-7 of the peak
    right = (c @ bx.T).astype(np.complex64)
    if alpha == 0:  # in focus the slit's field is real: two real products, not a complex one
        both = by.real.astype(np.float32) @ np.concatenate([right.real, right.imag], axis=1)
        return np.stack(np.split(both, 2, axis=1))
    return by.astype(np.complex64) @ right


def _pupil_field(c, orders, optics, grid, wavelength, corners):
    """The field of the pupil sampled at lambda f' / L, made periodic over L by the FFT.

    The stop is the disc within the square, or with ``corners`` the square's corners
    outside the disc. Built on the central block that holds it only.
    """
    f, z = optics.focal_length, optics.defocus
    f_image = f + z
    du = wavelength * f_image / grid.period
    extent = stop_extent(optics.aperture, None if corners else optics.stop_diameter)
    half_block = min(grid.n // 2 - 1, int(extent / 2 / du) + 1)
    u = np.arange(-half_block, half_block + 1) * du
    ex = np.exp(2j * np.pi * np.outer(u, orders) / optics.tile_period)  # x; y is conj(ex)
    side = np.where(np.abs(u) < optics.aperture / 2, 1.0, 0.0)
    side[np.abs(u) == optics.aperture / 2] = 0.5  # Poisson's convention on an edge
    disc = _disc(u, optics.stop_diameter)
    stop = np.outer(side, side) * (1 - disc if corners else disc)
    block = (np.conj(ex) @ c @ ex.T) * stop
    if z != 0:
        defocus = np.exp(-1j * np.pi * z * u**2 / (wavelength * f * f_image))
        block *= defocus[:, None] * defocus[None, :]
    pupil = np.zeros((grid.n, grid.n), np.complex64)
    lo, hi = grid.n // 2 - half_block, grid.n // 2 + half_block + 1
    pupil[lo:hi, lo:hi] = block
    field = scipy.fft.fftshift(scipy.fft.fft2(scipy.fft.ifftshift(pupil)))
    return field * np.complex64(du**2 / (wavelength * f_image))


def slit_field(x, width, alpha, wavelength, f_image):
    """Return the integral over |u| < width / 2 of exp(i (alpha u^2 - 2 pi u x / (lambda f'))).

    The square stop's amplitude PSF is slit_field(x) slit_field(y) / (lambda f'): a
    sinc in focus, a difference of Fresnel integrals out of focus (closed forms, so
    the tails are exact however far they reach).
    """
    a = width / 2
    beta = 2 * np.pi * x / (wavelength * f_image)
    if abs(alpha) * a**2 < 1e-9:  # in focus to 1e-9 rad at the stop's edge
        return width * np.sinc(beta * a / np.pi)
    sign, gamma = np.sign(alpha), np.sqrt(2 * abs(alpha) / np.pi)
    centre = beta / (2 * alpha)
    s2, c2 = scipy.special.fresnel(gamma * (a - centre))
    s1, c1 = scipy.special.fresnel(gamma * (-a - centre))
    return ((c2 - c1) + 1j * sign * (s2 - s1)) / gamma * np.exp(-1j * beta * centre / 2)


def _disc(u, diameter):
    """The round stop sampled at u x u, 1/2 on its edge."""
    r = np.hypot(u[:, None], u[None, :])
    return np.where(r < diameter / 2, 1.0, np.where(r == diameter / 2, 0.5, 0.0))


def rotate(points, angle):
    """Return (x, y) points (..., 2) turned counter-clockwise by ``angle`` (rad)."""
    c, s = math.cos(angle), math.sin(angle)
    x, y = points[..., 0], points[..., 1]
    return np.stack([c * x - s * y, s * x + c * y], axis=-1)


def area_transform(nu_x, nu_y, shape, size, angle):
    """Return the Fourier transform of an active area at frequencies (nu_x, nu_y) (1/m).

    ``shape`` "circle" (diameter ``size``) or "square" (side ``size``), turned
    counter-clockwise by ``angle`` (rad) about its centre.
    """
    if shape == "circle":
        a = size / 2
        rho = 2 * np.pi * a * np.hypot(nu_x, nu_y)
        safe = np.where(rho == 0, 1.0, rho)
        return np.pi * a**2 * np.where(rho == 0, 1.0, 2 * scipy.special.j1(safe) / safe)
    c, s = math.cos(angle), math.sin(angle)
    along_x, along_y = c * nu_x + s * nu_y, -s * nu_x + c * nu_y  # the area's own axes
    return size**2 * np.sinc(size * along_x) * np.sinc(size * along_y)


def integrate_areas(intensity, grid, centres, shape, size, angle):
    """Return the intensity integrated over an active area at each centre (C,).

    ``centres`` (C, 2) are (x, y) in metres; the intensity is a trigonometric
    polynomial on the grid (:func:`plan_grid`), so its integral over the area is
    the exact sum over frequencies of I^(nu) A^(nu) exp(2 pi i nu c) / L^2. The
    intensity is real: the sum runs over nu_x >= 0 (a real FFT), each pair of
    frequencies +-nu counted once as twice the real part.
    """
    spectrum = scipy.fft.rfft2(scipy.fft.ifftshift(intensity)) * grid.dx**2  # (n_y, n_x // 2 + 1)
    spectrum *= _area_weights(grid.n, grid.dx, shape, size, 0.0 if shape == "circle" else angle)
    nu = scipy.fft.fftfreq(grid.n, grid.dx)
    nu_x = scipy.fft.rfftfreq(grid.n, grid.dx)
    ex = np.exp(2j * np.pi * np.outer(centres[:, 0], nu_x))  # (C, n_x)
    ey = np.exp(2j * np.pi * np.outer(centres[:, 1], nu))  # (C, n_y)
    along_x = spectrum @ ex.T  # (n_y, C)
    return np.einsum("cy,yc->c", ey, along_x).real / grid.period**2


@functools.lru_cache(maxsize=8)
def _area_weights(n, dx, shape, size, angle):
    """A^(nu) on the real FFT's half plane, times 2 where -nu_x is not held (read-only).

    Cached: a budget's settings share a few grids, and the Bessel function over the
    whole grid costs as much as the rest of the integral.
    """
    nu = scipy.fft.fftfreq(n, dx)
    nu_x = scipy.fft.rfftfreq(n, dx)
    weights = area_transform(nu_x[None, :], nu[:, None], shape, size, angle)
    double = np.full(nu_x.size, 2.0)
    double[0] = 1.0
    if n % 2 == 0:
        double[-1] = 1.0  # the Nyquist column is its own mirror
    weights = weights * double[None, :]
    weights.flags.writeable = False
    return weights
