"""Design configuration: TOML schema, the embedded presets, validation, derived optics.

A design file is TOML with one table per concern (sensor, optics, psf,
material, fabrication, learning); every quantity carries its unit in the key
name. Inside the code everything is SI (metres). ``derive`` computes what an
optics engineer checks before fabrication.
"""

import math
import tomllib
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path
from typing import Literal

from doe.infra.errors import InputError
from doe.infra.files import LEVEL_COUNT_RULE, is_level_count, read_json
from doe.infra.flags import MINUTES_MAX, PHOTONS_MAX, SEED_MAX, STEPS_MAX
from doe.materials import MATERIALS, refractive_index


@dataclass(frozen=True)
class Sensor:
    columns: int
    rows: int
    pixel_pitch: float
    active_area: float
    active_area_shape: Literal["circle", "square"]
    active_offset: tuple[float, float]
    superres_factor: int


@dataclass(frozen=True)
class Optics:
    wavelength: float
    focal_length: float


@dataclass(frozen=True)
class Material:
    name: str
    thickness: float


@dataclass(frozen=True)
class Fabrication:
    levels: int
    feature_size: float
    aperture: float
    grid: float


@dataclass(frozen=True)
class Learning:
    seed: int
    minutes: float
    steps: int
    photons_per_pixel: float


@dataclass(frozen=True)
class Design:
    """A validated design, SI units throughout."""

    name: str
    description: str
    sensor: Sensor
    optics: Optics
    kernel_size: int
    material: Material
    fabrication: Fabrication
    learning: Learning


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


# (section, key) -> (type, unit scale to SI or None, check, explanation)
_POSITIVE = (lambda v: v > 0, "must be > 0")
_NONNEG = (lambda v: v >= 0, "must be >= 0")
SHORTEST_LENGTH, LONGEST_LENGTH = 1e-12, 1.0  # m, the range of every length in a design
_SCHEMA = {
    "sensor": {
        "columns": (int, None, _POSITIVE),
        "rows": (int, None, _POSITIVE),
        "pixel_pitch_um": (float, 1e-6, _POSITIVE),
        "active_area_um": (float, 1e-6, _POSITIVE),
        "active_area_shape": (
            str,
            None,
            (lambda v: v in ("circle", "square"), "must be 'circle' or 'square'"),
        ),
        "active_offset_um": (list, 1e-6, (lambda v: len(v) == 2, "must be [x, y]")),
        "superres_factor": (int, None, _POSITIVE),
    },
    "optics": {
        "wavelength_nm": (float, 1e-9, _POSITIVE),
        "focal_length_mm": (float, 1e-3, _POSITIVE),
    },
    "psf": {
        "kernel_size": (int, None, (lambda v: v > 0 and v % 2 == 1, "must be odd and > 0")),
    },
    "material": {
        "name": (
            str,
            None,
            (lambda v: v in MATERIALS, f"must be one of {', '.join(sorted(MATERIALS))}"),
        ),
        "thickness_mm": (float, 1e-3, _POSITIVE),
    },
    "fabrication": {
        "levels": (int, None, (is_level_count, f"must be {LEVEL_COUNT_RULE}")),
        "feature_size_um": (float, 1e-6, _POSITIVE),
        "aperture_mm": (float, 1e-3, _POSITIVE),
        "grid_nm": (int, 1e-9, _POSITIVE),
    },
    "learning": {
        "seed": (int, None, (lambda v: 0 <= v <= SEED_MAX, "must be 0 .. 2^63 - 1")),
        "minutes": (
            float,
            None,
            (lambda v: 0 < v <= MINUTES_MAX, f"must be > 0 and <= {MINUTES_MAX:g} (two years)"),
        ),
        "steps": (int, None, (lambda v: 0 < v <= STEPS_MAX, f"must be 1 .. {STEPS_MAX:g}")),
        "photons_per_pixel": (
            float,
            None,
            (lambda v: 0 < v <= PHOTONS_MAX, f"must be > 0 and <= {PHOTONS_MAX:g}"),
        ),
    },
}


def preset_names():
    """Return the names of the embedded presets."""
    files = resources.files("doe.presets").iterdir()
    return sorted(p.name.removesuffix(".toml") for p in files if p.name.endswith(".toml"))


DEFAULT_PRESET = "sun2020"


def load_design(path=None):
    """Load and validate a design.

    Parameters
    ----------
    path : str or Path or None
        A TOML file, or the name of an embedded preset, or None for the default.
        A file may set only some keys: the rest come from the default preset.
    """
    base = _read_preset(DEFAULT_PRESET)
    if path is None:
        return parse_design(base, DEFAULT_PRESET)
    if not str(path).strip():  # Path("") is the current folder: "cannot read '.'"
        raise InputError("--config", "is empty: give a design file or a preset name")
    if str(path) in preset_names():
        if Path(path).exists():  # which one the lab meant cannot be guessed
            raise InputError(
                path, f"names both a preset and a file here; pass ./{path} for the file"
            )
        return parse_design(_read_preset(str(path)), str(path))
    path = Path(path)
    try:
        # TOML is UTF-8 whatever the locale; "-sig" drops the BOM some Windows editors write.
        raw = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        raise InputError(
            path, f"no such design file, nor a preset (presets: {', '.join(preset_names())})"
        ) from None
    except UnicodeDecodeError as e:
        raise InputError(
            path,
            f"not UTF-8 text (byte {e.object[e.start]:#04x} at offset {e.start}); save it as UTF-8",
        ) from None
    except OSError as e:
        raise InputError(path, f"cannot read: {e}") from None
    except ValueError as e:  # TOMLDecodeError, or an integer past Python's digit limit
        raise InputError(path, f"not valid TOML: {e}") from None
    # A file that names no design is not the preset: it goes by its own name (etched
    # on every mask label), and its description says what it is made of (not where
    # the file lies: a moved file is the same design).
    own = {
        "name": path.stem,
        "description": f"the {DEFAULT_PRESET} preset with the values set in its design file",
    }
    return parse_design(_merge({**base, **own}, raw), path)


def _read_preset(name):
    return tomllib.loads(
        resources.files("doe.presets").joinpath(f"{name}.toml").read_text(encoding="utf-8")
    )


def _merge(base, override):
    out = dict(base)
    for k, v in override.items():
        out[k] = _merge(base[k], v) if isinstance(v, dict) and isinstance(base.get(k), dict) else v
    return out


def parse_design(raw, source="design"):
    """Validate a raw TOML mapping and return a :class:`Design` (raises InputError)."""
    si = {}
    for key in raw:
        if key not in _SCHEMA and key not in ("name", "description"):
            raise InputError(source, f"unknown section or key {key!r}")
    for section, fields in _SCHEMA.items():
        table = raw.get(section)
        if table is None:
            raise InputError(source, f"missing table [{section}]")
        if not isinstance(table, dict):  # [[optics]] or optics = 5
            raise InputError(source, f"[{section}] must be a table of keys, got {table!r}")
        unknown = set(table) - set(fields)
        if unknown:
            raise InputError(
                source, f"[{section}] has unknown key(s) {sorted(unknown)}; known: {sorted(fields)}"
            )
        for key, (typ, scale, (ok, why)) in fields.items():
            where = f"{source}: [{section}] {key}"
            if key not in table:
                raise InputError(where, "missing")
            si[section, key] = _check_value(where, table[key], typ, scale, ok, why)
    for key in ("name", "description"):
        if not isinstance(raw.get(key, ""), str):
            raise InputError(f"{source}: {key}", "must be a string")

    s = lambda sec, k: si[sec, k]  # noqa: E731
    design = Design(
        name=raw.get("name", Path(str(source)).stem),
        description=raw.get("description", ""),
        sensor=Sensor(
            s("sensor", "columns"),
            s("sensor", "rows"),
            s("sensor", "pixel_pitch_um"),
            s("sensor", "active_area_um"),
            s("sensor", "active_area_shape"),
            tuple(s("sensor", "active_offset_um")),
            s("sensor", "superres_factor"),
        ),
        optics=Optics(s("optics", "wavelength_nm"), s("optics", "focal_length_mm")),
        kernel_size=s("psf", "kernel_size"),
        material=Material(s("material", "name"), s("material", "thickness_mm")),
        fabrication=Fabrication(
            s("fabrication", "levels"),
            s("fabrication", "feature_size_um"),
            s("fabrication", "aperture_mm"),
            s("fabrication", "grid_nm"),
        ),
        learning=Learning(
            s("learning", "seed"),
            s("learning", "minutes"),
            s("learning", "steps"),
            s("learning", "photons_per_pixel"),
        ),
    )
    _check_consistency(design, source)
    return design


def _check_value(where, value, typ, scale, ok, why):
    # TOML integers have no size limit; past 64 bits they are typing errors that
    # would overflow float() or numpy with a traceback.
    too_big = [v for v in (value if isinstance(value, list) else [value]) if _huge_int(v)]
    if too_big:
        digits = int(abs(too_big[0]).bit_length() * math.log10(2))
        raise InputError(where, f"must be at most 2^63 - 1, got a number near 10^{digits}")
    if typ is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, typ) or isinstance(value, bool):
        raise InputError(where, f"must be {typ.__name__}, got {value!r}")
    if typ is list:
        if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value):
            raise InputError(where, f"must be a list of numbers, got {value!r}")
        value = [float(v) for v in value]
        if not all(math.isfinite(v) for v in value):
            raise InputError(where, f"must be finite, got {value!r}")
    elif typ is float and not math.isfinite(value):
        raise InputError(where, f"must be finite, got {value!r}")
    if not ok(value):
        raise InputError(where, f"{why}, got {value!r}")
    if scale is not None:
        given, value = value, [v * scale for v in value] if typ is list else value * scale
        # lengths outside 1 pm .. 1 m are typing errors, and would overflow the
        # derived quantities (a pitch squared) rather than fail a physical check
        sizes = [abs(v) for v in value if v != 0] if typ is list else [value]
        if not all(SHORTEST_LENGTH <= v <= LONGEST_LENGTH for v in sizes):
            raise InputError(where, f"must lie between 1 pm and 1 m, got {given!r}")
    return value


def _huge_int(v):
    return isinstance(v, int) and not isinstance(v, bool) and abs(v) > SEED_MAX


# Retrieval time and memory grow as N^2: N = 1024 took 183 s and 445 MB at peak on the
# 2-core machine, so N = 4096 takes ~50 min and ~7 GB. Larger tiles are refused.
MAX_TILE_PIXELS = 4096


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


# The tile's size is wavelength x focal length / sub-pixel pitch: a unit slip in
# any of these (um typed as mm) shows up first as a tile of the wrong size.
_TILE_SET_BY = (
    "the tile is wavelength x focal length / sub-pixel pitch: check [optics] "
    "wavelength_nm and focal_length_mm and [sensor] pixel_pitch_um"
)


def _check_consistency(d, source):
    sensor, fab = d.sensor, d.fabrication
    for key, count in (("columns", sensor.columns), ("rows", sensor.rows)):
        if count * sensor.pixel_pitch > LONGEST_LENGTH:  # a typing error, as any length past 1 m
            raise InputError(
                f"{source}: [sensor] {key}",
                f"{count} pixels of {sensor.pixel_pitch * 1e6:g} um make a sensor "
                f"{count * sensor.pixel_pitch:.3g} m across, longer than 1 m",
            )
    if sensor.active_area > sensor.pixel_pitch:
        raise InputError(
            f"{source}: [sensor] active_area_um",
            f"the active area ({sensor.active_area * 1e6:g} um) is larger than the pixel pitch "
            f"({sensor.pixel_pitch * 1e6:g} um, [sensor] pixel_pitch_um)",
        )
    reach = max(abs(v) for v in sensor.active_offset) + sensor.active_area / 2
    if reach > sensor.pixel_pitch / 2 * (1 + 1e-9):
        # The sensor model would clamp it into the pixel's corner cell without a word.
        raise InputError(
            f"{source}: [sensor] active_offset_um",
            f"the active area ({sensor.active_area * 1e6:g} um across, centre offset "
            f"({sensor.active_offset[0] * 1e6:g}, {sensor.active_offset[1] * 1e6:g}) um) "
            f"leaves its {sensor.pixel_pitch * 1e6:g} um pixel",
        )
    try:
        refractive_index(d.material.name, d.optics.wavelength)
    except InputError as e:
        raise InputError(f"{source}: [optics] wavelength_nm", e.problem) from None
    der = derive(d)
    deepest = sum(der.etch_depths)
    if d.material.thickness <= deepest:
        raise InputError(
            f"{source}: [material] thickness_mm",
            f"{d.material.thickness * 1e3:g} mm of glass is not thicker than the deepest "
            f"etch ({deepest * 1e9:.1f} nm)",
        )
    if der.tile_size > fab.aperture * (1 + 1e-9):  # a tile of exactly the aperture fits
        raise InputError(
            f"{source}: [fabrication] aperture_mm",
            f"the phase tile ({der.tile_size * 1e3:.6g} mm) is larger than the "
            f"aperture ({fab.aperture * 1e3:.6g} mm); {_TILE_SET_BY}",
        )
    from layouts.marks import check_marks_fit

    try:
        check_marks_fit(der.masks, round(fab.aperture * 1e9) // 2)
    except ValueError as e:
        raise InputError(f"{source}: [fabrication] aperture_mm", str(e)) from None
    if d.kernel_size > der.tile_pixels:
        raise InputError(
            f"{source}: [psf] kernel_size",
            f"K = {d.kernel_size} exceeds the tile's N = {der.tile_pixels} pixels (a "
            f"{der.tile_size_nominal * 1e6:.6g} um tile in pixels of "
            f"{fab.feature_size * 1e6:.6g} um: check [fabrication] feature_size_um; "
            f"{_TILE_SET_BY})",
        )
    if der.mask_pixel_pitch <= 0:
        raise InputError(
            f"{source}: [fabrication] grid_nm",
            f"the {fab.grid * 1e9:g} nm grid is coarser than a mask pixel of "
            f"{fab.feature_size * 1e6:.6g} um ([fabrication] feature_size_um)",
        )
    problem = lattice_problem(der, d.kernel_size, fab.grid)
    if problem:
        raise InputError(f"{source}: [fabrication] grid_nm", problem)
    if der.tile_pixels > MAX_TILE_PIXELS:
        raise InputError(
            f"{source}: [fabrication] feature_size_um",
            f"the tile needs N = {der.tile_pixels} pixels, more than {MAX_TILE_PIXELS} "
            "(retrieval time and memory grow as N^2)",
        )


def derive(d, tile_pixels=None):
    """Return the :class:`Derived` quantities of design ``d``.

    ``tile_pixels`` overrides N (default: the tile size divided by the target
    feature size, rounded).
    """
    sensor, fab, wl, f = d.sensor, d.fabrication, d.optics.wavelength, d.optics.focal_length
    subpixel = sensor.pixel_pitch / sensor.superres_factor
    tile_nominal = wl * f / subpixel  # order spacing lambda f / T = sub-pixel pitch
    n_pix = tile_pixels or max(1, round(tile_nominal / fab.feature_size))
    grid_steps = round(tile_nominal / n_pix / fab.grid)
    pitch = grid_steps * fab.grid
    tile = n_pix * pitch
    lattice = wl * f / tile if tile > 0 else math.inf
    half_width_subpixels = max(sensor.columns, sensor.rows) * sensor.superres_factor / 2
    n = refractive_index(d.material.name, wl)
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
        "material": {"name": d.material.name, "thickness_mm": as_typed(d.material.thickness, 1e3)},
        "fabrication": {
            "levels": d.fabrication.levels,
            "feature_size_um": as_typed(d.fabrication.feature_size, 1e6),
            "aperture_mm": as_typed(d.fabrication.aperture, 1e3),
            "grid_nm": round(d.fabrication.grid * 1e9),
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


# What a phase tile is made for: the sub-pixel grid its PSF is sampled on, the
# optics that map the tile onto that grid, and the glass and grid it is etched
# in. Aperture, substrate thickness, sensor size and learning do not change the
# tile. Its level count is not here: retrieve --levels may differ from the
# design's, so retrieval.json's own "levels" is what a tile is checked against.
TILE_KEYS = (
    ("sensor", "pixel_pitch_um"),
    ("sensor", "superres_factor"),
    ("optics", "wavelength_nm"),
    ("optics", "focal_length_mm"),
    ("material", "name"),
    ("fabrication", "grid_nm"),
)
# What a PSF is made for: the sub-pixel grid it is sampled on.
PSF_GRID_KEYS = (("sensor", "pixel_pitch_um"), ("sensor", "superres_factor"))
# A measured PSF is sampled on the plate's dot lattice, which matches the design's
# sub-pixel pitch to ppm; 2 % admits a hand-measured --lattice-pitch-um in verify.
LATTICE_MATCH_REL = 0.02


def design_differences(recorded, d, keys):
    """Return "key recorded -> d's" for each of ``keys`` where ``d`` differs from ``recorded``.

    ``recorded`` is a :func:`design_summary` dict read from a file (e.g. the
    ``design`` of retrieval.json); keys it lacks are not compared. Numbers agree
    to 1e-9 relative, which absorbs the round trip through the file's units.
    """
    return summary_differences(recorded, design_summary(d), keys)


def summary_differences(recorded, now, keys):
    """:func:`design_differences` between two :func:`design_summary` dicts.

    A key missing from either (a partial or hand-edited record) is not compared.
    """
    differences = []
    for section, key in keys:
        then = _field(_field(recorded, section), key)
        value = _field(_field(now, section), key)
        if then is None or value is None or _same_value(then, value):
            continue
        differences.append(f"{section}.{key} {_shown(then)} -> {_shown(value)}")
    return differences


def check_psf_grid(psf_path, d):
    """Refuse a PSF sampled on another sub-pixel grid than design d's (InputError).

    A PSF sampled on another sub-pixel grid makes a wrong tile or a wrong sensor model.
    """
    check_measured_psf(psf_path)
    problem = psf_grid_problem(psf_path, design_summary(d), f"design {d.name!r}")
    if problem:
        path, text = problem
        raise InputError(path, f"{text}; pass the design it was made for with --config")


def check_psf_kernel(psf, source, d):
    """Refuse a PSF of another size than design d's kernel (InputError naming ``source``).

    Else the design's records (learn.json, the fab manifest, verify's window)
    would contradict the PSF the plate is made for.
    """
    k, kd = psf.shape[0], d.kernel_size
    if k != kd:
        raise InputError(
            source,
            f"is {k} x {k}, but the kernel of design {d.name!r} is {kd} x {kd}; "
            "pass the design it was made for with --config",
        )


def check_measured_psf(psf_path):
    """Refuse a measured PSF whose ``verify.json`` says verify could not judge the capture.

    A capture of a mirrored, conjugate or other plate, a camera mounted otherwise
    than the flag said, clipped or too faint dots: its ``measured_psf.npy`` is not
    the plate's PSF in the design's frame, and a network tuned to it is tuned wrong.
    """
    verified = Path(psf_path).with_name("verify.json")
    if not verified.is_file():
        return
    report = read_json(verified)
    if report.get("measured_psf_usable") is False:
        codes = report.get("diagnosis")
        codes = ", ".join(map(str, codes)) if isinstance(codes, list) else "no diagnosis"
        raise InputError(
            verified,
            f"the PSF beside it comes from a capture that verify could not judge ({codes}): "
            "it is not the plate's PSF in the design's frame; see the report's notes",
        )


def psf_grid_problem(psf_path, summary, whose):
    """Return (report file, reason) when a PSF is sampled on another grid than ``summary``'s.

    The grid is read from the report written beside the PSF: ``learn.json`` (a
    learned psf.npy) or ``verify.json`` (a measured_psf.npy: the design's dot
    lattice pitch, which its sub-pixels must match). ``summary`` is a
    :func:`design_summary` dict; ``whose`` names it in the reason. None when
    neither report says otherwise.
    """
    learned = Path(psf_path).with_name("learn.json")
    if learned.is_file():
        recorded = read_json(learned).get("design")  # read_json: a JSON object
        differences = summary_differences(recorded, summary, PSF_GRID_KEYS)
        if differences:
            return learned, (
                f"the PSF was learned for another sub-pixel grid than {whose} "
                f"({'; '.join(differences)})"
            )
    verified = Path(psf_path).with_name("verify.json")
    if verified.is_file():
        report = read_json(verified)
        # The design's lattice (on its sensor); older reports hold only the capture's.
        lattice = report.get("design_lattice_pitch_um", report.get("lattice_pitch_um"))
        pitch = _field(_field(summary, "sensor"), "pixel_pitch_um")
        factor = _field(_field(summary, "sensor"), "superres_factor")
        if not all(_is_number(v) and v > 0 for v in (lattice, pitch, factor)):
            return None  # a report without the numbers: nothing to compare
        subpixel = pitch / factor
        if not math.isclose(lattice, subpixel, rel_tol=LATTICE_MATCH_REL):
            return verified, (
                f"the PSF was measured on a {lattice:g} um dot lattice, but {whose} "
                f"has {subpixel:g} um sub-pixels"
            )
    return None


def _field(record, key):
    """Return record[key] of a JSON object, None when it is not an object or lacks it."""
    return record.get(key) if isinstance(record, dict) else None


def _is_number(v):
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _same_value(a, b):
    return math.isclose(a, b, rel_tol=1e-9) if _is_number(a) and _is_number(b) else a == b


def _shown(v):
    return f"{v:g}" if _is_number(v) else repr(v)
