"""Whether a design's tiled plate forms a dot lattice on its sensor, and what to change if not.

Paraxially, with the plate at the lens's front focal plane, a tile of period
T = lambda f / s (s the sub-pixel pitch) puts its diffraction orders s apart on
the sensor. One tile alone gives a continuous far field; only the coherent sum
of n x n tiles narrows each order into a dot, whose first zeros lie
lambda f / (n T) = s / n from its centre: the dot's width is the sub-pixel pitch
over the tiles across. Per axis a square tiled area gives each dot a sinc^2
profile, whose power within its own sub-pixel (+-s/2, i.e. +-n/2 zeros) is
(2 / pi) (Si(pi n) - sin^2(pi n / 2) / (pi n / 2)); squared for the two axes it
is 60 % for one tile, 82 % for 2, 90 % for 4, 95 % for 8 and 97 % for 16 (the
sun2020 preset). The rest lands on the neighbouring sub-pixels, where the
network reads it as the PSF's own light.

- Fewer than :data:`TILES_MIN` = 2 whole tiles: 40 % of every dot's power leaves
  its sub-pixel, the PSF is no dot lattice: refused.
- Fewer than :data:`TILES_GOOD` = 8: more than 5 % leaks, more than an 8-level
  plate's quantisation scatters out of its orders (sinc^2(1/8) = 95 % stays):
  marginal (a warning).

The dot's diameter through the lens's stop (diameter = the aperture) is the Airy
diameter 2.44 lambda N at the working f-number N = f / aperture. A dot wider
than the active area loses light outside it (marginal). The grid-snapped tile
puts the dot lattice at lambda f / T_snapped, off the sub-pixel pitch; the
PSF's outermost dots (K // 2 sub-pixels out) wander by K // 2 times that, and a
dot that wanders further than the active area leaves around it slips partly off
its active area (marginal).
"""

import math
from dataclasses import dataclass

from scipy.special import sici

from doe.derived import derive, snapped_pixel_pitch

TILES_MIN = 2  # fewer whole tiles: refused
TILES_GOOD = 8  # fewer: marginal
AIRY = 2.44  # Airy diameter (first dark ring) in units of lambda N


@dataclass(frozen=True)
class Tiling:
    """The tiling figures of a design (SI units) and its verdict.

    ``verdict`` is ``"ok"``, ``"marginal"`` (``problems`` says why) or
    ``"refused"``; ``fixes`` are the changes, with values, that reach
    :data:`TILES_GOOD` tiles (or a dot inside the active area).
    """

    tile_size: float
    tiles: int
    tiles_exact: float
    own_cell_power: float
    f_number: float
    dot_diameter: float
    active_area: float
    subpixel_pitch: float
    lattice_mismatch: float
    kernel_edge_offset: float
    drift_at_edge: float
    verdict: str
    problems: tuple[str, ...]
    fixes: tuple[str, ...]


def own_cell_power(tiles):
    """Share of a lattice dot's power inside its own sub-pixel, for ``tiles`` tiles across.

    Each axis of a square tiled area gives a sinc^2 dot with zeros s / tiles apart;
    its power within +-s/2 is (2 / pi) (Si(pi n) - sin^2(pi n / 2) / (pi n / 2)).
    """
    if tiles <= 0:
        return 0.0
    x = math.pi * tiles / 2
    one_axis = 2 / math.pi * (sici(2 * x)[0] - math.sin(x) ** 2 / x)
    return float(one_axis**2)


def tiling(d):
    """Return the :class:`Tiling` of design ``d`` (a :class:`doe.design.Design`)."""
    der = derive(d)
    wl, f = d.optics.wavelength, d.optics.focal_length
    aperture, active = d.fabrication.aperture, d.sensor.active_area
    dot = AIRY * wl * f / aperture
    offset = d.kernel_size // 2 * abs(der.lattice_mismatch)
    problems = []
    if der.tiles < TILES_GOOD:
        problems.append(
            f"{der.tiles} whole tile(s) of {der.tile_size * 1e3:.4g} mm across the "
            f"{aperture * 1e3:g} mm aperture: each dot keeps {own_cell_power(der.tiles):.0%} of "
            f"its power in its sub-pixel (at least {TILES_MIN} tiles, {TILES_GOOD} for "
            f"{own_cell_power(TILES_GOOD):.0%})"
        )
    if dot > active:
        problems.append(
            f"the dot ({AIRY} lambda N = {dot * 1e6:.3g} um at f/{f / aperture:.3g}) is wider "
            f"than the {active * 1e6:g} um active area"
        )
    drifting = dot <= active and offset > (active - dot) / 2
    if drifting:
        problems.append(
            f"the PSF's outermost dots drift {offset * 1e6:.3g} um off their sub-pixels, "
            f"more than the {(active - dot) / 2 * 1e6:.3g} um the active area leaves around a "
            f"{dot * 1e6:.3g} um dot"
        )
    verdict = "refused" if der.tiles < TILES_MIN else "marginal" if problems else "ok"
    return Tiling(
        tile_size=der.tile_size,
        tiles=der.tiles,
        tiles_exact=aperture / der.tile_size,
        own_cell_power=own_cell_power(der.tiles),
        f_number=f / aperture,
        dot_diameter=dot,
        active_area=active,
        subpixel_pitch=der.subpixel_pitch,
        lattice_mismatch=der.lattice_mismatch,
        kernel_edge_offset=offset,
        drift_at_edge=der.lattice_drift_at_edge,
        verdict=verdict,
        problems=tuple(problems),
        fixes=tuple(_fixes(d, der, dot, drifting)) if problems else (),
    )


# The suggested values keep this margin from the thresholds: snapping the mask
# pitch to the grid moves the tile by up to half a grid step per pixel.
_MARGIN = 1e-3


def _fixes(d, der, dot, drifting):
    """The changes, with values, that give TILES_GOOD tiles, a dot inside the active area
    and outermost dots on their active areas."""
    wl, f, aperture = d.optics.wavelength, d.optics.focal_length, d.fabrication.aperture
    s, k = der.subpixel_pitch, d.kernel_size
    out = []
    if der.tiles < TILES_GOOD:
        out.append(_focal_fix(d, s, k))
        a_min = TILES_GOOD * der.tile_size * (1 + _MARGIN)
        out.append(f"[fabrication] aperture_mm >= {math.ceil(a_min * 1e5) / 100:g}")
        p, r = d.sensor.pixel_pitch, d.sensor.superres_factor
        r_max = math.floor(aperture * p / (wl * f * TILES_GOOD) * (1 - _MARGIN))
        if 2 <= r_max < r:  # a factor of 1 is no super-resolution
            out.append(f"[sensor] superres_factor <= {r_max}")
        elif r_max < 2 < r:  # tiles across = s / (lambda N): a wider sub-pixel and a shorter f
            out.append(f"[sensor] superres_factor = 2 with {_focal_fix(d, p / 2, k)}")
    if drifting:  # another tile pixel count N, whose snapped pitch drifts less
        out.append(_pixel_count_fix(d, der))
    if dot > d.sensor.active_area:
        a_dot = AIRY * wl * f / d.sensor.active_area * (1 + _MARGIN)
        out.append(f"[fabrication] aperture_mm >= {math.ceil(a_dot * 1e5) / 100:g} for the dot")
    return out


def _focal_fix(d, s, k):
    """The longest focal length that gives TILES_GOOD tiles of sub-pixel ``s``, and its f-number."""
    wl, aperture = d.optics.wavelength, d.fabrication.aperture
    f_max = math.floor(aperture * s / (wl * TILES_GOOD) * (1 - _MARGIN) * 1e4) / 1e4
    fix = f"[optics] focal_length_mm <= {f_max * 1e3:g} (f/{f_max / aperture:.2g})"
    feature_max = aperture / TILES_GOOD / k  # the smaller tile must keep N >= K pixels
    if d.fabrication.feature_size > feature_max:
        fix += f" and [fabrication] feature_size_um <= {math.floor(feature_max * 1e7) / 10:g}"
    return fix


def _pixel_count_fix(d, der):
    """The feature size, near the design's, whose grid-snapped pitch drifts least."""
    grid, nominal = d.fabrication.grid, der.tile_size_nominal
    counts = range(max(d.kernel_size, der.tile_pixels - 20), der.tile_pixels + 21)

    def feature(n):  # the feature size that gives N = n (derive's floor), on the 1 nm grid
        return math.floor(nominal / n * 1e9) * 1e-9

    def pitch(n):
        return snapped_pixel_pitch(nominal, n, grid, feature(n))

    best = min(counts, key=lambda n: abs(n * pitch(n) - nominal))
    return (
        f"[fabrication] feature_size_um = {feature(best) * 1e6:.6g} (N = {best}, whose "
        f"{pitch(best) * 1e9:g} nm pitch lands nearest the grid)"
    )


def summary_line(t):
    """One line: the verdict and its figures (for ``doefab presets``)."""
    head = (
        f"{t.verdict}: {t.tiles} tiles of {t.tile_size * 1e3:.3g} mm, "
        f"{t.own_cell_power:.0%} of a dot in its sub-pixel, dot {t.dot_diameter * 1e6:.3g} um "
        f"in a {t.active_area * 1e6:g} um active area"
    )
    return head if t.verdict == "ok" else f"{head}; {'; '.join(t.problems)}"


def refusal(t):
    """The one-line reason a refused design is refused, with what to change; None if not refused."""
    if t.verdict != "refused":
        return None
    return (
        f"no dot lattice forms: {t.problems[0]}; change {', or '.join(t.fixes)} "
        f"(the tile is wavelength x focal length / sub-pixel pitch)"
    )
