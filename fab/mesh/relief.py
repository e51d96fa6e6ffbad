"""Watertight 3-D model of a relief tile, built directly as a height field.

Geometry follows CONVENTIONS.md "3-D model": z up, back face at z = 0, the
unetched top at z = thickness, a pixel of level l has its top face at
thickness - (L - 1 - l) * step, and pixel (row r, column c) covers
x in [c p, (c + 1) p], y in [(N - 1 - r) p, (N - r) p].

The surface is assembled from planar polygons with exactly shared vertices:
one top quad per pixel, one vertical wall per pixel edge whose two cells differ
(its vertical sides carry a vertex at every level met at that grid corner, so no
T-junction exists), the outer side walls (the outside counts as level -1, the
back face) and the back face. Where two higher cells touch only at a corner (a
pinched corner, ``fab.mesh.chamfer``), the lower of the two is chamfered by a prism
of legs p / 1000, so that every edge has exactly two faces and every vertex one fan
even after the vertices are merged by position, as every STL reader does: the mesh
is a closed oriented 2-manifold by index and by position.

Values are SI metres inside; the mesh itself is in millimetres (a file
boundary), as every mesh writer expects.
"""

from dataclasses import dataclass

import numpy as np

from fab.mesh.chamfer import (
    CHAMFER_DENOM,
    chamfer_quadrant,
    chamfer_volume,
    cut_chamfer,
    ear_clip,
    tiled_pinch_count,
)

# Outer cells (beyond the tile edge) and the back face use this level index.
BACK = -1


@dataclass(frozen=True, eq=False)
class Relief:
    """A relief tile: level map plus the physical numbers that place it in space.

    Attributes
    ----------
    levels : ndarray of uint8, shape (H, W)
        Phase levels, row 0 = top edge (largest y), column 0 = left edge.
    n_levels : int
        Number of phase levels L.
    step : float
        Height of one level step (m).
    pitch : float
        Pixel pitch (m).
    thickness : float
        Substrate thickness, back face to unetched top (m).
    """

    levels: np.ndarray
    n_levels: int
    step: float
    pitch: float
    thickness: float

    def level_z(self):
        """Return the top height of each level, shape (L,), in metres."""
        return self.thickness - (self.n_levels - 1 - np.arange(self.n_levels)) * self.step

    def pixel_volume(self):
        """Return the volume of the pixel relief, p^2 * sum of pixel top heights (m^3)."""
        tops = self.level_z()[np.asarray(self.levels, np.int64)]
        return float(self.pitch**2 * tops.sum())

    def chamfer_volume(self):
        """Return the volume the chamfers at pinched corners remove (m^3, ``fab.mesh.chamfer``)."""
        return chamfer_volume(self.levels, self.step, self.pitch)

    def analytic_volume(self):
        """Return the exact volume of the modelled solid: pixel relief minus chamfers (m^3)."""
        return self.pixel_volume() - self.chamfer_volume()

    def tiled(self, nx, ny):
        """Return the relief of ``nx`` x ``ny`` tiles side by side as one level map."""
        return Relief(
            np.tile(self.levels, (ny, nx)), self.n_levels, self.step, self.pitch, self.thickness
        )


@dataclass(frozen=True, eq=False)
class Surface:
    """Closed polygonal surface of a relief in grid units (topology, no physics).

    Attributes
    ----------
    grid : ndarray of float64, shape (V, 3)
        Vertex (x, y, k): x, y in pixel pitches from the lower-left corner (a chamfer
        vertex lies 1 / denom off a grid corner), k the level index of its height
        (``BACK`` = the back face, z = 0).
    triangles : ndarray of int64, shape (F, 3)
        Vertex indices, counter-clockwise seen from outside the solid.
    loops : list of ndarray of int64
        The planar faces as vertex loops, counter-clockwise seen from outside:
        pixel tops, walls, chamfer bottoms and faces, then the back face last.
    loop_normals : ndarray of int8, shape (len(loops), 3)
        Outward normal of each loop: a unit axis vector, or (+-1, +-1, 0) (not
        normalised) for a chamfer face.
    chamfers : int
        The number of pinched corners chamfered.
    """

    grid: np.ndarray
    triangles: np.ndarray
    loops: list
    loop_normals: np.ndarray
    chamfers: int = 0


def relief_surface(levels, progress=True, denom=CHAMFER_DENOM):
    """Build the closed surface of a level map (grid units).

    Parameters
    ----------
    levels : array_like of int, shape (H, W)
        Level map, row 0 = largest y.
    progress : bool
        Show a progress bar over the grid corners on a terminal (it takes seconds
        at N = 175).
    denom : int
        Chamfer leg at pinched corners = 1 / ``denom`` pixel pitches (the default
        is the one ``Relief.analytic_volume`` counts with).

    Returns
    -------
    Surface
    """
    lev = np.asarray(levels, np.int64)
    if lev.ndim != 2 or lev.size == 0 or lev.min() < 0:
        raise ValueError(f"levels must be a non-empty 2-D map of levels >= 0, got {lev.shape}")
    hgt = lev[::-1]  # hgt[j, i]: cell i along x, j along y (bottom-up)
    rows, cols = hgt.shape
    pad = np.full((rows + 2, cols + 2), BACK, np.int64)
    pad[1:-1, 1:-1] = hgt
    pad_list = pad.tolist()

    cg = _corner_grid(pad_list, rows, cols, progress, int(denom))
    grid, top_vid, walls, back_vid = cg.grid, cg.top_vid, cg.walls, cg.back_vid
    tris, loops = _top_faces(grid, top_vid, cg.tops, denom)
    normals = [(0, 0, 1)] * len(loops)

    wall_tris, wall_loops, wall_normals = _wall_faces(walls, pad_list, grid, cg.notched, denom)
    tris.append(wall_tris)
    loops += wall_loops + [np.array(lp, np.int64) for lp, _ in cg.faces]
    normals += wall_normals + [n for _, n in cg.faces]
    tris.append(np.array([t for lp, _ in cg.faces for t in _fan(lp)], np.int64).reshape(-1, 3))

    # back face: boundary corners clockwise seen from above = counter-clockwise from below
    ring = [(0, j) for j in range(rows + 1)] + [(i, rows) for i in range(1, cols + 1)]
    ring += [(cols, j) for j in range(rows - 1, -1, -1)] + [(i, 0) for i in range(cols - 1, 0, -1)]
    back = np.array([back_vid[g] for g in ring], np.int64)
    centre = len(grid)
    grid.append((cols / 2, rows / 2, BACK))
    tris.append(np.stack([np.full(len(back), centre), back, np.roll(back, -1)], axis=1))
    loops.append(back)
    normals.append((0, 0, -1))

    return Surface(
        grid=np.array(grid, np.float64),
        triangles=np.concatenate(tris),
        loops=loops,
        loop_normals=np.array(normals, np.int8),
        chamfers=cg.chamfers,
    )


def _fan(loop):
    """Triangulate a convex loop (the chamfer triangle and rectangle) as a fan."""
    return [(loop[0], loop[m], loop[m + 1]) for m in range(1, len(loop) - 1)]


def _top_faces(grid, top_vid, tops, denom):
    """Return the pixel tops: [triangles (T, 3)] and one loop per pixel, row by row.

    A top quad SW, SE, NE, NW is counter-clockwise from above; a top with chamfer or
    chamfer-edge vertices (``tops``: (row, col, corner) -> vertices replacing that
    corner) is triangulated by ear clipping.
    """
    tv = top_vid.reshape(-1, 4)
    loops = list(tv)
    plain = np.ones(len(tv), bool)
    extra = []
    cols = top_vid.shape[1]
    for r, c in sorted({(r, c) for r, c, _ in tops}):
        loop = [v for corner in range(4) for v in tops.get((r, c, corner), [top_vid[r, c, corner]])]
        pts = [(round(grid[v][0] * denom), round(grid[v][1] * denom)) for v in loop]
        extra += ear_clip(loop, pts)
        loops[r * cols + c] = np.array(loop, np.int64)
        plain[r * cols + c] = False
    tq = tv[plain]
    tris = [tq[:, [0, 1, 2]], tq[:, [0, 2, 3]], np.array(extra, np.int64).reshape(-1, 3)]
    return tris, loops


# Quadrants around a corner, counter-clockwise: NE, NW, SW, SE. Edge d lies between
# quadrant d and d + 1: 0 north, 1 west, 2 south, 3 east. The corner is the SW corner
# of the NE cell, the SE corner of NW, NE of SW and NW of SE.
_CELL_CORNER_OF = (0, 1, 2, 3)
_EDGE_END = (0, 1, 1, 0)  # is the corner the start (0) or end (1) of edge d


@dataclass
class _CornerGrid:
    """The vertices of every grid corner (see :func:`_corner_grid`)."""

    grid: list
    top_vid: np.ndarray
    walls: dict
    back_vid: dict
    tops: dict
    notched: set
    faces: list
    chamfers: int


def _corner_grid(pad_list, rows, cols, progress, denom):
    """Create the vertices at every grid corner of a padded height map.

    Returns
    -------
    _CornerGrid
        ``grid``: list of (x, y, k) vertices, x and y in pixel pitches, k the level
        index. ``top_vid`` (rows, cols, 4): vertex of each pixel top's corner 0 SW,
        1 SE, 2 NE, 3 NW. ``walls``: key (kind, j, i) with kind 'v' (x = i, y in
        [j, j+1]) or 'h' (y = j, x in [i, i+1]); value [chain at start corner, chain
        at end corner], each a list of (k, 0 at the corner or 1 at a chamfer, vid).
        ``back_vid``: back-face vertex of each boundary corner (i, j). ``tops``,
        ``notched``, ``faces``, ``chamfers``: what the chamfers add (``chamfer.cut_chamfer``).
    """
    from tqdm import tqdm

    cg = _CornerGrid([], np.full((rows, cols, 4), -1, np.int64), {}, {}, {}, set(), [], 0)
    grid, top_vid = cg.grid, cg.top_vid
    corner_rows = tqdm(
        range(rows + 1), desc="mesh corners", unit="row", leave=False,
        disable=None if progress else True,
    )  # fmt: skip
    for j in corner_rows:
        for i in range(cols + 1):
            q = (pad_list[j + 1][i + 1], pad_list[j + 1][i], pad_list[j][i], pad_list[j][i + 1])
            cells = ((j, i), (j, i - 1), (j - 1, i - 1), (j - 1, i))
            if q[0] == q[1] == q[2] == q[3]:  # flat interior corner: one vertex
                vid = len(grid)
                grid.append((i, j, q[0]))
                for d in range(4):
                    top_vid[cells[d][0], cells[d][1], _CELL_CORNER_OF[d]] = vid
                continue
            edge_keys = (("v", j, i), ("h", j, i - 1), ("v", j - 1, i), ("h", j, i))
            dc = chamfer_quadrant(q)
            if dc is not None:  # at the corner itself the chamfered cell ends at z_lo
                z_lo = max(q[(dc + 1) % 4], q[(dc + 3) % 4])
                qc = tuple(z_lo if d == dc else q[d] for d in range(4))
            else:
                qc = q
            ks = sorted(set(qc))
            for n, k in enumerate(ks):
                _corner_vertices(
                    i, j, k, qc, ks, n, cells, edge_keys, _EDGE_END,
                    grid, top_vid, cg.walls, cg.back_vid, _CELL_CORNER_OF,
                )  # fmt: skip
            if dc is not None:
                cut_chamfer(cg, i, j, dc, q, z_lo, cells, edge_keys, 1 / denom, _EDGE_END)
    return cg


def _wall_faces(walls, pad_list, grid, notched, denom):
    """Return the wall triangles (W, 3), loops and outward normals of every wall.

    A wall is zipped between its two vertical chains; a wall with a chamfer notch is
    triangulated by ear clipping in its plane.
    """
    loops, normals, wall_tris = [], [], []
    for key, (chain0, chain1) in sorted(walls.items()):
        kind, j, i = key
        if kind == "v":  # from (i, j) to (i, j + 1); left cell (i-1, j)
            low_on_plus_side = pad_list[j + 1][i + 1] < pad_list[j + 1][i]
            plus = (1, 0, 0)
        else:  # from (i, j) to (i + 1, j); below cell (i, j - 1)
            low_on_plus_side = pad_list[j + 1][i + 1] < pad_list[j][i + 1]
            plus = (0, 1, 0)
        a = [v for *_, v in sorted(chain0)]
        b = [v for *_, v in sorted(chain1)]
        # loop a0 -> b0 .. b_top -> a_top .. a0 has normal t x z: +x for 'v', -y for 'h'
        keep = low_on_plus_side if kind == "v" else not low_on_plus_side
        loop = a[:1] + b + a[:0:-1]
        if key in notched:
            axis = 1 if kind == "v" else 0
            pts = [(round(grid[v][axis] * denom), grid[v][2]) for v in loop]
            ladder = ear_clip(loop, pts)
        else:
            ka = [k for k, *_ in sorted(chain0)]
            kb = [k for k, *_ in sorted(chain1)]
            ladder = _ladder(a, ka, b, kb)
        if keep:
            normal = plus if kind == "v" else (0, -1, 0)
        else:
            loop, ladder = loop[::-1], [t[::-1] for t in ladder]
            normal = (-1, 0, 0) if kind == "v" else (0, 1, 0)
        loops.append(np.array(loop, np.int64))
        normals.append(normal)
        wall_tris.extend(ladder)
    return np.array(wall_tris, np.int64).reshape(-1, 3), loops, normals


def _corner_vertices(
    i, j, k, q, ks, n, cells, edge_keys, edge_end, grid, top_vid, walls, back_vid, cell_corner_of
):
    """Create the vertices of grid corner (i, j) at level k, one per fan of faces.

    Faces meeting there: tops of quadrants at level k, walls of the four edges whose
    level span contains k, and the back face (k = BACK). Faces sharing an edge that
    ends at this vertex join one fan (union-find). ``q`` comes with the chamfered cell
    lowered to z_lo, so no corner is pinched and each level gets one fan.
    """
    lo = [min(q[d], q[(d + 1) % 4]) for d in range(4)]
    hi = [max(q[d], q[(d + 1) % 4]) for d in range(4)]
    nodes = {}  # face name -> parent

    def find(x):
        while nodes[x] != x:
            nodes[x] = nodes[nodes[x]]
            x = nodes[x]
        return x

    def union(x, y):
        nodes[find(x)] = find(y)

    for d in range(4):
        if q[d] == k and k != BACK:
            nodes["t", d] = ("t", d)
        if lo[d] < hi[d] and lo[d] <= k <= hi[d]:
            nodes["w", d] = ("w", d)
    if k == BACK:
        nodes["b"] = "b"
    # horizontal edges along each edge direction d at height k
    for d in range(4):
        on = [("t", c) for c in (d, (d + 1) % 4) if ("t", c) in nodes]
        if ("w", d) in nodes and k in (lo[d], hi[d]):
            on.append(("w", d))
        if k == BACK and ("w", d) in nodes:
            on.append("b")
        for f in on[1:]:
            union(on[0], f)
    # vertical edges just above and below k: one per run of solid quadrants
    for top in ([ks[n + 1]] if n + 1 < len(ks) else []) + [k]:
        if top == k and n == 0:
            continue  # nothing below the lowest level of this corner
        solid = [h >= top for h in q]
        for d in range(4):  # a run starts at quadrant d
            if solid[d] and not solid[d - 1]:
                e = d
                while solid[(e + 1) % 4]:
                    e = (e + 1) % 4
                union(("w", (d - 1) % 4), ("w", e))
    vid_of = {}
    for f in nodes:
        root = find(f)
        if root not in vid_of:
            vid_of[root] = len(grid)
            grid.append((i, j, k))
        vid = vid_of[root]
        if f == "b":
            back_vid[i, j] = vid
        elif f[0] == "t":
            r, c = cells[f[1]]
            top_vid[r, c, cell_corner_of[f[1]]] = vid
        else:
            chains = walls.setdefault(edge_keys[f[1]], ([], []))
            chains[edge_end[f[1]]].append((k, 0, vid))


def _ladder(a, ka, b, kb):
    """Triangulate a wall between vertical chains ``a`` (start) and ``b`` (end).

    Returns triangles oriented like the loop a0 -> b0 .. b_top -> a_top .. a0.
    """
    out, ia, ib = [], 0, 0
    while ia < len(a) - 1 or ib < len(b) - 1:
        if ib == len(b) - 1 or (ia < len(a) - 1 and ka[ia + 1] <= kb[ib + 1]):
            out.append((a[ia], b[ib], a[ia + 1]))
            ia += 1
        else:
            out.append((a[ia], b[ib], b[ib + 1]))
            ib += 1
    return out


def surface_points_mm(surface, relief):
    """Return the surface vertices in millimetres, shape (V, 3), float64."""
    g = surface.grid
    k = g[:, 2].astype(np.int64)
    z = np.where(k == BACK, 0.0, relief.level_z()[np.clip(k, 0, None)])
    return np.column_stack([g[:, 0] * relief.pitch, g[:, 1] * relief.pitch, z]) * 1e3


def tile_mesh(relief):
    """Build the watertight triangle mesh of a relief (millimetres).

    Returns
    -------
    vertices : ndarray of float64, shape (V, 3)
        Positions in mm.
    faces : ndarray of int64, shape (F, 3)
        Triangles, counter-clockwise seen from outside.
    """
    surface = relief_surface(relief.levels)
    return surface_points_mm(surface, relief), surface.triangles


def triangle_upper_bound(levels, tiles=1):
    """Return an upper bound on the triangle count of a merged ``tiles`` x ``tiles`` body.

    That of ``relief_surface`` of the tiled level map, counted without building it
    (cheap; checked before building a large merged body): tops, a wall per level
    step between neighbours (within tiles and across their seams), the outer walls
    and the back, plus 8 per chamfered corner (a vertex more in its cell's top, in
    the tops of the two lower neighbours and in the two notched walls; the chamfer
    face and its triangle at z_lo).
    """
    lev = np.asarray(levels, np.int64)
    rows, cols = lev.shape
    c = int(tiles)
    inside = np.abs(np.diff(lev, axis=1)).sum() + np.abs(np.diff(lev, axis=0)).sum()
    seams = np.abs(lev[:, 0] - lev[:, -1]).sum() + np.abs(lev[0] - lev[-1]).sum()
    edge = np.concatenate([lev[0], lev[-1], lev[:, 0], lev[:, -1]])
    walls = int(c * c * inside + c * (c - 1) * seams + c * (edge + 1).sum())
    chamfers = 8 * tiled_pinch_count(lev, c)
    return 2 * rows * cols * c * c + 2 * walls + 6 * c * (rows + cols) + chamfers


def mesh_volume(vertices, faces):
    """Return the signed volume enclosed by a closed triangle mesh (units^3)."""
    c = vertices.mean(axis=0)
    p = vertices[faces] - c
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6)


def instance_offsets_mm(relief, tiles, origin_mm=(0.0, 0.0)):
    """Return the lower-left corner (x, y, 0) of every tile of a ``tiles`` = (nx, ny) array.

    Returns
    -------
    ndarray of float64, shape (nx * ny, 3)
        Offsets in mm, x varying fastest, lower-left tile first.
    """
    nx, ny = tiles
    size = relief.levels.shape[1] * relief.pitch * 1e3, relief.levels.shape[0] * relief.pitch * 1e3
    return np.array(
        [
            (origin_mm[0] + ix * size[0], origin_mm[1] + iy * size[1], 0.0)
            for iy in range(ny)
            for ix in range(nx)
        ],
        np.float64,
    )
