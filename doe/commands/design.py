"""``doefab presets`` and ``doefab config show``."""

import json

from doe.derived import design_summary
from doe.design import DEFAULT_PRESET, load_design, preset_names


def register(sub):
    p = sub.add_parser("presets", help="list the embedded design presets")
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
    return 0


def _show(args):
    summary = design_summary(load_design(args.config))
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"design {summary['name']}: {summary['description']}")
    for section, table in summary.items():
        if isinstance(table, dict):
            print(f"[{section}]")
            for key, value in table.items():
                print(f"  {key:28s} {_fmt(value)}")
    return 0


def _fmt(v):
    if isinstance(v, bool):  # as a design file spells it
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v)
