"""Figures and the HTML report of ``doefab verify`` and the plot of ``doefab mtf``.

matplotlib (Agg) is imported inside the functions; PNG metadata is pinned so
the bytes depend only on the data. The page is the template
``fab/templates/verify_report.html``, filled with the rows built here.
"""

import numpy as np

from doe.figures import value_and_limit
from doe.infra.png import save_png
from fab.plate.budget import beyond, fit_sigma
from fab.templates import render_page
from fab.verify.diagnosis import fitted_fault, is_judged


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_verify_report(stage, report, image, grid, lattice, measured_psf, design_psf, orientation):
    """Write ``verify.png`` and ``verify_report.html`` into ``stage``.

    Parameters
    ----------
    stage : Path
        Output folder.
    report : dict
        The verify.json content.
    image : (H, W) float array
        Conditioned capture (DN).
    grid : fab.verify.lattice.OrderGrid
    lattice : fab.verify.lattice.Lattice
    measured_psf, design_psf : (K, K) float arrays
    orientation : str
    """
    plt = _pyplot()
    from matplotlib.colors import PowerNorm

    k = measured_psf.shape[0]
    fault = fitted_fault(report)  # a third row: the plate with that fault, and what remains
    fig, axes = plt.subplots(3 if fault else 2, 2, figsize=(10, 13.5 if fault else 9))
    r0, c0 = report["zero_order_px"]
    half = (k // 2 + 2) * lattice.pitch_px
    h, w = image.shape
    top, bottom = int(max(0, r0 - half)), int(min(h, r0 + half + 1))
    left, right = int(max(0, c0 - half)), int(min(w, c0 + half + 1))
    crop = image[top:bottom, left:right]
    ax = axes[0, 0]
    shown = np.clip(crop, 0, None)
    im = ax.imshow(
        shown,
        cmap="gray",
        # a square-root scale shows the faint orders beside the bright zero order
        norm=PowerNorm(0.5, vmin=0, vmax=max(float(np.percentile(shown, 99.8)), 1e-9)),
        interpolation="nearest",
        extent=(left - 0.5, right - 0.5, bottom - 0.5, top - 0.5),
    )
    fig.colorbar(im, ax=ax, fraction=0.046, label="DN")
    inside = (
        (grid.rows >= top)
        & (grid.rows < bottom)
        & (grid.cols >= left)
        & (grid.cols < right)
        & grid.valid
    )
    ax.plot(grid.cols[inside], grid.rows[inside], ".", color="tab:cyan", ms=1.5, alpha=0.6)
    ax.plot([c0], [r0], "o", mfc="none", mec="tab:red", ms=10, label="zero order")
    ax.set_title("capture around the zero order (sqrt), lattice fit")
    ax.legend(loc="upper right", fontsize=8)
    vmax = max(measured_psf.max(), design_psf.max())
    for ax, data, title in (
        (axes[0, 1], measured_psf, "measured PSF"),
        (axes[1, 0], design_psf, "design PSF (simulate_levels)"),
    ):
        im = ax.imshow(data, cmap="magma", vmin=0, vmax=vmax)
        ax.set_title(title)
        fig.colorbar(im, ax=ax, fraction=0.046)
    diff = measured_psf / measured_psf.max() - design_psf / design_psf.max()
    lim = max(float(np.abs(diff).max()), 1e-9)
    im = axes[1, 1].imshow(diff, cmap="RdBu_r", vmin=-lim, vmax=lim)
    axes[1, 1].set_title("difference (each / its peak)")
    fig.colorbar(im, ax=axes[1, 1], fraction=0.046)
    if fault:
        what, fitted = fault
        im = axes[2, 0].imshow(fitted, cmap="magma", vmin=0, vmax=vmax)
        axes[2, 0].set_title(f"fitted plate: {what}", fontsize=10)
        fig.colorbar(im, ax=axes[2, 0], fraction=0.046)
        rest = measured_psf / measured_psf.max() - fitted / fitted.max()
        im = axes[2, 1].imshow(rest, cmap="RdBu_r", vmin=-lim, vmax=lim)
        axes[2, 1].set_title("difference from the fitted plate (same scale)", fontsize=10)
        fig.colorbar(im, ax=axes[2, 1], fraction=0.046)
    verdict = "PASS" if report["pass"] else "FAIL"
    fig.suptitle(
        f"{verdict}: {', '.join(report['diagnosis'])}\ncorrelation "
        f"{report['correlation']:.4f}, rmse {report['rmse']:.4f}, orientation "
        f"{orientation}"
    )
    # room for the two-line title (a long diagnosis list would run past the figure's width)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.5 / fig.get_figheight()))
    save_png(fig, stage / "verify.png", dpi=90)
    plt.close(fig)
    (stage / "verify_report.html").write_text(_html(report), encoding="utf-8")


def _html(report):
    """Return the page ``verify_report.html`` of a verify.json ``report``."""
    verdict = "PASS" if report["pass"] else "FAIL"
    return render_page(
        "verify_report.html",
        verdict=verdict,
        diagnosis=", ".join(report["diagnosis"]),
        checks=_checks(report),
        measurement=_measurement(report),
        notes=report["notes"],
        sigmas=f"{report['thresholds']['significance_sigmas']:g}",
    )


def _checks(report):
    """Rows (figure, measured, threshold, verdict) of the acceptance table.

    The verdict is True (ok), False (fail) or None (not judged).
    """
    t = report["thresholds"]
    sig = t["significance_sigmas"]
    # After a diagnosis that the plate is not this design as oriented (or clipped or
    # too faint), the PSF and process figures are shown but not judged.
    judged = is_judged(report["diagnosis"])
    corr, rmse, snr = report["correlation"], report["rmse"], report["window_snr"]
    fit = report["deep_etch_error_fit"]  # None: the design leaves the error no trace
    checks = [  # (figure, value, comparison, limit, verdict; None: not judged)
        ("correlation", corr, ">=", t["correlation_min"], corr >= t["correlation_min"]),
        ("rmse", rmse, "<=", t["rmse_max"], rmse <= t["rmse_max"]),
        (
            f"efficiency (± {report['efficiency_sigma']:.2g})",
            report["efficiency"],
            ">=",
            t["efficiency_min"],
            report["efficiency"] + sig * report["efficiency_sigma"] >= t["efficiency_min"],
        ),
        (
            f"zero order, fraction of the beam (± {report['zero_order_sigma']:.2g})",
            report["zero_order"],
            "<=",
            t["zero_order_max"],
            report["zero_order"] - sig * report["zero_order_sigma"] <= t["zero_order_max"],
        ),
        (
            "deep-etch depth error fitted to the window (+ too deep, - too shallow)",
            fit,
            "|error| <=",
            t["deep_etch_error_max"],
            _deep_etch_verdict(report),
        ),
        ("window SNR", snr, ">=", t["min_window_snr"], snr >= t["min_window_snr"]),
        ("saturated dots", report["saturated_dots"], "=", 0, report["saturated_dots"] == 0),
    ]
    checks[:5] = [(n, v, op, lim, ok if judged else None) for n, v, op, lim, ok in checks[:5]]
    if report["pass"]:  # a row says FAIL only where the plate fails
        checks = [
            (n, v, op, lim, f"beyond the limit by less than {sig:g} sigma: not a failure")
            if ok is False
            else (n, v, op, lim, ok)
            for n, v, op, lim, ok in checks
        ]
    return [(n, *_figure_and_limit(v, op, lim), ok) for n, v, op, lim, ok in checks]


def _deep_etch_verdict(report):
    """Return the deep-etch row's verdict against its budget: False where the plate fails
    for it, None where the design leaves it no trace, else what the row means."""
    fit, limit = report["deep_etch_error_fit"], report["thresholds"]["deep_etch_error_max"]
    if fit is None:
        return None
    if "deep_etch_error" in report["diagnosis"]:
        return False
    if abs(fit) <= limit:
        return "within budget"
    sig = report["thresholds"]["significance_sigmas"]
    sigma = fit_sigma(fit, report["deep_etch_error_fit_significance"])
    joint = report["deep_etch_error_joint_fit"]
    if not beyond(fit, sigma, limit, sig):
        return f"beyond budget by less than {sig:g} sigma (± {sigma or 0:.2g}): not a failure"
    if joint is not None and abs(joint) <= limit:
        return f"beyond budget, explained by the other etches' errors (joint fit {joint:+.3g})"
    return "beyond budget, not a significant fit: not a failure"


def _measurement(report):
    """Rows (what, value) of the measurement table."""
    t = report["thresholds"]
    lat = report["lattice"]
    return [
        ("zero-order excess over the design", f"{report['zero_order_excess']:.4g}"),
        (
            "implied deep-etch depth error (from the zero order; sign from the window fit)",
            _fmt(report.get("implied_deep_etch_error"))
            + (
                f" ({report['implied_deep_etch_error_nm']:.1f} nm)"
                if "implied_deep_etch_error_nm" in report
                else ""
            ),
        ),
        (
            "power outside the window (share of the light in the orders with signal)",
            f"{report['power_outside_window']:.4g} ± {report['power_outside_window_sigma']:.2g}"
            f" (design: {report['expected_power_outside_window']:.4g}; summing every order "
            f"in the frame: {report['power_outside_window_all_orders']:.4g})",
        ),
        (
            "photometry aperture radius (px), orders with signal / measured",
            f"{report['aperture_radius_px']:.2f}, {report['orders_with_signal']} / "
            f"{report['orders_measured']}",
        ),
        ("overlay fit: one mask shifted (fitted when the PSF fails)", _overlay_text(report)),
        (
            "etch fit: every mask's depth error, fitted together (+ too deep; the gain "
            "is the chi-square each needs; fitted when the PSF fails)",
            _etch_text(report),
        ),
        (
            "overlay and etch fit: one mask shifted and every etch's depth, fitted together "
            "(when neither alone explains a failing PSF)",
            _both_text(report),
        ),
        (
            "frame correlation with design / rot180 / mirror-x / mirror-y",
            " / ".join(
                f"{report['frame_correlation'][k]:.3f}"
                for k in ("design", "rot180", "mirror-x", "mirror-y")
            )
            if np.isfinite(report["frame_correlation"]["design"])
            else "none: the design lights its zero order alone",
        ),
        (
            "zero-order search: chi-square gain of rot180 / mirror-x / mirror-y over the "
            "design (> 0: fits better), runner-up offset margin",
            " / ".join(
                f"{report['zero_order_search']['delta_chi2'][k]:.4g}"
                for k in ("rot180", "mirror-x", "mirror-y")
            )
            + f", {report['zero_order_search']['runner_up_margin']:.4g}",
        ),
        (
            "lattice pitch (px), rotation (deg), zero order (row, col px)",
            f"{lat['pitch_px']:.4f} ("
            + (
                "measured; no --pixel-pitch-um"
                if lat.get("nominal_pitch_px") is None
                else f"flags: {lat['nominal_pitch_px']:.4f}"
            )
            + f"), "
            f"{lat['rotation_deg']:.3f}, ({report['zero_order_px'][0]:.2f}, "
            f"{report['zero_order_px'][1]:.2f})",
        ),
        ("orientation", report["orientation"]),
        (
            "measured as (the design, or the reflection of it that the plate is)",
            report.get("measured_as", "design"),
        ),
        ("thresholds from", t["source"]),
        ("capture / dark", f"{report['inputs']['capture']} / {report['inputs']['dark']}"),
    ]


def _overlay_text(report):
    fit = report["overlay_error_fit"]
    if fit is None:
        return "not fitted"
    return (
        f"{_shift_text(fit)}; correlation "
        f"{fit['correlation']:.4f} with that plate (frame {fit['frame_correlation']:.3f}), "
        f"chi-square gain {fit['significance']:.3g}"
    )


def _fmt(v):
    return "n/a" if v is None else f"{v:+.4f}"


def _figure_and_limit(value, op, limit):
    """Return the texts of a figure (signed where the limit bounds its size) and its limit."""
    if value is None:
        return "n/a", f"{op} {limit:.5g}"
    if op.startswith("|"):
        shown, shown_limit = value_and_limit(abs(value), limit, 5)
        shown = ("-" if value < 0 else "+") + shown
    else:
        shown, shown_limit = value_and_limit(value, limit, 5)
    return shown, f"{op} {shown_limit}"


def mtf50_text(result):
    """MTF50 of a ``slanted_edge_mtf`` result in words (it may lie beyond the measured range)."""
    mtf50 = result["mtf50_cycles_per_pixel"]
    if mtf50 is None:
        f = np.asarray(result["frequencies_cycles_per_pixel"], float)
        top = f[np.isfinite(np.asarray(result["mtf"], float))].max()
        return f"> {top:.3g} cycles/pixel (above 0.5 wherever measured)"
    return f"{mtf50:.4f} cycles/pixel"


def write_mtf_plot(path, result):
    """Plot the MTF of ``result`` (from ``fab.verify.mtf.slanted_edge_mtf``) to a PNG."""
    plt = _pyplot()
    f = np.asarray(result["frequencies_cycles_per_pixel"])
    m = np.asarray(result["mtf"])
    fig, ax = plt.subplots(figsize=(6, 4))
    keep = f <= 1.0
    ax.plot(f[keep], m[keep], "-", color="tab:blue")
    ax.axhline(0.5, color="gray", lw=0.6)
    ax.axvline(0.5, color="gray", lw=0.6, ls=":")
    ax.set_xlabel("spatial frequency (cycles/pixel)")
    ax.set_ylabel("MTF")
    # A sharpened edge peaks above 1: the axis must show it, not cut it.
    ax.set_ylim(0, max(1.05, 1.05 * float(np.nanmax(np.asarray(result["mtf"], float)))))
    ax.set_title(f"slanted-edge MTF, MTF50 {mtf50_text(result)}")
    fig.tight_layout()
    save_png(fig, path, dpi=90)
    plt.close(fig)


def _etch_text(report):
    fit = report["etch_error_fit"]
    if fit is None:
        return "not fitted"
    nm = fit.get("errors_nm") or [None] * len(fit["errors"])
    figures = zip(
        fit["masks"], fit["errors"], fit["errors_sigma"], nm, fit["mask_significance"], strict=True
    )
    masks = ", ".join(
        f"{name} {err:+.1%} ± {sd:.1%}"
        + (f" ({e_nm:+.1f} nm)" if e_nm is not None else "")
        + f" gain {gain:.3g}"
        for name, err, sd, e_nm, gain in figures
    )
    edge = ", at the edge of the search: an error may be larger" if fit["at_search_edge"] else ""
    return (
        f"{masks}{edge}; correlation {fit['correlation']:.4f} with that plate (frame "
        f"{fit['frame_correlation']:.3f}), chi-square gain {fit['significance']:.3g}"
    )


def _both_text(report):
    fit = report["overlay_and_etch_fit"]
    if fit is None:
        return "not fitted"
    errors = ", ".join(
        f"{name} {err:+.1%} gain {gain:.3g}"
        for name, err, gain in zip(
            fit["masks"], fit["errors"], fit["mask_significance"], strict=True
        )
    )
    return (
        f"{_shift_text(fit)}, gain "
        f"{fit['shift_significance']:.3g}; {errors}; correlation {fit['correlation']:.4f} "
        f"with that plate (frame {fit['frame_correlation']:.3f}), chi-square gain over the "
        f"better single fit {fit['significance']:.3g}"
    )


def _shift_text(fit):
    """'M2_mid by y +1.50, x -0.50 mask pixels (+7.49 um, -2.50 um)' of a fitted shift."""
    dy, dx = fit["shift_px"]
    um = " ({:+.2f} um, {:+.2f} um)".format(*fit["shift_um"]) if "shift_um" in fit else ""
    return f"{fit['mask']} by y {dy:+.2f}, x {dx:+.2f} mask pixels{um}"
