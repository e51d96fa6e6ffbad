"""Figures of the optics stage (matplotlib, Agg backend, imported lazily).

PNG metadata is pinned so that the same data give byte-identical files.
"""

import numpy as np

from doe.infra.png import save_png


def correlation_text(value):
    """Return a correlation for people: 6 decimals, or why it is undefined (NaN)."""
    return "undefined (uniform target)" if np.isnan(value) else f"{value:.6f}"


def value_and_limit(value, limit, digits, kind="g"):
    """Return texts of a figure and its limit that compare as the numbers do.

    Each has ``digits`` digits (``kind`` "g": significant, "f": decimals), or more
    where fewer would round a correlation of 0.99989996 onto its goal of 0.9999,
    or show a threshold of 0.97646 as 0.9765 beside a plate's 0.97648 that passes.
    """
    for d in range(digits, 18):
        shown, shown_limit = f"{value:.{d}{kind}}", f"{limit:.{d}{kind}}"
        if np.sign(float(shown) - float(shown_limit)) == np.sign(value - limit):
            return shown, shown_limit
    return repr(float(value)), repr(float(limit))  # exact (NaN stays "nan")


def save_retrieval_figure(path, target, psf, levels, n_levels, quality):
    """Write a PNG of the target, the simulated PSF, their difference and the level map.

    Parameters
    ----------
    path : path
        PNG file to write.
    target, psf : (K, K) arrays
        Target and simulated (quantised) PSF, each summing to 1.
    levels : (N, N) uint8
        Level map (CONVENTIONS.md orientation: row 0 at the top).
    n_levels : int
        Number of levels L.
    quality : dict
        ``correlation``, ``rmse`` and ``efficiency`` of the level map.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    diff = psf / psf.max() - target / target.max()
    lim = max(float(np.abs(diff).max()), 1e-12)
    k = target.shape[0]
    ext = (-(k // 2) - 0.5, k // 2 + 0.5, k // 2 + 0.5, -(k // 2) - 0.5)
    fig, axes = plt.subplots(1, 4, figsize=(16, 4.2))
    panels = (
        (target / target.max(), "target (peak = 1)", "viridis", (0, 1)),
        (psf / psf.max(), "simulated, quantised (peak = 1)", "viridis", (0, 1)),
        (diff, "simulated - target", "RdBu_r", (-lim, lim)),
    )
    for ax, (img, title, cmap, (lo, hi)) in zip(axes, panels, strict=False):
        im = ax.imshow(img, cmap=cmap, vmin=lo, vmax=hi, extent=ext, interpolation="nearest")
        ax.set_title(title)
        ax.set_xlabel("order n (+x)")
        ax.set_ylabel("order m (-y)")
        fig.colorbar(im, ax=ax, fraction=0.046)
    im = axes[3].imshow(levels, cmap="viridis", vmin=0, vmax=n_levels - 1, interpolation="nearest")
    axes[3].set_title(f"level map ({n_levels} levels, {levels.shape[0]} px)")
    axes[3].set_xlabel("column (+x)")
    axes[3].set_ylabel("row (row 0 = top)")
    fig.colorbar(im, ax=axes[3], fraction=0.046, label="level (0 = deepest etch)")
    fig.suptitle(
        f"correlation {correlation_text(quality['correlation'])}   "
        f"rmse {quality['rmse']:.5f}   efficiency {quality['efficiency']:.4f}"
    )
    fig.tight_layout()
    save_png(fig, path, dpi=80)
    plt.close(fig)
