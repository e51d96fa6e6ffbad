"""``verify.json``: what ``doefab verify`` measured on a plate and concluded.

The file is the report of one capture (about 40 keys: the figures, the diagnosis,
the fits, the lattice, the flags and inputs). Other stages read a few of its keys:
whether the ``measured_psf.npy`` beside it may be used (``measured_psf_usable``,
``diagnosis``) and the grid that PSF is sampled on (``design_lattice_pitch_um``; older
reports hold only the capture's ``lattice_pitch_um``).
"""

from dataclasses import dataclass, field
from pathlib import Path

from doe.infra.files import read_json, write_json

VERIFY_JSON = "verify.json"  # its name in a verify output, beside measured_psf.npy


@dataclass(frozen=True)
class VerifyRecord:
    """One ``verify.json``.

    The named fields are the file's own values, as recorded (None when the key is
    absent): their types are not coerced, so that a reader decides what a value it
    cannot use means (an old or hand-written report may lack them or hold others).

    Attributes
    ----------
    passed : bool or None
        ``"pass"``: the plate passed.
    diagnosis : list of str or None
        The diagnosis codes, ``["ok"]`` for a plate that passed.
    measured_psf_usable : bool or None
        False when verify could not judge the capture: the measured PSF beside the
        file is then not the plate's PSF in the design's frame.
    lattice_pitch_um : float or None
        The order pitch on the camera the capture was measured at (um).
    design_lattice_pitch_um : float or None
        The design's own order pitch on its sensor (um): the grid ``measured_psf.npy``
        is sampled on.
    data : dict
        The whole JSON object, in the file's key order.
    """

    passed: object = None
    diagnosis: object = None
    measured_psf_usable: object = None
    lattice_pitch_um: object = None
    design_lattice_pitch_um: object = None
    data: dict = field(default_factory=dict, repr=False)

    @classmethod
    def from_dict(cls, report):
        """Return the record of a ``verify.json`` object (a dict)."""
        return cls(
            passed=report.get("pass"),
            diagnosis=report.get("diagnosis"),
            measured_psf_usable=report.get("measured_psf_usable"),
            lattice_pitch_um=report.get("lattice_pitch_um"),
            design_lattice_pitch_um=report.get("design_lattice_pitch_um"),
            data=report,
        )


def read_verify(path):
    """Read a ``verify.json``.

    Parameters
    ----------
    path : path
        The file.

    Returns
    -------
    VerifyRecord

    Raises
    ------
    InputError
        Naming the file when it is missing, not JSON or not a JSON object.
    """
    return VerifyRecord.from_dict(read_json(Path(path)))


def write_verify(path, report):
    """Write a ``verify.json`` (indented, key-sorted JSON; NaN as null), atomically.

    Parameters
    ----------
    path : path
        The file.
    report : VerifyRecord or dict
        The record, or the report dict it is made of.
    """
    write_json(path, report.data if isinstance(report, VerifyRecord) else report)
