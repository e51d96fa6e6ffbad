"""Encode relief meshes as PLY, GLB, 3MF, binary STL and a preview PNG (bytes, mm).

Every encoder returns the file's bytes; the command writes them through
``staged_output``. Outputs are deterministic: no timestamps, no random UUIDs,
fixed zip dates. Coordinates are millimetres in every format (3MF declares
``unit="millimeter"``; STL says "units mm" in its header; GLB, whose convention
is metres, holds millimetres too, so a viewer needs a 0.001 scale).
A scene (``offsets`` given) stores the tile once and places it by translation
only: GLB node instances, 3MF components.
"""

import io
import zipfile

import numpy as np

from doe.infra.png import save_png

STL_HEADER = b"doefab relief mesh; units mm; z up; back face z=0"
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


def ply_bytes(vertices, faces):
    """Return a binary little-endian PLY of a mesh (float64 vertices, int32 faces)."""
    v = np.ascontiguousarray(vertices, "<f8")
    f = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    f["n"], f["v"] = 3, faces
    head = (
        f"ply\nformat binary_little_endian 1.0\ncomment units mm\n"
        f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    return head.encode("ascii") + v.tobytes() + f.tobytes()


def stl_bytes(vertices, faces):
    """Return a binary STL (float32, per-face normals) whose header says "units mm"."""
    p = np.asarray(vertices, np.float64)[faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    rec = np.zeros(len(faces), dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["n"], rec["v"] = n, p
    header = STL_HEADER.ljust(80, b" ")
    return header + np.uint32(len(faces)).tobytes() + rec.tobytes()


def glb_bytes(vertices, faces, offsets=None):
    """Return a binary glTF holding the mesh once, placed at each of ``offsets`` (mm).

    ``offsets`` of shape (M, 3) gives M node instances of the one mesh; None
    places it once at the origin.
    """
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    scene = trimesh.Scene()
    offsets = np.zeros((1, 3)) if offsets is None else np.asarray(offsets, np.float64)
    for n, off in enumerate(offsets):
        m = np.eye(4)
        m[:3, 3] = off
        if n == 0:
            scene.add_geometry(mesh, geom_name="tile", node_name="tile_0", transform=m)
        else:
            scene.graph.update(frame_to=f"tile_{n}", matrix=m, geometry="tile")
    return scene.export(file_type="glb")


def threemf_bytes(vertices, faces, offsets=None):
    """Return a 3MF package (mm) with the mesh as one object, instanced by components.

    With ``offsets`` (M, 3) the build item is an assembly object whose M
    components reference the mesh object with a translation each.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    vert_xml = "".join(f'<vertex x="{x:.9f}" y="{y:.9f}" z="{z:.9f}"/>' for x, y, z in v.tolist())
    tri_xml = "".join(f'<triangle v1="{a}" v2="{b}" v3="{c}"/>' for a, b, c in f.tolist())
    objects = (
        f'<object id="1" name="tile" type="model"><mesh><vertices>{vert_xml}</vertices>'
        f"<triangles>{tri_xml}</triangles></mesh></object>"
    )
    if offsets is None:
        build = '<item objectid="1"/>'
    else:
        comps = "".join(
            f'<component objectid="1" transform="1 0 0 0 1 0 0 0 1 {x:.9f} {y:.9f} {z:.9f}"/>'
            for x, y, z in np.asarray(offsets, np.float64).tolist()
        )
        objects += (
            f'<object id="2" name="aperture" type="model"><components>{comps}</components></object>'
        )
        build = '<item objectid="2"/>'
    return threemf_package(f"<resources>{objects}</resources><build>{build}</build>")


def threemf_package(resources_and_build):
    """Return the bytes of a 3MF package (mm) whose model holds ``resources_and_build``.

    The zip members carry a fixed date, so equal models give equal bytes.
    """
    model = (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        '<model unit="millimeter" xml:lang="en-US" '
        'xmlns="http://schemas.microsoft.com/3dmanufacturing/core/2015/02">'
        f"{resources_and_build}</model>\n"
    )
    content_types = (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        '<Types xmlns="http://schemas.openxmlformats.org/package/2006/content-types">'
        '<Default Extension="rels" '
        'ContentType="application/vnd.openxmlformats-package.relationships+xml"/>'
        '<Default Extension="model" '
        'ContentType="application/vnd.ms-package.3dmanufacturing-3dmodel+xml"/></Types>\n'
    )
    rels = (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        '<Relationships xmlns="http://schemas.openxmlformats.org/package/2006/relationships">'
        '<Relationship Target="/3D/3dmodel.model" Id="rel0" '
        'Type="http://schemas.microsoft.com/3dmanufacturing/2013/01/3dmodel"/>'
        "</Relationships>\n"
    )
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for name, text in (
            ("[Content_Types].xml", content_types),
            ("_rels/.rels", rels),
            ("3D/3dmodel.model", model),
        ):
            info = zipfile.ZipInfo(name, date_time=_ZIP_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            z.writestr(info, text.encode("utf-8"), compresslevel=6)
    return buf.getvalue()


def preview_png_bytes(relief, title=""):
    """Return a PNG height map of the relief tile (row 0 at the top, as seen from above)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tops_um = relief.level_z()[np.asarray(relief.levels, np.int64)] * 1e6
    rows, cols = relief.levels.shape
    extent_mm = (0, cols * relief.pitch * 1e3, 0, rows * relief.pitch * 1e3)
    fig, ax = plt.subplots(figsize=(6, 5), dpi=120)
    im = ax.imshow(
        tops_um - relief.thickness * 1e6,
        origin="upper",
        extent=extent_mm,
        cmap="viridis",
        interpolation="nearest",
    )
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(title or f"relief tile {rows} x {cols} px, {relief.n_levels} levels")
    fig.colorbar(im, ax=ax, label="top height relative to the unetched surface (um)")
    buf = io.BytesIO()
    save_png(fig, buf)
    plt.close(fig)
    return buf.getvalue()
