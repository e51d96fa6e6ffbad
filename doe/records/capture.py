"""``capture.json``: the bench and the plate faults of a simulated capture.

``doefab simulate-capture`` writes it beside ``capture.tif`` and ``dark.tif``
(:func:`write_capture_record`); tests and a lab's scripts read it
(:func:`read_capture_record`) to know what a rehearsed verification should find.
Lengths carry their unit in the key.
"""

from dataclasses import dataclass, field
from pathlib import Path

from doe.infra.errors import InputError
from doe.infra.files import read_json, write_json

CAPTURE_JSON = "capture.json"
CAPTURE_FILE = "capture.tif"
DARK_FILE = "dark.tif"


@dataclass(frozen=True)
class CaptureRecord:
    """One ``capture.json``.

    Attributes
    ----------
    design_dir : str
        The design folder the plate was simulated from, as given.
    bench : dict
        The camera and lens: ``pixel_pitch_um``, ``bits``, ``peak_fraction``,
        ``full_well_e``, ``rotation_deg``, ``focal_length_mm``, ``spot_sigma_um``,
        ``frame_px``, ``orientation``, ``lattice_pitch_um`` (on the camera),
        ``lattice_pitch_px``, ``seed``, ``bandwidth_nm``, ``spectrum`` (a file or None),
        ``f_number`` and ``light``: the spectrum rendered (wavelengths and weights).
    faults : dict
        ``etch_errors`` (by mask name, fractions), ``overlay_um`` (by mask name,
        [dx, dy]), ``conjugate``, ``mirrored``, ``other_design`` (a folder or None).
    zero_order_px : list of float
        [row, col] of the zero order in the capture.
    files : dict
        ``capture`` and ``dark``: the image files beside it.
    """

    design_dir: str
    bench: dict
    faults: dict
    zero_order_px: list
    files: dict = field(default_factory=lambda: {"capture": CAPTURE_FILE, "dark": DARK_FILE})

    def as_dict(self):
        """Return the JSON object."""
        return {
            "design_dir": self.design_dir,
            "bench": self.bench,
            "faults": self.faults,
            "zero_order_px": self.zero_order_px,
            "files": self.files,
        }


def write_capture_record(path, record):
    """Write a ``capture.json`` (indented, key-sorted), atomically."""
    write_json(Path(path), record.as_dict())


def read_capture_record(path):
    """Read a ``capture.json``; InputError naming it when a key is missing."""
    data = read_json(Path(path))
    try:
        return CaptureRecord(
            design_dir=str(data["design_dir"]),
            bench=dict(data["bench"]),
            faults=dict(data["faults"]),
            zero_order_px=list(data["zero_order_px"]),
            files=dict(data["files"]),
        )
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(path, f"malformed {CAPTURE_JSON} ({e!r} missing or wrong)") from None
