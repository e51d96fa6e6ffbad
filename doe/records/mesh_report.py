"""``mesh_report.json``: what ``doefab mesh`` built (sizes, volumes, files), in mm.

The report lists every file of the mesh folder but itself with its size in bytes;
a later run into the same folder removes the ones it does not write again.
"""

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from doe.infra.errors import InputError
from doe.infra.files import previous_files, read_json, write_json

MESH_REPORT_NAME = "mesh_report.json"
UNITS = "mm"
CONVENTION = "z up, back face z=0, row 0 of levels at the largest y (CONVENTIONS.md)"
APERTURE_NOTE = (
    "lower-left tile at the manifest's array_origin_nm; the clipped edge tiles in the "
    "edge scene, same coordinates"
)


@dataclass(frozen=True)
class MeshReport:
    """The figures of one ``doefab mesh`` run.

    Attributes
    ----------
    tile : Mapping
        The tile's mesh: "triangles", "vertices", "size_mm" [x, y, z],
        "volume_mm3", "analytic_volume_mm3" (pixel relief minus chamfers),
        "volume_rel_err", "chamfers" ("corners", "leg_nm", "volume_mm3", "note": at
        pinched corners, fab.mesh.chamfer).
    aperture : Mapping
        The instanced aperture: "tiles" [nx, ny], "instances", "origin_mm",
        "pitch_mm", "note" (the whole tiles: ``aperture.*``), and the clipped edge
        tiles that fill the clear aperture around them: "edge_pieces" (distinct
        bodies), "edge_instances" (their placements) and "edge_scene" (the files
        that hold them, ``aperture_edge.*``; empty when there are none).
    files : Mapping of str to int
        Every file written but the report, with its size in bytes.
    crop : Mapping or None
        The merged crop ("tiles", "triangles", "origin_mm", "volume_mm3",
        "analytic_volume_mm3"); None when none was asked for.
    step : Mapping or None
        The STEP solid's check ("solids", "closed", "volume_mm3", "faces",
        "volume_rel_err", "ok", ...; with edge pieces also "edge": "solids",
        "volume_rel_err_max", "ok", and "ok" then covers them too); None when STEP
        was not written.
    units : str
    convention : str
    """

    tile: Mapping[str, Any]
    aperture: Mapping[str, Any]
    files: Mapping[str, int] = field(default_factory=dict)
    crop: Mapping[str, Any] | None = None
    step: Mapping[str, Any] | None = None
    units: str = UNITS
    convention: str = CONVENTION

    def as_dict(self):
        """Return the report as written to the file (no "crop" or "step" key when None)."""
        out = {
            "units": self.units,
            "convention": self.convention,
            "tile": dict(self.tile),
            "aperture": dict(self.aperture),
            "files": dict(self.files),
        }
        if self.crop is not None:
            out["crop"] = dict(self.crop)
        if self.step is not None:
            out["step"] = dict(self.step)
        return out


def write_mesh_report(path, report):
    """Write a :class:`MeshReport` (or its dict) as ``mesh_report.json``."""
    write_json(path, report.as_dict() if isinstance(report, MeshReport) else report)


def read_mesh_report(path):
    """Read a ``mesh_report.json``.

    Raises
    ------
    InputError
        Naming the file: missing, not a JSON object, a section missing or not an
        object, or "files" not a table of byte counts.
    """
    path = Path(path)
    report = read_json(path)
    for key in ("tile", "aperture", "files"):
        if not isinstance(report.get(key), dict):
            raise InputError(path, f"{key!r} must be an object, got {report.get(key)!r}")
    for key in ("crop", "step"):
        if key in report and not isinstance(report[key], dict):
            raise InputError(path, f"{key!r} must be an object, got {report[key]!r}")
    sizes = report["files"].values()
    if not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in sizes):
        raise InputError(path, "'files' must give each file's size in bytes")
    return MeshReport(
        tile=MappingProxyType(report["tile"]),
        aperture=MappingProxyType(report["aperture"]),
        files=MappingProxyType(report["files"]),
        crop=MappingProxyType(report["crop"]) if "crop" in report else None,
        step=MappingProxyType(report["step"]) if "step" in report else None,
        units=report.get("units", UNITS),
        convention=report.get("convention", CONVENTION),
    )


def previous_mesh_files(path):
    """Return the files an earlier ``mesh_report.json`` at ``path`` lists.

    For removing the ones a new run does not write again; empty when there is no
    such report or it cannot be read (then nothing is removed).
    """
    return previous_files(path, lambda report: report["files"])
