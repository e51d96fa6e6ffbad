"""Registration of the dot lattice in a capture.

The tiled plate puts its light into diffraction orders on a square lattice; the
capture is a grid of small dots. Registration needs no hint of where the dots
are, only the design's nominal pitch as a prior:

1. Dots standing out of the noise are detected (local maxima of the lightly
   smoothed capture) and centroided.
2. Their nearest-neighbour vectors give pitch and rotation (z^4 of the vector
   as a complex number is the same for all four neighbours of a square
   lattice); the origin is the brightest dot that has a neighbour.
3. Origin and both lattice vectors (6 parameters) are fitted by linear least
   squares to the dots, growing the region from the origin outwards so that
   the integer indices stay right, then to centroids measured at every
   predicted lattice point above the noise. A compact PSF (a few bright dots)
   registers as well as a dense one.

Lattice coordinates (u, v) count dots down and to the right in the camera frame;
which dot is the zero order is decided later against the design (``fab.verify.analysis``).
The orders' powers are measured on the lattice by ``fab.verify.photometry``; hot
pixels are repaired once it is known by ``fab.verify.hot_pixels``.
"""

from dataclasses import dataclass

import numpy as np

from fab.verify.conditioning import robust_sigma

# Pitch prior: the lattice pitch may differ from the nominal by this fraction
# (lens focal length, camera pixel pitch, magnification).
PITCH_TOLERANCE = 0.15
# Dots closer than this (px) are not registered and measured: at 3 px, spots of 0.7 px
# sigma fit a lattice a few per cent off (bench/README.md); at 3.5 px they measure as
# well as at 11 px. Below
# ``fab.verify.photometry.ANNULUS_MIN_PITCH_PX`` the orders are measured in their lattice
# cells (``fab.verify.cell_photometry``), as an aperture would overlap its annulus.
MIN_PITCH_PX = 3.4
# Below this pitch (px) a dot's centroid is taken over 3 x 3 pixels, not 5 x 5, so that
# its neighbours' light stays out.
TIGHT_PITCH_PX = 4.5
# A dot is detected when its smoothed peak stands this many noise sigmas out.
DETECT_SIGMAS = 8.0
# At most this many of the brightest dots are used to register the lattice.
MAX_DOTS = 20000
# One least-squares step may change a lattice vector by at most this fraction of the pitch.
MAX_BASIS_STEP = 0.05
# A focused dot puts at most ~82 % of its light in one pixel: an aperture with more
# in one pixel holds a hot pixel.
SPIKE_FRACTION = 0.95


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
            "origin_px": [float(self.origin[0]), float(self.origin[1])],
            "basis_px": self.basis.tolist(),
        }


class LatticeNotFound(ValueError):
    """No dot lattice near the nominal pitch in the image."""


def register_lattice(image, nominal_pitch_px, refine_iterations=2, quantum=0.0):
    """Find the dot lattice of a capture.

    Parameters
    ----------
    image : (H, W) float array
        Capture in DN (a constant pedestal is harmless).
    nominal_pitch_px : float
        Expected order pitch in camera pixels (lambda f / tile size / pixel pitch).
    refine_iterations : int
        Centroid least-squares passes over the whole frame at the end.
    quantum : float
        Step between the capture's codes in DN (``Capture.quantum``); 0 for float data.

    Returns
    -------
    (Lattice, notes)
        The lattice, origin at the lattice point nearest the image centre, and
        remarks for the report (e.g. when the pattern was too sparse to measure
        the pitch and the prior was used).

    Raises
    ------
    LatticeNotFound
        When no dot stands out of the noise, the dots fit no lattice near
        the nominal pitch, or they are closer than ``MIN_PITCH_PX``.
    """
    img = np.asarray(image, dtype=np.float32)
    h, w = img.shape
    pitch0 = float(nominal_pitch_px)
    # a start (the nearest neighbours' median, a little short) may lie below the floor
    # that the fitted pitch must reach
    if not pitch0 >= MIN_PITCH_PX * (1 - PITCH_TOLERANCE):
        raise LatticeNotFound(
            f"the dots would be {pitch0:.3g} px apart, closer than the {MIN_PITCH_PX:g} px "
            "the photometry needs; check --pixel-pitch-um and --lattice-pitch-um (both in um) "
            "or magnify the lattice"
        )
    if min(h, w) < 4 * pitch0:
        raise LatticeNotFound(
            f"image {w}x{h} px holds fewer than 4 dots across at the nominal pitch "
            f"{pitch0:.3g} px; "
            "check --pixel-pitch-um and --lattice-pitch-um (both in um)"
        )
    x, noise, dots, weight = _dots_of(img, pitch0, quantum)
    if dots.shape[0] == 0:
        raise LatticeNotFound(f"no dot stands {DETECT_SIGMAS:g} sigma above the noise")
    lattice, notes, partner, measured = _coarse_lattice(dots, weight, pitch0)
    if partner.sum() >= 3:
        # Dots with a neighbour at the pitch: lone noise peaks would pull the fit.
        dots, weight = dots[partner], weight[partner]
    # A pitch taken from the design (no dot had a neighbour one pitch away: a plate
    # lighting every other order) may be off by the whole tolerance; a measured one
    # is within a few per cent.
    max_step = MAX_BASIS_STEP if measured else PITCH_TOLERANCE + MAX_BASIS_STEP
    for reach in (3, 8, 20, None):  # grow the fitted region while the indices stay right
        lattice = _fit_dots(lattice, dots, weight, reach, max_step)
        max_step = MAX_BASIS_STEP
    ratio = lattice.pitch_px / pitch0
    if abs(ratio - 1) > PITCH_TOLERANCE:
        raise LatticeNotFound(
            f"the dots form a lattice of pitch {lattice.pitch_px:.4g} px, "
            f"{ratio - 1:+.0%} off the nominal {pitch0:.4g} px (allowed "
            f"±{PITCH_TOLERANCE:.0%}); check --pixel-pitch-um, and give --lattice-pitch-um "
            "for a lens of another focal length than the design's"
        )
    if lattice.pitch_px < MIN_PITCH_PX:
        raise LatticeNotFound(
            f"the dots are {lattice.pitch_px:.3g} px apart, closer than the "
            f"{MIN_PITCH_PX:g} px the photometry needs; magnify the lattice"
        )
    lattice = _recentre(lattice, (h, w))
    for _ in range(refine_iterations):
        lattice = _refine(x, lattice, noise)
    return lattice, notes


def on_lattice_share(image, lattice, nominal_pitch_px, quantum=0.0):
    """Return the share of the detected dots' light that lies on ``lattice``'s sites.

    Dots are detected as for registration, single-pixel spikes (hot pixels: at
    least ``SPIKE_FRACTION`` of the 3 x 3 light in one pixel) left out; a dot is
    on the lattice within a quarter pitch of a site. Near 1 for a capture of
    the plate registered at the right pitch; a lattice fitted at a wrong one
    (a wrong camera pixel pitch) leaves much of the light between its sites.
    None when every detected dot is a spike.
    """
    x, _, dots, weight = _dots_of(image, nominal_pitch_px, quantum)
    r, c = np.round(dots[:, 0]).astype(int), np.round(dots[:, 1]).astype(int)
    patch = np.clip(pixel_patches(x, r, c, 1), 0, None)
    spot = patch.max(axis=(1, 2)) < SPIKE_FRACTION * patch.sum(axis=(1, 2))
    if not spot.any():
        return None
    u, v = lattice.coordinates(dots[spot, 0], dots[spot, 1])
    on = np.hypot(u - np.round(u), v - np.round(v)) < 0.25
    return float(weight[spot][on].sum() / weight[spot].sum())


def _dots_of(image, pitch, quantum):
    """Return (image less its median, noise sigma, dot centroids, dot signals) of a capture."""
    x = np.asarray(image, dtype=np.float32)
    x = x - np.float32(np.median(x[::4, ::4]))
    noise = pixel_noise(x[::4, ::4], quantum)
    return (x, noise, *_detect_dots(x, pitch, noise))


def pixel_noise(values, quantum=0.0):
    """Return the noise sigma of one pixel: robust, and at least the rounding noise.

    A quiet camera (read noise well below 1 DN, or a black level clamped at 0)
    gives a background of one code, whose spread is 0; but every measured value
    still carries the error of rounding to codes ``quantum`` DN apart, whose
    sigma is quantum / sqrt(12).
    """
    return max(robust_sigma(values), quantum / np.sqrt(12.0), 1e-6)


def _detect_dots(x, pitch, noise):
    """Return (P, 2) centroids (row, col) and signals of the dots standing out of the noise."""
    from scipy import ndimage

    # a tight lattice's dots would merge under the 0.8 px smoothing
    blur = 0.5 if pitch < TIGHT_PITCH_PX else 0.8
    smooth = ndimage.gaussian_filter(x, blur)
    # Smoothing a pixel's white noise by a Gaussian of 0.8 px divides sigma by ~2.8.
    threshold = DETECT_SIGMAS * noise / (2 * np.sqrt(np.pi) * blur)
    size = max(3, int(0.6 * pitch) | 1)
    peak = (smooth == ndimage.maximum_filter(smooth, size=size)) & (smooth > threshold)
    r, c = np.nonzero(peak)
    order = np.argsort(smooth[r, c])[::-1][:MAX_DOTS]
    r, c = r[order], c[order]
    rad = 1 if pitch < TIGHT_PITCH_PX else 2
    inside = (r >= rad) & (r < x.shape[0] - rad) & (c >= rad) & (c < x.shape[1] - rad)
    r, c = r[inside], c[inside]
    patch = np.clip(pixel_patches(x, r, c, rad), 0, None).astype(np.float64)
    total = patch.sum(axis=(1, 2))
    off = np.arange(-rad, rad + 1, dtype=np.float64)
    safe = np.maximum(total, 1e-30)
    rows = r + (patch.sum(axis=2) @ off) / safe
    cols = c + (patch.sum(axis=1) @ off) / safe
    return np.stack([rows, cols], axis=1), total


def _coarse_lattice(dots, weight, pitch0):
    """Estimate pitch and rotation from nearest-neighbour vectors, origin at the brightest dot.

    Returns the lattice, notes, which dots have a neighbour at the pitch, and
    whether pitch and rotation were measured (else they are the nominal pitch, 0).

    A square lattice's four neighbour directions coincide under z -> z^4 (z the
    vector as a complex number), so the mean of z^4 gives the rotation without
    knowing which neighbour is which.
    """
    from scipy.spatial import cKDTree

    notes = []
    lo, hi = 0.8 * pitch0, 1.18 * pitch0
    pairs = cKDTree(dots).query_pairs(hi, output_type="ndarray")
    partner = np.zeros(dots.shape[0], bool)
    theta, pitch = 0.0, pitch0
    if pairs.size:
        d = dots[pairs[:, 1]] - dots[pairs[:, 0]]
        length = np.hypot(d[:, 0], d[:, 1])
        keep = (length >= lo) & (length <= hi)
        pairs, d, length = pairs[keep], d[keep], length[keep]
        partner[pairs.ravel()] = True
    measured = pairs.shape[0] >= 2
    if measured:
        z = (d[:, 1] - 1j * d[:, 0]) / length  # x right, y up
        wts = np.sqrt(weight[pairs[:, 0]] * weight[pairs[:, 1]])
        theta = float(np.angle(np.sum(wts * z**4)) / 4)
        pitch = float(np.median(length))
    else:
        notes.append(
            "too few neighbouring dots to measure the lattice: pitch and rotation "
            "start from the design's nominal pitch"
        )
    basis = pitch * np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    # The brightest dot with a neighbour (a lone bright spot may be a hot pixel).
    candidates = np.nonzero(partner)[0] if partner.any() else np.arange(dots.shape[0])
    origin = dots[candidates[np.argmax(weight[candidates])]]
    return Lattice(origin.copy(), basis), notes, partner, measured


def _fit_dots(lattice, dots, weight, reach, max_step=MAX_BASIS_STEP):
    """Least-squares fit of origin and basis to the detected dots within ``reach`` pitches.

    A basis that moves by more than ``max_step`` of the pitch is refused (the
    origin moves only).
    """
    u, v = lattice.coordinates(dots[:, 0], dots[:, 1])
    ku, kv = np.round(u), np.round(v)
    near = np.hypot(u - ku, v - kv) < 0.3
    if reach is not None:
        near &= np.hypot(ku, kv) <= reach
    if near.sum() < 3:
        return lattice
    design = np.stack([np.ones(near.sum()), ku[near], kv[near]], axis=1)
    if np.linalg.matrix_rank(design) < 3:
        # All dots on one lattice line: keep the basis, move the origin only.
        res = dots[near] - np.stack(lattice.positions(ku[near], kv[near]), axis=1)
        return Lattice(
            lattice.origin + np.average(res, axis=0, weights=weight[near]), lattice.basis
        )
    sw = np.sqrt(weight[near])[:, None]
    target = dots[near]
    use = np.ones(design.shape[0], bool)
    for _ in range(3):  # drop outliers (hot pixels near a lattice site) and refit
        coef_r, *_ = np.linalg.lstsq((design * sw)[use], (target[:, 0] * sw[:, 0])[use], rcond=None)
        coef_c, *_ = np.linalg.lstsq((design * sw)[use], (target[:, 1] * sw[:, 0])[use], rcond=None)
        resid = np.hypot(design @ coef_r - target[:, 0], design @ coef_c - target[:, 1])
        new = resid < max(3 * float(np.median(resid[use])), 0.3)
        if new.sum() < 3 or np.array_equal(new, use) or np.linalg.matrix_rank(design[new]) < 3:
            break
        use = new
    basis = np.array([[coef_r[1], coef_r[2]], [coef_c[1], coef_c[2]]])
    if np.abs(basis - lattice.basis).max() > max_step * lattice.pitch_px:
        # A jump this large comes from a stray dot, not from the lattice: keep the basis.
        res = dots[near] - np.stack(lattice.positions(ku[near], kv[near]), axis=1)
        return Lattice(lattice.origin + np.median(res, axis=0), lattice.basis)
    # The origin is the lattice point (0, 0) of the old indexing.
    return Lattice(np.array([coef_r[0], coef_c[0]]), basis)


def _recentre(lattice, shape):
    """Move the origin to the lattice point nearest the image centre."""
    centre = (np.asarray(shape, float) - 1) / 2
    u, v = lattice.coordinates(centre[0], centre[1])
    k = np.array([np.round(u), np.round(v)])
    return Lattice(lattice.origin + lattice.basis @ k, lattice.basis)


def lattice_points(lattice, shape, margin):
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


def pixel_patches(image, rows, cols, radius):
    """Return (P, 2r+1, 2r+1) patches of ``image`` centred on the rounded positions."""
    off = np.arange(-radius, radius + 1)
    rr = np.rint(rows).astype(np.intp)[:, None, None] + off[None, :, None]
    cc = np.rint(cols).astype(np.intp)[:, None, None] + off[None, None, :]
    return image[rr, cc]


def _refine(x, lattice, noise):
    """Refine origin and basis by least squares on the centroids of the dots above the noise."""
    radius = 1 if lattice.pitch_px < TIGHT_PITCH_PX else max(2, round(0.3 * lattice.pitch_px))
    u, v, rows, cols, valid = lattice_points(lattice, x.shape, radius)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    uu, vv, rows, cols = uu[valid], vv[valid], rows[valid], cols[valid]
    patch = pixel_patches(x, rows, cols, radius).astype(np.float64)
    # Each dot less its own background (the median of its patch's rim): a
    # background that varies across the frame would pull every centroid uphill.
    rim = np.concatenate(
        [patch[:, 0, :], patch[:, -1, :], patch[:, 1:-1, 0], patch[:, 1:-1, -1]], axis=1
    )
    # (a 3 x 3 patch's rim holds the dot's own light: the frame's median is its background)
    if radius > 1:
        patch = patch - np.median(rim, axis=1)[:, None, None]
    patch = np.clip(patch, 0, None)
    total = patch.sum(axis=(1, 2))
    signal = total - np.median(total)
    significant = signal > DETECT_SIGMAS * noise * (2 * radius + 1)
    # The brightest few thousand dots carry the geometry; the faint ones only add noise.
    keep = np.nonzero(significant)[0]
    keep = keep[np.argsort(total[keep])[::-1][:4000]]
    if keep.size < 3:
        return lattice
    off = np.arange(-radius, radius + 1, dtype=np.float64)
    pk = patch[keep]
    cr = np.rint(rows[keep]) + (pk.sum(axis=2) @ off) / total[keep]
    cc = np.rint(cols[keep]) + (pk.sum(axis=1) @ off) / total[keep]
    ku, kv = uu[keep].astype(float), vv[keep].astype(float)
    design = np.stack([np.ones_like(ku), ku, kv], axis=1)
    if np.linalg.matrix_rank(design) < 3:
        return lattice
    use = np.ones(keep.size, bool)
    for _ in range(3):  # drop outliers (hot pixels, merged dots) and refit
        coef_r, *_ = np.linalg.lstsq(design[use], cr[use], rcond=None)
        coef_c, *_ = np.linalg.lstsq(design[use], cc[use], rcond=None)
        resid = np.hypot(design @ coef_r - cr, design @ coef_c - cc)
        cut = max(3 * float(np.median(resid[use])), 0.2)
        new = resid < cut
        if new.sum() < 3 or np.array_equal(new, use) or np.linalg.matrix_rank(design[new]) < 3:
            break
        use = new
    origin = np.array([coef_r[0], coef_c[0]])
    basis = np.array([[coef_r[1], coef_r[2]], [coef_c[1], coef_c[2]]])
    return _recentre(Lattice(origin, basis), x.shape)
