"""What ``verify_plate`` tells the lab besides the figures: its notes and hints.

Notes describe the capture and what the figures can be trusted for (saturation, too
little signal, a reflection of the design, light outside the window not measured);
hints point to what to check when a plate fails: a wrong pitch flag, the camera
mounted otherwise, a mask printed off the others, etches off their depths.
"""

from fab.verify.analysis import ORIENTATIONS, orientations_fitting_better, orientations_matching
from fab.verify.diagnosis import SIGNIFICANCE, etched_off, explaining_fit, within_reach
from fab.verify.overlay import REACH_PX

# Below this share of the dots' light on the fitted lattice, "other_design" may be a
# wrong pitch flag. On simulated captures of random, designed, Gaussian and sparse-dot
# plates the share is 1.0 at the right pitch (0.81-0.94 with 300 hot pixels left by a
# dark frame) and 0.13-0.83 at 0.59 to 2 times it, except where the fitted lattice is
# finer than the plate's and holds it (0.5 or 0.7 times): 1.0.
ON_LATTICE_MIN = 0.9
# Below this share of the design's light outside the window in orders above the noise,
# the efficiency is the design's share, not a measurement (see capture_notes): 8-bit
# captures, whose outer orders drown in noise, reach 0-0.035 and read the design's
# efficiency whatever the plate; 16-bit ones reach 0.26-0.72 and measure it.
OUTSIDE_LIGHT_MEASURED_MIN = 0.1


def capture_notes(result, capture, design):
    """Return the notes on what a capture lets the figures say.

    Parameters
    ----------
    result : dict
        ``fab.verify.analysis.analyse``'s result.
    capture : fab.verify.conditioning.Capture
    design : fab.verify.design_ref.DesignRef

    Returns
    -------
    list of str
        Clipped pixels and dots, a reflection of the design, an ambiguous zero order,
        too little signal (each with its remedy), light outside the window not
        measured, default thresholds.
    """
    notes = []
    if capture.saturated.any() and not result["saturated_dots"]:
        notes.append(f"{int(capture.saturated.sum())} saturated pixel(s) outside the dots")
    if result["saturated_dots"]:
        notes.append(
            f"{result['saturated_dots']} dot(s) hold saturated pixels: their powers are "
            "clipped; shorten the exposure"
        )
    if {"conjugate_plate", "mirrored"} & set(result.get("diagnosis", [])):
        notes.append(
            "the orders match a reflection of the design: a faulty plate, or a "
            "camera mounted otherwise than --orientation says (it is never guessed)"
        )
        notes.append(
            f"measured as that reflection ({result['measured_as']}), at its own zero order: "
            "the figures and measured_psf.npy describe the plate as it is; correlation "
            "and rmse still compare it with the design"
        )
    if result.get("reflection_set_aside"):
        notes.append(
            f"a reflection of the design ({result['reflection_set_aside']}) fits the orders "
            "better than the bare design, but the design with a fitted plate fault fits "
            "them better still: measured as the design"
        )
    if "zero_order_ambiguous" in result.get("diagnosis", []):
        z = result["zero_order_search"]
        gains = ", ".join(f"{k} {v:.3g}" for k, v in z["delta_chi2"].items())
        notes.append(
            "the zero order is ambiguous: the orders outside the window do not stand out "
            "enough to tell the design from a reflection of it or the zero order from its "
            f"neighbour (chi-square gain over the design: {gains}"
            f"; runner-up offset {z['runner_up_margin']:.3g}); " + more_signal(capture)
        )
    if "low_signal" in result.get("diagnosis", []):
        notes.append(f"window SNR {result['window_snr']:.3g} is under 30: " + more_signal(capture))
    measured = result.get("outside_light_measured", 1.0)
    if measured < OUTSIDE_LIGHT_MEASURED_MIN:
        notes.append(
            f"only {measured:.0%} of the light the design sends outside the window lies in "
            "orders above the noise; the rest is taken at the design's share, so the "
            f"efficiency ({result['efficiency']:.4f}) is largely the design's own and a "
            "low efficiency goes unseen: a capture of more dynamic range (the camera's 12- "
            "or 16-bit mode, or averaged frames) measures it"
        )
    if design.acceptance is None:
        notes.append("no acceptance in the design folder: default thresholds used")
    return notes


def more_signal(capture):
    """Return how to get more signal: a longer exposure, unless the brightest pixel is
    near full scale already (a longer exposure would then clip the dots)."""
    if capture.full_scale and float(capture.image.max()) > 0.5 * capture.full_scale:
        return (
            "the brightest dot is near full scale already: use the camera's 12- or 16-bit "
            "mode, or average several frames"
        )
    return "lengthen the exposure (or average frames) until the brightest dot nears full scale"


def pitch_hint(result, on_lattice, pitch_px, pixel_pitch_um):
    """Return a note when a failed match may be a wrong pitch flag rather than another plate.

    A lattice fitted at a wrong pitch (e.g. --pixel-pitch-um of another camera)
    passes the pitch check when the fit cannot leave the nominal pitch, and its
    sites then sample the light in between the dots: "other_design" is then
    the wrong diagnosis, and most of the dots' light lies off the lattice.
    ``on_lattice`` is that share (``fab.verify.lattice.on_lattice_share``),
    ``pitch_px`` the fitted lattice's pitch, ``pixel_pitch_um`` the camera's.
    """
    failed_as_other = "other_design" in result.get("diagnosis", [])
    if not failed_as_other or on_lattice is None or on_lattice >= ON_LATTICE_MIN:
        return None
    return (
        f"only {on_lattice:.0%} of the dots' light lies on the fitted lattice "
        f"({pitch_px:.3g} px pitch): if this is the design's plate, the pitch is wrong; "
        + (f"check --pixel-pitch-um ({pixel_pitch_um:g} um) and " if pixel_pitch_um else "check ")
        + "the lattice pitch "
        "(--lattice-pitch-um, lens focal length)"
    )


def orientation_hint(result, grid, design, orientation):
    """Return a note when a capture failed as another design matches this one seen otherwise.

    A capture that fits a reflection of the design may fit the design seen turned far
    better still; one that fails as another design may match it seen otherwise than
    ``orientation``, the flag given. None when no other orientation fits, or every
    one does (no evidence). ``grid`` is the capture's order grid
    (``fab.verify.photometry.OrderGrid``), ``design`` a ``DesignRef``.
    """
    diagnosis = result.get("diagnosis", [])
    if {"conjugate_plate", "mirrored"} & set(diagnosis):
        z = result["zero_order_search"]
        turned = orientations_fitting_better(
            grid,
            design.levels,
            design.n_levels,
            design.kernel_size,
            min(z["chi2"].values()),
            z["inflation"],
        )
        if turned:
            return (
                f"the orders fit the design seen with --orientation {turned[0]} far better "
                f"than as {result['measured_as']}: if the camera or the plate is mounted so, "
                "verify again with that flag (it is never guessed)"
            )
    if "other_design" not in diagnosis:
        return None
    matching = orientations_matching(grid, design.levels, design.n_levels, design.kernel_size)
    others = [o for o in matching if o != orientation]
    if not others or set(matching) >= set(ORIENTATIONS):  # every one fits: no evidence
        return None
    return (
        f"the orders match the design seen with --orientation {' or '.join(others)}: "
        f"if the camera is mounted so, verify again with that flag (it is never guessed: "
        "a mirrored or conjugate plate seen otherwise can match too)"
    )


def fault_hint(result):
    """Return a note naming the plate faults that explain the PSF: a mask printed off the
    others, etches off their depths, or both; None when no fit explains it.

    ``result`` is the report, the fits with their shifts in um and errors in nm where
    the design folder gives the scale (``add_um_and_nm``).
    """
    fit = explaining_fit(result)
    if fit is None:
        return None
    faults, checks = [], []
    if "shift_px" in fit:
        in_um = "shift_um" in fit
        unit, shift = ("um", fit["shift_um"]) if in_um else ("mask pixels", fit["shift_px"])
        sd = fit.get("shift_sigma_um" if in_um else "shift_sigma_px")
        pm = [f" ± {v:.2f}" if sd else "" for v in (sd or [0, 0])]
        faults.append(
            f"mask {fit['mask']} printed off the other masks by {shift[0]:+.2f}{pm[0]} {unit} "
            f"in y (up) and {shift[1]:+.2f}{pm[1]} {unit} in x (right)"
        )
        checks.append("that exposure's alignment")
    if "errors" in fit:
        nm = dict(zip(fit["masks"], fit.get("errors_nm", []), strict=False))
        sigma = dict(zip(fit["masks"], fit.get("errors_sigma", []), strict=False))
        off = ", ".join(
            f"{name} {abs(err):.1%}"
            + (f" ± {sigma[name]:.1%}" if name in sigma else "")
            + f" too {'deep' if err > 0 else 'shallow'}"
            + (f" ({nm[name]:+.1f} nm)" if name in nm else "")
            for name, err in etched_off(fit)
        )
        faults.append(f"these etches off their depth: {off}")
        checks.append("those etches' depths")
    return (
        f"the window is the design's with {' and '.join(faults)} (correlation "
        f"{fit['correlation']:.4f} with that plate): check {' and '.join(checks)}"
    )


def beyond_reach_hint(report):
    """Return a note when the window is a mask printed off the others by more than the
    reach verify names an overlay in (none is named then).

    Not where an etch fit explains the window as well or better: an overlay fit that
    stopped at the edge of its search would then send the lab to an alignment that
    is right.
    """
    fit, etch = report["overlay_error_fit"], report.get("etch_error_fit")
    if (
        fit is None
        or "overlay_error" in report["diagnosis"]
        or {"deep_etch_error", "etch_depth_error"} & set(report["diagnosis"])
        or (etch is not None and etch["chi2"] <= fit["chi2"])
        or within_reach(fit)
        or fit["significance"] <= (SIGNIFICANCE + 1) ** 2
        or fit["correlation"] < report["thresholds"]["correlation_min"]
    ):
        return None
    unit, shift = ("um", fit["shift_um"]) if "shift_um" in fit else ("mask pixels", fit["shift_px"])
    return (
        f"the window matches the design with mask {fit['mask']} printed off the other masks "
        f"by {shift[0]:+.2f} {unit} in y (up) and {shift[1]:+.2f} {unit} in x (right) "
        f"(correlation {fit['correlation']:.4f}), at or beyond the {REACH_PX:g} mask pixels "
        "within which verify names an overlay: check that exposure's alignment"
    )


def add_um_and_nm(fit, design):
    """Add a fit's shift in um and etch errors in nm, where the design folder gives the scale."""
    if fit is None:
        return
    if "shift_px" in fit and design.mask_pixel_pitch:
        fit["shift_um"] = [v * design.mask_pixel_pitch * 1e6 for v in fit["shift_px"]]
        if fit.get("shift_sigma_px"):  # None for a fit at the edge of its reach
            fit["shift_sigma_um"] = [
                v * design.mask_pixel_pitch * 1e6 for v in fit["shift_sigma_px"]
            ]
    if "errors" in fit and len(fit["masks"]) == len(design.etch_depths):  # deepest first
        depths = zip(fit["errors"], design.etch_depths, strict=True)
        fit["errors_nm"] = [e * d * 1e9 for e, d in depths]
