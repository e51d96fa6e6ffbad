"""``doefab simulate-capture``: a design's plate as a bench would capture it, for verify."""

from doe.infra.errors import InputError


def register(sub):
    from fab.verify.capture_sim import ORIENTATIONS

    p = sub.add_parser(
        "simulate-capture",
        help="simulate a capture of a design's plate (and its faults) for doefab verify",
        description="Write DIR/capture.tif, DIR/dark.tif and DIR/capture.json: the dot "
        "lattice of the design folder's plate, with the faults asked for, on the camera "
        "and test lens given. Everything about the plate comes from the design folder.",
    )
    p.add_argument("design_dir", help="fab output (fab_manifest.json) or retrieve output")
    p.add_argument("--out", required=True, help="output folder")
    b = p.add_argument_group("bench")
    b.add_argument("--pixel-pitch-um", type=float, required=True, help="camera pixel pitch (um)")
    b.add_argument("--bits", type=int, choices=(8, 12, 16), default=12, help="ADC bits (12)")
    b.add_argument(
        "--peak-fraction",
        type=float,
        default=0.7,
        help="exposure: the brightest pixel as a fraction of full scale (0.7; > 1 saturates)",
    )
    b.add_argument(
        "--full-well-e", type=float, default=10000.0, help="electrons at full scale (10000)"
    )
    b.add_argument("--rotation-deg", type=float, default=0.0, help="lattice rotation (deg)")
    b.add_argument(
        "--focal-length-mm", type=float, help="test lens focal length (default: the design's)"
    )
    b.add_argument(
        "--spot-sigma-um",
        type=float,
        help="dot sigma on the camera (um; default 0.44 lambda f / D of the test lens)",
    )
    b.add_argument("--frame-px", type=int, help="square frame side (default: window + 8 orders)")
    b.add_argument(
        "--bandwidth-nm",
        type=float,
        default=0.0,
        help="FWHM of a Gaussian band-pass at the design wavelength (nm; default 0)",
    )
    b.add_argument("--spectrum", help="two-column file (nm, weight): the light instead")
    b.add_argument(
        "--f-number",
        type=float,
        help="the test lens's stop, f / N (default: the plate's aperture); sets the dots' size",
    )
    b.add_argument("--orientation", choices=ORIENTATIONS, default="as-designed")
    b.add_argument("--seed", type=int, default=0)
    f = p.add_argument_group("plate faults (fab.plate.model.PlateFaults)")
    f.add_argument(
        "--etch-error",
        action="append",
        default=[],
        metavar="MASK=FRACTION",
        help="a mask's etch depth error (+0.15: 15 %% too deep); repeatable",
    )
    f.add_argument(
        "--overlay-um",
        action="append",
        default=[],
        metavar="MASK=DX,DY",
        help="a mask printed off the others (um, x right, y up); repeatable",
    )
    f.add_argument("--conjugate", action="store_true", help="etch and glass swapped")
    f.add_argument("--mirrored", action="store_true", help="masks written mirrored left-right")
    f.add_argument("--other-design", metavar="DIR", help="another design's plate instead")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    p.set_defaults(func=_simulate)


def _simulate(args):
    from doe.infra import flags
    from fab.verify.capture_sim import Bench, Faults, simulate_design_capture

    for flag in ("pixel_pitch_um", "peak_fraction", "full_well_e", "focal_length_mm"):
        flags.positive("--" + flag.replace("_", "-"), getattr(args, flag))
    flags.positive("--spot-sigma-um", args.spot_sigma_um)
    flags.positive("--f-number", args.f_number)
    flags.positive("--frame-px", args.frame_px)
    flags.seed("--seed", args.seed)
    bench = Bench(
        pixel_pitch_um=args.pixel_pitch_um,
        bits=args.bits,
        peak_fraction=args.peak_fraction,
        full_well_e=args.full_well_e,
        rotation_deg=args.rotation_deg,
        focal_length_mm=args.focal_length_mm,
        spot_sigma_um=args.spot_sigma_um,
        frame_px=args.frame_px,
        orientation=args.orientation,
        seed=args.seed,
        bandwidth_nm=args.bandwidth_nm,
        spectrum=args.spectrum,
        f_number=args.f_number,
    )
    faults = Faults(
        etch_errors={m: float(v) for m, v in _pairs("--etch-error", args.etch_error, 1)},
        overlay_um={m: list(v) for m, v in _pairs("--overlay-um", args.overlay_um, 2)},
        conjugate=args.conjugate,
        mirrored=args.mirrored,
        other_design=args.other_design,
    )
    result = simulate_design_capture(args.design_dir, args.out, bench, faults, force=args.force)
    b = result.record.bench
    print(
        f"capture of {args.design_dir}: lattice {b['lattice_pitch_px']:.4g} px "
        f"({b['lattice_pitch_um']:.4g} um on {b['pixel_pitch_um']:g} um pixels), "
        f"spot sigma {b['spot_sigma_um'] / b['pixel_pitch_um']:.3g} px -> {args.out}"
    )
    return 0


def _pairs(flag, values, count):
    """Yield (mask, value) of MASK=V or MASK=V1,V2 flags; InputError if malformed."""
    import math

    for text in values:
        mask, _, rest = text.partition("=")
        try:
            numbers = [float(v) for v in rest.split(",")]
        except ValueError:
            numbers = []
        if not mask or len(numbers) != count or not all(math.isfinite(v) for v in numbers):
            form = "MASK=FRACTION" if count == 1 else "MASK=DX,DY"
            raise InputError(flag, f"{text!r} is not {form}")
        yield mask, numbers[0] if count == 1 else numbers
