"""The light a camera images: wavelengths and their weights.

Three kinds (:class:`Spectrum`): the design wavelength alone, a Gaussian
band-pass of a given full width at half maximum centred on it
(:func:`gaussian_band`), or a two-column text file of wavelength (nm) and
weight (:func:`read_spectrum`). Weights are normalised to sum 1; SI units inside.
"""

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from doe.infra.errors import InputError

# A Gaussian band is sampled over +-3 sigma (99.7 % of its weight; the rest is
# dropped and the weights renormalised).
GAUSSIAN_REACH_SIGMAS = 3.0
MAX_WAVELENGTHS = 401
SPECTRUM_RANGE = (200e-9, 20e-6)  # m: what a spectrum file's wavelengths may span


@dataclass(frozen=True)
class Spectrum:
    """Wavelengths (m, increasing) and weights (summing to 1), with a one-line description."""

    wavelengths: tuple[float, ...]
    weights: tuple[float, ...]
    description: str

    def as_dict(self):
        """Return the spectrum as a JSON-ready dict, units in the keys."""
        return {
            "description": self.description,
            "wavelengths_nm": [w * 1e9 for w in self.wavelengths],
            "weights": list(self.weights),
        }


def monochromatic(wavelength):
    """Return the spectrum of one wavelength (m)."""
    return Spectrum((float(wavelength),), (1.0,), f"monochromatic {wavelength * 1e9:g} nm")


def gaussian_band(centre, fwhm, step):
    """Return a Gaussian band-pass of full width ``fwhm`` (m) centred on ``centre`` (m).

    Sampled every ``step`` (m), on the odd number of wavelengths centre + k step
    that covers +-3 sigma (so that bands of one step share their wavelengths); the
    trapezoid rule on a grid that resolves the integrand converges exponentially for
    a Gaussian weight, and bench/camera.py measures the step the camera model needs. ``fwhm`` 0 is
    :func:`monochromatic`.
    """
    if fwhm < 0 or not math.isfinite(fwhm):
        raise InputError("--bandwidth-nm", f"must be >= 0, got {fwhm * 1e9:g}")
    if fwhm == 0:
        return monochromatic(centre)
    sigma = fwhm / (2 * math.sqrt(2 * math.log(2)))
    reach = GAUSSIAN_REACH_SIGMAS * sigma
    if reach >= centre:
        raise InputError("--bandwidth-nm", f"{fwhm * 1e9:g} nm is wider than the wavelength")
    half = max(1, math.ceil(reach / step))
    if 2 * half + 1 > MAX_WAVELENGTHS:
        half = (MAX_WAVELENGTHS - 1) // 2
        step = reach / half
    offsets = np.arange(-half, half + 1) * step  # one grid for every band of this step
    weights = np.exp(-0.5 * (offsets / sigma) ** 2)
    return Spectrum(
        tuple(float(centre + o) for o in offsets),
        tuple(float(w) for w in weights / weights.sum()),
        f"Gaussian band-pass {fwhm * 1e9:g} nm FWHM at {centre * 1e9:g} nm, "
        f"{2 * half + 1} wavelengths {step * 1e9:.3g} nm apart over +-{GAUSSIAN_REACH_SIGMAS:g} "
        "sigma",
    )


def read_spectrum(path):
    """Read a two-column text file (wavelength in nm, weight) into a :class:`Spectrum`.

    Comment lines start with ``#``; commas or white space separate the columns.
    Weights must be >= 0 with a positive sum, wavelengths distinct. Each line is
    one sample: the weights are used as given (a file sampled unevenly weights
    its samples as a lab means them).

    Raises
    ------
    InputError
        Naming the file and what is wrong with it.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError(path, "no such spectrum file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read the spectrum file as text ({e})") from None
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        fields = line.split()
        if len(fields) != 2:
            raise InputError(path, f"line {number} has {len(fields)} columns, not 2 (nm, weight)")
        try:
            rows.append((float(fields[0]), float(fields[1])))
        except ValueError:
            raise InputError(path, f"line {number} is not two numbers: {line!r}") from None
    return _checked(path, rows)


def _checked(path, rows):
    if not rows:
        raise InputError(path, "holds no (wavelength nm, weight) lines")
    nm, weight = np.array(rows, dtype=float).T
    lo, hi = (v * 1e9 for v in SPECTRUM_RANGE)
    if not np.all(np.isfinite(nm) & np.isfinite(weight)):
        raise InputError(path, "holds a value that is not a finite number")
    if np.any((nm < lo) | (nm > hi)):
        raise InputError(path, f"a wavelength lies outside {lo:g} .. {hi:g} nm (nm expected)")
    if np.any(weight < 0) or weight.sum() <= 0:
        raise InputError(path, "weights must be >= 0 with a positive sum")
    if len(np.unique(nm)) != len(nm):
        raise InputError(path, "a wavelength appears twice")
    if len(nm) > MAX_WAVELENGTHS:
        raise InputError(path, f"holds {len(nm)} wavelengths, more than {MAX_WAVELENGTHS}")
    keep = weight > 0
    order = np.argsort(nm[keep])
    nm, weight = nm[keep][order], weight[keep][order]
    return Spectrum(
        tuple(float(v) * 1e-9 for v in nm),
        tuple(float(w) for w in weight / weight.sum()),
        f"spectrum file {path.name}: {len(nm)} wavelengths, {nm[0]:g} .. {nm[-1]:g} nm",
    )
