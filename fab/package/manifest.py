"""The file records of a fabrication package: each file's SHA-256 and size.

The manifest itself (``fab_manifest.json``) is written and read by
:mod:`doe.records.fab_manifest`.
"""

import hashlib
from pathlib import Path


def file_records(out_dir, names):
    """Return [{"path", "sha256", "bytes"}] for the named files of ``out_dir`` (sorted by path)."""
    out = []
    for name in sorted(names):
        data = (Path(out_dir) / name).read_bytes()
        out.append({"path": name, "sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)})
    return out


def layout_keys(layout, masks, n_levels, level_step_nm, order_files=()):
    """Return the manifest keys of what the GDS holds beyond the tile.

    The GDS units, the write grid, the plate's outer size, the marks' feature size
    and vernier, each etch-depth pad (position, size, masks, depth and level), each
    CD structure, the die layout (``layout.dies``, a ``layouts.plate_plan.DieLayout``:
    dies, pitch, lane, plate and substrate size), and the order sheet's files.

    Parameters
    ----------
    layout : layouts.gds.PlateLayout
    masks : list of fab.package.masks.Mask
    n_levels : int
    level_step_nm : float
    order_files : sequence of str
        The order sheet's files (``fab.package.order``).
    """
    from layouts.gds import GDS_PRECISION, GDS_UNIT

    rules = layout.mark_rules
    name = {mk.gds_layer: mk.name for mk in masks}
    plate = 2 * int(layout.plate_half_nm)
    dies = getattr(layout, "dies", None)  # layouts.plate_plan.DieLayout
    return {
        "gds_unit_m": GDS_UNIT,
        "gds_precision_m": GDS_PRECISION,
        "write_grid_nm": int(rules.grid_nm),
        "plate_size_nm": [plate, plate],
        "mark_feature_nm": int(rules.feature_nm),
        "vernier": {
            "bar_nm": rules.bar_nm,
            "pitch_nm": rules.pitch_nm,
            "reference_pitch_nm": rules.ref_pitch_nm,
            "resolution_nm": rules.resolution_nm,
            "range_nm": rules.reading_range_nm,
        },
        "etch_pads": [
            {
                "code_steps": pad.code,
                "level": n_levels - 1 - pad.code,
                "depth_nm": pad.code * level_step_nm,
                "centre_nm": list(pad.centre_nm),
                "size_nm": pad.size_nm,
                "gds_layers": list(pad.layers),
                "masks": [name[layer] for layer in pad.layers],
            }
            for pad in layout.pads
        ],
        "cd_structures": [
            {
                "gds_layer": cd.layer,
                "mask": name[cd.layer],
                "width_nm": cd.width_nm,
                "lines": cd.lines,
                "orientation": cd.orientation,
                "centre_nm": list(cd.centre_nm),
                "length_nm": cd.length_nm,
            }
            for cd in layout.cd_structures
        ],
        "dies": dies.as_dict() if dies else {"nx": 1, "ny": 1, "pitch_nm": [plate, plate]},
        "mask_order": list(order_files),
    }
