"""One tolerance budget: the fab report, the manifest and verify.json quote the same limits,
and verify judges the deepest etch by its budget."""

import json

import pytest
from test_any_bench import GREEN, _retrieve_dir

from doe.infra.cli import main
from doe.records.verify import read_verify
from fab.plate.budget import beyond, fit_sigma


@pytest.fixture(scope="module")
def fab_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("budget")
    design = _retrieve_dir(root / "green", GREEN, 35, 11, 0)
    assert (
        main(["fab", str(design), "--out", str(root / "fab"), "--config", str(root / "green.toml")])
        == 0
    )
    return root / "fab"


def _verify_deep(tmp_path, fab_dir, error):
    cap, out = tmp_path / "cap", tmp_path / "ver"
    args = ["simulate-capture", str(fab_dir), "--out", str(cap), "--pixel-pitch-um", "3.45"]
    assert main([*args, "--etch-error", f"M1_deep={error}"]) == 0
    code = main(["verify", str(fab_dir), str(cap / "capture.tif"), "--dark", str(cap / "dark.tif"),
                 "--out", str(out)])  # fmt: skip
    return code, read_verify(out / "verify.json").data, (out / "verify_report.html").read_text()


def test_one_budget_in_the_report_the_manifest_and_verify(tmp_path, fab_dir):
    tolerance = json.loads((fab_dir / "fab_tolerance.json").read_text())
    acceptance = json.loads((fab_dir / "fab_manifest.json").read_text())["acceptance"]
    deep = next(b for b in tolerance["budget"] if b["kind"] == "etch" and b["mask"] == "M1_deep")
    # the deepest etch's limit is its own budget (2.28 % here), not a fixed 10 %
    assert acceptance == tolerance["acceptance"]
    limit = acceptance["deep_etch_error_max"]
    assert limit == deep["si_value"] < 0.05
    report = (fab_dir / "fab_report.md").read_text()
    assert f"| deep_etch_error_max | +-{limit:.4g} (its etch budget) |" in report
    # within its budget: passes, verify.json quoting the same limits
    code, verify, html = _verify_deep(tmp_path / "in", fab_dir, round(0.8 * limit, 4))
    assert code == 0 and all(verify["thresholds"][k] == v for k, v in acceptance.items())
    assert "<b>FAIL</b>" not in html and "within budget" in html
    # beyond it: the PSF alone is within its limit; the budget, not the PSF, fails the plate
    code, verify, html = _verify_deep(tmp_path / "out", fab_dir, round(1.8 * limit, 4))
    assert verify["rmse"] <= verify["thresholds"]["rmse_max"]
    assert code == 1 and verify["diagnosis"] == ["deep_etch_error"]
    assert "<b>FAIL</b>" in html


def test_beyond_needs_two_sigma():
    assert not beyond(0.03, 0.004, 0.025) and beyond(0.035, 0.004, 0.025)
    assert beyond(-0.04, None, 0.025) and not beyond(0.02, None, 0.025)
    # a quadratic chi-square: a gain of 100 puts the value 10 sigma from 0
    assert fit_sigma(0.05, 100.0) == pytest.approx(0.005)
    assert fit_sigma(0.05, 0.0) is None
