"""The figures of ``doefab camera``: the sensor plane with its active areas and the
effective PSF; the camera budget's curves."""

import math

import numpy as np
import scipy.ndimage

from doe.figures import correlation_text
from doe.infra.png import save_png


def sensor_view(result, rotation_deg):
    """Return (image, half-width m): the spectrum-averaged intensity in the sensor's frame.

    The model holds it in the plate's frame; a point X of the sensor sees the plate's
    Rot(-R) X. Rows of the image grow towards +y (drawn with origin "lower").
    """
    img, dx = result.sensor, result.sensor_dx
    n = img.shape[0]
    half = n // 2
    xs = (np.arange(n) - half) * dx
    x, y = np.meshgrid(xs, xs)
    a = -math.radians(rotation_deg)
    px, py = math.cos(a) * x - math.sin(a) * y, math.sin(a) * x + math.cos(a) * y
    coords = np.stack([py / dx + half, px / dx + half])
    return scipy.ndimage.map_coordinates(img, coords, order=1, cval=0.0), half * dx


def save_camera_figure(path, result, design, target, figures):
    """Write the PNG: the sensor plane (log intensity, active areas drawn) and E."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Rectangle

    settings = result.settings
    img, half = sensor_view(result, settings["rotation_deg"])
    k = result.psf.shape[0]
    sensor = design.sensor
    p = sensor.pixel_pitch / sensor.superres_factor * 1e6
    a = sensor.active_area * 1e6
    fig, axes = plt.subplots(1, 3, figsize=(17, 5.4))
    ax = axes[0]
    peak = max(float(img.max()), 1e-300)
    shown = np.log10(np.maximum(img / peak, 1e-5))
    ext = (-half * 1e6, half * 1e6, -half * 1e6, half * 1e6)
    im = ax.imshow(shown, origin="lower", extent=ext, cmap="magma", vmin=-5, vmax=0)
    fig.colorbar(im, ax=ax, fraction=0.046, label="log10 intensity / peak")
    offsets = (np.arange(k) - k // 2) * p
    for cy in offsets:
        for cx in offsets:
            if sensor.active_area_shape == "circle":
                patch = Circle((cx, cy), a / 2, fill=False, ec="cyan", lw=0.6)
            else:
                patch = Rectangle((cx - a / 2, cy - a / 2), a, a, fill=False, ec="cyan", lw=0.6)
            ax.add_patch(patch)
    ax.set_xlabel("x on the sensor (um, right)")
    ax.set_ylabel("y on the sensor (um, up)")
    ax.set_title("sensor plane, active areas (cyan); axis at (0, 0)")
    ext_k = (-(k // 2) - 0.5, k // 2 + 0.5, k // 2 + 0.5, -(k // 2) - 0.5)
    panels = (
        (result.psf, "effective PSF E (sum 1)"),
        (target, "design PSF (target)"),
    )
    for ax, (data, title) in zip(axes[1:], panels, strict=True):
        im = ax.imshow(data, extent=ext_k, cmap="viridis", interpolation="nearest")
        ax.set_title(title)
        ax.set_xlabel("sub-pixel j - K//2 (+x)")
        ax.set_ylabel("sub-pixel i - K//2 (row grows to -y)")
        fig.colorbar(im, ax=ax, fraction=0.046)
    f_number = settings["f_number"]
    stop = "square clear aperture" if f_number is None else f"f/{f_number:g}"
    fig.suptitle(
        f"{settings['spectrum']['description']}; stop {stop}; defocus "
        f"{settings['defocus_um']:g} um; rotation {settings['rotation_deg']:g} deg (+ = "
        f"counter-clockwise)\ncollected fraction {result.collected_fraction:.4f}   correlation "
        f"{correlation_text(figures['correlation'])}   rmse {figures['rmse']:.4f}"
    )
    fig.tight_layout()
    save_png(fig, path, dpi=80)
    plt.close(fig)


AXIS_LABELS = {
    "bandwidth_nm": "band-pass FWHM (nm)",
    "f_number": "f-number of a round stop",
    "defocus_um": "defocus (um, + = sensor behind the image plane)",
    "rotation_deg": "plate rotation (deg, + = counter-clockwise)",
}


def save_budget_figure(path, budget):
    """Write the camera budget (:func:`doe.camera_budget.camera_budget`): correlation, rmse
    and collected fraction against each setting; the nominal camera's figures dotted, the
    budget's rmse limit dashed, the design goals dash-dotted, the range within the
    budget shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    axes = budget["axes"]
    nominal, limit, goals = budget["nominal"], budget["limit"], budget["goals"]
    fig, grid = plt.subplots(3, len(axes), figsize=(4.2 * len(axes), 9), squeeze=False)
    rows = (
        ("correlation", [(goals["correlation_min"], "-.", "goal")], "correlation"),
        ("rmse", [(limit["rmse_max"], "--", "budget"), (goals["rmse_max"], "-.", "goal")],
         "rmse (peak-normalised, log)"),
        ("collected_fraction", [], "collected fraction"),
    )  # fmt: skip
    for col, (name, curve) in enumerate(axes.items()):
        x = np.asarray(curve["values"], float)
        span = curve["within_budget"]["range"]
        goal_runs = curve["within_goals"]["runs"]
        for row, (key, lines, label) in enumerate(rows):
            ax = grid[row][col]
            y = np.asarray([np.nan if v is None else v for v in curve[key]], float)
            ax.plot(x, y, "o-", ms=3, label="this camera")
            if nominal[key] is not None:
                ax.axhline(nominal[key], ls=":", color="tab:gray", lw=0.8, label="nominal camera")
            for value, style, what in lines:
                ax.axhline(value, ls=style, color="k", lw=0.8, label=f"{what} {value:.4g}")
            if span is not None:
                ax.axvspan(span[0], span[1], color="tab:green", alpha=0.12, lw=0)
            for lo, hi in goal_runs:  # hatched: where the design goals hold
                ax.axvspan(lo, hi, fill=False, hatch="//", edgecolor="tab:blue", lw=0)
            if key == "rmse":  # the limit near the nominal and the far points both show
                ax.set_yscale("log")
            else:
                ax.ticklabel_format(axis="y", useOffset=False)
            ax.set_ylabel(label)
            ax.set_xlabel(AXIS_LABELS.get(name, name))
            if col == 0:
                ax.legend(fontsize=7)
    fig.suptitle(
        "The plate in the camera: each setting varied alone from the nominal camera "
        f"(green: rmse within the nominal's + {limit['allowance']:g}; hatched: within the goals)"
    )
    # a fixed layout: tight_layout renders the twelve panels twice over (half the cost)
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.06, top=0.94, wspace=0.3, hspace=0.32)
    save_png(fig, path, dpi=70)
    plt.close(fig)


def save_psnr_figure(path, psnr):
    """Write the camera budget in dB (:mod:`doe.records.camera_psnr`): the reconstruction
    PSNR against each setting, the nominal camera's dotted, its less the allowance dashed,
    the range within it shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    axes = psnr["axes"]
    nominal, allowance = psnr["nominal"]["psnr"], psnr["allowance_db"]
    fig, grid = plt.subplots(1, len(axes), figsize=(4.2 * len(axes), 3.4), squeeze=False)
    for ax, (name, curve) in zip(grid[0], axes.items(), strict=True):
        ax.plot(curve["values"], curve["psnr"], "o-", ms=3, label="this camera")
        ax.axhline(nominal, ls=":", color="tab:gray", lw=0.8, label="nominal camera")
        ax.axhline(nominal - allowance, ls="--", color="k", lw=0.8, label=f"- {allowance:g} dB")
        span = curve["within_budget"]["range"]
        if span is not None:
            ax.axvspan(span[0], span[1], color="tab:green", alpha=0.12, lw=0)
        ax.set_xlabel(AXIS_LABELS.get(name, name))
        ax.set_ylabel("reconstruction PSNR (dB)")
    grid[0][0].legend(fontsize=7)
    fig.suptitle("The learned model's reconstructions, the plate in the camera (held-back images)")
    fig.tight_layout()
    save_png(fig, path, dpi=70)
    plt.close(fig)
