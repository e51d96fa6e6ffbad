"""Registration of the dot lattice in a capture and aperture photometry of its orders.

The tiled plate puts its light into diffraction orders on a square lattice; the
capture is a grid of small dots. Registration needs no hint of where the dots
are, only the design's nominal pitch as a prior:

1. The power spectrum of the capture peaks at the lattice's two reciprocal
   vectors (every dot adds in phase there, whatever its power); the strongest
   peak in an annulus around 1/pitch near each axis gives them (sub-bin by a
   parabola through the log power).
2. The phase of the capture's Fourier coefficient at those vectors gives the
   lattice origin modulo one cell.
3. Dot centroids of the brighter dots refine origin and basis by linear least
   squares (6 parameters: the origin and both lattice vectors).

Lattice coordinates (u, v) count dots down and to the right in the camera frame;
which dot is the zero order is decided later against the design (``fab.verify``).
"""

from dataclasses import dataclass

import numpy as np

from fab.capture import robust_sigma

# Pitch prior: the lattice pitch may differ from the nominal by this fraction
# (lens focal length, camera pixel pitch, magnification).
PITCH_TOLERANCE = 0.15
# Largest rotation of the lattice against the camera axes searched (degrees).
MAX_ROTATION_DEG = 20.0
# A reciprocal-lattice peak must stand this far above the median of its search region.
MIN_PEAK_CONTRAST = 8.0
# Aperture photometry radii as fractions of the pitch: dot aperture, background annulus.
APERTURE_RADIUS = 0.30
ANNULUS = (0.38, 0.50)


@dataclass(frozen=True)
class Lattice:
    """A square-ish lattice of dots in camera pixel coordinates.

    Attributes
    ----------
    origin : (2,) float array
        (row, col) in pixels of the dot with lattice coordinates (0, 0).
    basis : (2, 2) float array
        Columns are the displacements (row, col) in pixels of one step in u
        (down) and one step in v (right).
    """

    origin: np.ndarray
    basis: np.ndarray

    def positions(self, u, v):
        """Return (rows, cols) in pixels of lattice points (u, v) (arrays of equal shape)."""
        u, v = np.asarray(u, float), np.asarray(v, float)
        rows = self.origin[0] + u * self.basis[0, 0] + v * self.basis[0, 1]
        cols = self.origin[1] + u * self.basis[1, 0] + v * self.basis[1, 1]
        return rows, cols

    def coordinates(self, rows, cols):
        """Return fractional lattice coordinates (u, v) of pixel positions."""
        inv = np.linalg.inv(self.basis)
        dr, dc = np.asarray(rows, float) - self.origin[0], np.asarray(cols, float) - self.origin[1]
        return inv[0, 0] * dr + inv[0, 1] * dc, inv[1, 0] * dr + inv[1, 1] * dc

    @property
    def pitch_px(self):
        """Mean length of the two lattice vectors in pixels."""
        return float(np.mean(np.hypot(self.basis[0], self.basis[1])))

    @property
    def rotation_deg(self):
        """Angle of the +v (rightward) lattice vector from the camera's column axis.

        Positive is counter-clockwise as the image is displayed (row 0 at the top).
        """
        return float(np.degrees(np.arctan2(-self.basis[0, 1], self.basis[1, 1])))

    def summary(self):
        """Return the JSON-ready description used in verify.json."""
        return {
            "pitch_px": self.pitch_px,
            "rotation_deg": self.rotation_deg,
            "centre_px": [float(self.origin[0]), float(self.origin[1])],
            "basis_px": self.basis.tolist(),
        }


@dataclass(frozen=True)
class OrderGrid:
    """Aperture photometry of every lattice point in the frame.

    Attributes
    ----------
    u, v : (nu,) and (nv,) int arrays
        Lattice coordinates of the grid's rows and columns.
    power : (nu, nv) float array
        Background-subtracted dot signal in DN (NaN where not measured).
    valid : (nu, nv) bool array
        The dot's aperture and background annulus lie inside the frame.
    rows, cols : (nu, nv) float arrays
        Dot positions in pixels.
    saturated : (nu, nv) bool array
        The aperture holds a saturated pixel.
    noise_px : float
        Robust per-pixel noise (DN) of the background annuli.
    aperture_pixels : int
        Pixels in one aperture.
    """

    u: np.ndarray
    v: np.ndarray
    power: np.ndarray
    valid: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    saturated: np.ndarray
    noise_px: float
    aperture_pixels: int


class LatticeNotFound(ValueError):
    """No dot lattice near the nominal pitch in the image."""


def register_lattice(image, nominal_pitch_px, refine_iterations=2):
    """Find the dot lattice of a capture.

    Parameters
    ----------
    image : (H, W) float array
        Capture in DN (a constant pedestal is harmless).
    nominal_pitch_px : float
        Expected order pitch in camera pixels (lambda f / tile size / pixel pitch).
    refine_iterations : int
        Centroid least-squares passes after the Fourier estimate.

    Returns
    -------
    Lattice
        With origin at the lattice point nearest the image centre.

    Raises
    ------
    LatticeNotFound
        When the spectrum has no clear peak near the nominal pitch.
    """
    img = np.asarray(image, dtype=np.float32)
    h, w = img.shape
    if min(h, w) < 4 * nominal_pitch_px:
        raise LatticeNotFound(
            f"image {w}x{h} px holds fewer than 4 dots across "
            f"at the nominal pitch {nominal_pitch_px:.3g} px"
        )
    x = img - np.float32(np.median(img[::4, ::4]))
    win = np.hanning(h).astype(np.float32)[:, None] * np.hanning(w).astype(np.float32)[None, :]
    xw = x * win
    recip = _reciprocal_vectors(xw, nominal_pitch_px)
    basis = np.linalg.inv(recip)  # recip @ basis = identity
    phases = []
    for g in recip:
        er = np.exp(-2j * np.pi * g[0] * np.arange(h))
        ec = np.exp(-2j * np.pi * g[1] * np.arange(w))
        phases.append(-np.angle(er @ xw.astype(np.float64) @ ec) / (2 * np.pi))
    lattice = _recentre(Lattice(basis @ np.array(phases), basis), (h, w))
    for _ in range(refine_iterations):
        lattice = _refine(x, lattice)
    return lattice


def _reciprocal_vectors(xw, pitch):
    """Return (2, 2) rows g_u, g_v in cycles/pixel (row, col) from the spectrum's peaks."""
    import scipy.fft

    h, w = xw.shape
    spec = np.abs(scipy.fft.rfft2(xw, workers=-1)) ** 2
    tan = np.tan(np.radians(MAX_ROTATION_DEG))
    lo, hi = (1 - PITCH_TOLERANCE) / pitch, (1 + PITCH_TOLERANCE) / pitch
    out = []
    for axis in (0, 1):  # g_u: mainly along rows; g_v: mainly along columns
        n_main, n_side = (h, w) if axis == 0 else (w, h)
        k_main = np.arange(int(np.floor(lo * n_main)), int(np.ceil(hi * n_main)) + 1)
        side = int(np.ceil(tan * hi * n_side)) + 1
        k_side = np.arange(-side, side + 1)
        if axis == 0:
            kr, kc = k_main[:, None], k_side[None, :]
        else:
            kr, kc = k_side[:, None], k_main[None, :]
        fr, fc = kr / h, kc / w
        radius = np.hypot(fr, fc)
        main, other = (np.abs(fr), np.abs(fc)) if axis == 0 else (np.abs(fc), np.abs(fr))
        region = (radius >= lo) & (radius <= hi) & (other <= tan * main)
        p = _power_at(spec, kr, kc, h) * region
        best = np.unravel_index(int(np.argmax(p)), p.shape)
        floor = float(np.median(p[region]))
        if not p[best] > MIN_PEAK_CONTRAST * max(floor, 1e-30):
            raise LatticeNotFound(
                f"no dot lattice near the nominal pitch {pitch:.3g} px "
                f"(±{PITCH_TOLERANCE:.0%}): spectrum peak only "
                f"{p[best] / max(floor, 1e-30):.2g}x its surroundings"
            )
        r0, c0 = int(kr[best[0], 0]), int(kc[0, best[1]])
        dr = _parabola_peak(*(_power_at(spec, r0 + d, c0, h) for d in (-1, 0, 1)))
        dc = _parabola_peak(*(_power_at(spec, r0, c0 + d, h) for d in (-1, 0, 1)))
        g = np.array([(r0 + dr) / h, (c0 + dc) / w])
        if g[axis] < 0:
            g = -g
        out.append(g)
    return np.array(out)


def _power_at(spec, kr, kc, h):
    """Power at integer frequency indices of a real image's rfft2 (negative columns mirrored)."""
    kr, kc = np.broadcast_arrays(np.asarray(kr), np.asarray(kc))
    neg = kc < 0
    r = np.where(neg, -kr, kr) % h
    c = np.abs(kc)
    return spec[r, c]


def _parabola_peak(a, b, c):
    """Return the sub-sample offset of the vertex of a parabola through log(a), log(b), log(c)."""
    la, lb, lc = (np.log(max(float(v), 1e-30)) for v in (a, b, c))
    den = la - 2 * lb + lc
    return float(np.clip(0.5 * (la - lc) / den, -0.5, 0.5)) if den < 0 else 0.0


def _recentre(lattice, shape):
    """Move the origin to the lattice point nearest the image centre."""
    centre = (np.asarray(shape, float) - 1) / 2
    u, v = lattice.coordinates(centre[0], centre[1])
    k = np.array([np.round(u), np.round(v)])
    return Lattice(lattice.origin + lattice.basis @ k, lattice.basis)


def _lattice_points(lattice, shape, margin):
    """Return the lattice coordinates (u, v) grids covering the frame, and validity."""
    h, w = shape
    corners_r = np.array([0, 0, h - 1, h - 1], float)
    corners_c = np.array([0, w - 1, 0, w - 1], float)
    cu, cv = lattice.coordinates(corners_r, corners_c)
    u = np.arange(int(np.floor(cu.min())) - 1, int(np.ceil(cu.max())) + 2)
    v = np.arange(int(np.floor(cv.min())) - 1, int(np.ceil(cv.max())) + 2)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    rows, cols = lattice.positions(uu, vv)
    rr, cc = np.rint(rows), np.rint(cols)
    valid = (rr >= margin) & (rr <= h - 1 - margin) & (cc >= margin) & (cc <= w - 1 - margin)
    return u, v, rows, cols, valid


def _patches(image, rows, cols, radius):
    """Return (P, 2r+1, 2r+1) patches of ``image`` centred on the rounded positions."""
    off = np.arange(-radius, radius + 1)
    rr = np.rint(rows).astype(np.intp)[:, None, None] + off[None, :, None]
    cc = np.rint(cols).astype(np.intp)[:, None, None] + off[None, None, :]
    return image[rr, cc]


def _refine(x, lattice):
    """Refine origin and basis by least squares on the centroids of the brighter dots."""
    radius = max(2, round(0.3 * lattice.pitch_px))
    u, v, rows, cols, valid = _lattice_points(lattice, x.shape, radius)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    uu, vv, rows, cols = uu[valid], vv[valid], rows[valid], cols[valid]
    patch = np.clip(_patches(x, rows, cols, radius), 0, None).astype(np.float64)
    total = patch.sum(axis=(1, 2))
    # The brightest few thousand dots carry the geometry; the faint ones only add noise.
    keep = np.argsort(total)[::-1][: min(4000, max(12, total.size // 2))]
    keep = keep[total[keep] > 0]
    if keep.size < 6:
        return lattice
    off = np.arange(-radius, radius + 1, dtype=np.float64)
    pk = patch[keep]
    cr = np.rint(rows[keep]) + (pk.sum(axis=2) @ off) / total[keep]
    cc = np.rint(cols[keep]) + (pk.sum(axis=1) @ off) / total[keep]
    ku, kv = uu[keep].astype(float), vv[keep].astype(float)
    design = np.stack([np.ones_like(ku), ku, kv], axis=1)
    use = np.ones(keep.size, bool)
    for _ in range(3):  # drop outliers (hot pixels, merged dots) and refit
        coef_r, *_ = np.linalg.lstsq(design[use], cr[use], rcond=None)
        coef_c, *_ = np.linalg.lstsq(design[use], cc[use], rcond=None)
        resid = np.hypot(design @ coef_r - cr, design @ coef_c - cc)
        cut = max(3 * float(np.median(resid[use])), 0.2)
        new = resid < cut
        if new.sum() < 6 or np.array_equal(new, use):
            break
        use = new
    origin = np.array([coef_r[0], coef_c[0]])
    basis = np.array([[coef_r[1], coef_r[2]], [coef_c[1], coef_c[2]]])
    return _recentre(Lattice(origin, basis), x.shape)


def measure_orders(image, lattice, saturated=None):
    """Measure every dot's power by aperture photometry with a local background.

    Each dot's aperture is a disc of ``APERTURE_RADIUS`` pitches; its background
    is the median of an annulus (``ANNULUS`` pitches) around it, which also
    shrugs off stray hot pixels.

    Parameters
    ----------
    image : (H, W) float array
        Capture in DN.
    lattice : Lattice
    saturated : (H, W) bool array or None
        Saturated pixels of the raw capture.

    Returns
    -------
    OrderGrid
    """
    x = np.asarray(image, dtype=np.float32)
    pitch = lattice.pitch_px
    outer = int(np.ceil(ANNULUS[1] * pitch))
    u, v, rows, cols, valid = _lattice_points(lattice, x.shape, outer)
    off = np.arange(-outer, outer + 1)
    dist = np.hypot(off[:, None], off[None, :])
    aperture = dist <= max(APERTURE_RADIUS * pitch, 1.5)
    annulus = (dist >= ANNULUS[0] * pitch) & (dist <= ANNULUS[1] * pitch)
    pr, pc = rows[valid], cols[valid]
    patch = _patches(x, pr, pc, outer)
    ring = patch[:, annulus]
    background = np.median(ring, axis=1)
    signal = patch[:, aperture].astype(np.float64).sum(axis=1) - aperture.sum() * background
    noise = robust_sigma((ring - background[:, None])[:: max(1, ring.shape[0] // 2000)])
    power = np.full(valid.shape, np.nan)
    power[valid] = signal
    sat = np.zeros(valid.shape, bool)
    if saturated is not None and np.any(saturated):
        sat[valid] = _patches(saturated, pr, pc, outer)[:, aperture].any(axis=1)
    return OrderGrid(u, v, power, valid, rows, cols, sat, noise, int(aperture.sum()))
