"""``doefab camera``: the effective PSF of a plate in a lens (see doe.camera_stage)."""


def register(sub):
    p = sub.add_parser(
        "camera",
        help="the PSF the SPAD's active areas see through the plate in a lens",
        description="Image a point source through DESIGN_DIR's plate and a lens for a "
        "spectrum, stop, defocus and plate rotation, and write the effective PSF the "
        "active areas collect (effective_psf.npy, camera.json, camera.png).",
    )
    p.add_argument("design_dir", help="a doefab fab or doefab retrieve output folder")
    p.add_argument("--out", required=True, help="output folder")
    light = p.add_mutually_exclusive_group()
    light.add_argument(
        "--bandwidth-nm",
        type=float,
        default=0.0,
        help="FWHM of a Gaussian band-pass centred on the design wavelength (default 0)",
    )
    light.add_argument("--spectrum", help="two-column text file: wavelength (nm), weight")
    p.add_argument(
        "--f-number",
        type=float,
        help="round stop of diameter f / N (default: the plate's square clear aperture)",
    )
    p.add_argument(
        "--defocus-um",
        type=float,
        default=0.0,
        help="sensor distance behind the image plane (um; > 0 further from the lens)",
    )
    p.add_argument(
        "--rotation-deg",
        type=float,
        default=0.0,
        help="plate rotation about the axis (deg; > 0 counter-clockwise as the PSF is viewed)",
    )
    p.add_argument(
        "--budget",
        action="store_true",
        help="also the camera budget: the figures against band-pass, f-number, defocus and "
        "rotation, each varied alone (camera.json's budget, camera_budget.png)",
    )
    p.add_argument("--config", help="design TOML file or preset name (default: the default preset)")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    p.set_defaults(func=run)


def run(args):
    from doe.camera_stage import run_camera
    from doe.figures import correlation_text

    result = run_camera(
        args.design_dir,
        args.out,
        config=args.config,
        bandwidth_nm=args.bandwidth_nm,
        spectrum_file=args.spectrum,
        f_number=args.f_number,
        defocus_um=args.defocus_um,
        rotation_deg=args.rotation_deg,
        budget=args.budget,
        force=args.force,
    )
    rec = result.record
    print(
        f"camera: collected fraction {rec['collected_fraction']:.4f}, correlation "
        f"{correlation_text(rec['correlation'])}, rmse {rec['rmse']:.4f} against the design's "
        f"PSF ({rec['settings']['spectrum']['description']}) -> {args.out}"
    )
    budget = rec.get("budget")
    if budget is not None:
        print(
            f"  budget: rmse within the nominal camera's {budget['nominal']['rmse']:.4f} "
            f"+ {budget['limit']['allowance']:g}"
        )
        for axis, curve in budget["axes"].items():
            within = curve["within_budget"]
            r = within["range"]
            shown = within["why"] if r is None else f"{r[0]:.3g} .. {r[1]:.3g}"
            print(f"  within the budget: {axis} {shown}")
    return 0
