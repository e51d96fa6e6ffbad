"""What ``doefab verify`` reads from a design folder: a fab output or a retrieve output.

``read_design_dir`` parses the folder's ``fab_manifest.json`` (a ``doefab fab``
output) or ``retrieval.json`` (a ``doefab retrieve`` output) with its
``levels.npy`` and target PSF into a :class:`DesignRef`.
"""

import math
from dataclasses import dataclass
from pathlib import Path

from doe.derived import snapped_pixel_pitch
from doe.infra.errors import InputError
from doe.records.fab_manifest import (
    LEVELS_FILE,
    MANIFEST_NAME,
    TARGET_PSF_FILE,
    read_fab_manifest,
)
from doe.records.retrieval import RETRIEVAL_JSON, read_retrieval


@dataclass(frozen=True)
class DesignRef:
    """What verification needs from a design folder (SI units)."""

    levels: object
    n_levels: int
    kernel_size: int
    lattice_pitch: float
    etch_depths: tuple[float, ...]  # deepest first; () when the folder does not say
    acceptance: dict | None
    target_psf: object
    kind: str
    files: tuple[str, ...]
    mask_pixel_pitch: float | None = None  # None: the manifest does not say

    @property
    def deep_etch_depth(self):
        return self.etch_depths[0] if self.etch_depths else None


def read_design_dir(path):
    """Read a fab folder (fab_manifest.json) or a retrieve folder (retrieval.json).

    Raises
    ------
    InputError
        Missing or malformed files, naming them.
    """
    import numpy as np

    from doe.infra.files import LEVEL_COUNT_RULE, is_level_count, read_levels, read_psf

    path = Path(path)
    if not path.is_dir():
        raise InputError(path, "no such design folder (give a doefab fab or retrieve output)")
    manifest_path, retrieval_path = path / MANIFEST_NAME, path / RETRIEVAL_JSON
    if manifest_path.is_file():
        ref, source, kind = read_fab_manifest(manifest_path).plate_reference(), manifest_path, "fab"
    elif retrieval_path.is_file():
        ref, source, kind = _retrieval_reference(retrieval_path), retrieval_path, "retrieve"
    else:
        raise InputError(
            path,
            f"neither {MANIFEST_NAME} nor {RETRIEVAL_JSON} found; give a "
            "doefab fab or doefab retrieve output folder",
        )
    if not is_level_count(ref.n_levels):
        raise InputError(source, f"levels {ref.n_levels} must be {LEVEL_COUNT_RULE}")
    levels = read_levels(ref.levels_file, ref.n_levels)
    lattice, pitch = ref.lattice_pitch, ref.mask_pixel_pitch
    if kind == "retrieve":
        lattice, pitch = _retrieve_lattice(ref, levels.shape[0], source)
    kernel, target_file = ref.kernel_size, ref.target_psf_file
    if not 1 <= kernel <= levels.shape[0] or kernel % 2 == 0:
        raise InputError(source, f"kernel_size {kernel} must be odd, 1 .. N = {levels.shape[0]}")
    if ref.target_named and not target_file.is_file():
        raise InputError(target_file, f"named by {source.name} but missing")
    target = read_psf(target_file) if target_file.is_file() else None
    if target is not None and target.shape[0] != kernel:  # compared to nothing, silently
        raise InputError(
            target_file,
            f"is {target.shape[0]}x{target.shape[0]}, not the {source.name}'s kernel_size {kernel}",
        )
    _check_values(source, ref.acceptance, lattice, ref.etch_depths, pitch)
    files = [source.name, ref.levels_file.name] + ([target_file.name] if target is not None else [])
    return DesignRef(
        np.asarray(levels),
        ref.n_levels,
        kernel,
        lattice,
        tuple(ref.etch_depths),
        ref.acceptance,
        target,
        kind,
        tuple(files),
        pitch,
    )


@dataclass(frozen=True)
class _RetrievalReference:
    """A retrieve folder's :class:`PlateReference` fields and what its lattice needs."""

    n_levels: int
    levels_file: Path
    kernel_size: int
    etch_depths: tuple[float, ...]
    target_psf_file: Path
    wavelength: float
    focal_length: float
    grid: float
    tile_nominal: float
    feature_size: float = 0.0  # derive() snaps a pixel of at least it no lower
    lattice_pitch: float = math.nan  # from N, once the level map is read
    mask_pixel_pitch: float | None = None
    acceptance: None = None
    target_named: bool = False


def _retrieval_reference(source):
    """Return what verify reads from a ``retrieval.json``; InputError naming it if malformed."""
    ret = read_retrieval(source).as_dict()
    try:
        n_levels, kernel = int(ret["levels"]), int(ret["kernel_size"])
        design = ret["design"]
        derived = design["derived"]
        wavelength = float(design["optics"]["wavelength_nm"]) * 1e-9
        focal = float(design["optics"]["focal_length_mm"]) * 1e-3
        depths = [float(d) * 1e-9 for d in derived["etch_depths_nm"]]
        if not depths:
            raise IndexError("etch_depths_nm is empty")
        grid = float(design["fabrication"].get("grid_nm", 1)) * 1e-9
        tile_nominal = float(derived["tile_size_nominal_um"]) * 1e-6
        if not (grid > 0 and tile_nominal > 0 and math.isfinite(grid * tile_nominal)):
            raise ValueError("grid_nm and tile_size_nominal_um must be finite and > 0")
        return _RetrievalReference(
            n_levels=n_levels,
            levels_file=source.parent / LEVELS_FILE,
            kernel_size=kernel,
            etch_depths=tuple(depths),
            target_psf_file=source.parent / TARGET_PSF_FILE,
            wavelength=wavelength,
            focal_length=focal,
            grid=grid,
            tile_nominal=tile_nominal,
            feature_size=float(design["fabrication"].get("feature_size_um", 0)) * 1e-6,
        )
    except (KeyError, TypeError, ValueError, IndexError, OverflowError, AttributeError) as e:
        raise InputError(source, f"malformed {RETRIEVAL_JSON} ({e!r} missing or wrong)") from None


def _retrieve_lattice(ref, n, source):
    """Return (lattice pitch, mask pixel pitch) of a retrieve folder's tile of N = ``n``."""
    pitch = snapped_pixel_pitch(ref.tile_nominal, n, ref.grid, ref.feature_size)  # as derive()
    if pitch == 0:
        raise InputError(source, f"its grid_nm is coarser than the mask pixels of N = {n}")
    return ref.wavelength * ref.focal_length / (n * pitch), pitch


def _check_values(source, acceptance, lattice, depths, pitch):
    """Refuse thresholds, a lattice pitch, etch depths or a pixel pitch verify cannot use."""
    if acceptance is not None and not isinstance(acceptance, dict):
        raise InputError(source, "acceptance must be a table of thresholds")
    if not (math.isfinite(lattice) and lattice > 0):
        raise InputError(source, f"lattice pitch {lattice} m is not positive")
    for depth in depths:  # the scale of a fitted etch error
        if not (math.isfinite(depth) and depth > 0):
            raise InputError(source, f"an etch depth of {depth * 1e9:g} nm is not positive")
    if pitch is not None and not (math.isfinite(pitch) and pitch > 0):
        raise InputError(source, f"the mask pixel pitch {pitch * 1e9:g} nm is not positive")


@dataclass(frozen=True)
class DesignOptics:
    """The optics and glass a design folder states (SI units), and the file that says so."""

    source: Path
    wavelength: float
    focal_length: float
    aperture: float  # the patterned width: whole tiles in a fab folder, the design's in another
    material: dict  # the [material] table, or {"name": ...} from a manifest


def read_design_optics(path):
    """Read the optics of a fab folder (fab_manifest.json) or a retrieve folder (retrieval.json).

    InputError naming the file when a key is missing or a value is not a positive number.
    """
    path = Path(path)
    manifest, retrieval = path / MANIFEST_NAME, path / RETRIEVAL_JSON
    try:
        if manifest.is_file():
            source, man = manifest, read_fab_manifest(manifest).fields
            wavelength = float(man["wavelength_nm"]) * 1e-9
            focal = float(man["focal_length_mm"]) * 1e-3
            aperture = float(man["tile_size_um"]) * 1e-6 * max(man["tiles"])
            material = {"name": man["material"]}
        else:
            source, design = retrieval, read_retrieval(retrieval).as_dict()["design"]
            wavelength = float(design["optics"]["wavelength_nm"]) * 1e-9
            focal = float(design["optics"]["focal_length_mm"]) * 1e-3
            aperture = float(design["fabrication"]["aperture_mm"]) * 1e-3
            material = design["material"]
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(source, f"no optics to image the plate with ({e!r} missing)") from None
    if not all(math.isfinite(v) and v > 0 for v in (wavelength, focal, aperture)):
        raise InputError(source, "wavelength, focal length and aperture must be > 0")
    return DesignOptics(source, wavelength, focal, aperture, material)
