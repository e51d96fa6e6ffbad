"""The plate's design rules as a KLayout DRC script (``.lydrc``), for a lab or mask shop.

Run it in KLayout's batch mode on the written GDS::

    klayout -b -r drc.lydrc -rd input=mask.gds -rd report=drc_klayout.lyrdb

(``-rd flat=1`` checks the flattened plate instead of hierarchically; the counts are
the same.) It writes one category per layer and rule, named as
:func:`layouts.drc_rdb.category_name` names those of ``doefab fab``'s own marker
database, and prints each count, so the two can be compared line by line. In the
GUI, Macros > Macro Development opens it under DRC and runs it on the layout shown.
"""

from xml.sax.saxutils import escape

from layouts.drc import RULES
from layouts.drc_rdb import category_name, category_text

_CHECKS = {
    "width": "l.width({w}, euclidian)",
    "space": "l.space({s}, euclidian)",
    "notch": "l.notch({s}, euclidian)",
    "area": "l.with_area(nil, {a})",
    "off_grid": "l.ongrid({g})",
}


def deck_text(rules, design_name=""):
    """Return the Ruby DRC script (the DSL) of ``rules``.

    Parameters
    ----------
    rules : layouts.drc.DrcRules
    design_name : str
        Named in the header comment and the report's description.
    """
    w, s = f"{rules.min_width_nm / 1000:g}.um", f"{rules.min_space_nm / 1000:g}.um"
    a = f"{rules.min_area_nm2 / 1e6:g}.um2"
    g = f"{rules.grid_nm / 1000:g}.um"
    limits = rules.limits()
    lines = [
        f"# doefab design-rule deck: {design_name}",
        "# Rules per mask layer (pattern and marks; layer 200, the outline, is not written",
        "# and not checked):",
        *(f"#   {rule}: {limits[rule]}" for rule in RULES),
        "# Run: klayout -b -r drc.lydrc -rd input=mask.gds -rd report=drc_klayout.lyrdb",
        "",
        "source($input) if $input",
        f'report("doefab DRC {_ruby(design_name)}", $report || "drc_klayout.lyrdb")',
        "$flat ? flat : deep",
        "verbose(false)",
        "",
    ]
    for layer in rules.layers:
        lines.append(f"l = input({layer}, 0)")
        for rule in RULES:
            check = _CHECKS[rule].format(w=w, s=s, a=a, g=g)
            name = category_name(layer, rule)
            lines += [
                f"m = {check}",
                f'm.output("{name}", "{_ruby(category_text(layer, rule, limits[rule]))}")',
                f'puts "{name} #{{m.count}}"',
            ]
        lines.append("")
    return "\n".join(lines)


def deck_xml(rules, design_name=""):
    """Return the deck as a KLayout macro file (``.lydrc``: the script in XML)."""
    return (
        '<?xml version="1.0" encoding="utf-8"?>\n'
        "<klayout-macro>\n"
        f" <description>doefab DRC {escape(design_name)}</description>\n"
        " <version/>\n <category>drc</category>\n <prolog/>\n <epilog/>\n <doc/>\n"
        " <autorun>false</autorun>\n <autorun-early>false</autorun-early>\n <shortcut/>\n"
        " <show-in-menu>false</show-in-menu>\n <group-name>drc_scripts</group-name>\n"
        " <menu-path>tools_menu.drc.end</menu-path>\n <interpreter>dsl</interpreter>\n"
        " <dsl-interpreter-name>drc-dsl-xml</dsl-interpreter-name>\n"
        f" <text>{escape(deck_text(rules, design_name))}</text>\n"
        "</klayout-macro>\n"
    )


def _ruby(text):
    """Text safe inside a double-quoted Ruby string."""
    return str(text).replace("\\", "\\\\").replace('"', '\\"').replace("#", "\\#")
