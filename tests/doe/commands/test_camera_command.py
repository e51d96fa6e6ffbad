"""``doefab camera``: its files, refusals, the spectrum file, and the PSF's provenance."""

import json

import numpy as np
import pytest

from doe.camera import effective_psf
from doe.derived import derive, design_summary
from doe.design import load_design
from doe.fraunhofer import simulate_levels
from doe.infra.cli import main
from doe.records.camera import read_camera
from doe.records.psf_source import check_psf_grid
from doe.spectrum import gaussian_band, read_spectrum

SMALL = "name = 'small'\n[psf]\nkernel_size = 5\n[fabrication]\nfeature_size_um = 25.0\n"
# another pitch and glass: 532 nm, BK7, 4 levels, 10 um features, a 12.7 mm aperture
GREEN = (
    "name = 'green'\n[optics]\nwavelength_nm = 532.0\n[material]\nname = 'N-BK7'\n"
    "[psf]\nkernel_size = 5\n[fabrication]\nlevels = 4\nfeature_size_um = 20.0\n"
    "aperture_mm = 12.7\n"
)


@pytest.fixture
def folder(tmp_path):
    """Return make(text): a design file and a retrieve-like folder of a tile for it."""

    def make(text, name="small"):
        config = tmp_path / f"{name}.toml"
        config.write_text(text)
        d = load_design(config)
        n, k = derive(d).tile_pixels, d.kernel_size
        rng = np.random.default_rng(0)
        levels = rng.integers(0, d.fabrication.levels, (n, n)).astype(np.uint8)
        where = tmp_path / f"{name}_tile"
        where.mkdir()
        np.save(where / "levels.npy", levels)
        np.save(where / "target_psf.npy", simulate_levels(levels, d.fabrication.levels, k)[0])
        record = {"levels": d.fabrication.levels, "design": design_summary(d, n)}
        (where / "retrieval.json").write_text(json.dumps(record))
        return config, where, d, levels

    return make


@pytest.mark.parametrize("text, name", [(SMALL, "small"), (GREEN, "green")])
def test_camera_writes_the_effective_psf_and_its_record(folder, tmp_path, capsys, text, name):
    config, where, d, levels = folder(text, name)
    out = tmp_path / "cam"
    argv = ["camera", str(where), "--out", str(out), "--config", str(config)]
    flags = ["--bandwidth-nm", "8", "--f-number", "16", "--defocus-um", "50", "--rotation-deg", "2"]
    assert main([*argv, *flags]) == 0
    assert "collected fraction" in capsys.readouterr().out
    psf = np.load(out / "effective_psf.npy")
    assert psf.shape == (5, 5) and psf.dtype == np.float64 and psf.min() >= 0
    assert psf.sum() == pytest.approx(1.0, abs=1e-12)
    record = read_camera(out / "camera.json")
    s = record.settings
    assert (s["bandwidth_nm"], s["f_number"], s["defocus_um"], s["rotation_deg"]) == (8, 16, 50, 2)
    again = effective_psf(
        d, levels, bandwidth_nm=8, f_number=16, defocus_um=50, rotation_deg=2
    )  # the library gives the command's numbers
    assert np.array_equal(again.psf, psf)
    assert record.collected_fraction == pytest.approx(again.collected_fraction)
    target = np.load(where / "target_psf.npy")
    assert record.correlation == pytest.approx(np.corrcoef(psf.ravel(), target.ravel())[0, 1])
    assert (out / "camera.png").stat().st_size > 0
    assert main([*argv]) == 2  # nothing overwritten without --force
    assert "would overwrite" in capsys.readouterr().err
    check_psf_grid(out / "effective_psf.npy", d)  # the design it was computed for passes


def test_an_effective_psf_for_another_grid_is_refused(folder, tmp_path):
    from doe.infra.errors import InputError

    config, where, _, _ = folder(SMALL)
    out = tmp_path / "cam"
    assert main(["camera", str(where), "--out", str(out), "--config", str(config)]) == 0
    (tmp_path / "factor2.toml").write_text("[sensor]\nsuperres_factor = 2\n")
    with pytest.raises(InputError, match=r"camera\.json.*superres_factor 4 -> 2"):
        check_psf_grid(out / "effective_psf.npy", load_design(tmp_path / "factor2.toml"))


def test_a_folder_made_for_another_design_is_refused(folder, tmp_path, capsys):
    _, where, _, _ = folder(SMALL)
    (tmp_path / "other.toml").write_text(
        SMALL.replace("[fabrication]", "[optics]\nwavelength_nm = 600.0\n[fabrication]")
    )
    argv = [
        "camera",
        str(where),
        "--out",
        str(tmp_path / "o"),
        "--config",
        str(tmp_path / "other.toml"),
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "retrieval.json" in err and "wavelength_nm 655 -> 600" in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "text, problem",
    [
        ("", "holds no"),
        ("650 1\n660\n", "line 2 has 1 columns"),
        ("650 1\n660 -1\n", "weights must be >= 0"),
        ("0.65 1\n", "outside"),
        ("650 1\n650 2\n", "appears twice"),
        ("650 x\n", "not two numbers"),
    ],
)
def test_a_bad_spectrum_file_is_exit_2_naming_it(folder, tmp_path, capsys, text, problem):
    config, where, _, _ = folder(SMALL)
    bad = tmp_path / "light.txt"
    bad.write_text(text)
    argv = ["camera", str(where), "--out", str(tmp_path / "o"), "--config", str(config)]
    assert main([*argv, "--spectrum", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and problem in err and len(err.strip().splitlines()) == 1


def test_a_spectrum_file_and_a_gaussian_band(tmp_path):
    path = tmp_path / "light.csv"
    path.write_text("# nm, weight\n660, 1\n650, 3\n\n655, 0\n")
    s = read_spectrum(path)
    assert s.wavelengths == pytest.approx((650e-9, 660e-9)) and s.weights == (0.75, 0.25)
    band = gaussian_band(655e-9, 20e-9, 2e-9)
    w, wl = np.array(band.weights), np.array(band.wavelengths)
    assert w.sum() == pytest.approx(1.0) and np.sum(w * wl) == pytest.approx(655e-9)
    # a Gaussian of FWHM 20 nm: its weights fall to half 10 nm off centre
    half = np.interp(10e-9, wl - 655e-9, w) / w.max()
    assert half == pytest.approx(0.5, abs=0.01)
    sigma = 20e-9 / (2 * np.sqrt(2 * np.log(2)))
    assert np.sqrt(np.sum(w * (wl - 655e-9) ** 2)) == pytest.approx(sigma, rel=0.02)


def test_faults_reach_the_camera_through_the_plate_heights(folder):
    # every mask 10 % too deep: the heights scale by 1.1 (plus a constant phase),
    # so the plate model's heights give what scaled nominal heights give
    from fab.plate.model import PlateFaults, level_plate_model, tile_height

    _, _, d, levels = folder(SMALL)
    step = derive(d).level_step
    model = level_plate_model(levels, 8, supersample=2)
    heights = tile_height(model, PlateFaults(etch_errors=(0.1, 0.1, 0.1))) * step
    nominal = tile_height(model) * step
    assert np.array_equal(nominal[::2, ::2], levels * step)
    faulty = effective_psf(d, levels, heights=heights, supersample=2, f_number=20)
    scaled = effective_psf(d, levels, heights=nominal * 1.1, supersample=2, f_number=20)
    top = faulty.collected.max()
    assert faulty.collected == pytest.approx(scaled.collected, abs=1e-6 * top)  # float32 FFTs
    plain = effective_psf(d, levels, f_number=20)
    assert not np.allclose(faulty.collected, plain.collected, atol=1e-3)


def test_the_budget_goes_into_camera_json_and_its_figure(folder, tmp_path, monkeypatch, capsys):
    import doe.camera_budget

    monkeypatch.setattr(doe.camera_budget, "BUDGET_AXES", {"rotation_deg": (0.0, 3.0)})
    config, where, d, levels = folder(SMALL)
    out = tmp_path / "cam"
    argv = ["camera", str(where), "--out", str(out), "--config", str(config), "--budget"]
    assert main(argv) == 0
    assert "within the budget: rotation_deg" in capsys.readouterr().out
    curve = read_camera(out / "camera.json").data["budget"]["axes"]["rotation_deg"]
    assert curve["values"][0] == 0.0 and curve["values"][-1] == 3.0
    assert set(curve) >= {"rmse", "within_budget"}
    turned = effective_psf(d, levels, rotation_deg=3.0).collected_fraction
    assert curve["collected_fraction"][-1] == pytest.approx(turned, abs=1e-5)
    assert (out / "camera_budget.png").stat().st_size > 0


@pytest.mark.parametrize(
    "flags, named",
    [
        (["--f-number", "0"], "--f-number"),
        (["--defocus-um", "nan"], "--defocus-um"),
        (["--bandwidth-nm", "-1"], "--bandwidth-nm"),
        (["--rotation-deg", "inf"], "--rotation-deg"),
    ],
)
def test_unusable_camera_settings_are_exit_2_naming_the_flag(
    folder, tmp_path, capsys, flags, named
):
    config, where, _, _ = folder(SMALL)
    argv = ["camera", str(where), "--out", str(tmp_path / "o"), "--config", str(config)]
    assert main([*argv, *flags]) == 2
    err = capsys.readouterr().err
    assert named in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()
