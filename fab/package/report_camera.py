"""The fab report's section "In the camera": the plate's illumination and assembly budget.

``doefab fab`` computes :func:`doe.camera_budget.camera_budget` of the plate
(correlation, rmse and collected fraction against band-pass, f-number, defocus and
rotation, each varied alone from the nominal camera) into the report context's
``camera_budget`` (``--no-camera-budget`` leaves it out), and with ``--camera-psnr``
the reconstruction PSNR of a learned model at the same settings
(``doefab camera-psnr``, :mod:`doe.records.camera_psnr`) into ``camera_psnr``. This
module writes their figures and blocks.
"""

from doe.camera_figure import AXIS_LABELS, save_budget_figure
from doe.figures import correlation_text

CAMERA_FIGURE = "fab_camera_budget.png"
PSNR_FIGURE = "fab_camera_psnr.png"
CAMERA_REPORT_FIGURES = (CAMERA_FIGURE, PSNR_FIGURE)


def camera_figures(out_dir, context):
    """Write the budget figures the context holds; return the names written."""
    written = []
    if context.get("camera_budget") is not None:
        save_budget_figure(out_dir / CAMERA_FIGURE, context["camera_budget"])
        written.append(CAMERA_FIGURE)
    if context.get("camera_psnr") is not None:
        from doe.camera_figure import save_psnr_figure

        save_psnr_figure(out_dir / PSNR_FIGURE, context["camera_psnr"])
        written.append(PSNR_FIGURE)
    return written


def camera_blocks(context):
    """Return the report blocks of the camera budget (a note when none was computed)."""
    b = [("h2", "In the camera")]
    budget = context.get("camera_budget")
    if budget is None:
        b.append(("p", "Not computed in this build (doefab fab --no-camera-budget)."))
    else:
        b += _budget_blocks(budget)
    if context.get("camera_psnr") is not None:
        b += psnr_blocks(context["camera_psnr"])
    return b


def _budget_blocks(budget):
    b = []
    limit = budget["limit"]
    b.append(
        (
            "p",
            "The illumination and assembly budget, beside the fabrication budget above: the "
            "plate imaged through the lens onto the SPAD (doefab camera, docs/camera.md), the "
            "effective PSF its active areas collect compared with the design's PSF, each camera "
            "setting varied alone from the nominal camera (the design wavelength, the plate's "
            "square clear aperture as the stop, in focus, unrotated). The budget uses the "
            "fabrication budget's rule: a setting is within it while the rmse stays within the "
            f"nominal camera's + {limit['allowance']:g} (rmse <= {limit['rmse_max']:.4f}).",
        )
    )
    header = ["figure", "the nominal camera", "the plate's window powers", "design goal"]
    b.append(("table", header, _nominal_rows(budget)))
    b.append(("p", _goal_sentence(budget)))
    rows = [_axis_row(axis, curve) for axis, curve in budget["axes"].items()]
    header = ["setting", "explored", "within the budget", "within the design goals",
              "collected fraction", "rmse at the ends"]  # fmt: skip
    b.append(("table", header, rows))
    b.append(("fig", CAMERA_FIGURE, "The camera budget: each setting varied alone; dotted: the "
              "nominal camera; dashed: the budget's rmse limit; dash-dotted: the design goals; "
              "shaded: the range within the budget; hatched: where the goals hold."))  # fmt: skip
    return b


def _nominal_rows(budget):
    nominal, goals, window = budget["nominal"], budget["goals"], budget["window"]
    return [
        ["correlation", correlation_text(nominal["correlation"]),
         correlation_text(window["correlation"]), f">= {goals['correlation_min']:g}"],
        ["rmse", f"{nominal['rmse']:.4f}", f"{window['rmse']:.4f}", f"<= {goals['rmse_max']:g}"],
        ["collected fraction / efficiency", f"{nominal['collected_fraction']:.3f}",
         f"{window['efficiency']:.3f}", ""],
    ]  # fmt: skip


def _goal_sentence(budget):
    """Whether the design goals hold in the nominal camera, and why not."""
    nominal, goals, dots, window = (budget[k] for k in ("nominal", "goals", "dots", "window"))
    if goals["met"]:
        return "The design goals hold in the nominal camera."
    return (
        "The design goals do not hold in the nominal camera. Its dots are finite (about "
        f"{dots['width_um']:.1f} um between the first zeros of each dot, for the square clear "
        f"aperture), so part of each dot's light falls outside its {dots['active_area_um']:g} "
        f"um {dots['active_area_shape']} active area and part into its neighbours': the "
        f"active areas collect {nominal['collected_fraction']:.3f} of the light through the "
        f"stop where the plate's window of orders holds {window['efficiency']:.3f}, and the "
        f"PSF they sample has rmse {nominal['rmse']:.4f} against the design's, where the "
        f"plate's window powers (square pixels, the design wavelength) have {window['rmse']:.4f}. "
        "The budget is therefore measured from the nominal camera, not from the goals."
    )


def _axis_row(axis, curve):
    values = curve["values"]
    within = curve["within_budget"]
    if within["range"] is None:
        shown = f"none: {within['why']} (the limit)"
    else:
        shown = _range_text(within)
    goals = curve["within_goals"]
    cf = curve["collected_fraction"]
    return [
        AXIS_LABELS.get(axis, axis),
        f"{min(values):g} .. {max(values):g}",
        shown,
        _runs_text(goals["runs"]),
        f"{min(cf):.3f} .. {max(cf):.3f}",
        f"{curve['rmse'][0]:.4f} at {values[0]:g}, {curve['rmse'][-1]:.4f} at {values[-1]:g}",
    ]


def psnr_blocks(psnr):
    """The dB budget: the model's reconstruction PSNR on held-back images per setting."""
    b = [("h3", "In the camera, in dB of reconstruction PSNR")]
    nominal = psnr["nominal"]
    b.append(
        (
            "p",
            f"The learned model {psnr['model_dir']} reconstructs {len(psnr['images']['names'])} "
            f"held-back images ({psnr['images']['source']}, {psnr['images']['crop']} px crops) "
            "from captures simulated with the plate's effective PSF at each setting (doefab "
            f"camera-psnr). Nominal camera: {nominal['psnr']:.2f} dB (with the model's own PSF "
            f"{psnr['model_psf']['psnr']:.2f} dB). Within the budget: the PSNR stays within "
            f"{psnr['allowance_db']:g} dB of the nominal camera's.",
        )
    )
    rows = []
    for axis, curve in psnr["axes"].items():
        within = curve["within_budget"]
        shown = within["why"] if within["range"] is None else _range_text(within)
        pts = ", ".join(
            f"{v:g}: {p:.2f}" for v, p in zip(curve["values"], curve["psnr"], strict=True)
        )
        rows.append([AXIS_LABELS.get(axis, axis), shown, pts])
    b.append(("table", ["setting", "within the dB budget", "PSNR (dB) at each value"], rows))
    b.append(("fig", PSNR_FIGURE, "Reconstruction PSNR against each camera setting; "
              "dotted: the nominal camera; dashed: the dB budget; shaded: within it."))  # fmt: skip
    return b


def _runs_text(runs):
    if not runs:
        return "none of the values explored"
    return ", ".join(f"{lo:.3g} .. {hi:.3g}" for lo, hi in runs)


def _range_text(within):
    lo, hi = within["range"]
    # an end the curve never crossed: the budget reaches at least the last value explored
    marks = [" (explored)" if kind == "explored" else "" for kind in within["ends"]]
    return f"{lo:.3g}{marks[0]} .. {hi:.3g}{marks[1]}"
