"""The fab report's section "In the camera": the plate's budget against the camera.

``doefab fab --camera-budget`` computes :func:`doe.camera_budget.camera_budget` of
the plate (correlation, rmse and collected fraction against band-pass, f-number,
defocus and rotation, each varied alone) into the report context's
``camera_budget``; this module writes its figure and its blocks. Without it the
section says how to get it.
"""

from doe.camera_figure import AXIS_LABELS, save_budget_figure

CAMERA_FIGURE = "fab_camera_budget.png"


def camera_figures(out_dir, context):
    """Write the budget figure when the context holds a budget; return the names written."""
    budget = context.get("camera_budget")
    if budget is None:
        return []
    save_budget_figure(out_dir / CAMERA_FIGURE, budget)
    return [CAMERA_FIGURE]


def camera_blocks(context):
    """Return the report blocks of the camera budget (a note when none was computed)."""
    b = [("h2", "In the camera")]
    budget = context.get("camera_budget")
    if budget is None:
        b.append(("p", "Not computed in this build: doefab fab --camera-budget adds it."))
        return b
    b.append(
        (
            "p",
            "The plate imaged through the lens onto the SPAD (doefab camera, docs/camera.md): "
            "the effective PSF the active areas collect, against the design's PSF, with each "
            "camera setting varied alone from the default camera (the design wavelength, the "
            "plate's square clear aperture as the stop, in focus, unrotated). The range keeps "
            "correlation >= 0.9999 and rmse <= 0.005.",
        )
    )
    rows = []
    for axis, curve in budget.items():
        within = curve["within_goals"]
        shown = (
            "none (the default camera misses the goals)"
            if within is None
            else (f"{within[0]:g} .. {within[1]:g}")
        )
        worst = max(range(len(curve["values"])), key=lambda i: curve["rmse"][i])
        rows.append(
            [
                AXIS_LABELS.get(axis, axis),
                shown,
                f"{min(curve['collected_fraction']):.3f} .. {max(curve['collected_fraction']):.3f}",
                f"{curve['rmse'][worst]:.4f} at {curve['values'][worst]:g}",
            ]
        )
    b.append(("table", ["setting", "within the goals", "collected fraction", "worst rmse"], rows))
    b.append(("fig", CAMERA_FIGURE, "The camera budget: each setting varied alone; dashed: the "
              "goals; shaded: the range that keeps them."))  # fmt: skip
    return b
