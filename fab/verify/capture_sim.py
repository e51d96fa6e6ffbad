"""``doefab simulate-capture`` as a library: a design folder's plate as a bench would see it.

``simulate_design_capture`` reads the design folder as ``doefab verify`` does
(``fab.verify.design_ref.read_design_dir``: the level map, the lattice pitch, the mask
pixel pitch and names) and the optics it states (wavelength, the design's focal length,
the aperture), builds the plate with its faults (``fab.plate.model.PlateFaults``, the one
plate model) and images its dot lattice on the bench's camera
(``fab.verify.simulate.simulate_capture``); it writes ``capture.tif``, ``dark.tif`` and
``capture.json`` (``doe.records.capture``). Nothing is taken from the paper's prototype:
the lattice on the camera is the design's lattice pitch scaled by the test lens's focal
length over the design's, divided by the camera's pixel pitch.

The bench's band-pass (``--bandwidth-nm`` or ``--spectrum``) renders each wavelength's
dots (``fab.verify.bench_band``: the plate's phase dispersed, the lattice and the dots
scaled by lambda / lambda0) and sums them by weight; its stop (``--f-number``: a round
stop of f / N on the test lens, within the plate's aperture) sets the dots' size.
"""

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

from doe.infra.errors import InputError
from doe.infra.files import staged_output
from doe.records.capture import (
    CAPTURE_FILE,
    CAPTURE_JSON,
    DARK_FILE,
    CaptureRecord,
    write_capture_record,
)
from fab.package.masks import masks_from_levels
from fab.plate.model import PlateFaults
from fab.verify.bench_band import bench_band
from fab.verify.capture import write_image
from fab.verify.design_ref import read_design_dir, read_design_optics
from fab.verify.simulate import ORIENTATION_MAPS, simulate_capture

# The aperture's diffraction spot, as a Gaussian sigma in units of lambda f / D: a
# perfect lens gives 0.376; a real test lens a little more.
SPOT_SIGMA_LAMBDA_F_D = 0.44
# Orders beyond the K x K window the default frame holds on each side.
FRAME_MARGIN_ORDERS = 8
# Sub-samples per mask pixel for an overlay, at most this many along the tile.
OVERLAY_SAMPLES_MAX = 2048
EXPOSURE_S = 0.01  # written as both files' ExposureTime


@dataclass(frozen=True)
class Bench:
    """The camera and test lens a capture is simulated on.

    ``pixel_pitch_um`` is the camera's; ``focal_length_mm`` the test lens's (None: the
    design's); ``spot_sigma_um`` the dots' Gaussian sigma on the camera (None: 0.44
    lambda f / D of that lens over the plate's aperture); ``frame_px`` the square
    frame's side (None: the K x K window and 8 orders around it). Exposure:
    ``peak_fraction`` of full scale in the brightest pixel, ``full_well_e`` electrons
    at full scale (shot noise). ``bandwidth_nm`` (a Gaussian band-pass's FWHM, 0: the
    design wavelength) or ``spectrum`` (a two-column file, nm and weight) is the light;
    ``f_number`` (None: the plate's aperture) the test lens's stop.
    """

    pixel_pitch_um: float
    bits: int = 12
    peak_fraction: float = 0.7
    full_well_e: float = 10000.0
    rotation_deg: float = 0.0
    focal_length_mm: float | None = None
    spot_sigma_um: float | None = None
    frame_px: int | None = None
    orientation: str = "as-designed"
    seed: int = 0
    bandwidth_nm: float = 0.0
    spectrum: str | None = None
    f_number: float | None = None


@dataclass(frozen=True)
class Faults:
    """The plate's faults by mask name (fractions; um), as the command takes them."""

    etch_errors: dict = dataclasses.field(default_factory=dict)
    overlay_um: dict = dataclasses.field(default_factory=dict)
    conjugate: bool = False
    mirrored: bool = False
    other_design: str | None = None


@dataclass(frozen=True)
class SimulatedCapture:
    """What ``simulate_design_capture`` wrote: the record and the files."""

    record: CaptureRecord
    out: Path
    files: tuple[Path, ...]


def simulate_design_capture(design_dir, out, bench, faults=Faults(), force=False):
    """Simulate a capture of ``design_dir``'s plate on ``bench`` with ``faults``; write it.

    Returns
    -------
    SimulatedCapture

    Raises
    ------
    InputError
        An unusable design folder, a mask name it does not have, another design of
        another tile size or level count, a frame that cannot hold the window, existing
        files without ``force``.
    """
    ref = read_design_dir(design_dir)
    optics = read_design_optics(design_dir)
    wavelength, focal, aperture = optics.wavelength, optics.focal_length, optics.aperture
    lens = focal if bench.focal_length_mm is None else bench.focal_length_mm * 1e-3
    lattice_um = ref.lattice_pitch * 1e6 * lens / focal
    pitch_px = lattice_um / bench.pixel_pitch_um
    spot_um = bench.spot_sigma_um
    if spot_um is None:
        stop = aperture if bench.f_number is None else min(aperture, lens / bench.f_number)
        spot_um = SPOT_SIGMA_LAMBDA_F_D * wavelength * lens / stop * 1e6
    band = bench_band(design_dir, bench.bandwidth_nm, bench.spectrum)
    frame = bench.frame_px or math.ceil(pitch_px * (ref.kernel_size + 2 * FRAME_MARGIN_ORDERS))
    if frame < pitch_px * (ref.kernel_size + 2):
        raise InputError("--frame-px", f"{frame} px cannot hold the {ref.kernel_size} orders")
    plate, supersample = _plate_faults(ref, faults)
    sim = simulate_capture(
        ref.levels,
        ref.n_levels,
        shape=(frame, frame),
        pitch_px=pitch_px,
        rotation_deg=bench.rotation_deg,
        orientation=bench.orientation,
        faults=plate,
        mask_pixel_pitch=ref.mask_pixel_pitch,
        supersample=supersample,
        spot_sigma_px=spot_um / bench.pixel_pitch_um,
        peak_fraction=bench.peak_fraction,
        full_well_e=bench.full_well_e,
        bits=bench.bits,
        seed=bench.seed,
        band=None if band.monochromatic else band,
    )
    record = CaptureRecord(
        design_dir=str(design_dir),
        bench={
            **dataclasses.asdict(bench),
            "focal_length_mm": lens * 1e3,
            "spot_sigma_um": spot_um,
            "frame_px": frame,
            "lattice_pitch_um": lattice_um,
            "lattice_pitch_px": pitch_px,
            "exposure_s": EXPOSURE_S,
            "light": band.as_dict(),
        },
        faults=dataclasses.asdict(faults),
        zero_order_px=[float(v) for v in sim["zero_order_px"]],
    )
    names = (CAPTURE_FILE, DARK_FILE, CAPTURE_JSON)
    with staged_output(out, force, names=names) as stage:
        write_image(stage / CAPTURE_FILE, sim["capture"], exposure=EXPOSURE_S)
        write_image(stage / DARK_FILE, sim["dark"], exposure=EXPOSURE_S)
        write_capture_record(stage / CAPTURE_JSON, record)
    out = Path(out)
    return SimulatedCapture(record, out, tuple(out / n for n in names))


def _plate_faults(ref, faults):
    """Return the ``PlateFaults`` of ``faults`` on ``ref``'s masks, and the supersampling."""
    names = [mk.name for mk in masks_from_levels(ref.levels, ref.n_levels, 1.0)]
    for flag, given in (("--etch-error", faults.etch_errors), ("--overlay-um", faults.overlay_um)):
        unknown = sorted(set(given) - set(names))
        if unknown:
            raise InputError(flag, f"no mask {unknown[0]!r}; the masks are {', '.join(names)}")
    etch = tuple(float(faults.etch_errors.get(n, 0.0)) for n in names)
    shifts = [tuple(float(v) * 1e-6 for v in faults.overlay_um.get(n, (0, 0))) for n in names]
    other = None
    if faults.other_design is not None:
        other_ref = read_design_dir(faults.other_design)
        if other_ref.levels.shape != ref.levels.shape or other_ref.n_levels != ref.n_levels:
            raise InputError(
                faults.other_design,
                f"its tile is {other_ref.levels.shape[0]} px of {other_ref.n_levels} levels, "
                f"not {ref.levels.shape[0]} px of {ref.n_levels}: give a design of the same",
            )
        other = other_ref.levels
    supersample = 1
    if any(any(s) for s in shifts):
        if ref.mask_pixel_pitch is None:
            raise InputError("--overlay-um", "the design folder gives no mask pixel pitch")
        supersample = max(1, OVERLAY_SAMPLES_MAX // ref.levels.shape[0])
    plate = PlateFaults(
        etch_errors=etch if any(etch) else (),
        overlay=tuple(shifts) if supersample > 1 else (),
        conjugate=faults.conjugate,
        mirrored=faults.mirrored,
        other_levels=other,
    )
    return plate, supersample


ORIENTATIONS = tuple(ORIENTATION_MAPS)
