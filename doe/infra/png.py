"""PNG figures whose bytes depend only on what they show.

matplotlib stamps its version into a PNG's ``Software`` text chunk, so the same
figure saved by two installations would differ. Every figure of the project is
saved through :func:`save_png`, which leaves that stamp out.
"""

PNG_METADATA = {"Software": None}
"""savefig metadata for PNG: a key set to None is left out of the file."""


def save_png(fig, target, *, dpi=None):
    """Save a matplotlib figure as PNG with no version stamp.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure to save.
    target : path or binary file object
        Where the PNG goes.
    dpi : float, optional
        Resolution; None keeps matplotlib's ``savefig.dpi`` (by default the figure's own).
    """
    fig.savefig(target, format="png", dpi=dpi, metadata=dict(PNG_METADATA))
