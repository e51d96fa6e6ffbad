"""The retrieve stage: an L-level phase tile from a target PSF file, written to a folder.

:func:`retrieve` is what ``doefab retrieve`` does, callable from Python: it
checks the PSF against the design, runs :func:`doe.retrieval.retrieve_phase`,
and writes ``levels.npy``, ``phase.npy``, ``target_psf.npy``, ``retrieval.json``
(:mod:`doe.records.retrieval`) and ``retrieval.png`` into the output folder,
all or nothing. It prints nothing; the command prints the summary and the
warnings from the :class:`RetrieveResult`.
"""

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from doe import figures, fraunhofer
from doe.derived import derive, design_summary
from doe.design import MAX_TILE_PIXELS, load_design
from doe.goals import CORRELATION_GOAL, RMSE_GOAL, missed_goals
from doe.infra import flags
from doe.infra.errors import InputError
from doe.infra.files import (
    LEVEL_COUNT_RULE,
    is_level_count,
    read_psf,
    save_npy,
    sha256_file,
    staged_output,
)
from doe.mask_rules import corner_contacts
from doe.records.psf_source import check_psf_grid
from doe.records.retrieval import RETRIEVAL_JSON, RetrievalRecord, write_retrieval
from doe.retrieval import Retrieval, retrieve_phase

OUTPUTS = ("levels.npy", "phase.npy", "target_psf.npy", RETRIEVAL_JSON, "retrieval.png")
"""The files :func:`retrieve` writes into its output folder."""


@dataclass(frozen=True)
class RetrieveResult:
    """What :func:`retrieve` made.

    Attributes
    ----------
    out : Path
        The output folder.
    record : RetrievalRecord
        The content of its ``retrieval.json``.
    retrieval : Retrieval
        The level map, the continuous phase and their quality figures.
    target : (K, K) float64
        The target PSF as read.
    simulated_psf : (K, K) float64
        The level map's PSF in the model of CONVENTIONS.md (normalised).
    missed : tuple of str
        The quality goals the level map misses, one phrase each (empty: met).
    square_pixels_missed : tuple of str
        Those a plate of square pixels misses (their sinc^2 envelope).
    as_built_missed : tuple of str
        Those the plate as ``doefab fab`` builds it misses (the periodic pattern over
        the whole clear aperture, :mod:`doe.aperture`).
    files : tuple of str
        The files written, relative to ``out``.
    """

    out: Path
    record: RetrievalRecord
    retrieval: Retrieval
    target: np.ndarray
    simulated_psf: np.ndarray
    missed: tuple[str, ...]
    square_pixels_missed: tuple[str, ...]
    as_built_missed: tuple[str, ...] = ()
    files: tuple[str, ...] = OUTPUTS

    @property
    def goals_met(self):
        """Whether the level map meets the quality goals (CONVENTIONS.md's model)."""
        return not self.missed


def retrieve(
    psf,
    out,
    *,
    config=None,
    levels=None,
    tile_pixels=None,
    seed=None,
    force=False,
    progress=True,
):
    """Design an L-level phase tile for the target PSF in file ``psf``; write it to ``out``.

    Parameters
    ----------
    psf : str or Path
        Target PSF: a float64 (K, K) .npy, K odd, >= 0, sum 1. A ``learn.json``
        or ``verify.json`` beside it must agree with the design's sub-pixel grid.
    out : str or Path
        Output folder (created if needed); nothing appears in it unless every
        file is written.
    config : str or Path or None
        Design TOML file or preset name (None: the default preset).
    levels : int or None
        Phase levels L, a power of two from 2 to 256 (None: the design's).
    tile_pixels : int or None
        Tile size N in pixels (None: the design's).
    seed : int or None
        Seed of the random start (None: the design's ``[learning] seed``).
    force : bool
        Overwrite files of an earlier run in ``out``.
    progress : bool
        Show a progress bar on stderr (when it is a terminal).

    Returns
    -------
    RetrieveResult

    Raises
    ------
    InputError
        Unusable input, naming the file or the command's flag (``--levels``,
        ``--tile-pixels``, ``--seed``) as ``doefab retrieve`` does.
    """
    if not str(out).strip():  # Path("") would be the current folder
        raise InputError("--out", "is empty")
    design = load_design(config)
    n_levels, n, seed = _tile_settings(design, levels, tile_pixels, seed)
    target = read_psf(psf)
    check_psf_grid(psf, design)
    k = target.shape[0]
    if k > n:
        raise InputError(
            psf,
            f"kernel size K = {k} exceeds the tile size N = {n}; "
            "use a smaller PSF or a larger --tile-pixels",
        )
    with staged_output(out, force, names=OUTPUTS) as stage:
        allowed = design.fabrication.allow_corner_contacts
        result = retrieve_phase(
            target, n, n_levels, seed=seed, progress=progress, allow_corner_contacts=allowed
        )
        simulated, _ = fraunhofer.simulate_levels(result.levels, n_levels, k)
        record = _record(result, psf, target, _with_levels(design, n_levels), n)
        save_npy(stage / "levels.npy", result.levels)
        save_npy(stage / "phase.npy", result.phase.astype(np.float64))
        save_npy(stage / "target_psf.npy", target)
        write_retrieval(stage / RETRIEVAL_JSON, record)
        # looked up on its module at each call, where a caller (a test) may replace it
        figures.save_retrieval_figure(
            stage / "retrieval.png",
            target,
            simulated,
            result.levels,
            n_levels,
            result.quality_quantised,
        )
    missed, plate_missed = record.goals["missed"], record.square_pixels["missed"]
    built_missed = record.as_built["missed"] if record.as_built else ()
    return RetrieveResult(
        Path(out), record, result, target, simulated, tuple(missed), tuple(plate_missed),
        tuple(built_missed),
    )  # fmt: skip


def _record(result, psf, target, design, n):
    """Return the :class:`RetrievalRecord` of ``result``, a tile of N = ``n`` for ``design``."""
    n_levels = result.n_levels
    missed = missed_goals(result.quality_quantised)
    plate = fraunhofer.plate_quality(fraunhofer.level_phase(result.levels, n_levels), target)
    plate_missed = missed_goals(plate)
    return RetrievalRecord(
        continuous=result.quality_continuous,
        quantised=result.quality_quantised,
        goals={
            "correlation_min": CORRELATION_GOAL,
            "rmse_max": RMSE_GOAL,
            "met": not missed,
            "missed": missed,
        },
        # the quantised design as fabricated: square pixels, whose sinc^2
        # envelope the contract's figures leave out
        square_pixels={**plate, "goals_met": not plate_missed, "missed": plate_missed},
        corner_contacts={
            "allowed": design.fabrication.allow_corner_contacts,
            "per_mask": list(corner_contacts(result.levels, n_levels)),
        },
        as_built=_as_built(result.levels, n_levels, design, n, target),
        seconds=round(result.seconds, 3),
        seed=result.seed,
        levels=n_levels,
        tile_pixels=n,
        kernel_size=target.shape[0],
        # name and digest, not the path: the same input gives the same bytes
        target_psf=Path(psf).name,
        target_psf_sha256=sha256_file(psf),
        # the design as this tile realises it: its N and L, where flags set them
        design=design_summary(design, tile_pixels=n),
        versions=_versions(),
    )


def _as_built(levels, n_levels, design, n, target):
    """The figures of the plate fab lays out by default (None where the grid leaves no pitch)."""
    from doe.aperture import as_built, as_built_record, design_plate

    if derive(design, tile_pixels=n).mask_pixel_pitch <= 0:
        return None
    return as_built_record(as_built(levels, n_levels, design_plate(design, n), target))


def _tile_settings(design, levels, tile_pixels, seed):
    """Return (L, N, seed): the flags' values or the design's, checked (InputError)."""
    n_levels = design.fabrication.levels if levels is None else levels
    if not is_level_count(n_levels):
        raise InputError("--levels", f"must be {LEVEL_COUNT_RULE}, got {n_levels}")
    n = derive(design).tile_pixels if tile_pixels is None else tile_pixels
    if not 1 <= n <= MAX_TILE_PIXELS:
        raise InputError(
            "--tile-pixels",
            f"must be 1 to {MAX_TILE_PIXELS} pixels (time and memory grow as N^2), got {n}",
        )
    flags.seed("--seed", seed)
    return n_levels, n, design.learning.seed if seed is None else seed


def _versions():
    """Return the versions of the packages a level map depends on."""
    from importlib import metadata

    import nlopt
    import numpy
    import scipy

    try:
        doefab = metadata.version("doefab")
    except metadata.PackageNotFoundError:
        doefab = "unknown"
    return {
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "nlopt": nlopt.__version__,
        "doefab": doefab,
    }


def _with_levels(design, n_levels):
    """Return ``design`` quantised to ``n_levels`` (``--levels`` may differ from its own)."""
    return replace(design, fabrication=replace(design.fabrication, levels=n_levels))
