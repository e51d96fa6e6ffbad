"""``doefab camera-psnr DESIGN_DIR --model MODEL_DIR --out DIR``: the camera budget in dB.

The measurement is :func:`psf_learn.camera_psnr.camera_psnr`; this module parses the
flags, writes ``camera_psnr.json`` (:mod:`doe.records.camera_psnr`), prints and returns
the exit code. ``doefab fab --camera-psnr DIR`` puts it in the fab report.
"""

from psf_learn.camera_psnr import ALLOWANCE_DB, CROP


def register(sub):
    p = sub.add_parser(
        "camera-psnr",
        help="a learned model's reconstruction PSNR against band-pass, stop, defocus, rotation",
        description=(
            "Score MODEL_DIR's reconstructions of held-back images captured through "
            "DESIGN_DIR's plate in a camera: the effective PSF (doefab camera) at each "
            "band-pass, f-number, defocus and rotation of the budget, each varied alone. "
            "Writes DIR/camera_psnr.json for doefab fab --camera-psnr."
        ),
    )
    p.add_argument("design_dir", metavar="DESIGN_DIR", help="a doefab fab or retrieve output")
    p.add_argument("--model", required=True, metavar="MODEL_DIR", help="doefab learn's output")
    p.add_argument("--out", required=True, help="output folder (camera_psnr.json)")
    p.add_argument("--config", help="design TOML file or preset name (default preset if absent)")
    p.add_argument(
        "--eval-images",
        metavar="DIR",
        help="folder of grey images to score (default: the embedded held-back photos)",
    )
    p.add_argument(
        "--crop",
        type=int,
        default=CROP,
        help=f"centre crop of each image scored (default {CROP} px)",
    )
    p.add_argument(
        "--allowance-db",
        type=float,
        default=ALLOWANCE_DB,
        help=f"PSNR loss from the nominal camera within the budget (default {ALLOWANCE_DB:g} dB)",
    )
    p.add_argument("--force", action="store_true", help="overwrite camera_psnr.json")
    p.set_defaults(func=_camera_psnr)


def _camera_psnr(args):
    from doe.infra.files import staged_output
    from doe.records.camera_psnr import CAMERA_PSNR_JSON, write_camera_psnr
    from psf_learn.camera_psnr import camera_psnr

    with staged_output(args.out, args.force, names=[CAMERA_PSNR_JSON]) as stage:
        result = camera_psnr(
            args.design_dir,
            args.model,
            config=args.config,
            eval_images=args.eval_images,
            crop=args.crop,
            allowance_db=args.allowance_db,
        )
        write_camera_psnr(stage / CAMERA_PSNR_JSON, result.record)
    rec = result.record
    print(
        f"camera-psnr: {rec['nominal']['psnr']:.2f} dB in the nominal camera "
        f"({rec['model_psf']['psnr']:.2f} dB with the model's PSF), "
        f"{len(rec['images']['names'])} images, {result.seconds:.1f} s -> {args.out}"
    )
    for axis, curve in rec["axes"].items():
        r = curve["within_budget"]["range"]
        shown = curve["within_budget"]["why"] if r is None else f"{r[0]:.3g} .. {r[1]:.3g}"
        print(f"  within {rec['allowance_db']:g} dB: {axis} {shown}")
    return 0
