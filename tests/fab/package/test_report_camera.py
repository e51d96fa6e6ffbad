"""The fab report's "In the camera" section (fab.package.report_camera)."""

from test_report import make_context

from doe.camera_budget import camera_budget
from doe.design import load_design
from fab.package.report import REPORT_MD, write_fab_report
from fab.package.report_camera import CAMERA_FIGURE


def test_the_report_shows_the_camera_budget_when_the_build_computed_it(tmp_path):
    context = make_context(tmp_path, with_tolerance=False)
    axes = {"rotation_deg": (0.0, 2.0), "defocus_um": (-50.0, 0.0, 50.0)}
    budget = camera_budget(load_design(), context["levels"], context["target_psf"], axes)
    names = write_fab_report(tmp_path / "with", {**context, "camera_budget": budget})
    assert CAMERA_FIGURE in names and (tmp_path / "with" / CAMERA_FIGURE).stat().st_size > 0
    text = (tmp_path / "with" / REPORT_MD).read_text()
    assert "## In the camera" in text and "plate rotation (deg" in text
    assert CAMERA_FIGURE in text
    write_fab_report(tmp_path / "without", context)
    text = (tmp_path / "without" / REPORT_MD).read_text()
    assert "## In the camera" in text and "--camera-budget adds it" in text
    assert not (tmp_path / "without" / CAMERA_FIGURE).exists()
