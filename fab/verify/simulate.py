"""Simulated camera captures of a (possibly faulty) plate, for tests and benchmarks.

The physics, in order:

1. The plate's tile with its faults (``fab.plate.model.plate_phase``: the plate model's
   tile), supersampled S times per mask pixel when a mask is shifted (overlay error),
   with its phase 2 pi l / L, each mask's etch depth error applied to the pixels it
   etches, or etch and glass swapped (a conjugate plate).
2. Its far field: order (m, n) of the tiled plate carries
   ``|DFT[m mod NS, n mod NS]|^2 sinc^2(m / NS) sinc^2(n / NS)`` of the power
   (a piecewise-constant tile: the DFT times the sub-pixel's envelope; the
   powers of all orders sum to 1).
3. Order (m, n) lands on the camera at ``centre + scale * pitch * R(theta)
   T(m, n)``: T the camera orientation, R a small rotation.
4. Each dot is the aperture's diffraction spot, a Gaussian (the one with the
   FWHM of a square aperture's sinc^2 lobe has sigma = 0.376 lambda f / D; the
   default 0.3 px is 0.44 lambda f / D of the default optics, a little wider, as
   a real lens is), optionally blurred more, integrated over the camera's pixels.
5. Shot noise (Poisson in electrons), read noise, a dark pedestal with hot
   pixels (the same in capture and dark frame), 12-bit digitisation stored
   MSB-aligned in 16 bits, clipping at full scale (saturation).
"""

import numpy as np
from scipy.special import erf

from fab.plate.model import PlateFaults, plate_far_field, plate_phase

# Orientation of the camera against the design: design order offset (m, n)
# (down, right) lands at camera lattice offset (du, dv) (down, right).
ORIENTATION_MAPS = {
    "as-designed": lambda m, n: (m, n),
    "rot90": lambda m, n: (-n, m),  # image rotated 90 degrees counter-clockwise
    "rot180": lambda m, n: (-m, -n),
    "rot270": lambda m, n: (n, -m),
    "mirror-x": lambda m, n: (m, -n),  # left-right flipped
    "mirror-y": lambda m, n: (-m, n),  # upside down
    "transpose": lambda m, n: (n, m),  # reflected about the main diagonal
    "antitranspose": lambda m, n: (-n, -m),  # about the other diagonal
}


def simulate_capture(
    levels,
    n_levels,
    *,
    shape=(600, 600),
    pitch_px=37.504 / 3.45,
    centre=None,
    rotation_deg=0.0,
    scale=1.0,
    orientation="as-designed",
    faults=PlateFaults(),
    mask_pixel_pitch=4.99e-6,
    supersample=1,
    spot_sigma_px=0.3,
    blur_sigma_px=0.0,
    peak_fraction=0.7,
    full_well_e=10000.0,
    read_noise_dn=1.5,
    dark_level_dn=60.0,
    hot_pixels=0,
    bits=12,
    seed=0,
    band=None,
):
    """Simulate a capture of the plate's dot lattice and a matching dark frame.

    Parameters
    ----------
    levels : (N, N) uint8 array
        The design level map.
    n_levels : int
        L.
    shape : (H, W)
        Frame size in camera pixels.
    pitch_px : float
        Nominal order pitch in camera pixels (before ``scale``).
    centre : (row, col) or None
        Position of the zero order in pixels; default the frame centre.
    rotation_deg : float
        Lattice rotation, counter-clockwise as displayed.
    scale : float
        Magnification error: the pitch on the camera is ``scale * pitch_px``.
    orientation : str
        One of ``ORIENTATION_MAPS``.
    faults : PlateFaults
        The plate's faults (overlay in metres, x right and y up).
    mask_pixel_pitch : float
        Mask pixel pitch in metres (overlay shifts).
    supersample : int
        Sub-pixels per mask pixel (an overlay shift needs its resolution).
    spot_sigma_px, blur_sigma_px : float
        Diffraction spot (0.3 px ~ 0.44 lambda f / D / camera pitch for the
        default optics; a perfect lens gives 0.376 lambda f / D) and extra blur
        (defocus) in pixels.
    peak_fraction : float
        Exposure: the brightest pixel's mean signal as a fraction of full
        scale; above 1 the capture saturates.
    full_well_e, read_noise_dn, dark_level_dn : float
        Electrons at full scale, read noise (DN rms), dark pedestal (DN).
    hot_pixels : int
        Number of hot pixels (same positions in capture and dark frame).
    bits : int
        ADC bits; 12 is stored MSB-aligned in uint16, 8 as uint8, 16 as uint16.
    seed : int
    band : fab.verify.bench_band.Band or None
        The bench's spectrum (None: the design wavelength alone): each wavelength's
        dots, of its plate phase, at its lattice pitch and spot size, weighted.

    Returns
    -------
    dict
        "capture" and "dark" (H, W) integer arrays, "zero_order_px" (row, col),
        "order_power" (the function (m, n) -> power), "full_scale" (DN).
    """
    rng = np.random.default_rng(seed)
    h, w = shape
    centre = np.array(centre if centre is not None else ((h - 1) / 2, (w - 1) / 2), float)
    phase = plate_phase(levels, n_levels, faults, mask_pixel_pitch, supersample)
    sigma = float(np.hypot(spot_sigma_px, blur_sigma_px))
    if band is None:
        order_power = plate_far_field(phase)
        lattice = (pitch_px * scale, np.radians(rotation_deg), orientation)
        image = _dot_image(order_power, shape, centre, lattice, sigma)
    else:
        order_power, image = _band_image(phase, band, shape, centre, sigma, (
            pitch_px * scale, np.radians(rotation_deg), orientation))  # fmt: skip
    if not image.max() > 0:
        raise ValueError("no order lands in the frame: move centre nearer to it")
    exposure = (peak_fraction, full_well_e, read_noise_dn, dark_level_dn, hot_pixels, bits)
    capture, dark, full_scale = _frames(image, exposure, rng)
    return {
        "capture": capture,
        "dark": dark,
        "zero_order_px": tuple(centre),
        "order_power": order_power,
        "full_scale": full_scale,
    }


def _dot_image(order_power, shape, centre, lattice, sigma):
    """Return the noiseless image of the orders' dots (each of its order's power).

    ``lattice`` is (pitch in pixels, rotation in radians, orientation name).
    """
    h, w = shape
    p, theta, orientation = lattice
    b_u = p * np.array([np.cos(theta), np.sin(theta)])  # (row, col) per camera step down
    b_v = p * np.array([-np.sin(theta), np.cos(theta)])  # per camera step right
    # Orders out to the frame corner farthest from the zero order (it may lie outside).
    corners = np.array([(r, c) for r in (0, h - 1) for c in (0, w - 1)], float)
    reach = int(np.ceil(np.hypot(*(corners - centre).T).max() / p)) + 2
    du, dv = np.meshgrid(np.arange(-reach, reach + 1), np.arange(-reach, reach + 1), indexing="ij")
    rows = centre[0] + du * b_u[0] + dv * b_v[0]
    cols = centre[1] + du * b_u[1] + dv * b_v[1]
    rad = int(np.ceil(4 * sigma)) + 1
    inside = (rows > -rad) & (rows < h - 1 + rad) & (cols > -rad) & (cols < w - 1 + rad)
    m, n = _inverse_orientation(orientation, du[inside], dv[inside])
    power = order_power(m, n)
    return _render_dots(rows[inside], cols[inside], power, (h, w), sigma, rad)


def _band_image(phase, band, shape, centre, sigma, lattice):
    """Return (order power function, noiseless image) of the plate under ``band``: each
    wavelength's far field (phase scaled) at its pitch and spot size, weighted."""
    pitch, theta, orientation = lattice
    fields = [plate_far_field(f * phase) for f in band.phase_factor]
    image = np.zeros(shape)
    for weight, far, s in zip(band.weights, fields, band.scale, strict=True):
        image += weight * _dot_image(far, shape, centre, (pitch * s, theta, orientation), sigma * s)

    def order_power(m, n):
        return sum(w * far(m, n) for w, far in zip(band.weights, fields, strict=True))

    return order_power, image


def _frames(image, exposure, rng):
    """Return (capture, dark, full scale in DN) of a noiseless image (any units).

    ``exposure`` is (peak fraction, full well in electrons, read noise in DN, dark
    pedestal in DN, number of hot pixels, ADC bits), as ``simulate_capture`` takes them.
    """
    peak_fraction, full_well_e, read_noise_dn, dark_level_dn, hot_pixels, bits = exposure
    h, w = image.shape
    full_scale = {8: 255, 12: 4095, 16: 65535}[bits]
    gain = full_well_e / full_scale  # electrons per DN
    scale_e = peak_fraction * full_well_e / image.max()
    electrons = rng.poisson(image * scale_e).astype(np.float64)
    dark_e = np.zeros((h, w))
    if hot_pixels:
        idx = rng.choice(h * w, size=hot_pixels, replace=False)
        dark_e.flat[idx] = rng.uniform(0.2, 0.9, size=hot_pixels) * full_well_e
    capture = _digitise(
        electrons + rng.poisson(dark_e), gain, dark_level_dn, read_noise_dn, full_scale, bits, rng
    )
    dark = _digitise(
        rng.poisson(dark_e).astype(float), gain, dark_level_dn, read_noise_dn, full_scale, bits, rng
    )
    return capture, dark, full_scale


def _inverse_orientation(orientation, du, dv):
    """Return the design orders (m, n) that land at camera offsets (du, dv)."""
    forward = ORIENTATION_MAPS[orientation]
    # Every map is an orthogonal integer matrix: its inverse is its transpose.
    a = np.array([forward(1, 0), forward(0, 1)], dtype=int).T  # columns: images of e_m, e_n
    inv = a.T
    return inv[0, 0] * du + inv[0, 1] * dv, inv[1, 0] * du + inv[1, 1] * dv


def _render_dots(rows, cols, power, shape, sigma, rad):
    """Sum pixel-integrated Gaussian dots (total ``power`` each) into an image."""
    h, w = shape
    r0, c0 = np.rint(rows).astype(np.intp), np.rint(cols).astype(np.intp)
    off = np.arange(-rad, rad + 1)
    s2 = np.sqrt(2) * sigma

    def profile(centres, base):
        edges = base[:, None] + off[None, :] - centres[:, None]
        return 0.5 * (erf((edges + 0.5) / s2) - erf((edges - 0.5) / s2))

    gy, gx = profile(rows, r0), profile(cols, c0)
    vals = power[:, None, None] * gy[:, :, None] * gx[:, None, :]
    rr = r0[:, None, None] + off[None, :, None]
    cc = c0[:, None, None] + off[None, None, :]
    rr, cc = np.broadcast_arrays(rr, cc)
    ok = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
    flat = rr[ok] * w + cc[ok]
    return np.bincount(flat, weights=vals[ok], minlength=h * w).reshape(h, w)


def _digitise(electrons, gain, pedestal_dn, read_noise_dn, full_scale, bits, rng):
    dn = electrons / gain + pedestal_dn + rng.normal(0, read_noise_dn, electrons.shape)
    dn = np.clip(np.rint(dn), 0, full_scale)
    if bits == 8:
        return dn.astype(np.uint8)
    if bits == 12:
        return (dn.astype(np.uint16) << 4).astype(np.uint16)
    return dn.astype(np.uint16)
