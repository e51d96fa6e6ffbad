"""``fab_manifest.json``: the fabrication package's description (CONVENTIONS.md plus extras).

Lengths carry their unit in the key (nm for the lithography figures, um/mm
for the optics). Etch depths are written unrounded as exact multiples of
``level_step_nm`` so that summing the depths of the masks over a pixel and
dividing by the step gives an integer level again.

``doefab fab`` writes the file (:func:`build_fab_manifest`,
:func:`write_fab_manifest`); ``doefab mesh`` and ``doefab verify`` read it
(:func:`read_fab_manifest`). The two readers need different keys: mesh the tile's
geometry (:meth:`FabManifest.tile_geometry`), verify what a capture is compared
with (:meth:`FabManifest.plate_reference`). Each view checks only its own keys, so a
manifest written by hand for one of them (verify's tests, a lab's own plate) is
not refused for a key only the other needs.
"""

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from doe.derived import as_typed
from doe.design import LONGEST_LENGTH, SHORTEST_LENGTH
from doe.infra.errors import InputError
from doe.infra.files import LEVEL_COUNT_RULE, is_level_count, previous_files, read_json, write_json

MANIFEST_NAME = "fab_manifest.json"
GDS_NAME = "mask.gds"
OASIS_NAME = "mask.oas"
LEVELS_FILE = "levels.npy"
TARGET_PSF_FILE = "target_psf.npy"
DRC_DECK = "drc.lydrc"  # the design rules as a KLayout DRC script
DRC_MARKERS = "drc.lyrdb"  # the violations as a KLayout marker database

# Data polarity and resist tone: stated once, as data the manifest and report use.
DATA_POLARITY = "a polygon marks area to etch (etched = drawn)"
RESIST_TONE = (
    "positive resist: the drawn (etched) area is exposed, so the photomask is "
    "dark-field (chrome everywhere except clear windows at the drawn polygons)"
)
ORIENTATION = (
    "Viewed onto the patterned surface, right-reading: levels.npy row 0 is the top edge "
    "(largest y) and column 0 the left edge (smallest x) of every tile; pixel (r, c) covers "
    "x in [c p, (c+1) p], y in [(N-1-r) p, (N-r) p] from the tile origin. For a chrome-down "
    "(contact or proximity) exposure the mask writer must mirror the data (about the y axis) "
    "so the pattern lands right-reading on the substrate."
)
# The keys doefab mesh cannot build a tile without, in the order it names a missing one.
TILE_KEYS = ("levels", "level_step_nm", "pixel_pitch_nm", "tile_pixels", "tiles", "levels_file")


@dataclass(frozen=True)
class TileGeometry:
    """The tile a manifest describes, as ``doefab mesh`` builds it (SI units).

    Attributes
    ----------
    n_levels : int
        Number of phase levels L.
    level_step : float
        Height of one level step (m).
    pixel_pitch : float
        Mask pixel pitch p (m).
    tile_pixels : int
        N, pixels along a tile's side.
    tiles : tuple of int
        (nx, ny) tiles across the aperture.
    array_origin_mm : tuple of float
        (x0, y0) of the lower-left tile (mm, as the meshes are); (0, 0) when the
        manifest does not say.
    edge_pixels : tuple of int
        (left, right, bottom, top): pixel columns and rows of clipped tiles that
        continue the periodic pattern past the whole-tile array to the clear
        aperture (``plate.edge_pixels``); zeros when the manifest has no ``plate``.
    """

    n_levels: int
    level_step: float
    pixel_pitch: float
    tile_pixels: int
    tiles: tuple[int, int]
    array_origin_mm: tuple[float, float]
    edge_pixels: tuple[int, int, int, int] = (0, 0, 0, 0)


@dataclass(frozen=True)
class PlateReference:
    """What ``doefab verify`` compares a capture of the plate with (SI units).

    Attributes
    ----------
    n_levels : int
        Number of phase levels L.
    levels_file : pathlib.Path
        The level map, beside the manifest.
    kernel_size : int
        K, the window of orders the plate was made for.
    lattice_pitch : float
        Pitch of the dot lattice in the focal plane (m): ``lattice_pitch_um``, or
        lambda f / (N p) from the tile when the manifest does not give it.
    etch_depths : tuple of float
        Each mask's etch depth (m) in exposure order; () when the manifest lists no masks.
    mask_pixel_pitch : float or None
        p (m); None when the manifest does not say.
    acceptance : object
        The pass/fail thresholds as written: a dict, or None (unchecked here).
    target_psf_file : pathlib.Path
        The target PSF, beside the manifest.
    target_named : bool
        Whether the manifest names the target file (then it must exist).
    patterned_fraction : float
        Fraction of the clear aperture the pattern covers (``plate``; 1 when absent):
        below 1, plain glass adds to the zero order of a capture.
    """

    n_levels: int
    levels_file: Path
    kernel_size: int
    lattice_pitch: float
    etch_depths: tuple[float, ...]
    mask_pixel_pitch: float | None
    acceptance: Any
    target_psf_file: Path
    target_named: bool
    patterned_fraction: float = 1.0


@dataclass(frozen=True)
class FabManifest:
    """A ``fab_manifest.json`` as read.

    Attributes
    ----------
    path : pathlib.Path
        The file; the files it names lie beside it.
    fields : Mapping
        Every key of the file with its value as written (read-only).
    """

    path: Path
    fields: Mapping[str, Any]

    @property
    def folder(self):
        """The fab package's folder (where the manifest's files lie)."""
        return self.path.parent

    def tile_geometry(self):
        """Return the tile's geometry; raise InputError naming the file if unusable.

        Returns
        -------
        TileGeometry
        """
        man, path = self.fields, self.path
        for key in TILE_KEYS:
            if key not in man:
                raise InputError(path, f"missing key {key!r}")
        try:
            n_levels, n = _whole(man["levels"]), _whole(man["tile_pixels"])
            step, pitch = float(man["level_step_nm"]) * 1e-9, float(man["pixel_pitch_nm"]) * 1e-9
            tiles = [_whole(t) for t in man["tiles"]]
            origin = [float(v) * 1e-6 for v in man.get("array_origin_nm", [0.0, 0.0])]
            edges = _edge_pixels(man)
        except (TypeError, ValueError, OverflowError) as e:  # int(1e400): OverflowError
            raise InputError(path, f"malformed value ({e})") from None
        if len(tiles) != 2 or min(tiles) < 1 or len(origin) != 2:
            raise InputError(path, "tiles must be [nx, ny] >= 1 and array_origin_nm [x0, y0]")
        if not is_level_count(n_levels):
            raise InputError(path, f"levels {n_levels} must be {LEVEL_COUNT_RULE}")
        if not (step > 0 and pitch > 0 and n >= 1):
            raise InputError(path, "level_step_nm > 0, pixel_pitch_nm > 0 required")
        # as every length of a design: a pitch of 1e-300 nm divides a volume by 0
        lengths_ok = all(SHORTEST_LENGTH <= x <= LONGEST_LENGTH for x in (step, pitch))
        if not (lengths_ok and np.isfinite(origin).all()):
            raise InputError(
                path,
                "level_step_nm and pixel_pitch_nm must lie between 1 pm and 1 m, "
                "array_origin_nm be finite",
            )
        if min(edges) < 0 or max(edges) > n:
            raise InputError(path, f"plate.edge_pixels must lie in 0..{n} (the tile's N)")
        return TileGeometry(
            n_levels, step, pitch, n, (tiles[0], tiles[1]), (origin[0], origin[1]), edges
        )

    def drc(self):
        """Return the design-rule check's block (``drc``) as written, or None without one."""
        block = self.fields.get("drc")
        if block is not None and not isinstance(block, Mapping):
            raise InputError(self.path, f"drc must be an object, got {block!r}")
        return block

    def levels_path(self):
        """Return the level map's path (``levels_file``); InputError if it names no file."""
        name = self.fields.get("levels_file")
        if not isinstance(name, str):
            raise InputError(self.path, f"levels_file must be a file name, got {name!r}")
        return self.folder / name

    def plate_reference(self):
        """Return what a capture of the plate is compared with; InputError if malformed.

        Only the keys are read and converted here; the checks of their values
        against the level map and target (kernel size, positive pitches and depths)
        are the caller's, which shares them with a retrieve folder's.

        Returns
        -------
        PlateReference
        """
        man, folder = self.fields, self.folder
        try:
            n_levels = int(man["levels"])
            levels_file = folder / man.get("levels_file", LEVELS_FILE)
            kernel = int(man["kernel_size"])
            if "lattice_pitch_um" in man:
                lattice = float(man["lattice_pitch_um"]) * 1e-6
            else:
                tile = int(man["tile_pixels"]) * float(man["pixel_pitch_nm"]) * 1e-9
                lattice = (
                    float(man["wavelength_nm"]) * 1e-9 * float(man["focal_length_mm"]) * 1e-3 / tile
                )
            masks = sorted(man.get("masks", []), key=lambda mk: mk["exposure_order"])
            pitch = float(man["pixel_pitch_nm"]) * 1e-9 if "pixel_pitch_nm" in man else None
            depths = [float(mk["etch_depth_nm"]) * 1e-9 for mk in masks]
            acceptance = man.get("acceptance")
            target_file = folder / man.get("target_psf_file", TARGET_PSF_FILE)
            target_named = "target_psf_file" in man
            plate = man.get("plate") or {}
            fraction = float(plate.get("patterned_fraction", 1.0))
        except (KeyError, TypeError, ValueError, OverflowError, AttributeError) as e:  # 1e400
            raise InputError(self.path, f"malformed manifest ({e!r} missing or wrong)") from None
        return PlateReference(
            n_levels, levels_file, kernel, lattice, tuple(depths), pitch, acceptance,
            target_file, target_named, fraction,
        )  # fmt: skip


def _edge_pixels(man):
    """Return ``plate.edge_pixels`` as (left, right, bottom, top); zeros when absent."""
    plate = man.get("plate") or {}
    edges = plate.get("edge_pixels", {}) if isinstance(plate, Mapping) else None
    if not isinstance(edges, Mapping):
        raise ValueError("plate.edge_pixels must be an object of left, right, bottom, top")
    return tuple(_whole(edges.get(k, 0)) for k in ("left", "right", "bottom", "top"))


def _whole(value):
    """Return ``value`` as an int, refusing 8.9 or True (int() would make them 8 and 1)."""
    if isinstance(value, bool) or float(value) != int(value):
        raise ValueError(f"{value!r} is not a whole number")
    return int(value)


def read_fab_manifest(path):
    """Read a ``fab_manifest.json``.

    Raises
    ------
    InputError
        The file is missing, not JSON or not a JSON object (naming it). Its keys
        are checked by the view a reader asks for (:meth:`FabManifest.tile_geometry`,
        :meth:`FabManifest.plate_reference`).
    """
    path = Path(path)
    return FabManifest(path, MappingProxyType(read_json(path)))


def build_fab_manifest(
    design, derived, layout, masks, acceptance=None, extra=None, kernel_size=None
):
    """Return the manifest of a fabrication package as the dict written to the file.

    Parameters
    ----------
    design : doe.design.Design
    derived : doe.derived.Derived
        Derived quantities for the tile's N (``derive(design, tile_pixels=N)``).
    layout : layouts.gds.PlateLayout
        Cell names, pitch, tiles and array origin of the written GDS; its ``plate``
        (edge pixels, clear aperture, patterned fraction) becomes the ``plate`` record
        (``dies`` comes with ``fab.package.manifest.layout_keys`` in ``extra``).
    masks : list of fab.package.masks.Mask
    acceptance : dict or None
        Pass/fail thresholds from the tolerance analysis.
    extra : dict or None
        Further keys (e.g. "oasis", "target_psf_source").
    kernel_size : int or None
        K of the target PSF the plate was made for (default the design's): the
        window verify measures and the tolerances were computed on.
    """
    n, p_nm = layout.tile_pixels, layout.pixel_pitch_nm
    step_nm = derived.level_step * 1e9
    tile_size = n * p_nm * 1e-9
    manifest = {
        "wavelength_nm": as_typed(design.optics.wavelength, 1e9),
        "refractive_index": derived.refractive_index,
        "levels": design.fabrication.levels,
        "level_step_nm": step_nm,
        "pixel_pitch_nm": int(p_nm),
        "tile_pixels": int(n),
        "tiles": [int(t) for t in layout.tiles],
        "array_origin_nm": [int(v) for v in layout.array_origin_nm],
        "gds": GDS_NAME,
        "top_cell": layout.top_cell,
        "tile_cell": layout.tile_cell,
        "levels_file": LEVELS_FILE,
        "masks": [
            {
                "name": mk.name,
                "gds_layer": mk.gds_layer,
                "gds_datatype": mk.gds_datatype,
                "etch_depth_nm": mk.steps * step_nm,
                "etch_steps": mk.steps,
                "exposure_order": mk.exposure_order,
            }
            for mk in masks
        ],
        "design_name": design.name,
        "material": design.material.name,
        "substrate_thickness_mm": as_typed(design.material.thickness, 1e3),
        "kernel_size": int(kernel_size or design.kernel_size),
        "focal_length_mm": as_typed(design.optics.focal_length, 1e3),
        "tile_size_um": n * p_nm / 1000,
        "lattice_pitch_um": design.optics.wavelength * design.optics.focal_length / tile_size * 1e6,
        "aperture_mm": as_typed(design.fabrication.aperture, 1e3),
        "target_psf_file": TARGET_PSF_FILE,
        "resist_tone": RESIST_TONE,
        "data_polarity": DATA_POLARITY,
        "orientation": ORIENTATION,
        "marks_layers": [
            {
                "gds_layer": ml.gds_layer,
                "gds_datatype": ml.gds_datatype,
                "purpose": ml.purpose,
                "merge_with_mask": ml.merge_with_mask,
            }
            for ml in layout.mark_layers
        ],
        "acceptance": dict(acceptance) if acceptance else None,
    }
    if layout.plate is not None:
        manifest["plate"] = layout.plate.as_dict()
        manifest["plate"]["edge_cells"] = [name for name, _ in layout.edge_cells]
        manifest["plate_cell"] = layout.plate_cell
    manifest.update(extra or {})
    return manifest


def drc_record(result, allowed, corner_contacts_allowed):
    """Return the manifest's ``drc`` block of a design-rule check.

    Parameters
    ----------
    result : layouts.drc.DrcResult
    allowed : bool
        The package was written with violations because ``--allow-drc`` was given.
    corner_contacts_allowed : bool
        The design's process accepts pixels touching only at a corner.
    """
    r = result.rules
    return {
        "deck": DRC_DECK,
        "markers": DRC_MARKERS,
        "rules": {
            "layers": list(r.layers),
            "datatype": 0,
            "min_width_nm": r.min_width_nm,
            "min_space_nm": r.min_space_nm,
            "min_area_um2": r.min_area_nm2 / 1e6,
            "grid_nm": r.grid_nm,
            "metrics": "euclidean",
            "checks": dict(r.limits()),
        },
        "counts": [
            {
                "layer": c.layer,
                "rule": c.rule,
                "count": c.count,
                "at_corner_contacts": c.at_corners,
                "examples_um": [list(xy) for xy in c.examples_um],
            }
            for c in result.counts
        ],
        "corner_contacts": {str(k): v for k, v in sorted(result.corner_contacts.items())},
        "total": result.total,
        "corner_contacts_allowed": bool(corner_contacts_allowed),
        "violations_allowed": bool(allowed),
    }


def write_fab_manifest(path, manifest):
    """Write a manifest (a :class:`FabManifest` or the dict of :func:`build_fab_manifest`)."""
    fields = manifest.fields if isinstance(manifest, FabManifest) else manifest
    write_json(path, dict(fields))


def previous_package_files(path, image_names):
    """Return the files an earlier package's manifest at ``path`` names after its contents.

    For removing them when a package is written again: each mask's images
    (``image_names(mask_name)``) and the OASIS file if one was written. Empty
    when there is no such manifest or it cannot be read (then nothing is removed).
    """

    def named(manifest):
        names = [name for mk in manifest["masks"] for name in image_names(mk["name"])]
        drc = manifest.get("drc") or {}
        names += [drc[key] for key in ("deck", "markers") if key in drc]
        return names + ([manifest["oasis"]] if "oasis" in manifest else [])

    return previous_files(path, named)
