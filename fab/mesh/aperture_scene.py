"""The aperture's edge scene: the clipped edge tiles, each stored once, instanced.

The plate's pattern fills its clear aperture (:mod:`layouts.plate_plan`): whole tiles on
the [nx, ny] lattice, and around them at most eight clipped edge pieces (the tile's
pixels in a window, placed where the periodic pattern continues), as the manifest's
``plate.edge_pixels`` say. The whole tiles stay in ``aperture.{glb,3mf}``: one tile
geometry instanced on the lattice, the contract that an independent checker holds a
scene to. The edge pieces go to their own scene, ``aperture_edge.{glb,3mf}``
(:data:`EDGE_SCENE`), in the same coordinates, so that loading both shows the filled
aperture. Each piece is its own closed relief body (the same level map window, the
same substrate thickness), stored once and placed by translation: GLB node instances
of one mesh per piece, 3MF components of one object per piece. Units are mm;
lower-left of the whole-tile array at ``origin_mm``.
"""

import numpy as np

from fab.mesh import relief as mesh
from fab.mesh.formats import threemf_package
from layouts.plate_plan import PlatePattern, edge_pieces

EDGE_SCENE = "aperture_edge"
"""Stem of the edge pieces' scene files (``aperture_edge.glb``, ``aperture_edge.3mf``)."""


def aperture_parts(relief, tiles, origin_mm, edge_pixels):
    """Return the scene's parts: [(name, Relief, offsets (M, 3) mm)], the whole tile first.

    Parameters
    ----------
    relief : fab.mesh.relief.Relief
        The tile.
    tiles : (int, int)
        Whole tiles along x and y.
    origin_mm : (float, float)
        Lower-left corner of the whole-tile array.
    edge_pixels : (int, int, int, int)
        Pixel columns left and right, rows below and above the array (the clipped tiles).
    """
    parts = [("tile", relief, mesh.instance_offsets_mm(relief, tiles, origin_mm))]
    n = relief.levels.shape[0]
    p_mm = relief.pitch * 1e3
    # the plan in pixel units (pitch 1, origin 0): positions are then pixel counts
    plan = PlatePattern(n, 1, tuple(tiles), (0, 0), tuple(edge_pixels), 0, 0)
    for piece in edge_pieces(plan):
        (c0, c1), (r0, r1) = piece.columns, piece.rows
        window = mesh.Relief(
            relief.levels[r0:r1, c0:c1], relief.n_levels, relief.step, relief.pitch,
            relief.thickness,
        )  # fmt: skip
        # the window's lower-left pixel corner within its virtual tile
        offsets = [
            (origin_mm[0] + (x + c0) * p_mm, origin_mm[1] + (y + n - r1) * p_mm, 0.0)
            for x, y in piece.placements(n)
        ]
        parts.append((piece.suffix, window, np.array(offsets, np.float64)))
    return parts


def part_meshes(parts):
    """Return [(name, vertices, faces, offsets)]: each part's relief built as a mesh (mm)."""
    return [(name, *mesh.tile_mesh(relief), offsets) for name, relief, offsets in parts]


def scene_glb_bytes(meshes):
    """Return a binary glTF: each part's mesh once, a node per placement (mm)."""
    import trimesh

    scene = trimesh.Scene()
    for name, v, f, offsets in meshes:
        geometry = trimesh.Trimesh(v, f, process=False)
        for k, off in enumerate(offsets):
            m = np.eye(4)
            m[:3, 3] = off
            if k == 0:
                scene.add_geometry(geometry, geom_name=name, node_name=f"{name}_0", transform=m)
            else:
                scene.graph.update(frame_to=f"{name}_{k}", matrix=m, geometry=name)
    return scene.export(file_type="glb")


def scene_3mf_bytes(meshes, name=EDGE_SCENE):
    """Return a 3MF package (mm): one object per part, one assembly (``name``) of
    translated components."""
    objects, comps = [], []
    for i, (part, v, f, offsets) in enumerate(meshes, start=1):
        vert = "".join(
            f'<vertex x="{x:.9f}" y="{y:.9f}" z="{z:.9f}"/>'
            for x, y, z in np.asarray(v, np.float64).tolist()
        )
        tri = "".join(
            f'<triangle v1="{a}" v2="{b}" v3="{c}"/>' for a, b, c in np.asarray(f).tolist()
        )
        objects.append(
            f'<object id="{i}" name="{part}" type="model"><mesh><vertices>{vert}</vertices>'
            f"<triangles>{tri}</triangles></mesh></object>"
        )
        comps += [
            f'<component objectid="{i}" transform="1 0 0 0 1 0 0 0 1 {x:.9f} {y:.9f} {z:.9f}"/>'
            for x, y, z in np.asarray(offsets, np.float64).tolist()
        ]
    top = len(meshes) + 1
    objects.append(
        f'<object id="{top}" name="{name}" type="model"><components>{"".join(comps)}'
        "</components></object>"
    )
    return threemf_package(
        f'<resources>{"".join(objects)}</resources><build><item objectid="{top}"/></build>'
    )


SCENE_ENCODERS = {"glb": scene_glb_bytes, "3mf": scene_3mf_bytes}
