"""Figures of ``doefab depth`` / ``doefab transient``: maps, example fits, a GIF preview.

Matplotlib with the Agg backend; PNG metadata pinned so the bytes depend only
on the data.
"""

import numpy as np

PNG_META = {"Software": None}


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_map(path, image, title, label, cmap="gray", valid=None):
    """Save a (H, W) map with a colour bar; invalid pixels (``valid`` False) drawn grey."""
    plt = _pyplot()
    data = np.ma.masked_invalid(np.asarray(image, dtype=np.float64))
    if valid is not None:
        data = np.ma.masked_where(~np.asarray(valid), data)
    colors = plt.get_cmap(cmap).copy()
    colors.set_bad("0.6")
    h, w = data.shape
    fig, ax = plt.subplots(figsize=(6, 6 * h / w * 0.8 + 0.8))
    im = ax.imshow(data, cmap=colors, interpolation="nearest")
    ax.set_title(title)
    ax.set_xlabel("column")
    ax.set_ylabel("row")
    fig.colorbar(im, ax=ax, label=label, shrink=0.8)
    fig.savefig(path, dpi=100, metadata=PNG_META)
    plt.close(fig)


def save_pixel_fits(path, times, profiles, models, labels):
    """Save a grid of example time profiles (points) with their fitted models (lines).

    Parameters
    ----------
    times : (T,) array
        Scan times (s).
    profiles, models : (n, T) arrays
        Measured counts and fitted expected counts of n pixels.
    labels : list of str
        One title per pixel.
    """
    plt = _pyplot()
    n = len(profiles)
    cols = min(n, 2)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 3 * rows), squeeze=False)
    t_ps = np.asarray(times) / 1e-12
    for ax, y, m, label in zip(axes.flat, profiles, models, labels, strict=False):
        ax.plot(t_ps, y, ".", ms=3, color="0.3", label="counts")
        if m is not None:
            ax.plot(t_ps, m, "-", color="C3", label="fit")
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("scan time (ps)")
        ax.set_ylabel("counts")
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100, metadata=PNG_META)
    plt.close(fig)


def save_gif(path, frames, times, fps=10):
    """Save an animated GIF of (T, H, W) frames on one common grey scale."""
    plt = _pyplot()
    from matplotlib.animation import FuncAnimation, PillowWriter

    frames = np.asarray(frames, dtype=np.float64)
    vmax = float(frames.max()) or 1.0
    h, w = frames.shape[1:]
    fig, ax = plt.subplots(figsize=(4, 4 * h / w + 0.5))
    im = ax.imshow(frames[0], cmap="gray", vmin=0, vmax=vmax, interpolation="nearest")
    ax.set_axis_off()
    title = ax.set_title("")

    def show(k):
        im.set_data(frames[k])
        title.set_text(f"t = {times[k] / 1e-12:.0f} ps")
        return im, title

    anim = FuncAnimation(fig, show, frames=frames.shape[0], blit=False)
    anim.save(path, writer=PillowWriter(fps=fps), dpi=60)
    plt.close(fig)
