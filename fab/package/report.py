"""The fabrication report: ``fab_report.md``, ``fab_report.html`` and their figures.

The report is what a process engineer works from: what to etch, how deep, in
which order, which way up, how precisely, and which files carry it. One list
of blocks (headings, paragraphs, tables, figures) is rendered twice, to
Markdown and, through the template ``fab/templates/fab_report.html``, to
self-contained HTML (the shared stylesheet inline, figures as relative PNG
links), so the two never disagree. Output is deterministic for the same input.
"""

import math
import re
from pathlib import Path

import numpy as np

from doe.figures import correlation_text
from doe.fraunhofer import correlation, level_phase, rmse
from doe.goals import goals_missed
from doe.infra.files import atomic_write_bytes, write_json
from doe.materials import TABLE_KEY, index_source
from fab.package.drc_report import drc_blocks
from fab.package.layer_images import layer_image_blocks
from fab.package.manifest import file_records
from fab.package.polarity import masks_figure_description
from fab.package.report_camera import camera_blocks, camera_figures
from fab.package.report_marks import marks_blocks
from fab.package.report_plate import plate_blocks, summary_rows
from fab.templates import render_page

REPORT_MD = "fab_report.md"
REPORT_HTML = "fab_report.html"
TOLERANCE_JSON = "fab_tolerance.json"
FIGURES = {
    "levels": "fab_fig_levels.png",
    "masks": "fab_fig_masks.png",
    "psf": "fab_fig_psf.png",
    "lattice": "fab_fig_lattice.png",
    "tolerance": "fab_fig_tolerance.png",
}

CHROME_DOWN = (
    "Chrome-down exposure (contact or proximity printing, the usual case): the "
    "photomask must be written MIRRORED (about the y axis) relative to the GDS, i.e. "
    "order it 'right-reading chrome-down', so that the pattern lands right-reading on "
    "the substrate. Mirror every mask (and its alignment marks) the same way. A plate "
    "printed from unmirrored data yields a mirrored phase tile and a mirrored PSF."
)


def write_fab_report(out_dir, context):
    """Write the report, its figures and the tolerance table into ``out_dir``.

    Parameters
    ----------
    out_dir : path
        Folder to write into (normally the staging folder of ``doefab fab``).
    context : dict
        "design" (``design_summary``), "manifest" (fab_manifest dict), "masks"
        (list of dicts: name, gds_layer, etch_depth_nm, exposure_order,
        fill_fraction, polygon_count, min_feature_um), "levels" ((N, N) uint8),
        "target_psf", "simulated_psf" ((K, K)), "efficiency" (float),
        "tolerance" (``fab.plate.tolerance.tolerance_analysis`` dict or None),
        "orientation" (str), "files" (list of {"path", "sha256", "bytes"}).

    Returns
    -------
    list of str
        Names of the files written, relative to ``out_dir``.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = _write_figures(out_dir, context)
    tolerance = context.get("tolerance")
    if tolerance is not None:
        write_json(out_dir / TOLERANCE_JSON, tolerance)
        written.append(TOLERANCE_JSON)
    # The figures and the table are part of the package too: list them with the
    # rest (the report cannot list its own two files, whose hashes it would change).
    files = [*context.get("files", []), *file_records(out_dir, written)]
    context = {**context, "files": sorted(files, key=lambda f: f["path"])}
    blocks = report_blocks(context, figures=written)
    atomic_write_bytes(out_dir / REPORT_MD, render_markdown(blocks).encode())
    atomic_write_bytes(out_dir / REPORT_HTML, render_html(blocks).encode())
    return [REPORT_MD, REPORT_HTML, *written]


def _write_figures(out_dir, context):
    from fab.package import figures

    man = context["manifest"]
    levels = np.asarray(context["levels"])
    n_levels = int(man["levels"])
    pitch = man["pixel_pitch_nm"] * 1e-9
    written = []
    figures.level_map(out_dir / FIGURES["levels"], levels, n_levels, pitch)
    written.append(FIGURES["levels"])
    names, bitmaps, depths = _mask_bitmaps(levels, n_levels, man)
    figures.mask_bitmaps(out_dir / FIGURES["masks"], bitmaps, names, depths, pitch)
    written.append(FIGURES["masks"])
    figures.psf_comparison(
        out_dir / FIGURES["psf"],
        np.asarray(context["target_psf"]),
        np.asarray(context["simulated_psf"]),
    )
    written.append(FIGURES["psf"])
    lattice = man.get("lattice_pitch_um", context["design"]["derived"]["lattice_pitch_um"])
    figures.dot_lattice(
        out_dir / FIGURES["lattice"],
        level_phase(levels, n_levels),
        context["design"]["sensor"],
        lattice * 1e-6,
    )
    written.append(FIGURES["lattice"])
    if context.get("tolerance") is not None:
        figures.tolerance_curves(out_dir / FIGURES["tolerance"], context["tolerance"])
        written.append(FIGURES["tolerance"])
    return written + camera_figures(out_dir, context)


def _mask_bitmaps(levels, n_levels, manifest):
    """Return names, bitmaps and depths (nm) of the masks, rebuilt from the level map."""
    from fab.package.masks import masks_from_levels

    step = manifest["level_step_nm"] * 1e-9
    masks = masks_from_levels(levels, n_levels, step)
    return (
        [mk.name for mk in masks],
        [mk.bitmap for mk in masks],
        [mk.etch_depth * 1e9 for mk in masks],
    )


# ---------------------------------------------------------------- content


def report_blocks(context, figures=()):
    """Return the report as a list of blocks: (kind, ...) tuples rendered by both writers.

    Kinds: ("h1"|"h2"|"h3", text), ("p", text), ("ul"|"ol", [text]),
    ("table", header, rows), ("fig", file, caption).

    Parameters
    ----------
    context : dict
        As for :func:`write_fab_report`.
    figures : sequence of str
        Names of the figures written; each known one gets its captioned block.
    """
    d = context["design"]
    tol = context.get("tolerance")
    b = [("h1", f"Fabrication report: {d['name']}")]
    if d.get("description"):
        b.append(("p", d["description"]))
    b.append(
        (
            "p",
            "Written by doefab fab. Lengths carry their unit; every figure and file "
            "named here lies in this folder.",
        )
    )
    b += _summary_blocks(context)
    b += _design_blocks(d)
    b += _material_blocks(d, context["manifest"])
    b += _process_blocks(context)
    b += marks_blocks(context["manifest"]) + drc_blocks(context["manifest"])
    b += plate_blocks(context)
    b.append(("h2", "Orientation"))
    b.append(("p", context.get("orientation") or context["manifest"].get("orientation", "")))
    b.append(("p", CHROME_DOWN))
    b.append(("h2", "Figures"))
    b += [("fig", name, FIGURE_CAPTIONS[name]) for name in figures if name in FIGURE_CAPTIONS]
    b += layer_image_blocks(m["name"] for m in _sorted_masks(context))
    b.append(("h2", "Tolerances"))
    if tol is None:
        b.append(("p", "No tolerance analysis in this build."))
    else:
        b.extend(_tolerance_blocks(tol))
    b += camera_blocks(context)
    b.append(("h2", "Files"))
    b.append(("p", f"Every file of the package but {REPORT_MD} and {REPORT_HTML} themselves."))
    b.append(
        (
            "table",
            ["file", "bytes", "SHA-256"],
            [[f["path"], str(f["bytes"]), f["sha256"]] for f in context.get("files", [])],
        )
    )
    return b


FIGURE_CAPTIONS = {
    FIGURES["levels"]: "Level map of one tile (level l = l steps of glass above the floor).",
    FIGURES["masks"]: masks_figure_description(),
    FIGURES["psf"]: "Target and simulated PSF (nominal levels) and their difference.",
    FIGURES["lattice"]: "Simulated dot lattice on the sensor: SPAD pixels (white), "
    "active areas (cyan), sub-pixel grid (faint); zero order on the "
    "centre of the central pixel's active area; spots drawn 0.8 render "
    "pixels wide for visibility.",
    FIGURES["tolerance"]: "rmse against each fabrication error; dashed: rmse limit, "
    "dotted: budget.",
}


def _sorted_masks(context):
    return sorted(context["masks"], key=lambda m: m["exposure_order"])


def _summary_blocks(context):
    """The Summary: levels, depths, pitch, tiles, efficiency and the design goals."""
    man = context["manifest"]
    masks = _sorted_masks(context)
    target = np.asarray(context["target_psf"], float)
    sim = np.asarray(context["simulated_psf"], float)
    fit = {"correlation": correlation(sim, target), "rmse": rmse(sim, target)}
    missed, plate_missed = goals_missed(context["levels"], man["levels"], target, sim)
    step = man["level_step_nm"]
    n_levels = man["levels"]
    rows = [
        ["phase levels / masks", f"{n_levels} / {len(masks)}"],
        ["step height", f"{step:.2f} nm"],
        ["total depth (deepest floor to top)", f"{(n_levels - 1) * step:.2f} nm"],
        [
            "etch depths, exposure order",
            ", ".join(f"{m['name']} {m['etch_depth_nm']:.2f} nm" for m in masks),
        ],
        ["mask pixel pitch", f"{man['pixel_pitch_nm']} nm"],
        ["tile", f"{man['tile_pixels']} x {man['tile_pixels']} pixels"],
        ["tiles", " x ".join(str(t) for t in man["tiles"])],
        ["window efficiency (nominal)", f"{context['efficiency']:.4f}"],
        [
            "correlation / rmse vs target (nominal)",
            f"{correlation_text(fit['correlation'])} / {fit['rmse']:.5f}",
        ],
        *summary_rows(context, missed, plate_missed),
    ]
    return [("h2", "Summary"), ("table", ["quantity", "value"], rows)]


def _design_blocks(design):
    """Every value of the design and of the optics derived from it."""
    rows = []
    for section in ("sensor", "optics", "psf", "fabrication", "derived"):
        for key, value in design.get(section, {}).items():
            rows.append([f"{section}.{key}", _fmt(value)])
    return [("h2", "Design and derived optics"), ("table", ["key", "value"], rows)]


def _material_blocks(design, man):
    step = man["level_step_nm"]
    material = design["material"]
    how = "index table" if TABLE_KEY in material else "Sellmeier"
    rows = [
        ["substrate", str(material["name"])],
        ["source of the index", index_source(material)],
        ["thickness", f"{material['thickness_mm']:g} mm"],
        ["design wavelength", f"{man['wavelength_nm']:g} nm"],
        [f"refractive index at the design wavelength ({how})", f"{man['refractive_index']:.5f}"],
        ["step height lambda / ((n - 1) L)", f"{step:.2f} nm"],
    ]
    return [("h2", "Material"), ("table", ["quantity", "value"], rows)]


def _process_blocks(context):
    """The Process: polarity, tone, GDS cells, the mask table and the exposure steps."""
    man = context["manifest"]
    masks = _sorted_masks(context)
    tol = context.get("tolerance")
    b = [("h2", "Process")]
    b.append(("p", f"Data polarity: {man.get('data_polarity', 'a polygon marks area to etch')}."))
    b.append(("p", f"Resist tone: {man.get('resist_tone', 'positive resist, dark-field mask')}."))
    b.append(
        (
            "p",
            f"GDS: {man.get('gds', '')}, top cell {man.get('top_cell', '')}, tile cell "
            f"{man.get('tile_cell', '')}, array origin "
            f"{_fmt(man.get('array_origin_nm', ''))} nm (lower-left of the tiled area).",
        )
    )
    budget = {(x["kind"], x["mask"]): x for x in tol["budget"]} if tol else {}
    b.append(("table", MASK_TABLE_HEADER, [_mask_row(m, budget, tol) for m in masks]))
    steps = [
        f"Expose {m['name']} (GDS layer {m['gds_layer']}), develop, etch "
        f"{m['etch_depth_nm']:.2f} nm, strip the resist"
        + ("; this level is the overlay reference" if i == 0 else "; align to the first level")
        for i, m in enumerate(masks)
    ]
    b.append(("ol", steps))
    if budget.get(("cd_bias", "all")):
        cd = budget[("cd_bias", "all")]
        b.append(
            (
                "p",
                f"Critical dimension: every edge may move by +-{cd['value']:.3f} um (all "
                "masks)" + ("." if cd["limited_by_rmse"] else "; the whole tested range passes."),
            )
        )
    for ml in man.get("marks_layers") or []:
        b.append(
            (
                "p",
                f"Marks layer {ml.get('gds_layer')}/{ml.get('gds_datatype')}: "
                f"{ml.get('purpose', '')}",
            )
        )
    return b


MASK_TABLE_HEADER = [
    "exposure",
    "mask",
    "GDS layer/datatype",
    "etch depth (nm)",
    "etch tolerance",
    "overlay tolerance",
    "fill fraction",
    "polygons",
    "min feature (um)",
]


def _mask_row(m, budget, tol):
    """One mask's row of the Process table, with its etch and overlay tolerance."""
    etch_b = budget.get(("etch", m["name"]))
    at_least = "at least " if etch_b and not etch_b["limited_by_rmse"] else ""
    etch_tol = (
        at_least
        + f"+-{etch_b['value']:.2f} % (+-{etch_b['value'] / 100 * m['etch_depth_nm']:.1f} nm)"
        if etch_b
        else "-"
    )
    ov = budget.get(("overlay", m["name"]))
    ov_at_least = "at least " if ov and not ov["limited_by_rmse"] else ""
    ov_tol = f"{ov_at_least}+-{ov['value']:.3f} um" if ov else ("reference" if tol else "-")
    return [
        str(m["exposure_order"]),
        m["name"],
        f"{m['gds_layer']}/{m.get('gds_datatype', 0)}",
        f"{m['etch_depth_nm']:.2f}",
        etch_tol,
        ov_tol,
        f"{m['fill_fraction']:.4f}",
        str(m["polygon_count"]),
        f"{m['min_feature_um']:.3f}",
    ]


def _tolerance_blocks(tol):
    model = tol["model"]
    out = [
        (
            "p",
            f"Model: {model['sampling']}. Etch: {model['etch']}. Overlay: "
            f"{model['overlay']}. CD bias: {model['cd_bias']}.",
        )
    ]
    nom = tol["nominal"]
    out.append(
        (
            "p",
            f"rmse limit {tol['rmse_limit']:.4f} ({model['rmse_limit_rule']}); the "
            f"nominal plate in this model: correlation {_num(nom['correlation'], '.4f')}, "
            f"rmse {nom['rmse']:.4f}, efficiency {nom['efficiency']:.4f}, zero order "
            f"{nom['zero_order']:.2e}. Its efficiency is below the Summary's because the "
            "continuous plate's orders carry each mask pixel's sinc^2 envelope, which the "
            "contract's model (CONVENTIONS.md, the Summary) leaves out; the table's "
            "changes are taken against this nominal plate.",
        )
    )
    out.append(("h3", "Budget"))
    out.append(
        (
            "table",
            ["error", "mask", "largest tolerated", "worst rmse there", "note"],
            [
                [
                    x["kind"],
                    x["mask"],
                    f"+-{x['value']:.3f} {x['unit']}",
                    f"{x['rmse']:.4f}",
                    "limited by rmse" if x["limited_by_rmse"] else "whole tested range passes",
                ]
                for x in tol["budget"]
            ],
        )
    )
    acc = tol["acceptance"]
    out.append(("h3", "Acceptance thresholds (hardware verification)"))
    out.append(
        (
            "table",
            ["threshold", "value"],
            [
                ["correlation_min", _num(acc["correlation_min"], ".6g")],
                ["rmse_max", f"{acc['rmse_max']:.6g}"],
                ["efficiency_min", f"{acc['efficiency_min']:.6g}"],
                ["zero_order_max", f"{acc['zero_order_max']:.6g}"],
                *[
                    ["deep_etch_error_max", f"+-{v:.4g} (its etch budget)"]
                    for v in [acc.get("deep_etch_error_max")]
                    if v is not None
                ],
            ],
        )
    )
    out.append(("p", f"Rule: {model['acceptance_rule']}."))
    out.append(("h3", "Table"))
    out.append(
        (
            "table",
            [
                "error",
                "mask",
                "axis",
                "value",
                "correlation",
                "rmse",
                "efficiency",
                "zero order",
                "zero-order excess",
            ],
            [
                [
                    r["kind"],
                    r["mask"],
                    r["axis"] or "-",
                    f"{r['value']:+.3g} {r['unit']}".strip(),
                    _num(r["correlation"], ".4f"),
                    f"{r['rmse']:.4f}",
                    f"{r['efficiency']:.4f}",
                    f"{r['zero_order']:.2e}",
                    f"{r['zero_order_excess']:+.2e}",
                ]
                for r in tol["rows"]
            ],
        )
    )
    return out


def _num(v, spec):
    """Format a figure; None or NaN (a correlation with a uniform or 1 x 1 PSF) is undefined."""
    return "undefined" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:{spec}}"


def _fmt(v):
    if isinstance(v, float):
        return _num(v, ".6g")
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v)


# ---------------------------------------------------------------- renderers


def render_markdown(blocks):
    """Return the blocks as Markdown; their text is plain text, as in :func:`render_html`."""
    t = _md_text
    lines = []
    for block in blocks:
        kind = block[0]
        if kind in ("h1", "h2", "h3"):
            lines += ["#" * int(kind[1]) + " " + t(block[1]), ""]
        elif kind == "p":
            lines += [t(block[1]), ""]
        elif kind in ("ul", "ol"):
            mark = "-" if kind == "ul" else None
            lines += [f"{mark or f'{i + 1}.'} {t(item)}" for i, item in enumerate(block[1])]
            lines.append("")
        elif kind == "table":
            header, rows = block[1], block[2]
            lines.append("| " + " | ".join(_md_cell(h) for h in header) + " |")
            lines.append("|" + "---|" * len(header))
            lines += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in rows]
            lines.append("")
        elif kind == "fig":
            lines += [f"![{t(block[2])}]({block[1]})", "", f"*{t(block[2])}*", ""]
    return "\n".join(lines)


def _md_text(text):
    # A design name such as "plate <b>2</b> &amp; co" is text, but Markdown would pass its
    # tags on and decode its entity: escape what starts a tag or an entity, not "<=".
    return re.sub(r"<(?=[A-Za-z/!?])", "&lt;", re.sub(r"&(?=#?\w+;)", "&amp;", str(text)))


def _md_cell(text):
    return _md_text(text).replace("|", "\\|").replace("\n", " ")


def render_html(blocks):
    """Return the blocks as a self-contained HTML page (figures as relative links)."""
    title = next((b[1] for b in blocks if b[0] == "h1"), "Fabrication report")
    return render_page("fab_report.html", title=title, blocks=blocks)
