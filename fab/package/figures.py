"""Figures of the fabrication report (PNG, byte-identical for identical input).

Each function draws one figure onto a fresh ``matplotlib.figure.Figure`` (no
pyplot state) and saves it with pinned metadata, so two runs on the same data
write the same bytes. Lengths are SI inside; axes are labelled in um or in
sensor sub-pixels.
"""

import numpy as np

from doe.infra.png import save_png
from fab.package.polarity import POLARITY, masks_figure_description

_DPI = 100


def _figure(width, height):
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=_DPI, layout="constrained")


def _save(fig, path, description=None):
    save_png(fig, path, dpi=_DPI, description=description)


def _tile_extent(n, pitch):
    """Extent (um) of a tile image: row 0 at the top (largest y), column 0 at the left."""
    size = n * pitch * 1e6
    return (0.0, size, 0.0, size)


def level_map(path, levels, n_levels, pitch):
    """Draw the level map (N, N) with its physical extent; ``pitch`` in metres."""
    fig = _figure(5.6, 4.8)
    ax = fig.add_subplot()
    im = ax.imshow(
        levels,
        cmap="viridis",
        vmin=-0.5,
        vmax=n_levels - 0.5,
        extent=_tile_extent(levels.shape[0], pitch),
        interpolation="nearest",
    )
    ticks = range(n_levels) if n_levels <= 16 else None  # 256 labels print as a black bar
    label = f"level (0 = deepest etch, {n_levels - 1} = unetched)"
    fig.colorbar(im, ax=ax, ticks=ticks, label=label)
    ax.set(xlabel="x (um)", ylabel="y (um)", title="Level map, viewed onto the patterned surface")
    _save(fig, path, f"Level map of one tile, {label}: l steps of glass above the floor.")


def mask_bitmaps(path, bitmaps, names, depths_nm, pitch):
    """Draw each mask's etched area side by side, white = etched (``fab.package.polarity``)."""
    count = len(bitmaps)
    fig = _figure(4.2 * count, 5.0)
    axes = []
    for i, (bm, name, depth) in enumerate(zip(bitmaps, names, depths_nm, strict=True)):
        ax = fig.add_subplot(1, count, i + 1)
        im = ax.imshow(
            np.asarray(bm, bool),
            cmap="gray",
            vmin=0,
            vmax=1,
            extent=_tile_extent(bm.shape[0], pitch),
            interpolation="nearest",
        )
        ax.set(title=f"{name}: etch {depth:.1f} nm", xlabel="x (um)")
        if i == 0:
            ax.set_ylabel("y (um)")
        axes.append(ax)
    bar = fig.colorbar(im, ax=axes, ticks=[0.25, 0.75], shrink=0.6)
    bar.ax.set_yticklabels(["not etched", "etched"])
    fig.suptitle(f"Masks, viewed onto the patterned surface ({POLARITY})")
    _save(fig, path, masks_figure_description())


def psf_comparison(path, target, simulated):
    """Draw target, simulated and their difference, each normalised to its peak."""
    k = target.shape[0]
    h = k // 2
    # Row index grows downwards (-y): put row 0 at y = +K//2.
    extent = (-h - 0.5, h + 0.5, -h - 0.5, h + 0.5)
    t = target / target.max()
    s = simulated / simulated.max()
    diff = s - t
    lim = max(float(np.abs(diff).max()), 1e-12)
    fig = _figure(13.0, 4.2)
    panels = [
        (t, "target", "magma", 0, 1),
        (s, "simulated (nominal levels)", "magma", 0, 1),
        (diff, "simulated - target", "RdBu_r", -lim, lim),
    ]
    for i, (img, title, cmap, lo, hi) in enumerate(panels):
        ax = fig.add_subplot(1, 3, i + 1)
        im = ax.imshow(img, cmap=cmap, vmin=lo, vmax=hi, extent=extent, interpolation="nearest")
        fig.colorbar(im, ax=ax, shrink=0.85)
        ax.set(title=title, xlabel="x (sensor sub-pixels)")
        if i == 0:
            ax.set_ylabel("y (sensor sub-pixels)")
    fig.suptitle("PSF on the sensor's sub-pixel grid (peak-normalised); centre = optical axis")
    _save(fig, path)


def dot_lattice(path, phase, sensor, lattice_pitch, spad_pixels=3, px_per_subpixel=10):
    """Draw the dot lattice on a few SPAD pixels with their active areas overlaid.

    Parameters
    ----------
    phase : (N, N) array
        Tile phase (rad).
    sensor : dict
        ``design_summary(...)["sensor"]`` (um keys).
    lattice_pitch : float
        Spacing of the diffraction orders on the sensor (m).
    spad_pixels : int
        SPAD pixels shown across (odd: the zero order sits in the central one).
    """
    from matplotlib.patches import Circle, Rectangle

    from doe.fraunhofer import dot_lattice_image

    pitch = sensor["pixel_pitch_um"] * 1e-6
    sub = pitch / sensor["superres_factor"]
    render = sub / px_per_subpixel  # metres per rendered pixel
    size = round(spad_pixels * pitch / render)
    off_x, off_y = (v * 1e-6 for v in sensor["active_offset_um"])
    # Zero order on the centre of the central SPAD pixel's active area; rows grow to -y.
    centre = ((size - 1) / 2 - off_y / render, (size - 1) / 2 + off_x / render)
    img = dot_lattice_image(
        phase, (size, size), lattice_pitch / render, centre=centre, spot_sigma_px=0.8
    )
    half = spad_pixels * pitch / 2 * 1e6
    fig = _figure(6.2, 5.4)
    ax = fig.add_subplot()
    from matplotlib.colors import PowerNorm

    im = ax.imshow(
        img,
        cmap="inferno",
        norm=PowerNorm(0.5, vmin=0, vmax=float(img.max()) or 1),
        extent=(-half, half, -half, half),
        interpolation="nearest",
    )
    fig.colorbar(im, ax=ax, label="power per render pixel (sqrt scale)")
    area = sensor["active_area_um"]
    for i in range(spad_pixels):
        for j in range(spad_pixels):
            x0 = -half + j * pitch * 1e6
            y0 = -half + i * pitch * 1e6
            ax.add_patch(
                Rectangle(
                    (x0, y0), pitch * 1e6, pitch * 1e6, fill=False, edgecolor="white", linewidth=0.8
                )
            )
            cx = x0 + pitch * 1e6 / 2 + off_x * 1e6
            cy = y0 + pitch * 1e6 / 2 + off_y * 1e6
            if sensor["active_area_shape"] == "circle":
                patch = Circle((cx, cy), area / 2, fill=False, edgecolor="cyan", linewidth=1.0)
            else:
                patch = Rectangle(
                    (cx - area / 2, cy - area / 2),
                    area,
                    area,
                    fill=False,
                    edgecolor="cyan",
                    linewidth=1.0,
                )
            ax.add_patch(patch)
    ticks = np.arange(-half, half + 1e-9, sub * 1e6)
    ax.set_xticks(ticks, minor=True)
    ax.set_yticks(ticks, minor=True)
    ax.grid(which="minor", color="white", alpha=0.15, linewidth=0.5)
    ax.set(
        xlabel="x on the sensor (um)",
        ylabel="y on the sensor (um)",
        title=f"Dot lattice on {spad_pixels} x {spad_pixels} SPAD pixels "
        f"(pitch {lattice_pitch * 1e6:.3f} um)",
    )
    _save(fig, path)


def tolerance_curves(path, tolerance):
    """Draw rmse against each error kind (and the zero-order excess against etch)."""
    rows = tolerance["rows"]
    limit = tolerance["rmse_limit"]
    nominal = tolerance["nominal"]
    fig = _figure(14.0, 3.8)
    axes = [fig.add_subplot(1, 4, i + 1) for i in range(4)]
    kinds = [
        ("etch", "etch-depth error (%)"),
        ("overlay", "overlay error (um)"),
        ("cd_bias", "CD bias per edge (um)"),
    ]
    for ax, (kind, label) in zip(axes, kinds, strict=False):
        series = {}
        for r in rows:
            if r["kind"] == kind:
                key = r["mask"] + (f" {r['axis']}" if r["axis"] else "")
                series.setdefault(key, [(0.0, nominal["rmse"])]).append((r["value"], r["rmse"]))
        colours = {}
        for key in sorted(series):
            pts = sorted(series[key])
            (line,) = ax.plot([p[0] for p in pts], [p[1] for p in pts], marker="o", ms=3, label=key)
            colours.setdefault(key.split(" ")[0], line.get_color())
        ax.axhline(limit, color="k", ls="--", lw=0.8, label="rmse limit")
        for b in tolerance["budget"]:
            if b["kind"] == kind:  # in its mask's colour: masks' budgets differ
                for sign in (1, -1):
                    colour = colours.get(b["mask"], "gray")
                    ax.axvline(sign * b["value"], color=colour, ls=":", lw=1.0)
        ax.set(xlabel=label, ylabel="rmse", title=kind)
        ax.legend(fontsize=7)
    ax = axes[3]
    series = {}
    for r in rows:
        if r["kind"] == "etch":
            series.setdefault(r["mask"], [(0.0, 0.0)]).append((r["value"], r["zero_order_excess"]))
    for key in sorted(series):
        pts = sorted(series[key])
        ax.plot([p[0] for p in pts], [p[1] for p in pts], marker="o", ms=3, label=key)
    ax.set(xlabel="etch-depth error (%)", ylabel="zero-order power - nominal", title="zero order")
    ax.legend(fontsize=7)
    fig.suptitle("Tolerance of the fabricated plate (dotted: budget, in its mask's colour)")
    _save(fig, path)
