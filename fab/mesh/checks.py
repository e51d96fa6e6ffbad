"""What ``doefab mesh`` refuses before it builds anything: formats, sizes, float32 heights.

Every refusal is an InputError naming the flag or file to change, raised before
the output folder is touched.
"""

from doe.infra.errors import InputError

FORMATS = ("ply", "glb", "3mf", "stl", "step")
INSTANCED = ("glb", "3mf", "step")
# GLB and STL store float32 coordinates; at z = thickness they round heights by half
# a float32 spacing, which must stay within the 1 nm the mesh checks hold z to
# (float32 spacing is 1.9 nm up to 32 mm, 3.8 nm beyond).
FLOAT32_FORMATS = ("glb", "stl")
Z_ROUNDING_LIMIT_NM = 1.0
# Peak memory per triangle of the upper bound (fab.mesh.relief.triangle_upper_bound): numpy
# arrays plus the Python lists of the builder and the encoders (measured 150-270 B on
# random 300^2 to 1000^2 maps, whose bound is ~1.75 x their triangle count).
BYTES_PER_TRIANGLE = 300
MERGED_MEMORY_LIMIT_BYTES = 2 * 1024**3
# The tile is always built: a 0.25 um pitch design of N = 3494 needs ~43 GiB (over
# 15 min); this limit passes about N = 1500 at worst (a random map), 3000 for a smooth one.
TILE_MEMORY_LIMIT_BYTES = 8 * 1024**3


def parse_formats(text):
    """Return the formats named in a comma-separated ``--formats`` value, in FORMATS order."""
    formats = [f.strip().lower() for f in text.split(",") if f.strip()]
    bad = [f for f in formats if f not in FORMATS]
    if bad or not formats:
        raise InputError(
            "--formats", f"unknown format(s) {bad or text!r}; choose from {','.join(FORMATS)}"
        )
    return [f for f in FORMATS if f in formats]


def check_crop(relief, crop, tiles):
    """Refuse a merged crop that exceeds the aperture or the memory limit (InputError).

    Returns
    -------
    int
        The upper bound on the crop's triangles.
    """
    from fab.mesh.relief import triangle_upper_bound

    if crop < 1:
        raise InputError("--crop", f"must be >= 1 tile, got {crop}")
    if crop > min(tiles):
        raise InputError(
            "--crop", f"{crop} x {crop} tiles exceed the aperture's {tiles[0]} x {tiles[1]} tiles"
        )
    est = triangle_upper_bound(relief.levels, crop)
    need = est * BYTES_PER_TRIANGLE
    if need > MERGED_MEMORY_LIMIT_BYTES:
        raise InputError(
            "--crop",
            f"a merged {crop} x {crop}-tile body needs up to {est:,} "
            f"triangles (~{need / 1024**3:.1f} GiB, limit "
            f"{MERGED_MEMORY_LIMIT_BYTES / 1024**3:.0f} GiB); use the instanced "
            f"aperture.glb / aperture.3mf / aperture.step or a smaller --crop",
        )
    return est


def check_tile_size(relief, levels_path):
    """Refuse a tile whose mesh would exceed the memory limit (InputError)."""
    from fab.mesh.relief import triangle_upper_bound

    est = triangle_upper_bound(relief.levels)
    need = est * BYTES_PER_TRIANGLE
    if need > TILE_MEMORY_LIMIT_BYTES:
        n = relief.levels.shape[0]
        raise InputError(
            levels_path,
            f"the mesh of this {n} x {n}-pixel tile needs up to {est:,} triangles "
            f"(~{need / 1024**3:.0f} GiB, limit {TILE_MEMORY_LIMIT_BYTES / 1024**3:.0f} GiB); "
            "the fab package does not need it (doefab run --formats none skips the mesh)",
        )


def check_float32_heights(thickness_mm, formats, where):
    """Refuse float32 formats whose rounding at the top surface exceeds the z tolerance."""
    import numpy as np

    single = [f for f in formats if f in FLOAT32_FORMATS]
    with np.errstate(over="ignore"):
        rounding_nm = float(np.spacing(np.float32(thickness_mm))) / 2 * 1e6
    if not single or rounding_nm <= Z_ROUNDING_LIMIT_NM:
        return
    detail = (
        f"round heights at that z by up to {rounding_nm:.2g} nm"
        if np.isfinite(rounding_nm)
        else "cannot hold that z"
    )
    raise InputError(
        where,
        f"{thickness_mm:g} mm: {' and '.join(single)} store float32 coordinates, which "
        f"{detail} (limit {Z_ROUNDING_LIMIT_NM:g} nm); use a thinner substrate or drop "
        "them from --formats",
    )


def check_step_size(relief, manifest_path):
    """Refuse a tile whose STEP solid has too many faces to build in time (InputError)."""
    from fab.mesh.step import MAX_STEP_FACES, step_face_count

    faces = step_face_count(relief.levels)
    if faces > MAX_STEP_FACES:
        raise InputError(
            manifest_path,
            f"the tile needs {faces:,} planar STEP faces (limit "
            f"{MAX_STEP_FACES:,}), too complex to build in time; drop step "
            f"from --formats and use the mesh formats (ply, glb, 3mf, stl)",
        )
