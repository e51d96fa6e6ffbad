"""``doefab verify`` (a fabricated plate against its design) and ``doefab mtf`` (slanted edge)."""

import sys

from doe.infra.errors import InputError


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
        "--pixel-pitch-um",
        type=float,
        help="camera pixel pitch in um, cross-checked against the lattice pitch measured "
        "in the capture (default: the capture's own pitch alone)",
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
    p.add_argument(
        "--bandwidth-nm",
        type=float,
        default=0.0,
        help="the bench's light: FWHM of a Gaussian band-pass at the design wavelength "
        "(nm; default 0); the capture is compared with the design's order powers over it",
    )
    p.add_argument("--spectrum", help="the bench's light as a two-column file (nm, weight)")
    p.add_argument(
        "--f-number",
        type=float,
        help="the test lens's stop f / N (recorded; it sizes the dots, not their powers)",
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


def _verify(args):
    from doe.infra import flags
    from fab.verify.plate_check import save_verify, verify_plate

    flags.positive("--pixel-pitch-um", args.pixel_pitch_um)
    flags.positive("--lattice-pitch-um", args.lattice_pitch_um)
    flags.positive("--f-number", args.f_number)
    bench = {"bandwidth_nm": args.bandwidth_nm, "spectrum": args.spectrum}
    bench["f_number"] = args.f_number
    result = verify_plate(
        args.design_dir,
        args.capture,
        dark=args.dark,
        pixel_pitch_um=args.pixel_pitch_um,
        lattice_pitch_um=args.lattice_pitch_um,
        orientation=args.orientation,
        bench=bench,
    )
    for hint in result.hints:
        print(f"doefab verify: {hint}", file=sys.stderr)
    save_verify(result, args.out, force=args.force)
    # The remedies, where the lab reads them; after the output is in place, as a refusal
    # of --out is one line.
    for note in result.remedies:
        print(f"doefab verify: {note}", file=sys.stderr)
    print(f"{result.summary} -> {args.out}")
    return 0 if result.passed else 1


def _mtf(args):
    from fab.verify.mtf_check import measure_mtf, save_mtf

    if not 1 <= args.oversample <= 16:
        raise InputError("--oversample", f"must be 1..16, got {args.oversample}")
    result = measure_mtf(args.image, oversample=args.oversample)
    for line in result.messages:
        print(f"doefab mtf: {line}", file=sys.stderr)
    result = save_mtf(result, args.out, force=args.force)
    print(f"MTF50 {result.mtf50_text} -> {args.out}")
    return 0
