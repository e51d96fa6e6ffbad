"""verify and simulate-capture on a bench's light and stop: a band-pass and an f-number."""

import json

import numpy as np
import pytest
from test_any_bench import GREEN, _retrieve_dir

from doe.camera import design_heights, plate_orders
from doe.design import load_design
from doe.fraunhofer import simulate_levels
from doe.infra.cli import main
from doe.spectrum import gaussian_band

BENCH = ["--bandwidth-nm", "20", "--f-number", "8"]


def _verify(design, capture, out, *flags):
    code = main(["verify", str(design), str(capture / "capture.tif"), "--dark",
                 str(capture / "dark.tif"), "--out", str(out), *flags])  # fmt: skip
    return code, json.loads((out / "verify.json").read_text())


def test_a_capture_under_a_band_at_f8_is_judged_against_that_band(tmp_path):
    # 532 nm, BK7, 4 levels: a 20 nm band moves the window's orders by up to 5 x 20/532
    # of the pitch and brightens the zero order; f/8 makes the dots 0.54 px sigma
    design = _retrieve_dir(tmp_path / "green", GREEN, 35, 11, 0)
    capture = tmp_path / "cap"
    args = ["simulate-capture", str(design), "--out", str(capture), "--pixel-pitch-um", "3.45"]
    assert main([*args, *BENCH]) == 0
    recorded = json.loads((capture / "capture.json").read_text())["bench"]
    assert recorded["f_number"] == 8 and len(recorded["light"]["wavelengths_nm"]) > 9
    assert recorded["spot_sigma_um"] == pytest.approx(0.44 * 0.532 * 8)
    code, banded = _verify(design, capture, tmp_path / "band", *BENCH)
    assert code == 0, banded["diagnosis"]  # a stated bench never fails a nominal plate
    code, mono = _verify(design, capture, tmp_path / "mono")
    # The reference each compared with: the design's zero order over the band, by the
    # camera model's own dispersion (doe.camera.plate_orders), and at 532 nm alone.
    levels = np.load(design / "levels.npy")
    lab = load_design(tmp_path / "green.toml")
    band = gaussian_band(532e-9, 20e-9, 2.5e-9)
    heights = design_heights(lab, levels)
    zero = sum(
        w * abs(plate_orders(lab, heights, wl)[0, 0]) ** 2
        for wl, w in zip(band.wavelengths, band.weights, strict=True)
    )
    assert banded["design_zero_order"] == pytest.approx(zero, rel=1e-4)
    assert mono["design_zero_order"] == pytest.approx(
        simulate_levels(levels, 4, 11)[0][5, 5] * simulate_levels(levels, 4, 11)[1], rel=1e-9
    )
    assert banded["bench"]["f_number"] == 8 and mono["bench"]["spectrum"] is None
    print(  # the figures of both judgements
        f"band: corr {banded['correlation']:.5f} rmse {banded['rmse']:.5f} zero order "
        f"{banded['zero_order']:.4f} vs {banded['design_zero_order']:.4f}; monochromatic: "
        f"corr {mono['correlation']:.5f} rmse {mono['rmse']:.5f} vs "
        f"{mono['design_zero_order']:.4f} (exit {code})"
    )
