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
            "as one cell placed by one AREF over the aperture, alignment marks, layer images, "
            "a tolerance table, fab_manifest.json and fab_report.{md,html}."
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
        "--camera-budget",
        action="store_true",
        help="add the report's 'In the camera' budget: band-pass, f-number, defocus, rotation",
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
            camera_budget=args.camera_budget,
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
    print(
        f"doefab fab: wrote {len(result.files)} files to {args.out} "
        f"(N={m['tile_pixels']}, pitch {m['pixel_pitch_nm']} nm, tiles {m['tiles']}; {depths})"
    )
    return 0
