"""The camera budget in dB (psf_learn.camera_psnr, ``doefab camera-psnr``) and its place in
the fab report (``doefab fab --camera-psnr``), with a tiny model of a 532 nm / BK7 /
4-level / 12.7 mm design."""

import json

import numpy as np
import pytest
from package_helpers import make_design_dir

from doe.infra.cli import main
from doe.records.camera_psnr import read_camera_psnr

SMALL = ["--steps", "3", "--features", "4", "--stages", "1", "--batch", "2", "--patch", "16"]
GREEN = (
    "name = 'green'\n[optics]\nwavelength_nm = 532.0\n[material]\nname = 'N-BK7'\n"
    "[psf]\nkernel_size = 5\n[fabrication]\nlevels = 4\naperture_mm = 12.7\n"
)
pytestmark = pytest.mark.usefixtures("on_the_cpu")  # only CPU runs repeat bit for bit


def test_the_db_budget_scores_the_plates_effective_psfs_and_goes_into_the_report(
    tmp_path, image_folder
):
    cfg = tmp_path / "green.toml"
    cfg.write_text(GREEN)
    images = image_folder(tmp_path / "images")
    model = tmp_path / "model"
    learn = ["learn", "--out", str(model), "--images", str(images), "--config", str(cfg)]
    assert main([*learn, *SMALL, "--no-baseline"]) == 0
    design = tmp_path / "design"
    make_design_dir(design, n=15, n_levels=4, k=5)
    out = tmp_path / "psnr"
    argv = ["camera-psnr", str(design), "--model", str(model), "--out", str(out)]
    argv += ["--config", str(cfg), "--eval-images", str(images), "--crop", "64"]
    assert main(argv) == 0
    rec = read_camera_psnr(out, np.load(design / "levels.npy")).data
    assert rec["images"]["names"] == ["img0.png", "img1.png"]
    nominal = rec["nominal"]["psnr"]
    for axis, curve in rec["axes"].items():
        at_default = curve["psnr"][0 if axis == "f_number" else curve["values"].index(0.0)]
        assert at_default == pytest.approx(nominal, abs=1e-9)  # f/1.8 holds the square
        lo, hi = curve["within_budget"]["range"]
        for v, p in zip(curve["values"], curve["psnr"], strict=True):
            assert (nominal - p <= rec["allowance_db"]) or not lo <= v <= hi
    # one setting, the other way: doefab camera's effective PSF scored by doefab evaluate
    # (the 40 x 40 images lie within the 64 px crop)
    cam = tmp_path / "cam"
    assert main(["camera", str(design), "--out", str(cam), "--config", str(cfg),
                 "--defocus-um", "250"]) == 0  # fmt: skip
    scores = tmp_path / "scores.json"
    assert main(["evaluate", str(model), "--images", str(images), "--psf-file",
                 str(cam / "effective_psf.npy"), "--out", str(scores)]) == 0  # fmt: skip
    defocus = rec["axes"]["defocus_um"]
    at_250 = defocus["psnr"][defocus["values"].index(250.0)]
    assert at_250 == pytest.approx(json.loads(scores.read_text())["psnr"], abs=1e-9)
    # the fab report quotes the curves (the budget itself left out: the dB part stands alone)
    fab = tmp_path / "fab"
    assert main(["fab", str(design), "--out", str(fab), "--config", str(cfg),
                 "--camera-psnr", str(out)]) == 0  # fmt: skip
    text = (fab / "fab_report.md").read_text()
    assert "In the camera, in dB of reconstruction PSNR" in text and f"{nominal:.2f} dB" in text
    assert (fab / "fab_camera_psnr.png").stat().st_size > 0
    # refused for another tile, before anything is built
    other = tmp_path / "other"
    make_design_dir(other, n=15, n_levels=4, k=5, seed=1)
    assert main(["fab", str(other), "--out", str(tmp_path / "no"), "--config", str(cfg),
                 "--camera-psnr", str(out / "camera_psnr.json")]) == 2  # fmt: skip
    assert not (tmp_path / "no").exists()
