"""``doefab presets`` and ``doefab config show``."""

import json
import sys

from doe.derived import design_summary
from doe.design import DEFAULT_PRESET, load_design, preset_names
from doe.tiling import summary_line, tiling


def register(sub):
    p = sub.add_parser(
        "presets", help="list the embedded design presets and whether their tiling works"
    )
    p.set_defaults(func=_presets)
    p = sub.add_parser("config", help="show a resolved design with its derived optics")
    csub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    show = csub.add_parser("show", help="print the resolved design")
    show.add_argument(
        "--config", help="design TOML file or preset name (default: the default preset)"
    )
    show.add_argument("--json", action="store_true", help="print JSON instead of a table")
    show.set_defaults(func=_show)


def _presets(args):
    for name in preset_names():
        d = load_design(name)
        mark = " (default)" if name == DEFAULT_PRESET else ""
        print(f"{name}{mark}: {d.description}")
        print(f"  tiling {summary_line(tiling(d))}")
    return 0


def _show(args):
    design = load_design(args.config)  # a design that makes no dot lattice is refused here
    t = tiling(design)
    summary = {**design_summary(design), "tiling": _tiling_table(t)}
    if args.json:  # the reasons and fixes are sentences: the table prints them as warnings
        summary.update(tiling_problems=list(t.problems), tiling_fixes=list(t.fixes))
        print(json.dumps(summary, indent=2))
        return 0
    print(f"design {summary['name']}: {summary['description']}")
    for section, table in summary.items():
        if isinstance(table, dict):
            print(f"[{section}]")
            for key, value in table.items():
                print(f"  {key:28s} {_fmt(value)}")
    if t.verdict != "ok":
        for problem in t.problems:
            print(f"warning: the tiling is marginal: {problem}", file=sys.stderr)
        print(f"warning: to fix it change {', or '.join(t.fixes)}", file=sys.stderr)
    return 0


def _tiling_table(t):
    """The tiling figures and verdict (doe/tiling.py), the design file's units in the keys."""
    return {
        "verdict": t.verdict,
        "tiles_across": t.tiles,
        "aperture_over_tile": t.tiles_exact,
        "dot_power_in_subpixel": t.own_cell_power,
        "f_number": t.f_number,
        "dot_diameter_um": t.dot_diameter * 1e6,
        "active_area_um": t.active_area * 1e6,
        "lattice_drift_relative": t.lattice_mismatch / t.subpixel_pitch,
        "kernel_edge_drift_um": t.kernel_edge_offset * 1e6,
        "sensor_edge_drift_um": t.drift_at_edge * 1e6,
    }


def _fmt(v):
    if isinstance(v, bool):  # as a design file spells it
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v)
