"""``doefab depth`` and ``doefab transient``: gated-SPAD cubes to depth, intensity and frames."""

import sys
from pathlib import Path

import numpy as np

from doe.infra import flags
from doe.infra.errors import InputError
from psf_learn.depth_options import (
    add_gate_flags,
    add_scan_flag,
    responses_from_flags,
)

DEPTH_ARRAYS = (
    "timing_ps",
    "depth_m",
    "amplitude",
    "background",
    "fit_quality",
    "significance",
    "valid",
    "timing_sigma_ps",
    "depth_sigma_m",
)
DEPTH_FIGURES = ("intensity.png", "depth.png", "pixel_fits.png")
# Above this median Poisson deviance per degree of freedom (1 for profiles that
# follow the model) the returns do not follow it: a cube whose time axis is in the
# wrong place or scrambled gives 15 or more, pile-up about 10.
FIT_QUALITY_WARN = 3.0


def register(sub):
    p = sub.add_parser(
        "depth",
        help="fit arrival time (depth), amplitude and background per pixel of a gated SPAD cube",
    )
    _common(p)
    add_gate_flags(p)
    p.add_argument(
        "--min-significance",
        type=float,
        default=20.0,
        help="likelihood-ratio threshold 2 dlogL for a return (default 20, about "
        "1e-4 false returns per background pixel)",
    )
    p.add_argument(
        "--calibration",
        metavar="CAL",
        help="fit every pixel with its own gate: a folder from 'doefab depth-calibrate' "
        "of a scan with the same settings (not with --sr)",
    )
    p.set_defaults(func=_depth)

    p = sub.add_parser(
        "transient",
        help="write the per-time-bin frames of a gated SPAD cube (npy, PNG, animated GIF)",
    )
    _common(p, "super-resolve the frames with a model from 'doefab learn' (they replace them)")
    p.add_argument("--fps", type=float, default=10.0, help="GIF frame rate (default 10)")
    p.set_defaults(func=_transient)
    _register_calibrate(sub)


def _common(p, sr_help="also super-resolve with a model from 'doefab learn' (into sr/)"):
    p.add_argument(
        "cube",
        metavar="CUBE",
        help="(H, W, T) counts: .npy, or a folder of per-shift PNG/TIFF frames sorted by name",
    )
    p.add_argument(
        "--shift-ps",
        type=float,
        default=20.0,
        help="gate shift between samples: sample k is at k * shift (default 20)",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--sr",
        metavar="MODEL_DIR",
        help=sr_help,
    )
    add_scan_flag(p)
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")


GATE_CONVENTION = (
    "counts(t_k) = A h(t_k - mu) + b, t_k = k * shift, the "
    "gate's opening after the laser pulse; h(x) = integral G(t) Pi(t - x) dt; "
    "depth_m = c * mu / 2"
)
LASER_CONVENTION = (
    "counts(t_k) = A h(t_k - mu) + b, t_k = k * shift, the time-reversed (laser) scan; "
    "h(x) = integral G(t) Pi(x - t) dt = (G * Pi)(x); depth_m = c * mu / 2"
)


def _read_scan(args, responses):
    """Return the cube of ``args.cube`` and its shift (s); InputError if the scan cannot be fit."""
    from psf_learn.cubes import read_cube
    from psf_learn.depth import check_scan

    cube = read_cube(args.cube)
    shift = args.shift_ps * 1e-12
    try:
        check_scan(cube.shape[-1], shift, next(iter(responses.values())))
    except ValueError as e:
        raise InputError(args.cube, f"{e}; check --shift-ps and the gate flags") from None
    return cube, shift


def _depth(args):
    from doe.infra.files import previous_files, save_npy, staged_output, write_json
    from psf_learn.cubes import scan_gaps, super_resolve_cube

    responses, gate_summary = responses_from_flags(args)
    flags.non_negative("--min-significance", args.min_significance)
    cube, shift = _read_scan(args, responses)
    scan, native_fit, scan_summary, note = _scan_direction(args, cube, shift, responses)
    response = responses[scan]
    calibration = _calibration(args, cube, _with_scan(gate_summary, scan))
    cubes = {"": cube}
    if args.sr:
        cubes["sr/"] = super_resolve_cube(args.sr, cube)
    per_cube = [*(a + ".npy" for a in DEPTH_ARRAYS), *DEPTH_FIGURES]
    names = [f"{prefix}{n}" for prefix in cubes for n in per_cube] + ["depth.json"]
    # An earlier run's with --sr, as its depth.json says: a lab's own sr/ files stay.
    stale = previous_files(
        Path(args.out) / "depth.json", lambda old: [f"sr/{n}" for n in per_cube if "sr" in old]
    )
    with staged_output(args.out, args.force, names=names, stale=stale) as stage:
        summary = {
            "cube": str(args.cube),
            "shape": list(cube.shape),
            "shift_ps": args.shift_ps,
            "gate": gate_summary,
            "scan": scan_summary,
            "min_significance": args.min_significance,
            "timing_convention": LASER_CONVENTION if scan == "laser" else GATE_CONVENTION,
        }
        if calibration is not None:
            summary["calibration"] = str(args.calibration)
        for prefix, data in cubes.items():
            folder = stage / prefix
            folder.mkdir(exist_ok=True)
            fit = None if prefix else native_fit
            stats = _fit_and_write(
                folder, data, shift, response, args.min_significance, save_npy, calibration, fit
            )
            summary["sr" if prefix else "native"] = stats
        summary["warnings"] = (
            gate_summary.pop("warnings", []) + scan_gaps(args.cube) + _model_warnings(summary)
        )
        write_json(stage / "depth.json", summary)
    for warning in summary["warnings"]:
        print(f"depth: warning: {warning}", file=sys.stderr)
    if note:
        print(f"depth: {note}")
    s = summary["native"]
    timing = (
        f"timing {s['timing_ps_min']:.1f} .. {s['timing_ps_max']:.1f} ps"
        if s["valid_pixels"]
        else "no timing"
    )
    print(
        f"depth: {s['valid_pixels']}/{s['pixels']} pixels with a return, {timing}, "
        f"median fit quality {s['median_fit_quality']:.3g}; wrote {args.out}"
    )
    return 0


def _scan_direction(args, cube, shift, responses, threshold=None):
    """Return (direction, its native fit or None, the JSON record, a note to print or None).

    One response (--scan gate|laser, --irf) is the direction as given; two are fitted
    both ways by :func:`psf_learn.depth_scan.choose_scan`, refused (exit 2) when they
    are not told apart.
    """
    from psf_learn.depth_scan import choose_scan

    if len(responses) == 1:
        (scan,) = responses
        if scan == "irf":
            note = "scan direction fixed by the IRF (measured in the same scan)"
            return scan, None, {"direction": "irf", "chosen_by": "irf"}, note
        return scan, None, {"direction": scan, "chosen_by": "--scan"}, None
    threshold = args.min_significance if threshold is None else threshold
    choice = choose_scan(cube, shift, responses, threshold=threshold, progress=True)
    if choice.ambiguous:
        raise InputError(
            args.cube,
            "the scan directions are not told apart (log-likelihood difference "
            f"{choice.difference:.3g} < {choice.min_difference:g} over {choice.returns} "
            "returns): give --scan gate or --scan laser",
        )
    other = next(s for s in responses if s != choice.scan)
    note = (
        f"scan direction {choice.scan} (auto): log-likelihood {choice.difference:.4g} "
        f"above the {other} direction's"
        if choice.returns
        else "scan direction not determined (no return either way; nothing depends on it)"
    )
    return choice.scan, choice.fit, choice.summary(), note


def _with_scan(gate_summary, scan):
    """The gate settings a calibration is checked against: a laser scan says so."""
    return {**gate_summary, "scan": scan} if scan == "laser" else gate_summary


def _fit_and_write(folder, cube, shift, response, threshold, save_npy, calibration=None, raw=None):
    from psf_learn.depth import expected_counts, fit_profiles, scan_times
    from psf_learn.depth_calibration import apply_calibration
    from psf_learn.depth_plots import example_pixels, save_depth_maps, save_map, save_pixel_fits

    # raw: the fit against the common response, whose timing the pixel fits' models need
    if raw is None:
        raw = fit_profiles(cube, shift, response, threshold=threshold, progress=True)
    fit = raw if calibration is None else apply_calibration(raw, calibration)
    arrays = {
        "timing_ps": fit.timing / 1e-12,
        "depth_m": fit.depth,
        "amplitude": fit.amplitude,
        "background": fit.background,
        "fit_quality": fit.fit_quality,
        "significance": fit.significance,
        "valid": fit.valid,
        "timing_sigma_ps": fit.timing_sigma / 1e-12,
        "depth_sigma_m": fit.depth_sigma,
    }
    for name, value in arrays.items():
        save_npy(folder / f"{name}.npy", value)
    save_map(folder / "intensity.png", fit.amplitude, "fitted amplitude A", "peak counts")
    save_depth_maps(folder / "depth.png", fit.depth, fit.depth_sigma, fit.valid)
    times = scan_times(cube.shape[-1], shift)
    picks = example_pixels(fit)
    profiles = [cube[r, c] for r, c, _ in picks]
    models = [
        expected_counts(
            response,
            times,
            raw.amplitude[r, c],
            np.nan_to_num(raw.timing[r, c]),
            raw.background[r, c],
        )
        for r, c, _ in picks
    ]
    labels = [
        f"{why} ({r}, {c})"
        + (
            f": mu {fit.timing[r, c] / 1e-12:.1f} ps, A {fit.amplitude[r, c]:.3g}"
            if fit.valid[r, c]
            else ""
        )
        for r, c, why in picks
    ]
    save_pixel_fits(folder / "pixel_fits.png", times, profiles, models, labels)
    return _fit_stats(fit)


def _fit_stats(fit):
    """The depth.json summary of one fit: valid pixels, timing range, quality, precision."""
    valid_t = fit.timing[fit.valid] / 1e-12
    sigma_t = fit.timing_sigma[fit.valid] / 1e-12
    sigma_d = fit.depth_sigma[fit.valid]

    def stat(values, q):
        return float(np.percentile(values, q)) if values.size else float("nan")

    return {
        "pixels": int(fit.valid.size),
        "valid_pixels": int(fit.valid.sum()),
        "timing_ps_min": float(valid_t.min()) if valid_t.size else float("nan"),
        "timing_ps_max": float(valid_t.max()) if valid_t.size else float("nan"),
        "median_fit_quality": float(np.median(fit.fit_quality)),
        "median_fit_quality_of_returns": float(np.median(fit.fit_quality[fit.valid]))
        if fit.valid.any()
        else None,
        "timing_sigma_ps_median": stat(sigma_t, 50),
        "timing_sigma_ps_p90": stat(sigma_t, 90),
        "timing_sigma_ps_max": float(sigma_t.max()) if sigma_t.size else float("nan"),
        "depth_sigma_m_median": stat(sigma_d, 50),
        "depth_sigma_m_p90": stat(sigma_d, 90),
    }


def _transient_scan(args, cube):
    """The frames' scan direction, the arrival time each frame shows best, a note.

    The direction (given, or told from the cube with the default gate model as
    ``depth`` does) sets which arrival time peaks in frame k: ``t_k`` less the
    response's peak time. A cube too short to time, or without a return, leaves it
    undetermined (the frames themselves do not depend on it).
    """
    from psf_learn.depth import check_scan
    from psf_learn.depth_scan import scan_responses

    shift = args.shift_ps * 1e-12
    responses = scan_responses()
    if args.scan != "auto":
        responses = {args.scan: responses[args.scan]}
    else:
        try:
            check_scan(cube.shape[-1], shift, responses["gate"])
        except ValueError as e:
            note = f"scan direction not determined ({e}); --scan labels the frames"
            return {"direction": None, "chosen_by": "auto"}, None, note
    scan, _, record, note = _scan_direction(args, cube, shift, responses, threshold=20.0)
    if record.get("returns_either_direction") == 0:
        return {**record, "direction": None}, None, note
    peak_ps = responses[scan].peak_time / 1e-12
    arrival = [round(k * args.shift_ps - peak_ps, 6) for k in range(cube.shape[-1])]
    return record, arrival, note


def _model_warnings(summary):
    """Say when the returns' profiles do not follow the response model at all."""
    warnings = []
    for key in ("native", "sr"):
        quality = summary.get(key, {}).get("median_fit_quality_of_returns")
        if quality is not None and quality > FIT_QUALITY_WARN:
            warnings.append(
                f"the {key} returns' profiles do not follow the response model (median "
                f"fit quality {quality:.3g}; about 1 when they do): check that the cube "
                "is (H, W, T) with time last and its frames in scan order, --shift-ps, "
                "the gate parameters or --irf, and clipped or piled-up counts"
            )
    return warnings


def _transient(args):
    from doe.infra.files import previous_files, save_npy, staged_output, write_json
    from psf_learn.cubes import read_cube, scan_gaps, super_resolve_cube, write_frame_png16
    from psf_learn.depth_plots import gif_frame_centiseconds, gif_zoom, save_gif

    flags.positive("--shift-ps", args.shift_ps)
    try:
        gif_fps = 100 / gif_frame_centiseconds(args.fps)
    except ValueError as e:
        raise InputError("--fps", str(e)) from None
    cube = read_cube(args.cube, min_samples=1)
    gaps = scan_gaps(args.cube)
    scan_record, arrival, note = _transient_scan(args, cube)
    if args.sr:
        cube = super_resolve_cube(args.sr, cube)
    frames = np.moveaxis(cube, -1, 0)
    try:
        gif_zoom(*frames.shape[1:])
    except ValueError as e:
        raise InputError(args.cube, f"{e}; preview.gif cannot be written") from None
    scale = float(frames.max()) or 1.0
    pngs = [f"frames/frame_{k:04d}.png" for k in range(frames.shape[0])]
    names = ["frames.npy", "transient.json", "preview.gif", *pngs]
    stale = previous_files(
        Path(args.out) / "transient.json",
        lambda old: (f"frames/frame_{k:04d}.png" for k in range(old["frames"][0])),
    )
    with staged_output(args.out, args.force, names=names, stale=stale) as stage:
        save_npy(stage / "frames.npy", frames)
        (stage / "frames").mkdir()
        from tqdm import tqdm

        for k, name in enumerate(tqdm(pngs, desc="frames", disable=None)):
            write_frame_png16(stage / name, frames[k] / scale)
        save_gif(stage / "preview.gif", frames, fps=args.fps)
        write_json(
            stage / "transient.json",
            {
                "cube": str(args.cube),
                "frames": list(frames.shape),
                "shift_ps": args.shift_ps,
                "times_ps": [k * args.shift_ps for k in range(frames.shape[0])],
                "super_resolved": bool(args.sr),
                "png_full_scale_counts": scale,
                "png_note": "frame PNGs are 16-bit, counts = value / 65535 * png_full_scale_counts",
                "gif_fps": gif_fps,
                "scan": scan_record,
                "frame_arrival_ps": arrival,
                "warnings": gaps,
            },
        )
    for warning in gaps:
        print(f"transient: warning: {warning}", file=sys.stderr)
    if note:
        print(f"transient: {note}")
    if abs(gif_fps - args.fps) > 0.005 * args.fps:
        print(
            f"transient: preview.gif plays at {gif_fps:.4g} fps, the nearest to --fps "
            f"{args.fps:g} (a GIF frame lasts whole hundredths of a second)",
            file=sys.stderr,
        )
    print(
        f"transient: {frames.shape[0]} frames of {frames.shape[1]} x {frames.shape[2]} "
        "(rows x columns); "
        f"wrote {args.out}"
    )
    return 0


def _calibration(args, cube, gate_summary):
    """The calibration of --calibration, checked against the cube's scan; None without it."""
    if not args.calibration:
        return None
    from psf_learn.depth_calibration import CALIBRATION_JSON, read_calibration, scan_mismatch

    if args.sr:
        raise InputError(
            "--calibration",
            "holds native pixels' gates; the super-resolved cube has none (drop --sr)",
        )
    calibration = read_calibration(args.calibration)
    problem = scan_mismatch(calibration, cube.shape, args.shift_ps * 1e-12, gate_summary)
    if problem:
        record = Path(args.calibration) / CALIBRATION_JSON
        raise InputError(
            args.cube, f"taken with other scan settings than the calibration {record}: {problem}"
        )
    return calibration


def _register_calibrate(sub):
    p = sub.add_parser(
        "depth-calibrate",
        help="fit each pixel's gate delay from a gate scan of a flat target at a known distance",
    )
    p.add_argument("cube", metavar="CUBE", help="(H, W, T) counts of the flat target's scan")
    p.add_argument(
        "--distance-m", type=float, required=True, help="distance of the flat target (m)"
    )
    p.add_argument(
        "--shift-ps", type=float, default=20.0, help="gate shift between samples (default 20)"
    )
    p.add_argument("--out", required=True, help="calibration folder")
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    add_gate_flags(p)
    add_scan_flag(p)
    p.set_defaults(func=_calibrate)


def _calibrate(args):
    from psf_learn.cubes import scan_gaps
    from psf_learn.depth_calibration import calibrate_gates, write_calibration

    responses, gate_summary = responses_from_flags(args)
    flags.positive("--distance-m", args.distance_m)
    cube, shift = _read_scan(args, responses)
    scan, _, _, note = _scan_direction(args, cube, shift, responses, threshold=20.0)
    response = responses[scan]
    gate = {k: v for k, v in _with_scan(gate_summary, scan).items() if k != "warnings"}
    try:
        calibration = calibrate_gates(cube, shift, response, args.distance_m, gate=gate)
    except ValueError as e:
        raise InputError(args.cube, str(e)) from None
    warnings = gate_summary.get("warnings", []) + scan_gaps(args.cube)
    if calibration.median_fit_quality > FIT_QUALITY_WARN:
        warnings.append(
            f"the flat target's profiles do not follow the response model (median fit "
            f"quality {calibration.median_fit_quality:.3g}; about 1 when they do): its delays "
            "are not the gates'; check the cube's axes, --shift-ps and the gate flags or --irf"
        )
    write_calibration(args.out, calibration, args.cube, warnings, force=args.force)
    if note:
        print(f"depth-calibrate: {note}")
    for warning in warnings:
        print(f"depth-calibrate: warning: {warning}", file=sys.stderr)
    s = calibration.summary()
    print(
        f"depth-calibrate: {s['calibrated_pixels']}/{s['pixels']} pixels calibrated, gate delay "
        f"mean {s['mean_ps']:.1f} ps, std {s['std_ps']:.1f} ps (FWHM {s['fwhm_ps']:.1f} ps, "
        f"fit noise {s['median_sigma_ps']:.2f} ps); wrote {args.out}"
    )
    return 0
