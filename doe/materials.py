"""Refractive index of substrate glasses: catalogue glasses by name, custom ones from a design.

A catalogue glass may be named in any usual spelling (:func:`canonical_name`);
a custom glass gives its Sellmeier coefficients or an index table in its
``[material]`` table (:func:`material_dispersion`).
"""

import itertools
import math
from dataclasses import dataclass

import numpy as np

from doe.infra.errors import InputError


@dataclass(frozen=True)
class Sellmeier:
    """Three-term Sellmeier dispersion n^2 = 1 + sum B_i lambda^2 / (lambda^2 - C_i).

    Coefficients ``C`` are in um^2 as catalogues print them; ``valid`` is the
    wavelength range of the fit in metres.
    """

    name: str
    B: tuple[float, ...]
    C: tuple[float, ...]
    valid: tuple[float, float]
    source: str

    def index(self, wavelength):
        """Return the refractive index at ``wavelength`` (m)."""
        _check_range(self.name, "Sellmeier", self.valid, wavelength)
        lam2 = (wavelength * 1e6) ** 2
        n2 = 1 + sum(b * lam2 / (lam2 - c) for b, c in zip(self.B, self.C, strict=True))
        return float(np.sqrt(n2))


@dataclass(frozen=True)
class IndexTable:
    """Measured indices, interpolated linearly in wavelength; no extrapolation."""

    name: str
    wavelengths: tuple[float, ...]  # m, increasing
    indices: tuple[float, ...]
    source: str

    def index(self, wavelength):
        """Return the refractive index at ``wavelength`` (m)."""
        valid = (self.wavelengths[0], self.wavelengths[-1])
        _check_range(self.name, "index-table", valid, wavelength)
        return float(np.interp(wavelength, self.wavelengths, self.indices))


def _check_range(name, kind, valid, wavelength):
    lo, hi = valid
    if not lo * (1 - 1e-12) <= wavelength <= hi * (1 + 1e-12):
        raise InputError(
            f"material {name}",
            f"wavelength {wavelength * 1e9:g} nm is outside the {kind} range "
            f"{lo * 1e9:.0f}-{hi * 1e9:.0f} nm",
        )


MATERIALS = {
    "fused_silica": Sellmeier(
        "fused_silica",
        B=(0.6961663, 0.4079426, 0.8974794),
        C=(0.0684043**2, 0.1162414**2, 9.896161**2),
        valid=(0.21e-6, 3.71e-6),
        source="Sellmeier, Malitson, JOSA 55, 1205 (1965)",
    ),
    "bk7": Sellmeier(
        "bk7",
        B=(1.03961212, 0.231792344, 1.01046945),
        C=(0.00600069867, 0.0200179144, 103.560653),
        valid=(0.3e-6, 2.5e-6),
        source="Sellmeier, SCHOTT N-BK7 data sheet",
    ),
}

# The spellings each catalogue glass goes by, compared without case, spaces, "-" or "_".
ALIASES = {
    "fused_silica": ("fused silica", "FS", "silica", "Corning 7980", "HPFS", "Suprasil"),
    "bk7": ("N-BK7", "NBK7", "BK-7"),
}


def _squeeze(name):
    return "".join(c for c in name.lower() if c not in " -_\t")


_LOOKUP = {
    _squeeze(alias): canonical
    for canonical, aliases in ALIASES.items()
    for alias in (canonical, *aliases)
}


def canonical_name(name):
    """Return the MATERIALS key ``name`` spells (any case and usual alias), or None."""
    return _LOOKUP.get(_squeeze(name))


def refractive_index(material, wavelength):
    """Return the index of catalogue glass ``material`` (any alias) at ``wavelength`` (m)."""
    canonical = canonical_name(material)
    if canonical is None:
        raise InputError(
            "material.name",
            f"unknown material {material!r}; choose one of {', '.join(sorted(MATERIALS))}",
        )
    return MATERIALS[canonical].index(wavelength)


# The keys of a custom glass in a design's [material] table.
SELLMEIER_KEYS = ("sellmeier_b", "sellmeier_c_um2", "range_nm")
TABLE_KEY = "index_table"
CUSTOM_KEYS = (*SELLMEIER_KEYS, TABLE_KEY)
_CHOICES = (
    f"choose one of {', '.join(sorted(MATERIALS))} (or an alias: "
    + ", ".join(a for aliases in ALIASES.values() for a in aliases)
    + f"), or describe a custom glass with {', '.join(SELLMEIER_KEYS)} or {TABLE_KEY}"
)


def material_dispersion(table, where):
    """Return (name, dispersion) of a design's ``[material]`` table (raises InputError).

    A catalogue glass comes back under its canonical name; a custom one under
    the name the design gives it. ``where`` is "<design>: [material]".
    """
    name = table["name"]
    given = [k for k in CUSTOM_KEYS if k in table]
    canonical = canonical_name(name)
    if not given:
        if canonical is None:
            raise InputError(f"{where} name", f"unknown material {name!r}; {_CHOICES}")
        return canonical, MATERIALS[canonical]
    if canonical is not None:
        raise InputError(
            f"{where} name",
            f"{name!r} is the catalogue glass {canonical}; give the custom glass its own name",
        )
    if not name.strip():
        raise InputError(f"{where} name", "must name the custom glass")
    if TABLE_KEY in given:
        if len(given) > 1:
            raise InputError(
                f"{where} {TABLE_KEY}",
                f"give either {TABLE_KEY} or {', '.join(SELLMEIER_KEYS)}, not both",
            )
        return name, _index_table(name, table[TABLE_KEY], f"{where} {TABLE_KEY}")
    missing = [k for k in SELLMEIER_KEYS if k not in table]
    if missing:
        raise InputError(f"{where} {missing[0]}", "missing (a Sellmeier glass needs all three)")
    return name, _sellmeier(name, table, where)


def _numbers(value, where, length=None):
    ok = isinstance(value, list) and all(
        isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in value
    )
    if not ok or (length is not None and len(value) != length) or not value:
        size = f"{length} " if length else ""
        raise InputError(where, f"must be a list of {size}finite numbers, got {value!r}")
    return tuple(float(v) for v in value)


def _sellmeier(name, table, where):
    b = _numbers(table["sellmeier_b"], f"{where} sellmeier_b")
    c = _numbers(table["sellmeier_c_um2"], f"{where} sellmeier_c_um2", len(b))
    lo, hi = _numbers(table["range_nm"], f"{where} range_nm", 2)
    if not 0 < lo < hi:
        raise InputError(f"{where} range_nm", f"must be [shortest, longest] > 0, got {[lo, hi]}")
    glass = Sellmeier(name, b, c, (lo * 1e-9, hi * 1e-9), "design file: Sellmeier coefficients")
    for nm in np.linspace(lo, hi, 257):  # a pole or n < 1 inside the range is a typing error
        lam2 = (nm * 1e-3) ** 2
        terms = [lam2 - ci for ci in c]
        if any(abs(t) < 1e-12 for t in terms):
            n2 = 0.0
        else:
            n2 = 1 + sum(bi * lam2 / t for bi, t in zip(b, terms, strict=True))
        if not n2 > 1:
            raise InputError(
                f"{where} sellmeier_c_um2",
                f"the formula gives no index above 1 at {nm:.0f} nm, inside range_nm",
            )
    return glass


def _index_table(name, value, where):
    rows = value if isinstance(value, list) else None
    if not rows or len(rows) < 2:
        raise InputError(
            where, f"must be a list of at least two [wavelength_nm, n] pairs, got {value!r}"
        )
    pairs = [_numbers(row, where, 2) for row in rows]
    nm = [p[0] for p in pairs]
    n = [p[1] for p in pairs]
    if not all(a < b for a, b in itertools.pairwise(nm)) or nm[0] <= 0:
        raise InputError(where, f"wavelengths must be > 0 and increasing, got {nm}")
    if not all(v > 1 for v in n):
        raise InputError(where, f"every index must be > 1, got {n}")
    return IndexTable(
        name,
        tuple(v * 1e-9 for v in nm),
        tuple(n),
        f"design file: index table, {len(nm)} points, {nm[0]:g}-{nm[-1]:g} nm",
    )


def index_source(summary_material):
    """Where the index of a design summary's ``material`` comes from, for the fab report."""
    if TABLE_KEY in summary_material:
        return f"design file: index table, {len(summary_material[TABLE_KEY])} points"
    if "sellmeier_b" in summary_material:
        return "design file: Sellmeier coefficients"
    canonical = canonical_name(str(summary_material.get("name", "")))
    return MATERIALS[canonical].source if canonical else "unknown"
