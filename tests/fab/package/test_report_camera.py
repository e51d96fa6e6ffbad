"""The fab report's "In the camera" section (fab.package.report_camera), by default in every
report, on designs other than the default preset."""

import re

import numpy as np
import pytest
from package_helpers import make_design_dir
from test_report import make_context

from doe.camera import effective_psf
from doe.camera_budget import camera_budget
from doe.design import load_design
from doe.fraunhofer import rmse, simulate_levels
from doe.infra.cli import main
from fab.package.report import REPORT_HTML, REPORT_MD, write_fab_report
from fab.package.report_camera import CAMERA_FIGURE

# 532 nm, BK7, 4 levels, a 12.7 mm clear aperture, K = 5
GREEN = (
    "name = 'green'\n[optics]\nwavelength_nm = 532.0\n[material]\nname = 'N-BK7'\n"
    "[psf]\nkernel_size = 5\n[fabrication]\nlevels = 4\naperture_mm = 12.7\n"
)
# 10 um mask pixels, a 3 mm clear aperture, K = 5
FINE = (
    "name = 'fine'\n[psf]\nkernel_size = 5\n[fabrication]\nfeature_size_um = 10.0\n"
    "aperture_mm = 3.0\n"
)
LABELS = ("band-pass FWHM", "f-number", "defocus", "plate rotation")


def test_a_default_fab_report_shows_the_four_budgets(tmp_path, camera_budget_on):
    cfg = tmp_path / "green.toml"
    cfg.write_text(GREEN)
    d = tmp_path / "design"
    make_design_dir(d, n=15, n_levels=4, k=5)
    out = tmp_path / "out"
    assert main(["fab", str(d), "--out", str(out), "--config", str(cfg)]) == 0
    assert (out / CAMERA_FIGURE).stat().st_size > 0
    text = (out / REPORT_MD).read_text()
    section = text[text.index("## In the camera") : text.index("## Files")]
    assert "the nominal camera" in section and "fabrication budget's rule" in section
    assert re.search(r"The design goals (do not )?hold in the nominal camera", section)
    rows = [
        line for line in section.splitlines() if line.startswith(("| band", "| f-", "| de", "| pl"))
    ]
    assert [label for label in LABELS if any(label in row for row in rows)] == list(LABELS)
    for row in rows:  # each range is shown, or its absence is explained
        within = row.split("|")[3].strip()
        assert re.fullmatch(r"-?[\d.]+( \(explored\))? \.\. -?[\d.]+( \(explored\))?", within) or (
            within.startswith("none: ") and "exceeds" in within
        )
    assert "In the camera" in (out / REPORT_HTML).read_text()
    # built again without it: the section says so, and the old figure goes
    argv = ["fab", str(d), "--out", str(out), "--config", str(cfg), "--force"]
    assert main([*argv, "--no-camera-budget"]) == 0
    assert "(doefab fab --no-camera-budget)" in (out / REPORT_MD).read_text()
    assert not (out / CAMERA_FIGURE).exists()


def test_the_ranges_in_the_report_end_where_the_curves_cross_the_limit(tmp_path):
    cfg = tmp_path / "fine.toml"
    cfg.write_text(FINE)
    design = load_design(cfg)
    levels = np.random.default_rng(3).integers(0, 8, (30, 30)).astype(np.uint8)
    target = simulate_levels(levels, 8, 5)[0]
    axes = {"rotation_deg": (0.0, 1.0, 2.0, 4.0, 6.0), "defocus_um": (0.0, 100.0, 400.0)}
    budget = camera_budget(design, levels, target, axes, allowance=0.005)
    limit = budget["limit"]["rmse_max"]
    assert limit == pytest.approx(budget["nominal"]["rmse"] + 0.005)
    for axis, curve in budget["axes"].items():
        within = curve["within_budget"]
        assert within["ends"][0] == "nominal" and within["ends"][1] == "limit"
        end = within["range"][1]
        # the end on the piecewise-linear curve drawn: between its two neighbours
        i = np.searchsorted(curve["values"], end)
        assert curve["rmse"][i - 1] <= limit < curve["rmse"][i]
        # and, computed afresh, the camera is within the limit just short of the end and
        # beyond it just past (the bisection's resolution)
        step = {"rotation_deg": 0.25, "defocus_um": 20.0}[axis]
        short = effective_psf(design, levels, kernel_size=5, **{axis: end - step}).psf
        past = effective_psf(design, levels, kernel_size=5, **{axis: end + step}).psf
        assert rmse(short, target) <= limit < rmse(past, target)
    context = make_context(tmp_path, with_tolerance=False)
    write_fab_report(tmp_path / "report", {**context, "camera_budget": budget})
    text = (tmp_path / "report" / REPORT_MD).read_text()
    for curve in budget["axes"].values():
        lo, hi = curve["within_budget"]["range"]
        assert f"| {lo:.3g} .. {hi:.3g} |" in text
    assert (tmp_path / "report" / CAMERA_FIGURE).stat().st_size > 0
