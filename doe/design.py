"""Design configuration: TOML schema, the embedded presets, loading and validation.

A design file is TOML with one table per concern (sensor, optics, psf,
material, fabrication, learning); every quantity carries its unit in the key
name. Inside the code everything is SI (metres). :func:`doe.derived.derive`
computes what an optics engineer checks before fabrication, and
:mod:`doe.design_match` compares a record with a design.
"""

import math
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Literal

from doe.derived import derive, lattice_problem
from doe.infra.errors import InputError
from doe.infra.files import LEVEL_COUNT_RULE, is_level_count
from doe.infra.flags import MINUTES_MAX, PHOTONS_MAX, SEED_MAX, STEPS_MAX
from doe.materials import CUSTOM_KEYS, IndexTable, Sellmeier, material_dispersion
from doe.tiling import refusal, tiling


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
    """The substrate: ``name`` is canonical for a catalogue glass (``dispersion.source``
    says where its index comes from)."""

    name: str
    thickness: float
    dispersion: Sellmeier | IndexTable


@dataclass(frozen=True)
class Fabrication:
    """``allow_corner_contacts``: the process accepts etched pixels of one mask that touch
    only at a corner (the retrieval then leaves them; the design-rule check lists them)."""

    levels: int
    feature_size: float
    aperture: float
    grid: float
    allow_corner_contacts: bool = False


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
        "name": (str, None, (lambda v: True, "")),  # checked by material_dispersion
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


# Keys a table may hold beside its _SCHEMA keys; their checks are the section's own.
_OPTIONAL = {"material": CUSTOM_KEYS}

# Optional true/false keys: (section, key) -> the value when the file leaves it out.
_SWITCHES = {("fabrication", "allow_corner_contacts"): False}


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
        switches = [key for sec, key in _SWITCHES if sec == section]
        known = {*fields, *_OPTIONAL.get(section, ()), *switches}
        unknown = set(table) - known
        if unknown:
            raise InputError(
                source, f"[{section}] has unknown key(s) {sorted(unknown)}; known: {sorted(known)}"
            )
        for key, (typ, scale, (ok, why)) in fields.items():
            where = f"{source}: [{section}] {key}"
            if key not in table:
                raise InputError(where, "missing")
            si[section, key] = _check_value(where, table[key], typ, scale, ok, why)
        for key in switches:
            value = table.get(key, _SWITCHES[section, key])
            if not isinstance(value, bool):
                raise InputError(
                    f"{source}: [{section}] {key}", f"must be true or false, got {value!r}"
                )
            si[section, key] = value
    for key in ("name", "description"):
        if not isinstance(raw.get(key, ""), str):
            raise InputError(f"{source}: {key}", "must be a string")

    s = lambda sec, k: si[sec, k]  # noqa: E731
    glass, dispersion = material_dispersion(raw["material"], f"{source}: [material]")
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
        material=Material(glass, s("material", "thickness_mm"), dispersion),
        fabrication=Fabrication(
            s("fabrication", "levels"),
            s("fabrication", "feature_size_um"),
            s("fabrication", "aperture_mm"),
            s("fabrication", "grid_nm"),
            s("fabrication", "allow_corner_contacts"),
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


# Retrieval time and memory grow as N^2: N = 4096 takes about 50 min and 7 GB on a
# 2-core machine. Larger tiles are refused.
MAX_TILE_PIXELS = 4096


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
        d.material.dispersion.index(d.optics.wavelength)
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
    refused = refusal(tiling(d))  # one or two tiles make no dot lattice (doe/tiling.py)
    if refused:
        raise InputError(f"{source}: [fabrication] aperture_mm", refused)
    from layouts.marks import check_marks_fit

    try:  # the marks are sized to the feature size: checked once the tile is sound
        check_marks_fit(
            der.masks, round(fab.aperture * 1e9) // 2, round(fab.feature_size * 1e9),
            round(fab.grid * 1e9),
        )  # fmt: skip
    except ValueError as e:
        raise InputError(f"{source}: [fabrication] aperture_mm", str(e)) from None
