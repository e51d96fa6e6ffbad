"""The HTML pages from fab/templates: one base, one stylesheet, text escaped, links relative."""

import json
import re
import types
from importlib import resources

import pytest

from fab.package.report import render_html
from fab.run.summary import write_index
from fab.templates import STYLESHEET, render_page
from fab.verify.report import _html as verify_html

HOSTILE = "plate <b>2</b> & <script>alert(1)</script>"


def stylesheet():
    return resources.files("fab.templates").joinpath(STYLESHEET).read_text()


def verify_report(**changes):
    """A verify.json report with every figure the page shows."""
    fits = {"overlay_error_fit": None, "etch_error_fit": None, "overlay_and_etch_fit": None}
    # fmt: off
    return {
        "pass": False,
        "diagnosis": ["deep_etch_error"],
        "thresholds": {
            "correlation_min": 0.9, "rmse_max": 0.01, "efficiency_min": 0.5,
            "zero_order_max": 0.02, "deep_etch_error_max": 0.05, "min_window_snr": 20.0,
            "significance_sigmas": 3.0, "source": "fab_tolerance.json",
        },
        "lattice": {"pitch_px": 12.0, "nominal_pitch_px": 12.0, "rotation_deg": 0.1},
        "correlation": 0.95, "rmse": 0.02, "window_snr": 40.0, "efficiency": 0.6,
        "efficiency_sigma": 0.01, "zero_order": 0.01, "zero_order_sigma": 0.001,
        "deep_etch_error_fit": 0.08, "saturated_dots": 0, "zero_order_excess": 0.002,
        "implied_deep_etch_error": 0.07, "power_outside_window": 0.2,
        "power_outside_window_sigma": 0.01, "expected_power_outside_window": 0.18,
        "power_outside_window_all_orders": 0.21, "aperture_radius_px": 2.5,
        "orders_with_signal": 90, "orders_measured": 121,
        "frame_correlation": {"design": 0.9, "rot180": 0.5, "mirror-x": 0.4, "mirror-y": 0.3},
        "zero_order_search": {
            "delta_chi2": {"rot180": -5.0, "mirror-x": -6.0, "mirror-y": -7.0},
            "runner_up_margin": 3.0,
        },
        "zero_order_px": [100.0, 120.0], "orientation": "design", "notes": [],
        "inputs": {"capture": "capture.tif", "dark": None}, **fits, **changes,
    }
    # fmt: on


def run_index(tmp_path, name=HOSTILE, description="a & b"):
    (tmp_path / "retrieve").mkdir()
    report = {"levels": 8, "quantised": {"correlation": 0.99, "rmse": 0.01, "efficiency": 0.7}}
    (tmp_path / "retrieve" / "retrieval.json").write_text(json.dumps(report))
    (tmp_path / "retrieve" / "retrieval.png").write_bytes(b"\x89PNG")
    (tmp_path / "retrieve" / "report <1>.html").write_text("")
    files = {"retrieval.json": "x", "retrieval.png": "y", "report <1>.html": "z"}
    (tmp_path / "run_state.json").write_text(json.dumps({"retrieve": {"files": files}}))
    write_index(tmp_path, types.SimpleNamespace(name=name, description=description), ["retrieve"])
    return (tmp_path / "index.html").read_text()


def pages(tmp_path):
    fab = render_html([("h1", "Fabrication report: x"), ("fig", "fab_fig_psf.png", "PSF")])
    return {"fab": fab, "verify": verify_html(verify_report()), "run": run_index(tmp_path)}


def test_every_page_extends_the_base_with_the_one_stylesheet_inline(tmp_path):
    css = stylesheet()
    for name, page in pages(tmp_path).items():
        assert page.startswith('<!DOCTYPE html>\n<html lang="en">\n<head>\n'), name
        assert f"<style>\n{css}</style>" in page, name
        assert page.endswith("</body>\n</html>\n"), name
        assert "<link" not in page and "http" not in page, name  # self-contained


def test_every_page_links_its_figures_relative_to_itself(tmp_path):
    links = {name: re.findall(r'(?:src|href)="([^"]+)"', page)
             for name, page in pages(tmp_path).items()}  # fmt: skip
    assert links["fab"] == ["fab_fig_psf.png"]
    assert links["verify"] == ["verify.png"]
    assert links["run"] == [
        "manifest.json",
        "retrieve/report &lt;1&gt;.html",
        "retrieve/retrieval.png",
        "retrieve/retrieval.png",
        "retrieve/report &lt;1&gt;.html",
        "retrieve/retrieval.json",
        "retrieve/retrieval.png",
    ]


def test_the_fab_report_escapes_its_text(tmp_path):
    page = render_html(
        [
            ("h1", f"Fabrication report: {HOSTILE}"),
            ("p", "rmse <= 0.005 & a<3"),
            ("table", ["<th>"], [['a "quoted" <i>cell</i>']]),
            ("ol", ["<li>step</li>"]),
            ("fig", 'a"b.png', "caption <x>"),
        ]
    )
    assert "<script>" not in page and "<b>" not in page and "<i>" not in page
    assert "<title>Fabrication report: plate &lt;b&gt;2&lt;/b&gt; &amp; &lt;script&gt;" in page
    assert "<p>rmse &lt;= 0.005 &amp; a&lt;3</p>" in page
    assert "<th>&lt;th&gt;</th>" in page and "<td>a &#34;quoted&#34; &lt;i&gt;cell" in page
    assert "<ol><li>&lt;li&gt;step&lt;/li&gt;</li></ol>" in page
    assert '<img src="a&#34;b.png" alt="caption &lt;x&gt;">' in page


def test_the_verify_report_escapes_its_text_and_marks_each_verdict():
    note = "capture <raw> & dark"
    page = verify_html(verify_report(notes=[note], orientation="<mirror-x>"))
    assert "<li>capture &lt;raw&gt; &amp; dark</li>" in page and "<raw>" not in page
    assert "<td>orientation</td><td>&lt;mirror-x&gt;</td>" in page
    assert "<title>doefab verify: FAIL</title>" in page
    assert "<p>Diagnosis: <b>deep_etch_error</b></p>" in page
    assert re.search(r"<td>correlation</td><td>0\.95</td><td>&gt;= 0\.9</td><td>ok</td>", page)
    assert re.search(r"<td>rmse</td><td>[^<]*</td><td>[^<]*</td><td><b>FAIL</b></td>", page)
    assert "fail only when they miss the threshold by\n3 sigma" in page
    assert "<li>none</li>" in verify_html(verify_report())


def test_the_run_index_escapes_the_design_and_the_file_names(tmp_path):
    page = run_index(tmp_path)
    assert "<script>" not in page and "<b>2</b>" not in page
    assert "<h1>doefab run: plate &lt;b&gt;2&lt;/b&gt; &amp; &lt;script&gt;" in page
    assert "<p>a &amp; b</p>" in page
    assert "<td>efficiency (8 levels)</td><td>0.7</td>" in page
    assert '<p><b>Report:</b> <a href="retrieve/report &lt;1&gt;.html">' in page
    assert '<div class="gallery">' in page and "(4 bytes)" in page


@pytest.mark.parametrize("template", ["fab_report.html", "verify_report.html", "run_index.html"])
def test_a_value_the_page_names_but_was_not_given_is_an_error(template):
    # A misspelt name would otherwise render as an empty string, silently.
    import jinja2

    with pytest.raises(jinja2.UndefinedError):
        render_page(template)
