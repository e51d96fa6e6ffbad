"""The slanted-edge MTF of an image file: ``doefab mtf`` as a library.

``measure_mtf`` reads the image, measures the MTF across its edge
(``fab.verify.mtf.slanted_edge_mtf``) and says what may overstate it (clipped pixels,
a region too small for the edge's blur); ``save_mtf`` writes ``mtf.json`` and
``mtf.png``.

Examples
--------
>>> from fab.verify.mtf_check import measure_mtf
>>> result = measure_mtf("edge.tif", out="out/mtf")
>>> result.mtf50, result.messages                                    # doctest: +SKIP
(0.291..., ())
"""

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from doe.infra.errors import InputError
from doe.infra.files import staged_output, write_json
from fab.verify.capture import read_raw_image
from fab.verify.mtf import REACH_PER_RISE, EdgeNotFound, clipped_pixels, slanted_edge_mtf

MTF_FILES = ("mtf.json", "mtf.png")


@dataclass(frozen=True)
class MtfResult:
    """What ``measure_mtf`` measured.

    Attributes
    ----------
    record : dict
        The content of ``mtf.json``: frequencies (cycles per pixel), MTF, MTF50, the
        edge's angle, rise and reach, clipped pixels, the reader's notes.
    messages : tuple of str
        How the file was read and what may overstate the MTF, one line each, the
        image as given first (the command says them on stderr).
    out : Path or None
        The output folder, once written (``save_mtf``).
    files : tuple of Path
        The files written there.
    """

    record: dict
    messages: tuple[str, ...]
    out: Path | None = None
    files: tuple[Path, ...] = ()

    @property
    def mtf50(self):
        """The frequency (cycles per pixel) where the MTF falls to 0.5; None above the
        frequencies measured."""
        return self.record["mtf50_cycles_per_pixel"]

    @property
    def mtf50_text(self):
        """MTF50 as the command prints it."""
        from fab.verify.report import mtf50_text

        return mtf50_text(self.record)


def measure_mtf(image, *, oversample=4, out=None, force=False):
    """Measure the MTF across the slanted edge of an image file.

    Parameters
    ----------
    image : path
        An image of one straight edge a few degrees off the pixel axes (8/16-bit TIFF
        or PNG, float TIFF/EXR).
    oversample : int
        Edge-spread bins per pixel, 1 to 16.
    out : path or None
        Output folder; None writes nothing (``save_mtf`` can, later).
    force : bool
        Overwrite existing output files.

    Returns
    -------
    MtfResult

    Raises
    ------
    InputError
        An unreadable image or one without a usable edge (naming it), an oversampling
        out of range, existing output files without ``force``.
    """
    if not 1 <= oversample <= 16:
        raise InputError("oversample", f"must be 1..16, got {oversample}")
    raw = read_raw_image(image)
    try:
        record = slanted_edge_mtf(raw.data, oversample=oversample)
    except EdgeNotFound as e:
        raise InputError(image, str(e)) from None
    record["image"] = Path(image).name
    # How the file was read (an Orientation tag, bits MSB-aligned): edge_orientation
    # describes the image as stored.
    record["notes"] = list(raw.notes)
    messages = [f"{image}: {note}" for note in raw.notes]
    # Clipping flattens a side of the edge spread and so overstates the MTF.
    dark, bright = clipped_pixels(raw.data, raw.full_scale)
    record["saturated_pixels"], record["clipped_dark_pixels"] = bright, dark
    for count, where, remedy in (
        (bright, f"at the image's maximum {raw.data.max():g}", "shorten the exposure"),
        (dark, f"at the image's minimum {raw.data.min():g}", "keep the camera's black level"),
    ):
        if count:
            messages.append(
                f"warning: {image}: {count} pixel(s) {where}, taken as "
                f"clipped; a clipped edge overstates the MTF: {remedy}"
            )
    if record["region_too_small"]:
        messages.append(
            f"warning: {image}: the region reaches "
            f"{record['edge_reach_px']:.1f} px either side of the edge, under "
            f"{REACH_PER_RISE:g} times its 10-90 % rise ({record['edge_rise_px']:.2f} px): "
            "the cut edge profile overstates the MTF; give a larger region, or centre "
            "the edge in it"
        )
    result = MtfResult(record, tuple(messages))
    return result if out is None else save_mtf(result, out, force=force)


def save_mtf(result, out, *, force=False):
    """Write a ``measure_mtf`` result into ``out``: ``mtf.json`` and ``mtf.png``.

    Returns
    -------
    MtfResult
        ``result`` with ``out`` and ``files`` set.

    Raises
    ------
    InputError
        Existing output files without ``force``; an unusable output folder.
    """
    from fab.verify.report import write_mtf_plot

    with staged_output(out, force, names=MTF_FILES) as stage:
        write_json(stage / "mtf.json", result.record)
        write_mtf_plot(stage / "mtf.png", result.record)
    out = Path(out)
    return dataclasses.replace(result, out=out, files=tuple(out / name for name in MTF_FILES))
