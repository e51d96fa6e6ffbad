"""``doefab fab DESIGN_DIR --out DIR``: the fabrication package of a phase tile.

The package is built by :func:`fab.package.build.build_package`; this module
parses the flags, prints and sets the exit code.
"""

import sys


def register(sub):
    p = sub.add_parser(
        "fab",
        help="write masks (GDSII), layer images, tolerances, manifest and report of a design",
        description=(
            "Turn DESIGN_DIR/levels.npy (uint8 N x N, values 0..L-1) into a fabrication "
            "package: binary masks with Sellmeier etch depths, a GDSII file with the tile "
            "as one cell placed by one AREF and clipped edge tiles that fill the clear "
            "aperture, alignment marks, layer images, a tolerance table, fab_manifest.json "
            "and fab_report.{md,html}."
        ),
    )
    p.add_argument(
        "design_dir",
        metavar="DESIGN_DIR",
        help="folder with levels.npy "
        "(target_psf.npy and retrieval.json optional), e.g. doefab retrieve's --out",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--config", help="design TOML file or preset name (default preset if absent)")
    p.add_argument("--force", action="store_true", help="overwrite existing files in --out")
    p.add_argument("--oasis", action="store_true", help="also write mask.oas (KLayout)")
    p.add_argument(
        "--no-camera-budget",
        action="store_true",
        help="leave the report's 'In the camera' budget out (band-pass, f-number, defocus, "
        "rotation; about 1.5 s of CPU)",
    )
    p.add_argument(
        "--camera-psnr",
        metavar="FILE",
        help="camera_psnr.json of doefab camera-psnr (or its folder): the same budget in dB "
        "of a learned model's reconstruction PSNR, in the report",
    )
    fewer = p.add_mutually_exclusive_group()
    fewer.add_argument(
        "--whole-tiles",
        action="store_true",
        help="whole tiles only (no clipped edge tiles); the clear-aperture frame shrinks to them",
    )
    fewer.add_argument(
        "--tiles",
        type=int,
        metavar="N",
        help="N x N whole tiles only (at most those that fit); the frame shrinks to them",
    )
    p.add_argument(
        "--keep-aperture",
        action="store_true",
        help="with --whole-tiles or --tiles: keep the design's frame, plain glass around the tiles",
    )
    p.add_argument(
        "--dies",
        type=int,
        nargs=2,
        metavar=("NX", "NY"),
        default=(1, 1),
        help="NX x NY plates on the substrate with dicing lanes between them (default 1 1)",
    )
    p.add_argument(
        "--lane-um", type=float, default=200.0, help="dicing lane width in um (default 200)"
    )
    p.add_argument(
        "--allow-drc",
        action="store_true",
        help="write the package even when the design-rule check (drc.lydrc: width and space "
        "at the feature size, Euclidean) finds violations; the report lists them",
    )
    p.set_defaults(func=_fab)


def _fab(args):
    from fab.package.build import PackageCheckFailed, build_package

    try:
        result = build_package(
            args.design_dir, args.out, config=args.config, force=args.force, oasis=args.oasis,
            camera_budget=False if args.no_camera_budget else None, camera_psnr=args.camera_psnr,
            tiles=args.tiles, whole_tiles=args.whole_tiles, keep_aperture=args.keep_aperture,
            dies=tuple(args.dies), lane_um=args.lane_um,
            allow_drc=args.allow_drc,
        )  # fmt: skip
    except PackageCheckFailed as e:
        print(f"doefab fab: FAIL {e}; nothing written", file=sys.stderr)
        return 1
    for warning in result.warnings:  # once the package is in place: a refusal stays one line
        print(f"doefab fab: {warning}", file=sys.stderr)
    m = result.manifest.fields
    drc = m["drc"]
    if drc["violations_allowed"]:
        print(
            f"doefab fab: warning: {drc['total']} design-rule markers allowed by --allow-drc "
            f"(markers in {drc['markers']})",
            file=sys.stderr,
        )
    depths = ", ".join(f"{mk['name']} {mk['etch_depth_nm']:.1f} nm" for mk in m["masks"])
    plate = m["plate"]
    dies = m["dies"]["nx"], m["dies"]["ny"]
    print(
        f"doefab fab: wrote {len(result.files)} files to {args.out} "
        f"(N={m['tile_pixels']}, pitch {m['pixel_pitch_nm']} nm, tiles {m['tiles']}, "
        f"{plate['patterned_fraction']:.2%} of the clear aperture patterned, "
        f"{dies[0]} x {dies[1]} dies; {depths})"
    )
    return 0
