"""The design-rule check of a package's GDS: run, write the deck and markers, refuse or allow.

``doefab fab`` checks every mask layer (pattern and marks) at the design's feature
size with :mod:`layouts.drc`, writes the same rules as a KLayout DRC script
(``drc.lydrc``) and the markers as a KLayout marker database (``drc.lyrdb``), and
refuses a package with violations unless ``--allow-drc`` is given. A design whose
``[fabrication] allow_corner_contacts = true`` states that its process prints pixels
touching only at a corner: those markers are then listed but not refused.
"""

import shutil
import tempfile
from pathlib import Path

from doe.infra.errors import InputError
from doe.records.fab_manifest import DRC_DECK, DRC_MARKERS, GDS_NAME


class DrcRefused(InputError):
    """The package has design-rule violations and ``--allow-drc`` was not given (exit 2)."""


def allows_corner_contacts(design):
    """Whether the design's process accepts pixels touching only at a corner
    (``[fabrication] allow_corner_contacts``; False for a design that does not say)."""
    return bool(getattr(design.fabrication, "allow_corner_contacts", False))


def design_rules(design, masks):
    """Return the design's rules (:class:`layouts.drc.DrcRules`) for its mask layers."""
    from layouts.drc import plate_rules

    feature_nm = round(design.fabrication.feature_size * 1e9)
    grid_nm = round(design.fabrication.grid * 1e9)
    return plate_rules(sorted({mk.gds_layer for mk in masks}), feature_nm, grid_nm)


def refused_count(result, allow_corners):
    """The violations that refuse a package: every marker, less the corner contacts
    when the process accepts them."""
    return result.beyond_corners() if allow_corners else result.total


def run_package_drc(stage, design, masks, allow_drc, out):
    """Check ``stage``/mask.gds, write the deck and the markers beside it.

    Parameters
    ----------
    stage : pathlib.Path
        The staging folder holding mask.gds.
    design : doe.design.Design
    masks : list of fab.package.masks.Mask
    allow_drc : bool
        Write the package even with violations (``--allow-drc``).
    out : pathlib.Path
        The package's folder (named in the refusal).

    Returns
    -------
    (layouts.drc.DrcResult, dict)
        The result and the manifest's ``drc`` block.

    Raises
    ------
    DrcRefused
        Violations without ``allow_drc``: the GDS, deck and markers are copied to a
        new temporary folder for review, and nothing is written to ``out``.
    """
    from doe.records.fab_manifest import drc_record
    from layouts.drc import check_plate
    from layouts.drc_deck import deck_xml
    from layouts.drc_rdb import write_lyrdb

    rules = design_rules(design, masks)
    result = check_plate(stage / GDS_NAME, rules)
    (stage / DRC_DECK).write_text(deck_xml(rules, design.name))
    write_lyrdb(stage / DRC_MARKERS, result, GDS_NAME, design.name)
    allow_corners = allows_corner_contacts(design)
    refused = refused_count(result, allow_corners)
    if refused and not allow_drc:
        review = Path(tempfile.mkdtemp(prefix="doefab-drc-"))
        for name in (GDS_NAME, DRC_DECK, DRC_MARKERS):
            shutil.copyfile(stage / name, review / name)
        raise DrcRefused(
            review / DRC_MARKERS,
            f"{refused} design-rule markers ({violation_summary(result, allow_corners)}); "
            f"nothing written to {out}; review with `klayout {review / GDS_NAME} -m "
            f"{review / DRC_MARKERS}`, or pass --allow-drc to write the package anyway",
        )
    return result, drc_record(result, allow_drc and refused > 0, allow_corners)


def violation_summary(result, allow_corners=False):
    """Return 'L1 width 336, L1 space 12 (all at corner contacts), ...' for the non-zero counts."""
    parts = []
    for c in result.counts:
        if not c.count:
            continue
        if c.at_corners == c.count:
            note = " (corner contacts, allowed)" if allow_corners else " (all at corner contacts)"
        elif c.at_corners:
            note = f" ({c.at_corners} at corner contacts)"
        else:
            note = ""
        parts.append(f"L{c.layer} {c.rule} {c.count}{note}")
    return ", ".join(parts) or "none"
