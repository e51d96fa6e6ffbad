"""The optics that follow from a design: tile, mask pixel pitch, dot lattice, etch depths.

:func:`derive` computes what an optics engineer checks before fabrication;
:func:`design_summary` is the design with those quantities as a JSON-ready dict
(the ``design`` that retrieval.json, learn.json and the fab manifest record).
SI units inside, the design file's units in the summary's keys.
"""

import math
from dataclasses import asdict, dataclass

from doe.materials import MATERIALS, IndexTable


@dataclass(frozen=True)
class Derived:
    """Quantities that follow from a design (SI units).

    ``tile_size`` is N * ``mask_pixel_pitch`` after snapping the pitch to the
    GDS grid; the dot lattice that the tiled plate puts on the sensor then has
    pitch lambda f / tile_size, slightly off the sub-pixel pitch, and
    ``lattice_drift_at_edge`` is how far the outermost dot has wandered, along the
    sensor's longer side, when the zero order sits at the sensor centre. Both are
    paraxial (order m at m lambda f / tile_size) and count the grid snap only: a
    lens that maps angle as f tan(theta) puts order 128 of the default design 22 um
    further out (an f sin(theta) Fourier lens does not).
    """

    subpixel_pitch: float
    tile_size_nominal: float
    tile_pixels: int
    mask_pixel_pitch: float
    tile_size: float
    lattice_pitch: float
    lattice_mismatch: float
    lattice_drift_at_edge: float
    tiles: int
    tiled_size: float
    refractive_index: float
    level_step: float
    etch_depths: tuple[float, ...]
    masks: int
    fill_factor: float


# A coarse GDS grid rounds the mask pixel pitch, which scales the whole PSF: its
# outermost orders may land at most this fraction of a sub-pixel off their sub-pixels.
LATTICE_OFFSET_MAX = 0.05


def lattice_problem(der, kernel_size, grid):
    """Return why a tile's dot lattice misses the sub-pixel grid, or None if it fits.

    ``der`` is :func:`derive` for the tile, ``grid`` the GDS grid (m).
    """
    offset = kernel_size // 2 * abs(der.lattice_mismatch) / der.subpixel_pitch
    if offset <= LATTICE_OFFSET_MAX:
        return None
    return (
        f"the {grid * 1e9:g} nm grid snaps the mask pixel pitch to "
        f"{der.mask_pixel_pitch * 1e9:g} nm (the tile wants "
        f"{der.tile_size_nominal / der.tile_pixels * 1e9:.1f} nm), which puts the dot "
        f"lattice {der.lattice_mismatch / der.subpixel_pitch:+.2%} off the sub-pixel pitch: "
        f"the {kernel_size} x {kernel_size} PSF's outermost dots land {offset:.0%} of a "
        f"sub-pixel off theirs (at most {LATTICE_OFFSET_MAX:.0%}); use a finer grid"
    )


# Relative slack of the pixel-count floor: a tile of exactly N feature sizes (up to
# float noise in the SI round trip) has N pixels, not N - 1.
_FLOOR_SLACK = 1e-9


def tile_pixel_count(tile_nominal, feature_size):
    """Return N, the most pixels per tile that are each at least the feature size.

    Rounding to the nearest N would make the pixel up to half a pixel's share
    narrower than the feature size, and a Euclidean width rule at the feature size
    then flags every single-pixel line.
    """
    return max(1, math.floor(tile_nominal / feature_size * (1 + _FLOOR_SLACK)))


def snapped_pixel_pitch(tile_nominal, tile_pixels, grid, minimum=0.0):
    """Return the mask pixel pitch (m): the nominal tile over N pixels, snapped to the grid.

    The snap does not take a pixel of at least ``minimum`` (the feature size) below
    it: it then goes one grid step up instead of down. A pixel already below
    ``minimum`` (a tile of more pixels than the feature size allows) snaps to the
    nearest grid step. 0 when the grid is coarser than twice the pitch (the caller
    refuses that).
    """
    nominal = tile_nominal / tile_pixels
    steps = round(nominal / grid)
    if 0 < steps * grid < minimum * (1 - _FLOOR_SLACK) <= nominal:
        steps += 1
    return steps * grid


def derive(d, tile_pixels=None):
    """Return the :class:`Derived` quantities of design ``d``.

    ``tile_pixels`` overrides N (default: :func:`tile_pixel_count`, the most pixels
    of at least the feature size that fit the tile).
    """
    sensor, fab, wl, f = d.sensor, d.fabrication, d.optics.wavelength, d.optics.focal_length
    subpixel = sensor.pixel_pitch / sensor.superres_factor
    tile_nominal = wl * f / subpixel  # order spacing lambda f / T = sub-pixel pitch
    n_pix = tile_pixels or tile_pixel_count(tile_nominal, fab.feature_size)
    pitch = snapped_pixel_pitch(tile_nominal, n_pix, fab.grid, fab.feature_size)
    tile = n_pix * pitch
    lattice = wl * f / tile if tile > 0 else math.inf
    half_width_subpixels = max(sensor.columns, sensor.rows) * sensor.superres_factor / 2
    n = d.material.dispersion.index(wl)
    step = wl / (n - 1) / fab.levels
    masks = int(math.log2(fab.levels))
    if sensor.active_area_shape == "circle":
        active = math.pi * (sensor.active_area / 2) ** 2
    else:
        active = sensor.active_area**2
    return Derived(
        subpixel_pitch=subpixel,
        tile_size_nominal=tile_nominal,
        tile_pixels=n_pix,
        mask_pixel_pitch=pitch,
        tile_size=tile,
        lattice_pitch=lattice,
        lattice_mismatch=lattice - subpixel,
        lattice_drift_at_edge=(lattice - subpixel) * half_width_subpixels,
        tiles=max(1, math.floor(fab.aperture / tile + 1e-9)) if tile > 0 else 0,
        tiled_size=math.floor(fab.aperture / tile + 1e-9) * tile if tile > 0 else 0.0,
        refractive_index=n,
        level_step=step,
        etch_depths=tuple(step * 2**k for k in reversed(range(masks))),
        masks=masks,
        fill_factor=active / sensor.pixel_pitch**2,
    )


def as_typed(value, scale):
    """Return a value held in SI units in the unit the design file gives it in.

    Rounded to 12 significant digits, which undoes the float noise of the SI round
    trip (655 nm is stored as 6.55e-7 m and comes back as 655.0000000000001).
    """
    return float(f"{value * scale:.12g}")


def material_summary(m):
    """The summary's ``[material]``: a custom glass with its coefficients or index table."""
    out = {"name": m.name, "thickness_mm": as_typed(m.thickness, 1e3)}
    glass = m.dispersion
    if MATERIALS.get(m.name) is glass:
        return out
    if isinstance(glass, IndexTable):
        rows = zip(glass.wavelengths, glass.indices, strict=True)
        return {**out, "index_table": [[as_typed(w, 1e9), n] for w, n in rows]}
    return {
        **out,
        "sellmeier_b": list(glass.B),
        "sellmeier_c_um2": list(glass.C),
        "range_nm": [as_typed(v, 1e9) for v in glass.valid],
    }


def design_summary(d, tile_pixels=None):
    """Return the design and its derived quantities as a JSON-ready dict, units in the keys.

    ``tile_pixels`` overrides N as in :func:`derive` (a tile of another size).
    """
    der = derive(d, tile_pixels)
    return {
        "name": d.name,
        "description": d.description,
        "sensor": {
            "columns": d.sensor.columns,
            "rows": d.sensor.rows,
            "pixel_pitch_um": as_typed(d.sensor.pixel_pitch, 1e6),
            "active_area_um": as_typed(d.sensor.active_area, 1e6),
            "active_area_shape": d.sensor.active_area_shape,
            "active_offset_um": [as_typed(v, 1e6) for v in d.sensor.active_offset],
            "superres_factor": d.sensor.superres_factor,
        },
        "optics": {
            "wavelength_nm": as_typed(d.optics.wavelength, 1e9),
            "focal_length_mm": as_typed(d.optics.focal_length, 1e3),
        },
        "psf": {"kernel_size": d.kernel_size},
        "material": material_summary(d.material),
        "fabrication": {
            "levels": d.fabrication.levels,
            "feature_size_um": as_typed(d.fabrication.feature_size, 1e6),
            "aperture_mm": as_typed(d.fabrication.aperture, 1e3),
            "grid_nm": round(d.fabrication.grid * 1e9),
            "allow_corner_contacts": d.fabrication.allow_corner_contacts,
        },
        "learning": asdict(d.learning),
        "derived": {
            "subpixel_pitch_um": der.subpixel_pitch * 1e6,
            "fill_factor": der.fill_factor,
            "tile_size_nominal_um": der.tile_size_nominal * 1e6,
            "tile_pixels": der.tile_pixels,
            "mask_pixel_pitch_nm": round(der.mask_pixel_pitch * 1e9),
            "tile_size_um": der.tile_size * 1e6,
            "lattice_pitch_um": der.lattice_pitch * 1e6,
            "lattice_mismatch_um": der.lattice_mismatch * 1e6,
            "lattice_drift_at_edge_um": der.lattice_drift_at_edge * 1e6,
            "tiles_across_aperture": der.tiles,
            "tiled_size_mm": der.tiled_size * 1e3,
            "refractive_index": der.refractive_index,
            "level_step_nm": der.level_step * 1e9,
            "etch_depths_nm": [v * 1e9 for v in der.etch_depths],
            "masks": der.masks,
        },
    }
