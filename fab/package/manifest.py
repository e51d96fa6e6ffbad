"""``fab_manifest.json``: the fabrication package's description (CONVENTIONS.md plus extras).

Lengths carry their unit in the key (nm for the lithography figures, um/mm
for the optics). Etch depths are written unrounded as exact multiples of
``level_step_nm`` so that summing the depths of the masks over a pixel and
dividing by the step gives an integer level again.
"""

import hashlib
from pathlib import Path

from doe.design import as_typed
from doe.infra.files import write_json
from fab.package.masks import DATA_POLARITY, RESIST_TONE

MANIFEST_NAME = "fab_manifest.json"
GDS_NAME = "mask.gds"
OASIS_NAME = "mask.oas"
LEVELS_FILE = "levels.npy"
TARGET_PSF_FILE = "target_psf.npy"

ORIENTATION = (
    "Viewed onto the patterned surface, right-reading: levels.npy row 0 is the top edge "
    "(largest y) and column 0 the left edge (smallest x) of every tile; pixel (r, c) covers "
    "x in [c p, (c+1) p], y in [(N-1-r) p, (N-r) p] from the tile origin. For a chrome-down "
    "(contact or proximity) exposure the mask writer must mirror the data (about the y axis) "
    "so the pattern lands right-reading on the substrate."
)


def build_manifest(design, derived, layout, masks, acceptance=None, extra=None, kernel_size=None):
    """Return the manifest dict.

    Parameters
    ----------
    design : doe.design.Design
    derived : doe.design.Derived
        Derived quantities for the tile's N (``derive(design, tile_pixels=N)``).
    layout : layouts.gds.PlateLayout
        Cell names, pitch, tiles and array origin of the written GDS.
    masks : list of fab.package.masks.Mask
    acceptance : dict or None
        Pass/fail thresholds from the tolerance analysis.
    extra : dict or None
        Further keys (e.g. "oasis", "target_psf_source").
    kernel_size : int or None
        K of the target PSF the plate was made for (default the design's): the
        window verify measures and the tolerances were computed on.
    """
    n, p_nm = layout.tile_pixels, layout.pixel_pitch_nm
    step_nm = derived.level_step * 1e9
    tile_size = n * p_nm * 1e-9
    manifest = {
        "wavelength_nm": as_typed(design.optics.wavelength, 1e9),
        "refractive_index": derived.refractive_index,
        "levels": design.fabrication.levels,
        "level_step_nm": step_nm,
        "pixel_pitch_nm": int(p_nm),
        "tile_pixels": int(n),
        "tiles": [int(t) for t in layout.tiles],
        "array_origin_nm": [int(v) for v in layout.array_origin_nm],
        "gds": GDS_NAME,
        "top_cell": layout.top_cell,
        "tile_cell": layout.tile_cell,
        "levels_file": LEVELS_FILE,
        "masks": [
            {
                "name": mk.name,
                "gds_layer": mk.gds_layer,
                "gds_datatype": mk.gds_datatype,
                "etch_depth_nm": mk.steps * step_nm,
                "etch_steps": mk.steps,
                "exposure_order": mk.exposure_order,
            }
            for mk in masks
        ],
        "design_name": design.name,
        "material": design.material.name,
        "substrate_thickness_mm": as_typed(design.material.thickness, 1e3),
        "kernel_size": int(kernel_size or design.kernel_size),
        "focal_length_mm": as_typed(design.optics.focal_length, 1e3),
        "tile_size_um": n * p_nm / 1000,
        "lattice_pitch_um": design.optics.wavelength * design.optics.focal_length / tile_size * 1e6,
        "aperture_mm": as_typed(design.fabrication.aperture, 1e3),
        "target_psf_file": TARGET_PSF_FILE,
        "resist_tone": RESIST_TONE,
        "data_polarity": DATA_POLARITY,
        "orientation": ORIENTATION,
        "marks_layers": [
            {
                "gds_layer": ml.gds_layer,
                "gds_datatype": ml.gds_datatype,
                "purpose": ml.purpose,
                "merge_with_mask": ml.merge_with_mask,
            }
            for ml in layout.mark_layers
        ],
        "acceptance": dict(acceptance) if acceptance else None,
    }
    manifest.update(extra or {})
    return manifest


def write_manifest(out_dir, manifest):
    """Write ``fab_manifest.json`` into ``out_dir``; return its file name."""
    write_json(Path(out_dir) / MANIFEST_NAME, manifest)
    return MANIFEST_NAME


def file_records(out_dir, names):
    """Return [{"path", "sha256", "bytes"}] for the named files of ``out_dir`` (sorted by path)."""
    out = []
    for name in sorted(names):
        data = (Path(out_dir) / name).read_bytes()
        out.append({"path": name, "sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)})
    return out
