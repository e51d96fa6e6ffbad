"""Helpers shared by verify's tests: the design, its plate's lattice on the camera, a run.

Importable by name from the tests (pyproject's pytest ``pythonpath`` holds this folder).
"""

import json

from doe.fraunhofer import simulate_levels
from doe.infra.cli import main
from doe.infra.files import save_npy, write_json
from fab.verify.capture import write_image
from fab.verify.simulate import simulate_capture

N, K, L = 35, 11, 8
PITCH_UM, CAMERA_UM = 37.504, 3.45
PITCH_PX = PITCH_UM / CAMERA_UM


def make_design_dir(path, levels, acceptance=None):
    """A minimal fab folder: manifest with the keys verify reads, levels, target PSF."""
    path.mkdir(parents=True, exist_ok=True)
    save_npy(path / "levels.npy", levels)
    save_npy(path / "target_psf.npy", simulate_levels(levels, L, K)[0])
    manifest = {
        "levels": L,
        "kernel_size": K,
        "lattice_pitch_um": PITCH_UM,
        "levels_file": "levels.npy",
        "target_psf_file": "target_psf.npy",
        # listed in any order: exposure_order 1 is the deep etch
        "masks": [
            {"name": "M3_shallow", "etch_depth_nm": 179.4, "exposure_order": 3},
            {"name": "M2_mid", "etch_depth_nm": 358.8, "exposure_order": 2},
            {"name": "M1_deep", "etch_depth_nm": 717.6, "exposure_order": 1},
        ],
    }
    if acceptance is not None:
        manifest["acceptance"] = acceptance
    write_json(path / "fab_manifest.json", manifest)
    return path


def run_verify(
    tmp_path, levels, sim_kwargs, name="capture.png", flags=(), dark=True, design_levels=None
):
    design = make_design_dir(
        tmp_path / "design", levels if design_levels is None else design_levels
    )
    sim = simulate_capture(levels, L, **{"pitch_px": PITCH_PX, **sim_kwargs})
    write_image(tmp_path / name, sim["capture"], exposure=0.01)
    # the tests' bench, stated: a sparse or dim capture cannot tell its own pitch
    if not any(str(f).startswith("--pixel-pitch-um") for f in flags):
        flags = ("--pixel-pitch-um", str(CAMERA_UM), *flags)
    args = ["verify", str(design), str(tmp_path / name), "--out", str(tmp_path / "out"), *flags]
    if dark:
        write_image(tmp_path / ("dark" + name[name.index(".") :]), sim["dark"], exposure=0.01)
        args += ["--dark", str(tmp_path / ("dark" + name[name.index(".") :]))]
    code = main(args)
    report = None
    if (tmp_path / "out" / "verify.json").exists():
        report = json.loads((tmp_path / "out" / "verify.json").read_text())
    return code, report, sim
