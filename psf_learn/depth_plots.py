"""Figures of ``doefab depth`` / ``doefab transient``: maps, example fits, a GIF preview.

Matplotlib with the Agg backend; PNG metadata pinned so the bytes depend only
on the data.
"""

import numpy as np

from doe.infra.png import save_png

# A GIF frame lasts a whole number of centiseconds, up to 65535 (a 16-bit field);
# browsers play 0 or 1 centisecond as 10, so 2 (50 fps) is the shortest that plays.
GIF_FPS_RANGE = (100 / 65535, 50.0)
GIF_MAX_SIDE = 65535  # a GIF stores its width and height in 16 bits


def _figure(figsize):
    """A bare Agg figure: no pyplot, whose import alone costs about a second."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig


def _draw_map(fig, ax, image, title, label, cmap="gray", valid=None):
    """Draw a (H, W) map with a colour bar on ``ax``; invalid pixels (``valid`` False) grey."""
    from matplotlib import colormaps

    data = np.ma.masked_invalid(np.asarray(image, dtype=np.float64))
    if valid is not None:
        data = np.ma.masked_where(~np.asarray(valid), data)
    colors = colormaps[cmap].with_extremes(bad="0.6")
    im = ax.imshow(data, cmap=colors, interpolation="nearest")
    ax.set_title(title)
    ax.set_xlabel("column")
    ax.set_ylabel("row")
    fig.colorbar(im, ax=ax, label=label, shrink=0.8)


def save_map(path, image, title, label, cmap="gray", valid=None):
    """Save a (H, W) map with a colour bar; invalid pixels (``valid`` False) drawn grey."""
    h, w = np.shape(image)
    fig = _figure((6, 6 * h / w * 0.8 + 0.8))
    _draw_map(fig, fig.add_subplot(), image, title, label, cmap, valid)
    save_png(fig, path, dpi=100)


def save_depth_maps(path, depth, depth_sigma, valid):
    """Save the depth map (m) beside its precision, the 1-sigma of each depth (mm).

    Both panels draw pixels without a return grey.
    """
    h, w = np.shape(depth)
    fig = _figure((12, 6 * h / w * 0.8 + 0.8))
    left, right = fig.subplots(1, 2)
    _draw_map(fig, left, depth, "depth (c mu / 2); grey: no return", "depth (m)", "viridis", valid)
    sigma_mm = np.asarray(depth_sigma, dtype=np.float64) * 1e3
    _draw_map(
        fig, right, sigma_mm, "precision: 1-sigma of the depth", "depth sigma (mm)", "magma", valid
    )
    save_png(fig, path, dpi=100)


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
    n = len(profiles)
    cols = min(n, 2)
    rows = int(np.ceil(n / cols))
    fig = _figure((5 * cols, 3 * rows))
    axes = fig.subplots(rows, cols, squeeze=False)
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
    # Fixed margins: tight_layout would cost more than drawing the figure.
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.1, top=0.93, wspace=0.25, hspace=0.5)
    save_png(fig, path, dpi=100)


def gif_frame_centiseconds(fps):
    """Return how long a GIF frame lasts to play nearest ``fps`` (whole centiseconds).

    The nearest rate, not the nearest duration: 41 fps plays at 33.3 (3 cs), not 50.
    Raises ValueError unless a GIF can play ``fps`` frames per second.
    """
    lo, hi = GIF_FPS_RANGE
    if not lo <= fps <= hi:
        raise ValueError(f"a GIF plays {lo:.4g} to {hi:g} frames per second, got {fps:g}")
    shorter = min(max(int(100 // fps), 2), 65535)
    return min((shorter, min(shorter + 1, 65535)), key=lambda cs: abs(100 / cs - fps))


def gif_zoom(height, width, min_width=256):
    """Return the whole enlargement that makes frames ``min_width`` wide, within a GIF's sides.

    Raises ValueError for frames a GIF cannot hold (a side over 65535 pixels).
    """
    if max(height, width) > GIF_MAX_SIDE:
        raise ValueError(
            f"frames of {height} x {width} pixels do not fit a GIF "
            f"(at most {GIF_MAX_SIDE} pixels a side)"
        )
    wanted = int(np.ceil(min_width / width))
    return max(1, min(wanted, GIF_MAX_SIDE // height, GIF_MAX_SIDE // width))


def save_gif(path, frames, fps=10, min_width=256):
    """Save an animated GIF of (T, H, W) frames on one common grey scale.

    Frames are enlarged by an integer factor (nearest neighbour) to at least
    ``min_width`` pixels so that a 64 x 32 sensor is visible; Pillow writes the
    file directly (no per-frame figure drawing), which is fast and byte-stable.
    """
    from PIL import Image

    centiseconds = gif_frame_centiseconds(fps)
    frames = np.asarray(frames, dtype=np.float64)
    vmax = float(frames.max()) or 1.0
    zoom = gif_zoom(*frames.shape[1:], min_width)
    grey = np.round(np.clip(frames / vmax, 0, 1) * 255).astype(np.uint8)
    grey = np.repeat(np.repeat(grey, zoom, axis=1), zoom, axis=2)
    images = [Image.fromarray(g) for g in grey]  # uint8 (H, W): greyscale "L"
    images[0].save(
        path,
        format="GIF",
        save_all=True,
        append_images=images[1:],
        duration=10 * centiseconds,  # ms; Pillow stores whole centiseconds
        loop=0,
    )


def example_pixels(fit):
    """Up to four (row, col, reason) pixels: brightest, median, dimmest return, a non-return."""
    picks = []
    flat_valid = np.flatnonzero(fit.valid.ravel())
    if flat_valid.size:
        amp = fit.amplitude.ravel()[flat_valid]
        order = flat_valid[np.argsort(amp, kind="stable")]
        for why, i in (
            ("brightest", order[-1]),
            ("median", order[order.size // 2]),
            ("dimmest", order[0]),
        ):
            if all(i != p for p, _ in picks):
                picks.append((i, why))
    invalid = np.flatnonzero(~fit.valid.ravel())
    if invalid.size:
        picks.append((invalid[0], "no return"))
    shape = fit.valid.shape
    return [(*np.unravel_index(i, shape), why) for i, why in picks]
