"""``doefab verify`` (a fabricated plate against its design) and ``doefab mtf`` (slanted edge)."""

import math
import sys
from dataclasses import dataclass
from pathlib import Path

from doe.infra.errors import InputError

VERIFY_FILES = ("verify.json", "measured_psf.npy", "verify_report.html", "verify.png")
MTF_FILES = ("mtf.json", "mtf.png")
# Below this share of the dots' light on the fitted lattice, "other_design" may be a
# wrong pitch flag. Measured on simulated captures of random, designed, Gaussian and
# sparse-dot plates: 1.0 at the right pitch (0.81-0.94 with 300 hot pixels left by
# a dark frame); 0.13-0.83 at 0.59, 0.75, 1.33, 1.7 and 2 times it, except where the
# fitted lattice is finer than the plate's and holds it (0.5 or 0.7 times): 1.0.
ON_LATTICE_MIN = 0.9
# Below this share of the design's light outside the window in orders above the noise,
# the efficiency is the design's share, not a measurement (see _notes): 0-0.035 on
# 8-bit captures of 4, 8 and 16-level designs, whose faulty plates read the design's
# efficiency (0.713 for a true 0.551); 0.26-0.72 on 16-bit ones, which measured it.
OUTSIDE_LIGHT_MEASURED_MIN = 0.1


def register(sub):
    from fab.verify.analysis import ORIENTATIONS

    p = sub.add_parser(
        "verify",
        help="verify a fabricated plate from a capture of its dot lattice (exit 0 pass, 1 fail)",
        description="Register the dot lattice in a point-source capture through the plate, "
        "measure the K x K PSF and compare it with the design. Exit 0 when the plate "
        "passes, 1 when it fails, 2 when the input is unusable.",
    )
    p.add_argument(
        "design_dir",
        help="fab output (fab_manifest.json, levels.npy) or a "
        "retrieve output (retrieval.json, levels.npy)",
    )
    p.add_argument("capture", help="capture image: 8/16-bit TIFF or PNG, float TIFF or EXR")
    p.add_argument("--dark", help="dark frame of the same size and exposure")
    p.add_argument(
        "--pixel-pitch-um", type=float, default=3.45, help="camera pixel pitch in um (default 3.45)"
    )
    p.add_argument(
        "--lattice-pitch-um",
        type=float,
        help="order pitch on the camera in um (default: from the design, lambda f / tile size)",
    )
    p.add_argument(
        "--orientation",
        choices=ORIENTATIONS,
        default="as-designed",
        help="how the camera sees the design (default as-designed: camera row "
        "index grows downwards = -y, columns = +x, as the PSF); never guessed",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    p.set_defaults(func=_verify)

    p = sub.add_parser("mtf", help="slanted-edge MTF of an image (ISO 12233 style)")
    p.add_argument("image", help="image of a slanted edge (8/16-bit TIFF or PNG, float TIFF/EXR)")
    p.add_argument("--oversample", type=int, default=4, help="edge-spread bins per pixel (4)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    p.set_defaults(func=_mtf)


@dataclass(frozen=True)
class DesignRef:
    """What verification needs from a design folder (SI units)."""

    levels: object
    n_levels: int
    kernel_size: int
    lattice_pitch: float
    etch_depths: tuple[float, ...]  # deepest first; () when the folder does not say
    acceptance: dict | None
    target_psf: object
    kind: str
    files: tuple[str, ...]
    mask_pixel_pitch: float | None = None  # None: the manifest does not say

    @property
    def deep_etch_depth(self):
        return self.etch_depths[0] if self.etch_depths else None


def read_design_dir(path):
    """Read a fab folder (fab_manifest.json) or a retrieve folder (retrieval.json).

    Raises
    ------
    InputError
        Missing or malformed files, naming them.
    """
    import numpy as np

    from doe.infra.files import LEVEL_COUNT_RULE, is_level_count, read_json, read_levels, read_psf

    path = Path(path)
    if not path.is_dir():
        raise InputError(path, "no such design folder (give a doefab fab or retrieve output)")
    manifest_path, retrieval_path = path / "fab_manifest.json", path / "retrieval.json"
    if manifest_path.is_file():
        man = read_json(manifest_path)
        source = manifest_path
        try:
            n_levels = int(man["levels"])
            levels_file = path / man.get("levels_file", "levels.npy")
            kernel = int(man["kernel_size"])
            if "lattice_pitch_um" in man:
                lattice = float(man["lattice_pitch_um"]) * 1e-6
            else:
                tile = int(man["tile_pixels"]) * float(man["pixel_pitch_nm"]) * 1e-9
                lattice = (
                    float(man["wavelength_nm"]) * 1e-9 * float(man["focal_length_mm"]) * 1e-3 / tile
                )
            masks = sorted(man.get("masks", []), key=lambda mk: mk["exposure_order"])
            pitch = float(man["pixel_pitch_nm"]) * 1e-9 if "pixel_pitch_nm" in man else None
            depths = [float(mk["etch_depth_nm"]) * 1e-9 for mk in masks]
            acceptance = man.get("acceptance")
            target_file = path / man.get("target_psf_file", "target_psf.npy")
            target_named = "target_psf_file" in man
        except (KeyError, TypeError, ValueError, OverflowError) as e:  # int(1e400) overflows
            raise InputError(source, f"malformed manifest ({e!r} missing or wrong)") from None
        kind = "fab"
    elif retrieval_path.is_file():
        ret = read_json(retrieval_path)
        source = retrieval_path
        try:
            n_levels = int(ret["levels"])
            kernel = int(ret["kernel_size"])
            levels_file = path / "levels.npy"
            design = ret["design"]
            derived = design["derived"]
            wavelength = float(design["optics"]["wavelength_nm"]) * 1e-9
            focal = float(design["optics"]["focal_length_mm"]) * 1e-3
            depths = [float(d) * 1e-9 for d in derived["etch_depths_nm"]]
            if not depths:
                raise IndexError("etch_depths_nm is empty")
            grid = float(design["fabrication"].get("grid_nm", 1)) * 1e-9
            tile_nominal = float(derived["tile_size_nominal_um"]) * 1e-6
            if not (grid > 0 and tile_nominal > 0 and math.isfinite(grid * tile_nominal)):
                raise ValueError("grid_nm and tile_size_nominal_um must be finite and > 0")
            target_file = path / "target_psf.npy"
            target_named = False
            acceptance = None
        except (KeyError, TypeError, ValueError, IndexError, OverflowError, AttributeError) as e:
            raise InputError(source, f"malformed retrieval.json ({e!r} missing or wrong)") from None
        kind = "retrieve"
    else:
        raise InputError(
            path,
            "neither fab_manifest.json nor retrieval.json found; give a "
            "doefab fab or doefab retrieve output folder",
        )
    if not is_level_count(n_levels):
        raise InputError(source, f"levels {n_levels} must be {LEVEL_COUNT_RULE}")
    levels = read_levels(levels_file, n_levels)
    if kind == "retrieve":
        # The mask pixel pitch snaps to the GDS grid for this N (as doe.design.derive does).
        n = levels.shape[0]
        pitch = round(tile_nominal / n / grid) * grid
        if pitch == 0:
            raise InputError(source, f"its grid_nm is coarser than the mask pixels of N = {n}")
        lattice = wavelength * focal / (n * pitch)
    if not 1 <= kernel <= levels.shape[0] or kernel % 2 == 0:
        raise InputError(source, f"kernel_size {kernel} must be odd, 1 .. N = {levels.shape[0]}")
    if target_named and not target_file.is_file():
        raise InputError(target_file, f"named by {source.name} but missing")
    target = read_psf(target_file) if target_file.is_file() else None
    if target is not None and target.shape[0] != kernel:  # compared to nothing, silently
        raise InputError(
            target_file,
            f"is {target.shape[0]}x{target.shape[0]}, not the {source.name}'s kernel_size {kernel}",
        )
    if acceptance is not None and not isinstance(acceptance, dict):
        raise InputError(source, "acceptance must be a table of thresholds")
    if not (math.isfinite(lattice) and lattice > 0):
        raise InputError(source, f"lattice pitch {lattice} m is not positive")
    for depth in depths:  # the scale of a fitted etch error
        if not (math.isfinite(depth) and depth > 0):
            raise InputError(source, f"an etch depth of {depth * 1e9:g} nm is not positive")
    if pitch is not None and not (math.isfinite(pitch) and pitch > 0):
        raise InputError(source, f"the mask pixel pitch {pitch * 1e9:g} nm is not positive")
    files = [source.name, levels_file.name] + ([target_file.name] if target is not None else [])
    return DesignRef(
        np.asarray(levels),
        n_levels,
        kernel,
        lattice,
        tuple(depths),
        acceptance,
        target,
        kind,
        tuple(files),
        pitch,
    )


def _refuse_a_dark_frame_with_dots(args, nominal_px):
    """Name the dark frame when it holds the dots that the dark-subtracted capture lacks.

    Files swapped, or a dark taken with the light on, left "no dot stands out" on the
    capture, which sent the lab to its plate or camera rather than to the dark frame.
    """
    import numpy as np

    from fab.verify.capture import read_raw_image
    from fab.verify.lattice import LatticeNotFound, register_lattice

    def holds_a_lattice(path):
        raw = read_raw_image(path)
        try:
            register_lattice(raw.data.astype(np.float32), nominal_px, quantum=raw.quantum)
        except LatticeNotFound:
            return False
        return True

    if not holds_a_lattice(args.dark):
        return
    if holds_a_lattice(args.capture):
        raise InputError(
            args.dark,
            "the dark frame holds the capture's dot lattice, so none is left once it is "
            "subtracted; take the dark with the light blocked",
        )
    raise InputError(
        args.dark,
        f"the dark frame holds a dot lattice and the capture {Path(args.capture).name} "
        "none: are the capture and --dark swapped?",
    )


def _verify(args):
    import numpy as np

    from doe.fraunhofer import correlation, simulate_levels
    from doe.infra import flags
    from doe.infra.files import save_npy, staged_output, write_json
    from fab.verify.analysis import analyse, design_order_power, resolve_thresholds
    from fab.verify.capture import read_capture, repair_pixels
    from fab.verify.diagnosis import best_frame_correlation, is_judged
    from fab.verify.lattice import (
        LatticeNotFound,
        measure_orders,
        on_lattice_share,
        register_lattice,
        repair_hot_pixels,
        repair_stray_spikes,
    )

    flags.positive("--pixel-pitch-um", args.pixel_pitch_um)
    flags.positive("--lattice-pitch-um", args.lattice_pitch_um)
    design = read_design_dir(args.design_dir)
    lattice_pitch = design.lattice_pitch
    if args.lattice_pitch_um is not None:
        lattice_pitch = args.lattice_pitch_um * 1e-6
    nominal_px = lattice_pitch / (args.pixel_pitch_um * 1e-6)
    capture = read_capture(args.capture, args.dark)
    # The lattice is found with every hot pixel of the dark frame repaired.
    found = repair_pixels(capture.image, capture.hot)
    try:
        lattice, lattice_notes = register_lattice(found, nominal_px, quantum=capture.quantum)
    except LatticeNotFound as e:
        if args.dark is not None:
            _refuse_a_dark_frame_with_dots(args, nominal_px)
        extra = (
            f"; {int(capture.saturated.sum())} saturated pixels" if capture.saturated.any() else ""
        )
        raise InputError(args.capture, f"{e}{extra}") from None
    remedies = []  # printed on stderr once the output is in place
    if args.dark is None:
        image, repaired = repair_stray_spikes(capture.image, lattice, capture.quantum)
        if repaired.any():
            lattice_notes.append(
                f"{int(repaired.sum())} hot pixel(s) away from the dots repaired (no dark "
                "frame; median of neighbours)"
            )
            # Those within 1.5 px of a site stay, and cannot be told from a dot's light.
            share = min(math.pi * 1.5**2 / lattice.pitch_px**2, 0.5)
            on_dots = repaired.sum() * share / (1 - share)
            if on_dots >= 5:
                hint = (
                    f"about {on_dots:.0f} more hot pixels may lie on dots, where without a "
                    "dark frame they add to the orders' powers (300 such pixels read a good "
                    "plate as conjugate_plate): give --dark"
                )
                lattice_notes.append(hint)
                remedies.append(hint)
            lattice, _ = register_lattice(image, nominal_px, quantum=capture.quantum)
    else:
        image, repaired = repair_hot_pixels(capture.image, capture.hot, capture.saturated, lattice)
        if capture.hot.any():
            lattice_notes.append(
                f"{int(capture.hot.sum())} hot pixel(s) in the dark frame: "
                f"{int(repaired.sum())} repaired (median of neighbours), "
                f"{int((capture.hot & ~repaired).sum())} on a dot kept with the dark subtracted"
            )
    grid = measure_orders(image, lattice, capture.saturated & ~repaired, capture.quantum)
    # before the spike repair, which would clear true dots off a wrongly fitted lattice
    on_lattice = on_lattice_share(found, lattice, nominal_px, capture.quantum)
    design_psf, design_eff = simulate_levels(design.levels, design.n_levels, design.kernel_size)
    try:
        thresholds = resolve_thresholds(
            design.acceptance, design_eff, design_order_power(design.levels, design.n_levels)[0, 0]
        )
    except ValueError as e:
        raise InputError(Path(args.design_dir) / "fab_manifest.json", str(e)) from None
    result, measured = analyse(
        grid, design.levels, design.n_levels, design.kernel_size, args.orientation, thresholds
    )
    if measured is None:
        r, c = result["zero_order_px"]
        why = (
            "too little signal to find the zero order: no order stands out of the noise; "
            "lengthen the exposure"
            if best_frame_correlation(result) < 0.5 or result["window_in_frame"]
            else f"the {design.kernel_size}x{design.kernel_size} window around the zero order "
            f"at row {r:.0f}, col {c:.0f} runs off the frame; centre the zero order"
        )
        raise InputError(args.capture, why)
    report = {
        **result,
        # The lattice's centre is its zero order (the origin of the fit is only
        # the lattice point nearest the image centre).
        "lattice": {
            **lattice.summary(),
            "centre_px": result["zero_order_px"],
            "nominal_pitch_px": nominal_px,
            "on_lattice_light": on_lattice,
        },
        "thresholds": thresholds,
        "orientation": args.orientation,
        "pixel_pitch_um": args.pixel_pitch_um,
        "lattice_pitch_um": lattice_pitch * 1e6,
        # The design's own lattice, on its sensor: the grid measured_psf.npy is for
        # (a test bench's lens gives another lattice_pitch_um, not another PSF).
        "design_lattice_pitch_um": design.lattice_pitch * 1e6,
        # A capture verify could not judge gives no PSF to train for.
        "measured_psf_usable": is_judged(result["diagnosis"]),
        "inputs": {
            "design_dir": str(args.design_dir),
            "design_files": list(design.files),
            "capture": Path(args.capture).name,
            "dark": Path(args.dark).name if args.dark else None,
        },
        "notes": capture.notes + lattice_notes + _notes(result, capture, design),
    }
    for key in ("overlay_error_fit", "etch_error_fit", "overlay_and_etch_fit"):
        _in_um_and_nm(report[key], design)
    hints = [
        _pitch_hint(result, on_lattice, lattice.pitch_px, args),
        _orientation_hint(result, grid, design, args.orientation),
        _fault_hint(report),
        _beyond_reach_hint(report),
    ]
    for hint in filter(None, hints):
        report["notes"].append(hint)
        print(f"doefab verify: {hint}", file=sys.stderr)
    if result["implied_deep_etch_error"] is not None and design.deep_etch_depth:
        report["implied_deep_etch_error_nm"] = (
            result["implied_deep_etch_error"] * design.deep_etch_depth * 1e9
        )
    if design.target_psf is not None:
        report["correlation_target"] = correlation(measured, design.target_psf)
    with staged_output(args.out, args.force, names=VERIFY_FILES) as stage:
        from fab.verify.report import write_verify_report

        save_npy(stage / "measured_psf.npy", np.asarray(measured, dtype=np.float64))
        write_json(stage / "verify.json", report)
        write_verify_report(
            stage, report, image, grid, lattice, measured, design_psf, args.orientation
        )
    # The remedies, where the lab reads them; after the output is in place, as a refusal
    # of --out is one line.
    if not report["pass"]:
        remedies += [n for n in _notes(result, capture, design) if "acceptance" not in n]
    for note in remedies:
        print(f"doefab verify: {note}", file=sys.stderr)
    # A capture too bright, too dim or ambiguous says nothing of the plate: take another.
    # (A conjugate, mirrored or other plate is a verdict on the plate.)
    unjudged = {"saturated", "low_signal", "zero_order_ambiguous"} & set(report["diagnosis"])
    verdict = "PASS" if report["pass"] else "FAIL (capture not judged)" if unjudged else "FAIL"
    print(
        f"{verdict}: {', '.join(report['diagnosis'])}  correlation {report['correlation']:.4f}"
        f"  rmse {report['rmse']:.4f}  efficiency {report['efficiency']:.4f}"
        f"  zero order {report['zero_order']:.4g} -> {args.out}"
    )
    return 0 if report["pass"] else 1


def _in_um_and_nm(fit, design):
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


def _beyond_reach_hint(report):
    """Return a note when the window is a mask printed off the others by more than the
    reach verify names an overlay in (none is named then), and no etch fit explains it
    better (a 16-level plate's deepest etch 25 % off, named, came with an instruction to
    check an alignment that was right: the overlay fit had stopped at its search's edge)."""
    from fab.verify.diagnosis import SIGNIFICANCE, within_reach
    from fab.verify.overlay import REACH_PX

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


def _fault_hint(result):
    """Return a note naming the plate faults that explain the PSF: a mask printed off the
    others, etches off their depths, or both."""
    from fab.verify.diagnosis import etched_off, explaining_fit

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


def _pitch_hint(result, on_lattice, pitch_px, args):
    """Return a note when a failed match may be a wrong pitch flag rather than another plate.

    A lattice fitted at a wrong pitch (e.g. --pixel-pitch-um of another camera)
    passes the pitch check when the fit cannot leave the nominal pitch, and its
    sites then sample the light in between the dots: "other_design" is then
    the wrong diagnosis, and most of the dots' light lies off the lattice.
    """
    failed_as_other = "other_design" in result.get("diagnosis", [])
    if not failed_as_other or on_lattice is None or on_lattice >= ON_LATTICE_MIN:
        return None
    return (
        f"only {on_lattice:.0%} of the dots' light lies on the fitted lattice "
        f"({pitch_px:.3g} px pitch): if this is the design's plate, the pitch is wrong; "
        f"check --pixel-pitch-um ({args.pixel_pitch_um:g} um) and the lattice pitch "
        "(--lattice-pitch-um, lens focal length)"
    )


def _orientation_hint(result, grid, design, orientation):
    """Return a note when a capture failed as another design matches this one seen otherwise."""
    from fab.verify.analysis import ORIENTATIONS, orientations_fitting_better, orientations_matching

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


def _more_signal(capture):
    """Return how to get more signal: a longer exposure, unless the brightest pixel is
    near full scale already (an 8-bit capture at 94 % was told to lengthen it)."""
    if capture.full_scale and float(capture.image.max()) > 0.5 * capture.full_scale:
        return (
            "the brightest dot is near full scale already: use the camera's 12- or 16-bit "
            "mode, or average several frames"
        )
    return "lengthen the exposure (or average frames) until the brightest dot nears full scale"


def _notes(result, capture, design):
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
            f"; runner-up offset {z['runner_up_margin']:.3g}); " + _more_signal(capture)
        )
    if "low_signal" in result.get("diagnosis", []):
        notes.append(f"window SNR {result['window_snr']:.3g} is under 30: " + _more_signal(capture))
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


def _mtf(args):
    from doe.infra.files import staged_output, write_json
    from fab.verify.capture import read_raw_image
    from fab.verify.mtf import REACH_PER_RISE, EdgeNotFound, clipped_pixels, slanted_edge_mtf

    if not 1 <= args.oversample <= 16:
        raise InputError("--oversample", f"must be 1..16, got {args.oversample}")
    raw = read_raw_image(args.image)
    try:
        result = slanted_edge_mtf(raw.data, oversample=args.oversample)
    except EdgeNotFound as e:
        raise InputError(args.image, str(e)) from None
    result["image"] = Path(args.image).name
    # How the file was read (an Orientation tag, bits MSB-aligned): edge_orientation
    # describes the image as stored.
    result["notes"] = list(raw.notes)
    for note in raw.notes:
        print(f"doefab mtf: {args.image}: {note}", file=sys.stderr)
    # Clipping flattens a side of the edge spread and so overstates the MTF.
    dark, bright = clipped_pixels(raw.data, raw.full_scale)
    result["saturated_pixels"], result["clipped_dark_pixels"] = bright, dark
    for count, where, remedy in (
        (bright, f"at the image's maximum {raw.data.max():g}", "shorten the exposure"),
        (dark, f"at the image's minimum {raw.data.min():g}", "keep the camera's black level"),
    ):
        if count:
            print(
                f"doefab mtf: warning: {args.image}: {count} pixel(s) {where}, taken as "
                f"clipped; a clipped edge overstates the MTF: {remedy}",
                file=sys.stderr,
            )
    if result["region_too_small"]:
        print(
            f"doefab mtf: warning: {args.image}: the region reaches "
            f"{result['edge_reach_px']:.1f} px either side of the edge, under "
            f"{REACH_PER_RISE:g} times its 10-90 % rise ({result['edge_rise_px']:.2f} px): "
            "the cut edge profile overstates the MTF; give a larger region, or centre "
            "the edge in it",
            file=sys.stderr,
        )
    with staged_output(args.out, args.force, names=MTF_FILES) as stage:
        from fab.verify.report import mtf50_text, write_mtf_plot

        write_json(stage / "mtf.json", result)
        write_mtf_plot(stage / "mtf.png", result)
    print(f"MTF50 {mtf50_text(result)} -> {args.out}")
    return 0
