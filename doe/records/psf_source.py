"""Where a PSF file comes from: the learn.json, verify.json or camera.json written beside it.

A learned ``psf.npy`` has ``learn.json`` beside it, a measured
``measured_psf.npy`` has ``verify.json``, a camera's ``effective_psf.npy`` has
``camera.json``; these checks read them to refuse a PSF
sampled on another sub-pixel grid than the design's, or one measured from a
capture that verify could not judge. The optics modules of :mod:`doe` read no
other stage's files; this module does it for them.
"""

import math
from pathlib import Path

from doe.derived import design_summary
from doe.design_match import PSF_GRID_KEYS, is_number, summary_differences, summary_field
from doe.infra.errors import InputError
from doe.records.camera import CAMERA_JSON, read_camera
from doe.records.learn import LEARN_JSON, read_learn
from doe.records.verify import VERIFY_JSON, read_verify

# A measured PSF is sampled on the plate's dot lattice, which matches the design's
# sub-pixel pitch to ppm; 2 % admits a hand-measured --lattice-pitch-um in verify.
LATTICE_MATCH_REL = 0.02


def check_psf_grid(psf_path, d):
    """Refuse a PSF sampled on another sub-pixel grid than design d's (InputError).

    A PSF sampled on another sub-pixel grid makes a wrong tile or a wrong sensor model.
    """
    check_measured_psf(psf_path)
    problem = psf_grid_problem(psf_path, design_summary(d), f"design {d.name!r}")
    if problem:
        path, text = problem
        raise InputError(path, f"{text}; pass the design it was made for with --config")


def check_measured_psf(psf_path):
    """Refuse a measured PSF whose ``verify.json`` says verify could not judge the capture.

    A capture of a mirrored, conjugate or other plate, a camera mounted otherwise
    than the flag said, clipped or too faint dots: its ``measured_psf.npy`` is not
    the plate's PSF in the design's frame, and a network tuned to it is tuned wrong.
    """
    verified = Path(psf_path).with_name(VERIFY_JSON)
    if not verified.is_file():
        return
    report = read_verify(verified)
    if report.measured_psf_usable is False:
        codes = report.diagnosis
        codes = ", ".join(map(str, codes)) if isinstance(codes, list) else "no diagnosis"
        raise InputError(
            verified,
            f"the PSF beside it comes from a capture that verify could not judge ({codes}): "
            "it is not the plate's PSF in the design's frame; see the report's notes",
        )


def psf_grid_problem(psf_path, summary, whose):
    """Return (report file, reason) when a PSF is sampled on another grid than ``summary``'s.

    The grid is read from the report written beside the PSF: ``learn.json`` (a
    learned psf.npy), ``camera.json`` (an effective_psf.npy) or ``verify.json`` (a
    measured_psf.npy: the design's dot lattice pitch, which its sub-pixels must
    match). ``summary`` is a :func:`design_summary` dict; ``whose`` names it in the
    reason. None when no report says otherwise.
    """
    learned = Path(psf_path).with_name(LEARN_JSON)
    if learned.is_file():
        recorded = read_learn(learned).design
        differences = summary_differences(recorded, summary, PSF_GRID_KEYS)
        if differences:
            return learned, (
                f"the PSF was learned for another sub-pixel grid than {whose} "
                f"({'; '.join(differences)})"
            )
    camera = Path(psf_path).with_name(CAMERA_JSON)
    if camera.is_file():
        differences = summary_differences(read_camera(camera).design, summary, PSF_GRID_KEYS)
        if differences:
            return camera, (
                f"the effective PSF was computed for another sub-pixel grid than {whose} "
                f"({'; '.join(differences)})"
            )
    verified = Path(psf_path).with_name(VERIFY_JSON)
    if verified.is_file():
        report = read_verify(verified)
        # The design's lattice (on its sensor); older reports hold only the capture's.
        has_design_lattice = "design_lattice_pitch_um" in report.data
        lattice = report.design_lattice_pitch_um if has_design_lattice else report.lattice_pitch_um
        pitch = summary_field(summary_field(summary, "sensor"), "pixel_pitch_um")
        factor = summary_field(summary_field(summary, "sensor"), "superres_factor")
        if not all(is_number(v) and v > 0 for v in (lattice, pitch, factor)):
            return None  # a report without the numbers: nothing to compare
        subpixel = pitch / factor
        if not math.isclose(lattice, subpixel, rel_tol=LATTICE_MATCH_REL):
            return verified, (
                f"the PSF was measured on a {lattice:g} um dot lattice, but {whose} "
                f"has {subpixel:g} um sub-pixels"
            )
    return None
