"""The fab report's "Design rules" section: what was checked, what was found, what was allowed.

Read from the manifest's ``drc`` block (:func:`doe.records.fab_manifest.drc_record`).
"""

RULE_TEXT = {
    "width": "width",
    "space": "space (between and inside polygons)",
    "notch": "notch (space inside a polygon)",
    "area": "area",
    "off_grid": "vertex on grid",
}


def drc_blocks(manifest):
    """Return the report blocks of the design-rule check (none for a manifest without one)."""
    drc = manifest.get("drc")
    if not drc:
        return []
    rules = drc["rules"]
    b = [("h2", "Design rules")]
    b.append(
        (
            "p",
            f"Every mask layer ({', '.join(f'{x}/0' for x in rules['layers'])}; pattern and "
            "marks together, the outline layer is not checked) was checked with KLayout on the "
            f"whole plate: width and space at least {rules['min_width_nm'] / 1000:g} um "
            f"(the feature size; Euclidean, so pixels touching only at a corner are a width "
            f"and a space of 0), area at least {rules['min_area_um2']:g} um^2, vertices on the "
            f"{rules['grid_nm']} nm grid. The same rules as a KLayout DRC script: "
            f"{drc['deck']} (klayout -b -r {drc['deck']} -rd input=mask.gds -rd "
            f"report=drc_klayout.lyrdb); the markers: {drc['markers']} "
            f"(klayout mask.gds -m {drc['markers']}).",
        )
    )
    b.append(("p", verdict(drc)))
    rows = [_row(c, rules) for c in drc["counts"] if c["count"]]
    if rows:
        header = ["layer", "rule", "count", "at corner contacts", "where (x, y um)"]
        b.append(("table", header, rows))
    contacts = {k: v for k, v in drc.get("corner_contacts", {}).items() if v}
    if contacts:
        listed = ", ".join(f"layer {k}: {v}" for k, v in contacts.items())
        b.append(("p", f"Points where pixels touch only at a corner: {listed}."))
    return b


def verdict(drc):
    """One sentence: clean, or what was allowed and by what."""
    total = drc["total"]
    corners = sum(c["at_corner_contacts"] for c in drc["counts"])
    if total == 0:
        return "No violations."
    parts = [f"{total} markers"]
    if drc.get("corner_contacts_allowed") and corners:
        parts.append(
            f"{corners} of them at corner contacts, which the design's process accepts "
            "([fabrication] allow_corner_contacts = true)"
        )
    if drc.get("violations_allowed"):
        parts.append("ALLOWED by --allow-drc: this plate breaks the design rules listed below")
    return "; ".join(parts) + "."


def _row(c, rules):
    where = "; ".join(f"({x:.3f}, {y:.3f})" for x, y in c["examples_um"])
    return [
        f"{c['layer']}/0",
        f"{RULE_TEXT.get(c['rule'], c['rule'])} {rules['checks'].get(c['rule'], '')}".strip(),
        str(c["count"]),
        str(c["at_corner_contacts"]),
        where,
    ]
