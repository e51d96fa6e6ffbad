"""Every preset through ``doefab simulate-capture`` and ``doefab verify``: the nominal plate
passes, a conjugate one fails, on the bench each preset was measured with."""

import json
import time

import numpy as np
import pytest

from doe.derived import derive, design_summary
from doe.design import load_design
from doe.fraunhofer import round_levels, simulate_levels
from doe.gerchberg_saxton import gerchberg_saxton
from doe.infra.cli import main
from doe.targets import make_target
from fab.verify.plate_check import verify_plate

# The bench of each preset (camera pixel pitch in um, test lens focal length in mm;
# None: the design's own lens).
BENCHES = {
    "sun2020": (3.45, 50.0),
    "pf32": (2.2, None),
    "swissspad": (3.45, 50.0),
    "swissspad2": (3.45, 50.0),
}


# The tile in mask pixels: the preset's own tile (its size, so its lattice on the camera)
# cut into 35 x 35 coarser pixels. A tile of the preset's N (175-266) costs verify's fault
# fits of a conjugate plate about 20 s and a retrieval minutes; the lattice, the dots and
# the orders verify measures are the preset's own.
TILE_PIXELS = 35


def _design_dir(path, name):
    """A retrieve folder of the preset (its optics, sensor, material, K and L) with a
    TILE_PIXELS tile, its level map retrieved at the least effort: weighted quantised
    Gerchberg-Saxton (verify judges the plate against the level map it is given)."""
    design = load_design(name)
    k, levels_n = design.kernel_size, design.fabrication.levels
    target = make_target("asymmetric", k)
    rng = np.random.default_rng(0)
    phase, _ = gerchberg_saxton(target, TILE_PIXELS, 30, rng, n_levels=levels_n)
    levels = round_levels(phase, levels_n)
    path.mkdir(parents=True)
    np.save(path / "levels.npy", levels)
    np.save(path / "target_psf.npy", simulate_levels(levels, levels_n, k)[0])
    summary = design_summary(design, TILE_PIXELS)
    record = {"levels": levels_n, "kernel_size": k, "design": summary}
    (path / "retrieval.json").write_text(json.dumps(record))
    # the preset's own lattice: the tile's size is the preset's whatever its pixels
    assert derive(design, TILE_PIXELS).lattice_pitch == pytest.approx(
        derive(design).lattice_pitch, rel=1e-3
    )
    return path


def test_every_preset_passes_its_nominal_plate_and_fails_a_conjugate_one(tmp_path, preset):
    assert set(BENCHES) >= {preset}, f"give the {preset} preset a bench here"
    start = time.perf_counter()
    design = _design_dir(tmp_path / "design", preset)
    camera_um, lens_mm = BENCHES[preset]
    bench = ["--pixel-pitch-um", str(camera_um)]
    stated = bench  # verify is told the camera, and the lattice a test lens makes
    if lens_mm is not None:
        bench = [*bench, "--focal-length-mm", str(lens_mm)]
        own = load_design(preset)
        lattice = derive(own, TILE_PIXELS).lattice_pitch
        lattice_um = lattice * 1e6 * lens_mm * 1e-3 / own.optics.focal_length
        stated = [*stated, "--lattice-pitch-um", f"{lattice_um:.6g}"]
    for plate, faults in (("nominal", []), ("conjugate", ["--conjugate"])):
        args = ["simulate-capture", str(design), "--out", str(tmp_path / plate), *bench, *faults]
        assert main(args) == 0
    out = tmp_path / "verify"
    code = main(["verify", str(design), str(tmp_path / "nominal" / "capture.tif"), "--dark",
                 str(tmp_path / "nominal" / "dark.tif"), "--out", str(out), *stated])  # fmt: skip
    report = json.loads((out / "verify.json").read_text())
    assert code == 0, report["diagnosis"]
    # the camera's pixels from the lattice measured in the capture (swissspad2's dots of
    # 0.27 px sigma, 5.9 px apart, read 0.46 % wide)
    assert report["implied_pixel_pitch_um"] == pytest.approx(camera_um, rel=1e-2)
    # the conjugate plate through the library verify runs (its report figures take a
    # second a preset): the command's exit code is 0 exactly when it passes
    conjugate = tmp_path / "conjugate"
    result = verify_plate(
        design, conjugate / "capture.tif", dark=conjugate / "dark.tif", **_stated(stated)
    )
    assert not result.passed and result.report["diagnosis"] == ["conjugate_plate"]
    print(f"{preset}: {time.perf_counter() - start:.2f} s")


def _stated(flags):
    """verify_plate's keywords of the command-line flags ``flags``."""
    pairs = dict(zip(flags[::2], flags[1::2], strict=True))
    return {k.lstrip("-").replace("-", "_"): float(v) for k, v in pairs.items()}
