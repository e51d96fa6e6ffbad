"""Refractive index of substrate glasses from their Sellmeier dispersion."""

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
    B: tuple[float, float, float]
    C: tuple[float, float, float]
    valid: tuple[float, float]
    source: str

    def index(self, wavelength):
        """Return the refractive index at ``wavelength`` (m)."""
        lo, hi = self.valid
        if not lo <= wavelength <= hi:
            raise InputError(
                f"material {self.name}",
                f"wavelength {wavelength * 1e9:g} nm is outside the Sellmeier range "
                f"{lo * 1e9:.0f}-{hi * 1e9:.0f} nm",
            )
        lam2 = (wavelength * 1e6) ** 2
        n2 = 1 + sum(b * lam2 / (lam2 - c) for b, c in zip(self.B, self.C, strict=True))
        return float(np.sqrt(n2))


MATERIALS = {
    "fused_silica": Sellmeier(
        "fused_silica",
        B=(0.6961663, 0.4079426, 0.8974794),
        C=(0.0684043**2, 0.1162414**2, 9.896161**2),
        valid=(0.21e-6, 3.71e-6),
        source="Malitson, JOSA 55, 1205 (1965)",
    ),
    "bk7": Sellmeier(
        "bk7",
        B=(1.03961212, 0.231792344, 1.01046945),
        C=(0.00600069867, 0.0200179144, 103.560653),
        valid=(0.3e-6, 2.5e-6),
        source="SCHOTT N-BK7 data sheet",
    ),
}


def refractive_index(material, wavelength):
    """Return the refractive index of ``material`` (a key of MATERIALS) at ``wavelength`` (m)."""
    if material not in MATERIALS:
        raise InputError(
            "material.name",
            f"unknown material {material!r}; choose one of {', '.join(sorted(MATERIALS))}",
        )
    return MATERIALS[material].index(wavelength)
