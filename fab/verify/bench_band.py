"""The bench's band-pass on a plate: the spectrum, and the plate's phase at each wavelength.

A plate of glass heights h delays 2 pi (n(lambda) - 1) h / lambda: at wavelength lambda
its phase is the design wavelength's (``fab.plate.model.plate_phase``, faults included)
times ``(n(lambda) - 1) lambda0 / ((n(lambda0) - 1) lambda)``, the camera model's
dispersion (``doe.camera.plate_orders``) written as a factor. Order (m, n) lands at
``lambda / lambda0`` times its place at the design wavelength; its dot grows with
lambda too. A capture under a band is the weighted sum of the monochromatic ones.
"""

import math
from dataclasses import dataclass

import numpy as np

from doe.fraunhofer import level_phase, order_amplitudes, window_indices
from doe.infra.errors import InputError
from doe.materials import material_dispersion
from doe.spectrum import Spectrum, gaussian_band, monochromatic, read_spectrum
from fab.verify.design_ref import read_design_optics

# Wavelengths a Gaussian band is sampled at, per FWHM: the trapezoid rule over +-3
# sigma of a Gaussian converges long before (doe.spectrum.gaussian_band).
SAMPLES_PER_FWHM = 8


@dataclass(frozen=True)
class Band:
    """The bench's spectrum and, per wavelength, the factors it applies to the plate.

    ``phase_factor[i]`` multiplies the design wavelength's plate phase;
    ``scale[i]`` = lambda_i / lambda0 multiplies the lattice pitch and the dot's size.
    """

    spectrum: Spectrum
    phase_factor: tuple[float, ...]
    scale: tuple[float, ...]

    @property
    def wavelengths(self):
        return self.spectrum.wavelengths

    @property
    def weights(self):
        return self.spectrum.weights

    @property
    def monochromatic(self):
        return len(self.wavelengths) == 1 and self.scale[0] == 1.0

    def as_dict(self):
        return self.spectrum.as_dict()


def design_glass(design_dir):
    """Return (design wavelength m, dispersion) of a fab or retrieve output folder."""
    optics = read_design_optics(design_dir)
    _, dispersion = material_dispersion(optics.material, f"{optics.source}: [material]")
    return optics.wavelength, dispersion


def bench_band(design_dir, bandwidth_nm=0.0, spectrum_file=None):
    """Return the :class:`Band` of a bench: monochromatic at the design wavelength, a
    Gaussian band-pass of FWHM ``bandwidth_nm`` centred on it, or a spectrum file."""
    if spectrum_file is not None and bandwidth_nm:
        raise InputError("--spectrum", "give either a spectrum file or --bandwidth-nm")
    if not (math.isfinite(bandwidth_nm) and bandwidth_nm >= 0):
        raise InputError("--bandwidth-nm", f"must be >= 0, got {bandwidth_nm:g}")
    wavelength, dispersion = design_glass(design_dir)
    if spectrum_file is not None:
        spectrum = read_spectrum(spectrum_file)
    elif bandwidth_nm == 0:
        spectrum = monochromatic(wavelength)
    else:
        fwhm = bandwidth_nm * 1e-9
        spectrum = gaussian_band(wavelength, fwhm, fwhm / SAMPLES_PER_FWHM)
    delay0 = (dispersion.index(wavelength) - 1) / wavelength
    factors = tuple(float((dispersion.index(w) - 1) / w / delay0) for w in spectrum.wavelengths)
    return Band(
        spectrum,
        phase_factor=factors,
        scale=tuple(float(w / wavelength) for w in spectrum.wavelengths),
    )


def band_order_power(phase, band):
    """Return the (N, N) order powers |DFT|^2 of a tile phase under ``band`` (FFT index
    order, sum 1): the weighted sum over its wavelengths."""
    total = np.zeros(phase.shape)
    for weight, factor in zip(band.weights, band.phase_factor, strict=True):
        total += weight * np.abs(order_amplitudes(factor * phase)) ** 2
    return total


def reference_order_power(levels, n_levels, band=None):
    """Return the (N, N) order powers verify compares a capture with (FFT index order, sum
    1): the design tile's at its wavelength, or averaged over the bench's ``band``."""
    phase = level_phase(levels, n_levels)
    if band is None or band.monochromatic:
        return np.abs(order_amplitudes(phase)) ** 2
    return band_order_power(phase, band)


def reference_window(levels, n_levels, kernel, band=None):
    """Return (psf, efficiency) of the K x K window of :func:`reference_order_power`, as
    ``doe.fraunhofer.simulate_levels`` gives them at the design wavelength."""
    power = reference_order_power(levels, n_levels, band)
    idx = window_indices(power.shape[0], kernel)
    window = power[np.ix_(idx, idx)]
    efficiency = float(window.sum())
    return window / efficiency, efficiency


def light(bench):
    """Return ``bench_band``'s keywords of verify's ``bench`` dict."""
    return {
        "bandwidth_nm": bench.get("bandwidth_nm") or 0.0,
        "spectrum_file": bench.get("spectrum"),
    }


def bench_record(bench, band):
    """Return verify.json's ``bench``: the light and stop stated, and the spectrum used."""
    bench = bench or {}
    return {
        "bandwidth_nm": bench.get("bandwidth_nm") or 0.0,
        "spectrum_file": None if bench.get("spectrum") is None else str(bench["spectrum"]),
        "f_number": bench.get("f_number"),
        "spectrum": None if band is None else band.as_dict(),
    }
