"""``doefab mesh``: 3-D models (PLY, GLB, 3MF, STL, STEP) of the tile and the tiled aperture.

Reads FAB_DIR/fab_manifest.json and its levels file; writes into --out:

- ``tile.{ply,glb,3mf,stl,step}``: one tile, lower-left corner at the origin;
- ``aperture.{glb,3mf,step}``: the tile stored once and instanced on the
  tiles [nx, ny] lattice, pitch N p, lower-left tile at the manifest's
  ``array_origin_nm`` (converted to mm; (0, 0) when absent);
- ``aperture_edge.{glb,3mf,step}`` when the plate has edge pixels: the clipped
  edge tiles that fill the clear aperture, in the same coordinates;
- ``crop_CxC.{ply,glb,3mf,stl}`` with ``--crop C``: one merged body of C x C
  tiles, lower-left at the same origin (refused when too large to build);
- ``preview.png`` and ``mesh_report.json``.

Units are mm everywhere (STL stores none: its header says "units mm").
"""

from fab.mesh.checks import FORMATS


def register(sub):
    p = sub.add_parser(
        "mesh",
        help="3-D models of the tile and the tiled aperture",
        description=__doc__.split("\n\n", 1)[1],
    )
    p.add_argument("fab_dir", metavar="FAB_DIR", help="folder with fab_manifest.json")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--formats",
        default=",".join(FORMATS),
        help=f"comma-separated subset of {','.join(FORMATS)} (default: all)",
    )
    p.add_argument(
        "--crop",
        type=int,
        metavar="TILES",
        help="also write one merged body of TILES x TILES tiles",
    )
    p.add_argument(
        "--thickness-mm",
        type=float,
        help="substrate thickness (default: the manifest's substrate_thickness_mm)",
    )
    p.add_argument("--force", action="store_true", help="overwrite existing files")
    p.set_defaults(func=_mesh)


def _mesh(args):
    from fab.mesh.build import build_meshes

    result = build_meshes(
        args.fab_dir,
        args.out,
        formats=args.formats,
        crop=args.crop,
        thickness_mm=args.thickness_mm,
        force=args.force,
    )
    tile, aperture = result.report.tile, result.report.aperture
    timing = ", ".join(f"{k} {v:.1f} s" for k, v in result.seconds.items())
    edges = aperture.get("edge_instances", 0)
    edges = f" + {edges} edge pieces (aperture_edge.*)" if edges else ""
    print(
        f"doefab mesh: {tile['triangles']:,} triangles per tile, "
        f"{aperture['instances']} instances{edges}, "
        f"volume rel. err {tile['volume_rel_err']:.1e}; {timing}; wrote {args.out}"
    )
    if result.step_ok is False:
        print(f"doefab mesh: STEP solid check failed: {dict(result.report.step)}")
        return 1
    return 0
