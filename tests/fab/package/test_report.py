"""Tests of fab.package.report: every section present, files exist, bytes deterministic."""

import hashlib
import re

import numpy as np
import pytest

from doe.derived import derive, design_summary
from doe.design import load_design
from doe.fraunhofer import simulate_levels
from fab.package.masks import masks_from_levels
from fab.package.polarity import POLARITY
from fab.package.report import FIGURES, REPORT_HTML, REPORT_MD, TOLERANCE_JSON, write_fab_report
from fab.plate.tolerance import tolerance_analysis

N, K, L = 24, 7, 8


def make_context(tmp_path, with_tolerance=True):
    design = load_design()
    der = derive(design)
    rng = np.random.default_rng(7)
    levels = rng.integers(0, L, (N, N)).astype(np.uint8)
    simulated, eff = simulate_levels(levels, L, K)
    target = rng.uniform(0.5, 1.0, (K, K))
    target /= target.sum()
    masks = masks_from_levels(levels, L, der.level_step)
    pitch_nm = round(der.mask_pixel_pitch * 1e9)
    tolerance = None
    if with_tolerance:
        tolerance = tolerance_analysis(
            levels,
            L,
            target,
            masks,
            der.mask_pixel_pitch,
            der.level_step,
            design.optics.wavelength,
            der.refractive_index,
            seed=1,
        )
    listed = tmp_path / "listed.bin"
    listed.write_bytes(rng.bytes(100))
    manifest = {
        "wavelength_nm": 655.0,
        "refractive_index": der.refractive_index,
        "levels": L,
        "level_step_nm": der.level_step * 1e9,
        "pixel_pitch_nm": pitch_nm,
        "tile_pixels": N,
        "tiles": [3, 3],
        "array_origin_nm": [0, 0],
        "gds": "mask.gds",
        "top_cell": "TOP",
        "tile_cell": "TILE",
        "resist_tone": "positive resist, dark-field mask",
        "data_polarity": "a polygon marks area to etch",
        "masks": [
            {
                "name": mk.name,
                "gds_layer": mk.gds_layer,
                "gds_datatype": 0,
                "etch_depth_nm": mk.etch_depth * 1e9,
                "exposure_order": mk.exposure_order,
            }
            for mk in masks
        ],
    }
    return {
        "design": design_summary(design),
        "manifest": manifest,
        "masks": [
            {
                "name": mk.name,
                "gds_layer": mk.gds_layer,
                "etch_depth_nm": mk.etch_depth * 1e9,
                "exposure_order": mk.exposure_order,
                "fill_fraction": mk.fill_fraction,
                "polygon_count": 10 + i,
                "min_feature_um": pitch_nm / 1000,
            }
            for i, mk in enumerate(masks)
        ],
        "levels": levels,
        "target_psf": target,
        "simulated_psf": simulated,
        "efficiency": eff,
        "tolerance": tolerance,
        "orientation": "Viewed onto the patterned surface, right-reading.",
        "files": [
            {
                "path": "listed.bin",
                "bytes": 100,
                "sha256": hashlib.sha256(listed.read_bytes()).hexdigest(),
            }
        ],
    }


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    base = tmp_path_factory.mktemp("report")
    context = make_context(base)
    out = base / "out"
    names = write_fab_report(out, context)
    return context, out, names


def test_every_listed_file_exists_and_figures_are_png(written):
    _, out, names = written
    assert {REPORT_MD, REPORT_HTML, TOLERANCE_JSON, *FIGURES.values()} == set(names)
    for name in names:
        assert (out / name).is_file(), name
    for name in FIGURES.values():
        data = (out / name).read_bytes()
        assert data.startswith(b"\x89PNG")
        assert b"matplotlib" not in data.lower()  # no version stamp: deterministic bytes


@pytest.mark.parametrize("name", [REPORT_MD, REPORT_HTML])
def test_report_has_every_required_section(written, name):
    context, out, _ = written
    text = (out / name).read_text()
    for section in (
        "Summary",
        "Design and derived optics",
        "Material",
        "Process",
        "Orientation",
        "Figures",
        "Tolerances",
        "Budget",
        "Acceptance thresholds",
        "Files",
    ):
        assert section in text, section
    for m in context["masks"]:
        assert f"{m['etch_depth_nm']:.2f}" in text  # etch depth of every mask
        assert m["name"] in text
        assert f"| {m['polygon_count']} |" in text or f"<td>{m['polygon_count']}</td>" in text
    assert context["files"][0]["sha256"] in text
    assert f"{context['manifest']['refractive_index']:.5f}" in text
    assert "a polygon marks area to etch" in text
    assert "positive resist" in text
    assert "MIRRORED" in text and "chrome-down" in text
    assert f"{context['manifest']['level_step_nm']:.2f} nm" in text
    acc = context["tolerance"]["acceptance"]
    shown = re.search(r"rmse_max(?: \| |</td><td>)([-+.e\d]+)", text)  # its table row
    assert shown and float(shown.group(1)) == pytest.approx(acc["rmse_max"], rel=1e-5)
    for fig in FIGURES.values():
        assert fig in text


@pytest.mark.parametrize("name", [REPORT_MD, REPORT_HTML])
def test_files_table_lists_the_figures_and_the_tolerance_table_with_their_hashes(written, name):
    _, out, names = written
    text = (out / name).read_text()
    for listed in set(names) - {REPORT_MD, REPORT_HTML}:
        data = (out / listed).read_bytes()
        assert hashlib.sha256(data).hexdigest() in text, listed
        assert str(len(data)) in text, listed


def test_html_is_self_contained_with_relative_figure_links(written):
    _, out, _ = written
    page = (out / REPORT_HTML).read_text()
    assert page.startswith("<!DOCTYPE html>")
    links = re.findall(r'(?:src|href)="([^"]+)"', page)
    assert sorted(links) == sorted(FIGURES.values())
    for link in links:
        assert (out / link).is_file()
    assert "<style>" in page and "http" not in page


def test_same_input_gives_identical_bytes(written, tmp_path):
    context, out, names = written
    again = write_fab_report(tmp_path / "again", context)
    assert again == names
    for name in names:
        assert (tmp_path / "again" / name).read_bytes() == (out / name).read_bytes(), name


def test_report_without_tolerance_analysis(tmp_path):
    context = make_context(tmp_path, with_tolerance=False)
    names = write_fab_report(tmp_path / "out", context)
    assert FIGURES["tolerance"] not in names and TOLERANCE_JSON not in names
    text = (tmp_path / "out" / REPORT_MD).read_text()
    assert "No tolerance analysis" in text
    assert context["files"][0]["sha256"] in text


def test_summary_states_whether_the_design_meets_the_goals(written, tmp_path):
    # random levels against a random target: both goals missed, each named with its value
    _, out, _ = written
    text = (out / REPORT_MD).read_text()
    assert "design goals (correlation >= 0.9999, rmse <= 0.005) | MISSED: correlation" in text
    assert re.search(r"MISSED: correlation 0\.\d{6} < 0\.9999; rmse 0\.\d{5} > 0\.005", text)
    # the same plate against its own simulated PSF: met
    context = make_context(tmp_path, with_tolerance=False)
    context["target_psf"] = context["simulated_psf"]
    write_fab_report(tmp_path / "own", context)
    text = (tmp_path / "own" / REPORT_MD).read_text()
    assert "design goals (correlation >= 0.9999, rmse <= 0.005) | met |" in text
    assert "1.000000 / 0.00000" in text


def test_summary_judges_the_plate_of_square_pixels_too(tmp_path):
    # The plate against its own simulated PSF meets the goals in the contract's model;
    # etched, its square pixels dim order m by sinc^2(m / N), and on this small tile it
    # misses them, which the Summary hid under "met" (the tolerance section said so).
    context = make_context(tmp_path, with_tolerance=False)
    target = context["target_psf"] = context["simulated_psf"]
    env = np.sinc((np.arange(K) - K // 2) / N) ** 2
    plate = target * np.outer(env, env)
    corr = np.corrcoef(plate.ravel(), target.ravel())[0, 1]
    assert corr < 0.9999
    write_fab_report(tmp_path / "own", context)
    text = (tmp_path / "own" / REPORT_MD).read_text()
    assert "design goals (correlation >= 0.9999, rmse <= 0.005) | met |" in text
    row = re.search(r"as a plate of square pixels \(sinc\^2 envelope\) \| MISSED: correlation "
                    r"(0\.\d+) < 0\.9999", text)  # fmt: skip
    assert row and float(row[1]) == pytest.approx(corr, abs=1e-6)


def test_an_undefined_correlation_reads_undefined_not_nan(tmp_path):
    # A 1 x 1 or uniform PSF has no correlation: the tolerance section printed "nan".
    context = make_context(tmp_path)
    tol = context["tolerance"]
    tol["nominal"]["correlation"] = float("nan")
    tol["acceptance"]["correlation_min"] = float("nan")
    for row in tol["rows"]:
        row["correlation"] = float("nan")
    write_fab_report(tmp_path / "out", context)
    for name in (REPORT_MD, REPORT_HTML):
        text = (tmp_path / "out" / name).read_text()
        assert "nominal plate in this model: correlation undefined" in text
        assert not re.search(r"\bnan\b", text, re.IGNORECASE)
    text = (tmp_path / "out" / REPORT_MD).read_text()
    assert "| correlation_min | undefined |" in text


def test_markdown_report_gives_a_design_name_as_text(tmp_path):
    # "plate <b>2</b>" came out as a tag in fab_report.md (the HTML report escaped it)
    from fab.package.report import render_markdown

    blocks = [
        ("h1", "Fabrication report: plate <b>2</b> &amp; <script>x</script>"),
        ("p", "rmse <= 0.005 & a<3"),
        ("table", ["name"], [["<i>a|b</i>"]]),
    ]
    text = render_markdown(blocks)
    assert "<b>" not in text and "<script>" not in text and "<i>" not in text
    assert "&lt;b>2&lt;/b> &amp;amp; &lt;script>" in text
    assert "rmse <= 0.005 & a<3" in text  # what starts no tag or entity stays readable
    assert "| &lt;i>a\\|b&lt;/i> |" in text


def test_tile_figures_show_row_0_at_the_top_and_column_0_at_the_left(
    tmp_path, saved_figures, colour_at
):
    # One lit pixel at row 0, last column: top right in x-y, as the level map and the
    # masks are viewed onto the patterned surface (CONVENTIONS.md); a transposed,
    # flipped or mirrored picture lights another corner.
    from fab.package import figures

    n, pitch = 4, 5e-6
    levels = np.zeros((n, n), np.uint8)
    levels[0, n - 1] = L - 1
    lo, hi = 2.5, n * pitch * 1e6 - 2.5  # um: centres of the corner pixels
    corners = {"top right": (hi, hi), "top left": (lo, hi), "bottom right": (hi, lo),
               "bottom left": (lo, lo)}  # fmt: skip

    def lit(ax, points, background):
        return [k for k, p in points.items() if np.abs(colour_at(ax, *p) - background).max() > 60]

    figures.level_map(tmp_path / "levels.png", levels, L, pitch)
    ax = saved_figures[-1].axes[0]
    assert lit(ax, corners, colour_at(ax, lo, lo)) == ["top right"]  # against level 0
    figures.mask_bitmaps(tmp_path / "masks.png", [levels > 0], ["M"], [1.0], pitch)
    ax = saved_figures[-1].axes[0]
    assert colour_at(ax, hi, hi).min() > 190  # a polygon: etched, drawn white
    assert lit(ax, corners, np.zeros(3)) == ["top right"]
    # the PSF: row 0 at y = +K//2 (rows grow to -y), column 0 at x = -K//2
    psf = np.full((5, 5), 1.0)
    psf[0, 4] = 20.0
    figures.psf_comparison(tmp_path / "psf.png", psf, psf)
    ax = saved_figures[-1].axes[0]
    cells = {"top right": (2, 2), "top left": (-2, 2), "bottom right": (2, -2),
             "bottom left": (-2, -2)}  # fmt: skip
    assert lit(ax, cells, colour_at(ax, 0, 0)) == ["top right"]


@pytest.mark.parametrize("n_levels", [8, 16, 256])
def test_the_level_maps_colour_bar_labels_each_of_up_to_16_levels(
    tmp_path, saved_figures, n_levels
):
    # 256 labels, one a level, printed over each other as a black bar
    from fab.package import figures

    levels = (np.arange(16, dtype=np.uint8).reshape(4, 4) * (n_levels // 16)).astype(np.uint8)
    figures.level_map(tmp_path / "levels.png", levels, n_levels, 5e-6)
    bar = saved_figures[-1].axes[1]
    ticks = [t for t in bar.get_yticks() if -0.5 <= t <= n_levels - 0.5]
    if n_levels <= 16:
        assert ticks == list(range(n_levels))
    else:
        assert 3 <= len(ticks) <= 12 and all(t == round(t) for t in ticks)


@pytest.mark.parametrize("shape", ["circle", "square"])
def test_dot_lattice_outlines_each_active_area_in_its_shape(tmp_path, saved_figures, shape):
    from matplotlib.patches import Circle, Rectangle

    from fab.package import figures

    sensor = dict(design_summary(load_design())["sensor"], active_area_shape=shape)
    sensor["active_offset_um"] = [10.0, -5.0]
    figures.dot_lattice(tmp_path / "dots.png", np.zeros((8, 8)), sensor, 37.5e-6, spad_pixels=1)
    (ax,) = [a for a in saved_figures[-1].axes if a.get_title().startswith("Dot lattice")]
    (area,) = [p for p in ax.patches if p.get_edgecolor()[:3] == (0.0, 1.0, 1.0)]  # cyan
    # one 150 um SPAD pixel centred on the origin; its 30 um active area moved by the offset
    if shape == "circle":
        assert isinstance(area, Circle)
        assert area.center == pytest.approx((10.0, -5.0)) and area.radius == pytest.approx(15.0)
    else:
        assert isinstance(area, Rectangle) and area.get_xy() == pytest.approx((-5.0, -20.0))
        assert (area.get_width(), area.get_height()) == pytest.approx((30.0, 30.0))


@pytest.mark.parametrize("description", ["", "a plate for the SPAD array"])
def test_a_design_without_a_description_gets_no_empty_paragraph(tmp_path, description):
    # description = "" in a design file: the title goes straight on to the report's
    # own first paragraph; a description stands right under the title.
    from fab.package.report import render_markdown, report_blocks

    context = make_context(tmp_path, with_tolerance=False)
    context["design"]["description"] = description
    blocks = report_blocks(context)
    own = blocks[2] if description else blocks[1]
    assert own[0] == "p" and own[1].startswith("Written by doefab fab")
    assert ("p", "") not in blocks and (blocks[1] == ("p", description)) == bool(description)
    text = render_markdown(blocks)
    title = f"# Fabrication report: {context['design']['name']}\n\n"
    assert text.startswith(title + (f"{description}\n\n" if description else "") + "Written by")


def test_html_report_escapes_the_design_and_carries_the_shared_stylesheet(tmp_path):
    # The page is the template fab_report.html over the one base and stylesheet.
    from importlib import resources

    context = make_context(tmp_path, with_tolerance=False)
    context["design"]["name"] = "plate <b>2</b> & <script>x</script>"
    context["design"]["description"] = 'a "quoted" <i>plate</i>'
    write_fab_report(tmp_path / "out", context)
    page = (tmp_path / "out" / REPORT_HTML).read_text()
    assert "<script>" not in page and "<b>" not in page and "<i>" not in page
    heading = "Fabrication report: plate &lt;b&gt;2&lt;/b&gt; &amp; &lt;script&gt;x&lt;/script&gt;"
    assert f"<title>{heading}</title>" in page and f"<h1>{heading}</h1>" in page
    assert "<p>a &#34;quoted&#34; &lt;i&gt;plate&lt;/i&gt;</p>" in page
    css = resources.files("fab.templates").joinpath("style.css").read_text()
    assert f"<style>\n{css}</style>" in page
    for name in (FIGURES["levels"], FIGURES["psf"]):
        assert f'<img src="{name}" alt="' in page
    # every mask image shown or listed states its polarity (fab.package.polarity)
    caption = page.split(f'<img src="{FIGURES["masks"]}"')[1].split("</figcaption>")[0]
    assert POLARITY in caption
    for m in context["masks"]:
        for name in (f"{m['name']}_tile.tif", f"{m['name']}_plate.png"):
            assert POLARITY in page.split(f"<li>{name}: ")[1].split("</li>")[0], name


@pytest.mark.parametrize(
    ("material", "source", "how"),
    [
        ({"name": "fused_silica"}, "Sellmeier, Malitson, JOSA 55, 1205 (1965)", "Sellmeier"),
        ({"name": "bk7"}, "Sellmeier, SCHOTT N-BK7 data sheet", "Sellmeier"),
        (
            {"name": "g", "sellmeier_b": [1.0], "sellmeier_c_um2": [0.01], "range_nm": [300, 900]},
            "design file: Sellmeier coefficients",
            "Sellmeier",
        ),
        (
            {"name": "g", "index_table": [[400.0, 1.5], [700.0, 1.4]]},
            "design file: index table, 2 points",
            "index table",
        ),
    ],
)
def test_the_material_table_names_the_glass_and_the_source_of_its_index(
    tmp_path, material, source, how
):
    from fab.package.report import render_markdown, report_blocks

    context = make_context(tmp_path, with_tolerance=False)
    context["design"]["material"] = {**material, "thickness_mm": 0.5}
    text = render_markdown(report_blocks(context))
    assert f"| substrate | {material['name']} |" in text
    assert f"| source of the index | {source} |" in text
    assert f"| refractive index at the design wavelength ({how}) |" in text
