"""Verify a fabricated plate from a capture of its dot lattice: ``doefab verify`` as a library.

``verify_plate`` reads the design folder, the capture and its dark frame, checks the
dark frame, repairs hot pixels, registers the lattice, measures every order, compares
the K x K window with the design and diagnoses the plate; ``save_verify`` writes
``verify.json``, ``measured_psf.npy``, ``verify.png`` and ``verify_report.html``.

Examples
--------
>>> from fab.verify.plate_check import verify_plate
>>> result = verify_plate("out/fab", "capture.tif", dark="dark.tif", out="out/verify")
>>> result.passed, result.diagnosis                                  # doctest: +SKIP
(False, ('overlay_error', 'psf_mismatch'))
"""

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from doe.fraunhofer import correlation
from doe.infra import flags
from doe.infra.errors import InputError
from doe.infra.files import save_npy, staged_output
from doe.records.fab_manifest import MANIFEST_NAME
from doe.records.verify import VERIFY_JSON, VerifyRecord, write_verify
from fab.verify.analysis import ORIENTATIONS, analyse, design_order_power, resolve_thresholds
from fab.verify.bench_band import (
    bench_band,
    bench_record,
    reference_order_power,
    reference_window,
)
from fab.verify.bench_band import (
    light as _light,
)
from fab.verify.capture import read_capture
from fab.verify.cell_photometry import measure_cells
from fab.verify.conditioning import repair_pixels
from fab.verify.dark_frame import refuse_a_dark_frame_with_dots
from fab.verify.design_ref import DesignRef, read_design_dir
from fab.verify.diagnosis import best_frame_correlation, is_judged
from fab.verify.hints import (
    add_um_and_nm,
    beyond_reach_hint,
    capture_notes,
    fault_hint,
    orientation_hint,
    pitch_hint,
)
from fab.verify.hot_pixels import repair_hot_pixels, repair_stray_spikes
from fab.verify.lattice import LatticeNotFound, on_lattice_share, register_lattice
from fab.verify.photometry import ANNULUS_MIN_PITCH_PX, measure_orders
from fab.verify.pitch import capture_pitch, check_stated_pitch

VERIFY_FILES = (VERIFY_JSON, "measured_psf.npy", "verify_report.html", "verify.png")
# A capture too bright, too dim or ambiguous says nothing of the plate: take another.
# (A conjugate, mirrored or other plate is a verdict on the plate.)
UNJUDGED = frozenset({"saturated", "low_signal", "zero_order_ambiguous"})


@dataclass(frozen=True, eq=False)
class _ReportFigures:
    """What the report's figures are drawn from besides the report itself."""

    image: np.ndarray  # the repaired capture (DN)
    grid: object  # fab.verify.photometry.OrderGrid
    lattice: object  # fab.verify.lattice.Lattice
    design_psf: np.ndarray
    orientation: str


@dataclass(frozen=True, eq=False)
class VerifyResult:
    """What ``verify_plate`` measured on a plate and concluded.

    Attributes
    ----------
    passed : bool
        The plate passed (``diagnosis == ("ok",)``).
    verdict : str
        "PASS", "FAIL", or "FAIL (capture not judged)" when the capture says nothing
        of the plate (saturated, too little signal, an ambiguous zero order).
    diagnosis : tuple of str
        The diagnosis codes.
    measured_psf : (K, K) float64 array
        The measured PSF (>= 0, sum 1), in the design's frame.
    report : dict
        The content of ``verify.json`` (figures, fits, notes, flags and inputs).
    hints : tuple of str
        What to check where the plate fails (a wrong pitch flag, the camera mounted
        otherwise, a mask off the others, etches off their depths); also in the
        report's notes. The command says them before writing its output.
    remedies : tuple of str
        What to do about the capture or the plate: a dark frame to give, and where the
        plate fails the notes on the capture. The command says them once its output
        is in place.
    out : Path or None
        The output folder, once written (``save_verify``).
    files : tuple of Path
        The files written there.
    """

    passed: bool
    verdict: str
    diagnosis: tuple[str, ...]
    measured_psf: np.ndarray
    report: dict
    hints: tuple[str, ...]
    remedies: tuple[str, ...]
    figures: _ReportFigures = dataclasses.field(repr=False)
    out: Path | None = None
    files: tuple[Path, ...] = ()

    @property
    def notes(self):
        """The report's notes: on the capture, the lattice, the figures, and the hints."""
        return tuple(self.report["notes"])

    @property
    def record(self):
        """The report as ``verify.json``'s record (``doe.records.verify.VerifyRecord``)."""
        return VerifyRecord.from_dict(self.report)

    @property
    def summary(self):
        """One line: the verdict, the diagnosis and the figures it rests on."""
        r = self.report
        return (
            f"{self.verdict}: {', '.join(r['diagnosis'])}  correlation {r['correlation']:.4f}"
            f"  rmse {r['rmse']:.4f}  efficiency {r['efficiency']:.4f}"
            f"  zero order {r['zero_order']:.4g}"
        )


@dataclass(frozen=True, eq=False)
class _Registered:
    """The capture's lattice, and the capture with its hot pixels repaired off the dots."""

    lattice: object  # fab.verify.lattice.Lattice
    image: np.ndarray
    repaired: np.ndarray  # the pixels repaired
    found: np.ndarray  # the capture the lattice was first found in
    notes: list
    remedies: list


def verify_plate(
    design,
    capture,
    *,
    out=None,
    dark=None,
    pixel_pitch_um=None,
    lattice_pitch_um=None,
    orientation="as-designed",
    force=False,
    bench=None,
):
    """Verify a fabricated plate from a point-source capture of its dot lattice.

    Parameters
    ----------
    design : path or DesignRef
        A ``doefab fab`` output (``fab_manifest.json``, ``levels.npy``) or a ``doefab
        retrieve`` output (``retrieval.json``, ``levels.npy``), or what
        ``fab.verify.design_ref.read_design_dir`` read from one.
    capture : path
        The capture: 8/16-bit TIFF or PNG, float TIFF or EXR.
    out : path or None
        Output folder; None writes nothing (``save_verify`` can, later).
    dark : path or None
        A dark frame of the same size and exposure.
    pixel_pitch_um : float or None
        The camera's pixel pitch (um), cross-checked against the pitch measured in the
        capture (a contradiction: InputError with both); None: the measured pitch alone.
    lattice_pitch_um : float or None
        The order pitch on the camera (um); None: the design's, lambda f / tile size.
    orientation : str
        How the camera sees the design (``fab.verify.analysis.ORIENTATIONS``); never
        guessed.
    force : bool
        Overwrite existing output files.
    bench : dict or None
        ``bandwidth_nm`` or ``spectrum``, ``f_number`` (``fab.verify.bench_band``).

    Returns
    -------
    VerifyResult

    Raises
    ------
    InputError
        An unusable design folder, capture or dark frame (naming the file), a capture
        whose dots or zero-order window cannot be measured, existing output files
        without ``force``.
    """
    setup = _setup(design, capture, dark, pixel_pitch_um, lattice_pitch_um, orientation)
    ref = setup.ref
    cap = read_capture(capture, dark)
    pitch_px = _pitch_of(cap, setup, capture, dark)
    registered = _register(cap, capture, dark, pitch_px)
    lattice = registered.lattice
    if setup.nominal_px is not None:
        check_stated_pitch(lattice.pitch_px, *_stated(setup))
    measure = measure_cells if lattice.pitch_px < ANNULUS_MIN_PITCH_PX else measure_orders
    grid = measure(registered.image, lattice, cap.saturated & ~registered.repaired, cap.quantum)
    # before the spike repair, which would clear true dots off a wrongly fitted lattice
    on_lattice = on_lattice_share(registered.found, lattice, pitch_px, cap.quantum)
    band, design_psf, thresholds = _reference(setup, bench)
    result, measured = analyse(
        grid, ref.levels, ref.n_levels, ref.kernel_size, orientation, thresholds, band
    )
    if measured is None:
        raise InputError(capture, _why_no_psf(result, ref))
    notes = capture_notes(result, cap, ref)
    report = _report(setup, result, (thresholds, bench_record(bench, band)), lattice,
                     on_lattice, cap.notes + registered.notes + notes)  # fmt: skip
    hints = [
        pitch_hint(result, on_lattice, lattice.pitch_px, pixel_pitch_um),
        orientation_hint(result, grid, ref, orientation),
        fault_hint(report),
        beyond_reach_hint(report),
    ]
    report["notes"] += (hints := [hint for hint in hints if hint])
    if result["implied_deep_etch_error"] is not None and ref.deep_etch_depth:
        report["implied_deep_etch_error_nm"] = (
            result["implied_deep_etch_error"] * ref.deep_etch_depth * 1e9
        )
    if ref.target_psf is not None:
        report["correlation_target"] = correlation(measured, ref.target_psf)
    remedies = list(registered.remedies)
    if not report["pass"]:
        remedies += [n for n in notes if "acceptance" not in n]
    unjudged = UNJUDGED & set(report["diagnosis"])
    verdict = "PASS" if report["pass"] else "FAIL (capture not judged)" if unjudged else "FAIL"
    verified = VerifyResult(
        passed=report["pass"],
        verdict=verdict,
        diagnosis=tuple(report["diagnosis"]),
        measured_psf=measured,
        report=report,
        hints=tuple(hints),
        remedies=tuple(remedies),
        figures=_ReportFigures(registered.image, grid, lattice, design_psf, orientation),
    )
    return verified if out is None else save_verify(verified, out, force=force)


def _reference(setup, bench):
    """Return the bench's Band (None: the design wavelength), the design's PSF under it
    and the thresholds."""
    ref = setup.ref
    stated = bench and (bench.get("bandwidth_nm") or bench.get("spectrum"))
    band = bench_band(setup.design, **_light(bench)) if stated else None
    psf, efficiency = reference_window(ref.levels, ref.n_levels, ref.kernel_size, band)
    return band, psf, _thresholds(setup.design, ref, efficiency, band)


@dataclass(frozen=True, eq=False)
class _Setup:
    """What ``verify_plate`` was asked to verify, and at which pitch."""

    design: object  # the design folder as given, or the DesignRef
    ref: DesignRef
    capture: object  # the capture file as given
    dark: object  # the dark frame as given, or None
    pixel_pitch_um: float | None
    lattice_pitch: float  # m
    nominal_px: float | None  # the lattice pitch in camera pixels the flags give
    orientation: str


def _setup(design, capture, dark, pixel_pitch_um, lattice_pitch_um, orientation):
    """Check the arguments of ``verify_plate`` and read the design folder."""
    flags.positive("pixel_pitch_um", pixel_pitch_um)
    flags.positive("lattice_pitch_um", lattice_pitch_um)
    if orientation not in ORIENTATIONS:
        raise InputError("orientation", f"must be one of {', '.join(ORIENTATIONS)}")
    ref = design if isinstance(design, DesignRef) else read_design_dir(design)
    lattice_pitch = ref.lattice_pitch
    if lattice_pitch_um is not None:
        lattice_pitch = lattice_pitch_um * 1e-6
    nominal_px = None if pixel_pitch_um is None else lattice_pitch / (pixel_pitch_um * 1e-6)
    return _Setup(
        design, ref, capture, dark, pixel_pitch_um, lattice_pitch, nominal_px, orientation
    )


def _report(setup, result, judged, lattice, on_lattice, notes):
    """Return the report (``verify.json``'s content) of an analysis ``result``: with the
    lattice, ``judged`` (the thresholds, the bench's record), the flags and inputs it ran
    with, and ``notes``; the fits' shifts in um and etch errors in nm where the design
    folder gives the scale."""
    ref, design, dark = setup.ref, setup.design, setup.dark
    thresholds, bench = judged
    report = {
        **result,
        # The lattice's centre is its zero order (the origin of the fit is only
        # the lattice point nearest the image centre).
        "lattice": {
            **lattice.summary(),
            "centre_px": result["zero_order_px"],
            "nominal_pitch_px": setup.nominal_px,
            "on_lattice_light": on_lattice,
        },
        "thresholds": thresholds,
        "bench": bench,
        "orientation": setup.orientation,
        "pixel_pitch_um": setup.pixel_pitch_um,
        # the camera's pixels as the measured lattice implies them at lattice_pitch_um
        "implied_pixel_pitch_um": setup.lattice_pitch * 1e6 / lattice.pitch_px,
        "lattice_pitch_um": setup.lattice_pitch * 1e6,
        # The design's own lattice, on its sensor: the grid measured_psf.npy is for
        # (a test bench's lens gives another lattice_pitch_um, not another PSF).
        "design_lattice_pitch_um": ref.lattice_pitch * 1e6,
        # A capture verify could not judge gives no PSF to train for.
        "measured_psf_usable": is_judged(result["diagnosis"]),
        "inputs": {
            "design_dir": None if isinstance(design, DesignRef) else str(design),
            "design_files": list(ref.files),
            "capture": Path(setup.capture).name,
            "dark": Path(dark).name if dark else None,
        },
        "notes": notes,
    }
    for key in ("overlay_error_fit", "etch_error_fit", "overlay_and_etch_fit"):
        add_um_and_nm(report[key], ref)
    return report


def save_verify(result, out, *, force=False):
    """Write a ``verify_plate`` result into ``out``: ``verify.json``, ``measured_psf.npy``,
    ``verify.png`` and ``verify_report.html``.

    Nothing is written unless all of them are (``doe.infra.files.staged_output``).

    Returns
    -------
    VerifyResult
        ``result`` with ``out`` and ``files`` set.

    Raises
    ------
    InputError
        Existing output files without ``force``; an unusable output folder.
    """
    from fab.verify.report import write_verify_report

    figures = result.figures
    with staged_output(out, force, names=VERIFY_FILES) as stage:
        save_npy(stage / "measured_psf.npy", np.asarray(result.measured_psf, dtype=np.float64))
        write_verify(stage / VERIFY_JSON, result.report)
        write_verify_report(
            stage,
            result.report,
            figures.image,
            figures.grid,
            figures.lattice,
            result.measured_psf,
            figures.design_psf,
            figures.orientation,
        )
    out = Path(out)
    return dataclasses.replace(result, out=out, files=tuple(out / name for name in VERIFY_FILES))


def _register(cap, capture, dark, nominal_px):
    """Find the capture's dot lattice and repair its hot pixels off the dots.

    The lattice is found with every hot pixel of the dark frame repaired; with no
    dark frame, single-pixel spikes away from the dots are repaired and the lattice
    found again.

    Raises
    ------
    InputError
        No dot lattice near the nominal pitch (naming the dark frame when it holds
        the dots the dark-subtracted capture lacks).
    """
    found = repair_pixels(cap.image, cap.hot)
    try:
        lattice, notes = register_lattice(found, nominal_px, quantum=cap.quantum)
    except LatticeNotFound as e:
        if dark is not None:
            refuse_a_dark_frame_with_dots(capture, dark)
        extra = f"; {int(cap.saturated.sum())} saturated pixels" if cap.saturated.any() else ""
        raise InputError(capture, f"{e}{extra}") from None
    remedies = []
    if dark is None:
        image, repaired = repair_stray_spikes(cap.image, lattice, cap.quantum)
        if repaired.any():
            notes.append(
                f"{int(repaired.sum())} hot pixel(s) away from the dots repaired (no dark "
                "frame; median of neighbours)"
            )
            hint = _hot_pixels_on_dots_hint(repaired, lattice)
            if hint:
                notes.append(hint)
                remedies.append(hint)
            lattice, _ = register_lattice(image, nominal_px, quantum=cap.quantum)
    else:
        image, repaired = repair_hot_pixels(cap.image, cap.hot, cap.saturated, lattice)
        if cap.hot.any():
            notes.append(
                f"{int(cap.hot.sum())} hot pixel(s) in the dark frame: "
                f"{int(repaired.sum())} repaired (median of neighbours), "
                f"{int((cap.hot & ~repaired).sum())} on a dot kept with the dark subtracted"
            )
    return _Registered(lattice, image, repaired, found, notes, remedies)


def _hot_pixels_on_dots_hint(repaired, lattice):
    """Return a hint to give a dark frame when the spikes repaired off the dots imply
    5 or more on them, where they cannot be told from a dot's light (those within 1.5
    px of a site stay) and add to the orders' powers; None when fewer."""
    share = min(math.pi * 1.5**2 / lattice.pitch_px**2, 0.5)
    on_dots = repaired.sum() * share / (1 - share)
    if on_dots < 5:
        return None
    return (
        f"about {on_dots:.0f} more hot pixels may lie on dots, where without a "
        "dark frame they add to the orders' powers (300 such pixels read a good "
        "plate as conjugate_plate): give --dark"
    )


def _pitch_of(cap, setup, capture, dark):
    """Return the capture's lattice pitch in pixels to register it at: measured (and
    cross-checked against the flags), or the flags' where the capture cannot tell."""
    ref = setup.ref
    found = repair_pixels(cap.image, cap.hot)
    try:
        power = design_order_power(ref.levels, ref.n_levels)
        return capture_pitch(found, cap.quantum, power, _stated(setup), capture)
    except InputError:
        if dark is not None:
            refuse_a_dark_frame_with_dots(capture, dark)
        raise


def _stated(setup):
    """Return (stated px, lattice pitch um, pixel pitch um, flag) for the pitch checks."""
    return (setup.nominal_px, setup.lattice_pitch * 1e6, setup.pixel_pitch_um, "--pixel-pitch-um")


def _thresholds(design, ref, design_efficiency, band=None):
    """Return the pass/fail thresholds: the design folder's acceptance, or the defaults.

    Raises InputError naming the manifest when its acceptance lacks a threshold or
    holds one that is no number.
    """
    zero_order = reference_order_power(ref.levels, ref.n_levels, band)[0, 0]
    try:
        return resolve_thresholds(ref.acceptance, design_efficiency, zero_order)
    except ValueError as e:  # only a fab folder's manifest holds an acceptance
        where = "." if isinstance(design, DesignRef) else design
        raise InputError(Path(where) / MANIFEST_NAME, str(e)) from None


def _why_no_psf(result, ref):
    """Return why a capture gave no measured PSF: too little signal, or a window that
    runs off the frame."""
    if best_frame_correlation(result) < 0.5 or result["window_in_frame"]:
        return (
            "too little signal to find the zero order: no order stands out of the noise; "
            "lengthen the exposure"
        )
    r, c = result["zero_order_px"]
    k = ref.kernel_size
    return (
        f"the {k}x{k} window around the zero order at row {r:.0f}, col {c:.0f} runs off "
        "the frame; centre the zero order"
    )
