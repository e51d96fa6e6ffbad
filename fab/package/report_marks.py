"""The fab report's section on the marks, process monitors and the mask order sheet.

Read from the manifest's keys (``fab.package.manifest.layout_keys``), the same
figures the order sheet and the GDS were made from.
"""


def marks_blocks(manifest):
    """Return the report blocks of the marks, etch-depth pads, CD structures and order sheet.

    Empty when the manifest has no such keys (a package written without marks).
    """
    m = manifest
    if "etch_pads" not in m:
        return []
    v = m["vernier"]
    plate = m["plate_size_nm"]
    b = [("h2", "Marks, process monitors and the order sheet")]
    b.append(
        (
            "p",
            f"GDS units: user unit {m['gds_unit_m']:g} m (1 um), database unit "
            f"{m['gds_precision_m']:g} m (1 nm); write grid {m['write_grid_nm']} nm. Plate "
            f"(outer edge of layer 200): {plate[0] / 1e6:g} x {plate[1] / 1e6:g} mm, centred "
            "on the GDS origin.",
        )
    )
    b.append(
        (
            "p",
            f"Every mark, label stroke and monitor, and every gap between them, is at least "
            f"{m['mark_feature_nm'] / 1000:g} um wide on each mask layer. Vernier: bars "
            f"{v['bar_nm'] / 1000:g} um, later mask's pitch {v['pitch_nm'] / 1000:g} um, "
            f"reference pitch {v['reference_pitch_nm'] / 1000:g} um: resolution "
            f"{v['resolution_nm'] / 1000:g} um per bar, range +-{v['range_nm'] / 1000:g} um.",
        )
    )
    b.append(
        (
            "p",
            "Etch-depth pads: clear squares etched by the masks listed, so that a stylus "
            "profilometer run from the unetched glass across a pad reads the depth of the "
            "level named (single etches and every combination).",
        )
    )
    b.append(
        (
            "table",
            ["level", "steps", "depth (nm)", "etched by", "GDS layers", "centre (mm)", "size (um)"],
            [
                [
                    str(p["level"]),
                    str(p["code_steps"]),
                    f"{p['depth_nm']:.2f}",
                    ", ".join(p["masks"]),
                    ", ".join(str(x) for x in p["gds_layers"]),
                    _mm(p["centre_nm"]),
                    f"{p['size_nm'] / 1000:g} x {p['size_nm'] / 1000:g}",
                ]
                for p in m["etch_pads"]
            ],
        )
    )
    b.append(
        (
            "p",
            "CD test structures: gratings of equal lines (drawn, etched) and spaces, "
            "at 1x, 1.5x and 2x the feature size, lines along y (vertical) and along x.",
        )
    )
    b.append(
        (
            "table",
            ["mask", "GDS layer", "line = space (um)", "lines", "orientation", "centre (mm)"],
            [
                [
                    c["mask"],
                    str(c["gds_layer"]),
                    f"{c['width_nm'] / 1000:g}",
                    str(c["lines"]),
                    c["orientation"],
                    _mm(c["centre_nm"]),
                ]
                for c in m["cd_structures"]
            ],
        )
    )
    dies = m["dies"]
    files = " and ".join(m.get("mask_order", []))
    b.append(
        (
            "p",
            f"Order sheet: {files} (one entry per mask: GDS file, cell, layer, tone, "
            "polarity, mirroring, write grid, CD and tolerance, field, plate and blank, "
            f"exposure order and etch depth). Dies: {dies['nx']} x {dies['ny']}.",
        )
    )
    return b


def _mm(xy):
    return f"({xy[0] / 1e6:.3f}, {xy[1] / 1e6:.3f})"
