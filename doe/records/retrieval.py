"""``retrieval.json``: what ``doefab retrieve`` made, from which PSF, and how well.

The retrieve stage writes it beside ``levels.npy``, ``phase.npy`` and
``target_psf.npy``; fab, verify and the run summary read it. This module is its
one writer (:func:`write_retrieval`) and its one reader (:func:`read_retrieval`).

The file is a JSON object (indented, keys sorted) with

- ``continuous``, ``quantised``: the quality figures (``correlation``, ``rmse``,
  ``efficiency``) of the continuous phase and of the level map, in the model of
  CONVENTIONS.md; a uniform target's correlation is null;
- ``goals``: ``correlation_min``, ``rmse_max``, whether the level map ``met``
  them and the ``missed`` ones, one phrase each;
- ``square_pixels``: the level map's figures as a plate of square pixels (their
  sinc^2 envelope), with ``goals_met`` and ``missed``;
- ``corner_contacts``: whether the design ``allowed`` them (``[fabrication]
  allow_corner_contacts``) and their count ``per_mask``, M1 (deepest) first,
  periodic (:func:`doe.mask_rules.corner_contacts`);
- ``as_built``: the figures of the plate ``doefab fab`` lays out by default (the
  periodic pattern over the whole clear aperture, :mod:`doe.aperture`), with its
  ``patterned_fraction``, ``zero_order``, ``goals_met`` and ``missed``;
- ``seconds``, ``seed``, ``levels`` (L), ``tile_pixels`` (N), ``kernel_size`` (K);
- ``target_psf``, ``target_psf_sha256``: the input PSF's file name and digest;
- ``design``: :func:`doe.derived.design_summary` of the design as the tile
  realises it (its N and L);
- ``versions``: of numpy, scipy, nlopt and doefab.
"""

from dataclasses import dataclass, fields
from pathlib import Path

from doe.infra.errors import InputError
from doe.infra.files import read_json, write_json

RETRIEVAL_JSON = "retrieval.json"
"""The record's file name in a retrieve folder."""

_WHOLE_NUMBERS = ("levels", "tile_pixels", "kernel_size", "seed")
_NUMBERS = ("seconds",)
_OBJECTS = (
    "continuous",
    "quantised",
    "goals",
    "square_pixels",
    "corner_contacts",
    "as_built",
    "design",
    "versions",
)
_TEXTS = ("target_psf", "target_psf_sha256")


@dataclass(frozen=True)
class RetrievalRecord:
    """The content of ``retrieval.json``, one field per key (see the module's docstring).

    ``doefab retrieve`` writes every field; a record read from a partial or
    hand-written file has None for each key the file lacks (or holds as null),
    and keys this record does not know are not read.
    """

    continuous: dict | None = None
    quantised: dict | None = None
    goals: dict | None = None
    square_pixels: dict | None = None
    corner_contacts: dict | None = None
    as_built: dict | None = None
    seconds: float | None = None
    seed: int | None = None
    levels: int | None = None
    tile_pixels: int | None = None
    kernel_size: int | None = None
    target_psf: str | None = None
    target_psf_sha256: str | None = None
    design: dict | None = None
    versions: dict | None = None

    @property
    def goals_met(self):
        """Whether the level map meets the quality goals (None when the record does not say)."""
        return self.goals.get("met") if self.goals is not None else None

    @property
    def square_pixels_goals_met(self):
        """Whether the plate of square pixels meets them (None when the record does not say)."""
        return self.square_pixels.get("goals_met") if self.square_pixels is not None else None

    def as_dict(self):
        """Return the record as the JSON object of the file: its keys, without the absent ones."""
        return {
            f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None
        }


def read_retrieval(path):
    """Read and check ``retrieval.json`` (a file, or the retrieve folder that holds it).

    Parameters
    ----------
    path : str or Path
        The file, or a folder with :data:`RETRIEVAL_JSON` in it.

    Returns
    -------
    RetrievalRecord

    Raises
    ------
    InputError
        Naming the file: missing, not readable JSON, not a JSON object, or a key
        of the wrong type ("'levels' must be a whole number, got 8.5").
    """
    path = Path(path)
    if path.is_dir():
        path = path / RETRIEVAL_JSON
    raw = read_json(path)
    values = {}
    for f in fields(RetrievalRecord):
        value = raw.get(f.name)
        if value is not None:
            _check_type(path, f.name, value)
        values[f.name] = value
    return RetrievalRecord(**values)


def write_retrieval(path, record):
    """Write ``record`` (a :class:`RetrievalRecord` or a dict of its keys) to ``path``, atomically.

    The bytes are those of :func:`doe.infra.files.write_json`: indented, keys
    sorted, NaN as null; the same record gives the same bytes.
    """
    if isinstance(record, RetrievalRecord):
        record = record.as_dict()
    write_json(path, record)


def _check_type(path, key, value):
    """Refuse a value of the wrong JSON type for ``key`` (InputError naming the file)."""
    if key in _WHOLE_NUMBERS and not _is_whole_number(value):
        raise InputError(path, f"'{key}' must be a whole number, got {value!r}")
    if key in _NUMBERS and not (isinstance(value, int | float) and not isinstance(value, bool)):
        raise InputError(path, f"'{key}' must be a number, got {value!r}")
    if key in _OBJECTS and not isinstance(value, dict):
        raise InputError(path, f"'{key}' must be a JSON object, got {value!r}")
    if key in _TEXTS and not isinstance(value, str):
        raise InputError(path, f"'{key}' must be a string, got {value!r}")


def _is_whole_number(value):
    return isinstance(value, int) and not isinstance(value, bool)
