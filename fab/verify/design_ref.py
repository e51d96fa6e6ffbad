"""What ``doefab verify`` reads from a design folder: a fab output or a retrieve output.

``read_design_dir`` parses the folder's ``fab_manifest.json`` (a ``doefab fab``
output) or ``retrieval.json`` (a ``doefab retrieve`` output) with its
``levels.npy`` and target PSF into a :class:`DesignRef`.
"""

import math
from dataclasses import dataclass
from pathlib import Path

from doe.infra.errors import InputError


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

    from doe.infra.files import LEVEL_COUNT_RULE, is_level_count, read_json, read_levels, read_psf

    path = Path(path)
    if not path.is_dir():
        raise InputError(path, "no such design folder (give a doefab fab or retrieve output)")
    manifest_path, retrieval_path = path / "fab_manifest.json", path / "retrieval.json"
    if manifest_path.is_file():
        man = read_json(manifest_path)
        source = manifest_path
        try:
            n_levels = int(man["levels"])
            levels_file = path / man.get("levels_file", "levels.npy")
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
            target_file = path / man.get("target_psf_file", "target_psf.npy")
            target_named = "target_psf_file" in man
        except (KeyError, TypeError, ValueError, OverflowError) as e:  # int(1e400) overflows
            raise InputError(source, f"malformed manifest ({e!r} missing or wrong)") from None
        kind = "fab"
    elif retrieval_path.is_file():
        ret = read_json(retrieval_path)
        source = retrieval_path
        try:
            n_levels = int(ret["levels"])
            kernel = int(ret["kernel_size"])
            levels_file = path / "levels.npy"
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
            target_file = path / "target_psf.npy"
            target_named = False
            acceptance = None
        except (KeyError, TypeError, ValueError, IndexError, OverflowError, AttributeError) as e:
            raise InputError(source, f"malformed retrieval.json ({e!r} missing or wrong)") from None
        kind = "retrieve"
    else:
        raise InputError(
            path,
            "neither fab_manifest.json nor retrieval.json found; give a "
            "doefab fab or doefab retrieve output folder",
        )
    if not is_level_count(n_levels):
        raise InputError(source, f"levels {n_levels} must be {LEVEL_COUNT_RULE}")
    levels = read_levels(levels_file, n_levels)
    if kind == "retrieve":
        # The mask pixel pitch snaps to the GDS grid for this N (as doe.derived.derive does).
        n = levels.shape[0]
        pitch = round(tile_nominal / n / grid) * grid
        if pitch == 0:
            raise InputError(source, f"its grid_nm is coarser than the mask pixels of N = {n}")
        lattice = wavelength * focal / (n * pitch)
    if not 1 <= kernel <= levels.shape[0] or kernel % 2 == 0:
        raise InputError(source, f"kernel_size {kernel} must be odd, 1 .. N = {levels.shape[0]}")
    if target_named and not target_file.is_file():
        raise InputError(target_file, f"named by {source.name} but missing")
    target = read_psf(target_file) if target_file.is_file() else None
    if target is not None and target.shape[0] != kernel:  # compared to nothing, silently
        raise InputError(
            target_file,
            f"is {target.shape[0]}x{target.shape[0]}, not the {source.name}'s kernel_size {kernel}",
        )
    if acceptance is not None and not isinstance(acceptance, dict):
        raise InputError(source, "acceptance must be a table of thresholds")
    if not (math.isfinite(lattice) and lattice > 0):
        raise InputError(source, f"lattice pitch {lattice} m is not positive")
    for depth in depths:  # the scale of a fitted etch error
        if not (math.isfinite(depth) and depth > 0):
            raise InputError(source, f"an etch depth of {depth * 1e9:g} nm is not positive")
    if pitch is not None and not (math.isfinite(pitch) and pitch > 0):
        raise InputError(source, f"the mask pixel pitch {pitch * 1e9:g} nm is not positive")
    files = [source.name, levels_file.name] + ([target_file.name] if target is not None else [])
    return DesignRef(
        np.asarray(levels),
        n_levels,
        kernel,
        lattice,
        tuple(depths),
        acceptance,
        target,
        kind,
        tuple(files),
        pitch,
    )
