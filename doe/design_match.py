"""Whether a record (a tile, a PSF) was made for a design: the keys that matter, compared.

A record holds the :func:`doe.derived.design_summary` of the design it was made
for; these functions compare it with another design, key by key, in the file's
units.
"""

import math

from doe.derived import design_summary
from doe.infra.errors import InputError

# What a phase tile is made for: the sub-pixel grid its PSF is sampled on, the
# optics that map the tile onto that grid, and the glass and grid it is etched
# in. Aperture, substrate thickness, sensor size and learning do not change the
# tile. Its level count is not here: retrieve --levels may differ from the
# design's, so retrieval.json's own "levels" is what a tile is checked against.
TILE_KEYS = (
    ("sensor", "pixel_pitch_um"),
    ("sensor", "superres_factor"),
    ("optics", "wavelength_nm"),
    ("optics", "focal_length_mm"),
    ("material", "name"),
    ("fabrication", "grid_nm"),
)
# What a PSF is made for: the sub-pixel grid it is sampled on.
PSF_GRID_KEYS = (("sensor", "pixel_pitch_um"), ("sensor", "superres_factor"))


def design_differences(recorded, d, keys):
    """Return "key recorded -> d's" for each of ``keys`` where ``d`` differs from ``recorded``.

    ``recorded`` is a :func:`design_summary` dict read from a file (e.g. the
    ``design`` of retrieval.json); keys it lacks are not compared. Numbers agree
    to 1e-9 relative, which absorbs the round trip through the file's units.
    """
    return summary_differences(recorded, design_summary(d), keys)


def summary_differences(recorded, now, keys):
    """:func:`design_differences` between two :func:`design_summary` dicts.

    A key missing from either (a partial or hand-edited record) is not compared.
    """
    differences = []
    for section, key in keys:
        then = summary_field(summary_field(recorded, section), key)
        value = summary_field(summary_field(now, section), key)
        if then is None or value is None or _same_value(then, value):
            continue
        differences.append(f"{section}.{key} {_shown(then)} -> {_shown(value)}")
    return differences


def check_psf_kernel(psf, source, d):
    """Refuse a PSF of another size than design d's kernel (InputError naming ``source``).

    Else the design's records (learn.json, the fab manifest, verify's window)
    would contradict the PSF the plate is made for.
    """
    k, kd = psf.shape[0], d.kernel_size
    if k != kd:
        raise InputError(
            source,
            f"is {k} x {k}, but the kernel of design {d.name!r} is {kd} x {kd}; "
            "pass the design it was made for with --config",
        )


def summary_field(record, key):
    """Return record[key] of a JSON object, None when it is not an object or lacks it."""
    return record.get(key) if isinstance(record, dict) else None


def is_number(v):
    """Whether ``v`` is a JSON number (a bool is not one)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _same_value(a, b):
    return math.isclose(a, b, rel_tol=1e-9) if is_number(a) and is_number(b) else a == b


def _shown(v):
    return f"{v:g}" if is_number(v) else repr(v)
