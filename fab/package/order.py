"""The photomask order sheet: ``mask_order.md`` and ``mask_order.json`` (``doefab fab``).

One entry per mask with what a mask shop asks for: the GDS file, cell and
layer/datatype, tone and polarity, mirroring, write grid and address unit, CD and
its tolerance, field and plate size, blank size and material, exposure order and
etch depth; plus what not to write (layer 200) and the die layout. Everything is
taken from the package's manifest (which the GDS was written from), so the sheet,
the manifest and the file agree. Only ``doefab fab`` writes the sheet; nothing
reads it back.
"""

from doe.infra.files import atomic_write_bytes, write_json
from fab.package.manifest import file_records

ORDER_MD = "mask_order.md"
ORDER_JSON = "mask_order.json"
ORDER_FILES = (ORDER_MD, ORDER_JSON)

TONE = "dark field"
POLARITY = (
    "clear (chrome removed) = the drawn polygons = area to etch; chrome = everything "
    "not drawn (positive resist on the substrate)"
)
MIRRORING = (
    "right-reading chrome-down (RRCD): the GDS is drawn as seen looking onto the "
    "patterned surface of the plate, right-reading (docs/CONVENTIONS.md: row 0 at the "
    "top, column 0 at the left); the mask must read right looking through the glass "
    "at the chrome, i.e. the chrome side viewed directly is the data mirrored about "
    "the y axis, so that a chrome-down contact or proximity exposure prints the GDS "
    "as drawn. Do not mirror the data file itself"
)
# Standard photomask blanks: (name, side mm, thickness mm, default material).
BLANKS = (
    ('5" x 5" x 0.090" (5009)', 127.0, 2.29),
    ('6" x 6" x 0.250" (6025)', 152.4, 6.35),
    ('7" x 7" x 0.150" (7015)', 177.8, 3.81),
)
BLANK_BORDER_MM = 12.7  # edge exclusion per side (handling and clamping)
SODA_LIME_MIN_CD_UM = 2.0  # below this CD, or on 6" and larger blanks, quartz
BLANK_RULE = (
    f"the smallest standard blank whose area inside a {BLANK_BORDER_MM:g} mm border "
    "holds the field; soda-lime on a 5 inch blank when the CD is at least "
    f"{SODA_LIME_MIN_CD_UM:g} um, else quartz (fused silica); 6 and 7 inch blanks in "
    "quartz; chrome with an anti-reflective layer, resist-coated"
)
CD_RULE = (
    "the mask's CD error may use half the plate's budget (fab/plate/tolerance.py, "
    "cd_bias: every edge moved by +-b, a line width by +-2b), the other half is left "
    "to lithography and etch: mask CD tolerance = +-b"
)
CD_DEFAULT_FRACTION = 0.05  # +-5 % of the CD when the package has no tolerance analysis


def blank_for(field_mm, cd_um):
    """Return the blank dict for a square field of ``field_mm`` and the smallest CD (um)."""
    for name, side, thickness in BLANKS:
        if field_mm <= side - 2 * BLANK_BORDER_MM:
            quartz = side > BLANKS[0][1] or cd_um < SODA_LIME_MIN_CD_UM
            return {
                "size": name,
                "side_mm": side,
                "thickness_mm": thickness,
                "material": "quartz (fused silica)" if quartz else "soda-lime glass",
                "coating": "chrome, anti-reflective, positive resist",
                "rule": BLANK_RULE,
            }
    return {
        "size": "custom (larger than a 7 inch blank)",
        "side_mm": None,
        "thickness_mm": None,
        "material": "quartz (fused silica)",
        "coating": "chrome, anti-reflective, positive resist",
        "rule": BLANK_RULE,
    }


def cd_tolerance(pitch_nm, tolerance):
    """Return (tolerance nm, source) of the mask's CD from the tolerance budget."""
    budget = {(x["kind"], x["mask"]): x for x in (tolerance or {}).get("budget", [])}
    cd = budget.get(("cd_bias", "all"))
    if cd is None:
        value = CD_DEFAULT_FRACTION * pitch_nm
        return value, (
            f"stated default: +-{CD_DEFAULT_FRACTION:.0%} of the CD (the package has no "
            "CD budget from a tolerance analysis)"
        )
    edge_nm = cd["value"] * 1000  # budget value in um
    whole = "" if cd["limited_by_rmse"] else " (the whole tested range passes: at least)"
    return edge_nm, f"{CD_RULE}; b = {edge_nm:.0f} nm{whole}"


def build_mask_order(manifest, out_dir, tolerance=None):
    """Return the order sheet as a dict, from the manifest and the written GDS in ``out_dir``.

    Parameters
    ----------
    manifest : dict
        ``fab_manifest.json``'s fields (with :func:`fab.package.manifest.layout_keys`).
    out_dir : path
        The package's folder holding the GDS (for its size and SHA-256).
    tolerance : dict or None
        ``fab.plate.tolerance.tolerance_analysis``'s result (the CD budget).
    """
    m = manifest
    # the narrowest line or space drawn: one tile pixel, or a mark at the feature size
    cd_nm = min(int(m["pixel_pitch_nm"]), int(m["mark_feature_nm"]))
    tol_nm, tol_source = cd_tolerance(cd_nm, tolerance)
    plate_nm = [int(v) for v in m["plate_size_nm"]]
    dies = m["dies"]
    field_nm = [
        (int(dies["nx"]) - 1) * int(dies["pitch_nm"][0]) + plate_nm[0],
        (int(dies["ny"]) - 1) * int(dies["pitch_nm"][1]) + plate_nm[1],
    ]
    blank = blank_for(max(field_nm) / 1e6, cd_nm / 1000)
    (gds,) = file_records(out_dir, [m["gds"]])
    outline = [ml for ml in m.get("marks_layers", []) if ml.get("merge_with_mask") is None]
    masks = sorted(m["masks"], key=lambda mk: mk["exposure_order"])
    cds = m["cd_structures"]
    entries = [
        {
            "mask": mk["name"],
            "exposure_order": mk["exposure_order"],
            "gds_file": m["gds"],
            "cell": m["top_cell"],
            "gds_layer": mk["gds_layer"],
            "gds_datatype": mk["gds_datatype"],
            "tone": TONE,
            "polarity": POLARITY,
            "mirroring": MIRRORING,
            "write_grid_nm": m["write_grid_nm"],
            "address_unit_nm": m["write_grid_nm"],
            "cd_nm": cd_nm,
            "cd_tolerance_nm": tol_nm,
            "cd_tolerance_source": tol_source,
            "cd_structures_width_nm": sorted(
                {c["width_nm"] for c in cds if c["gds_layer"] == mk["gds_layer"]}
            ),
            "field_size_nm": field_nm,
            "plate_size_nm": plate_nm,
            "blank": blank,
            "etch_depth_nm": mk["etch_depth_nm"],
        }
        for mk in masks
    ]
    return {
        "design_name": m["design_name"],
        "gds": {
            "file": gds["path"],
            "sha256": gds["sha256"],
            "bytes": gds["bytes"],
            "top_cell": m["top_cell"],
            "user_unit_m": m["gds_unit_m"],
            "database_unit_m": m["gds_precision_m"],
        },
        "do_not_write": [
            {
                "gds_layer": ml["gds_layer"],
                "gds_datatype": ml["gds_datatype"],
                "content": ml["purpose"],
            }
            for ml in outline
        ],
        "dies": {**dies, "field_size_nm": field_nm},
        "coordinates": "GDS origin at the plate's centre; the field is centred on the blank",
        "masks": entries,
    }


def write_mask_order(out_dir, manifest, tolerance=None):
    """Write ``mask_order.json`` and ``mask_order.md`` into ``out_dir``; return their names."""
    order = build_mask_order(manifest, out_dir, tolerance)
    write_json(out_dir / ORDER_JSON, order)
    atomic_write_bytes(out_dir / ORDER_MD, render_order_markdown(order).encode())
    return list(ORDER_FILES)


def render_order_markdown(order):
    """Return the order sheet as Markdown: the plate-wide facts, then one table per mask."""
    g = order["gds"]
    dies = order["dies"]
    lines = [
        f"# Photomask order: {order['design_name']}",
        "",
        f"- GDS file: `{g['file']}` ({g['bytes']} bytes, SHA-256 `{g['sha256']}`), "
        f"top cell `{g['top_cell']}`",
        f"- GDS units: user unit {g['user_unit_m']:g} m (1 um), database unit "
        f"{g['database_unit_m']:g} m (1 nm)",
        f"- {order['coordinates']}",
        f"- Dies: {dies['nx']} x {dies['ny']} at a pitch of "
        f"{dies['pitch_nm'][0] / 1e6:g} x {dies['pitch_nm'][1] / 1e6:g} mm; field "
        f"{dies['field_size_nm'][0] / 1e6:g} x {dies['field_size_nm'][1] / 1e6:g} mm",
    ]
    lines += [
        f"- DO NOT WRITE layer {d['gds_layer']}/{d['gds_datatype']} ({d['content']})"
        for d in order["do_not_write"]
    ]
    lines.append("")
    for e in order["masks"]:
        b = e["blank"]
        rows = [
            ("exposure order", str(e["exposure_order"])),
            ("GDS file / cell", f"{e['gds_file']} / {e['cell']}"),
            ("layer/datatype", f"{e['gds_layer']}/{e['gds_datatype']}"),
            ("tone", e["tone"]),
            ("polarity", e["polarity"]),
            ("mirroring", e["mirroring"]),
            ("write grid / address unit", f"{e['write_grid_nm']} nm / {e['address_unit_nm']} nm"),
            ("CD", f"{e['cd_nm'] / 1000:g} um (the narrowest line or space: a pixel or a mark)"),
            ("CD tolerance", f"+-{e['cd_tolerance_nm']:.0f} nm: {e['cd_tolerance_source']}"),
            (
                "CD structures (lines = spaces)",
                ", ".join(f"{w / 1000:g} um" for w in e["cd_structures_width_nm"]),
            ),
            (
                "field / plate size",
                f"{e['field_size_nm'][0] / 1e6:g} x {e['field_size_nm'][1] / 1e6:g} mm / "
                f"{e['plate_size_nm'][0] / 1e6:g} x {e['plate_size_nm'][1] / 1e6:g} mm",
            ),
            ("blank", f"{b['size']}, {b['material']}, {b['coating']}"),
            ("blank rule", b["rule"]),
            ("etch depth", f"{e['etch_depth_nm']:.2f} nm"),
        ]
        lines += [f"## {e['mask']}", "", "| field | value |", "|---|---|"]
        lines += [f"| {k} | {v.replace('|', '/')} |" for k, v in rows]
        lines.append("")
    return "\n".join(lines)
