"""The retrieve stage as a library: doe.retrieve.retrieve and its RetrieveResult."""

import json

import numpy as np
import pytest

from doe import fraunhofer, targets
from doe.derived import design_summary
from doe.design import load_design
from doe.infra.errors import InputError
from doe.records.retrieval import read_retrieval
from doe.retrieve import OUTPUTS, RetrieveResult, retrieve


def _psf_file(folder, psf, name="psf.npy"):
    path = folder / name
    np.save(path, psf)
    return path


def test_retrieve_returns_what_it_wrote_and_prints_nothing(tmp_path, capsys):
    psf = _psf_file(tmp_path, targets.asymmetric(7))
    out = tmp_path / "out"
    result = retrieve(psf, out, tile_pixels=31, seed=2, progress=False)
    assert isinstance(result, RetrieveResult)
    assert capsys.readouterr() == ("", "")  # the command prints; the library returns
    assert result.out == out and result.files == OUTPUTS
    assert sorted(p.name for p in out.iterdir()) == sorted(OUTPUTS)
    record = result.record
    assert record == read_retrieval(out / "retrieval.json")
    assert (record.levels, record.tile_pixels, record.kernel_size, record.seed) == (8, 31, 7, 2)
    assert record.target_psf == "psf.npy" and record.design["name"] == "sun2020"
    levels = np.load(out / "levels.npy")
    np.testing.assert_array_equal(levels, result.retrieval.levels)
    np.testing.assert_array_equal(result.target, targets.asymmetric(7))
    assert record.quantised == result.retrieval.quality_quantised
    assert record.quantised == pytest.approx(
        fraunhofer.quality(fraunhofer.level_phase(levels, 8), targets.asymmetric(7)), rel=1e-12
    )
    np.testing.assert_array_equal(result.simulated_psf, fraunhofer.simulate_levels(levels, 8, 7)[0])
    assert result.goals_met and record.goals_met is True and result.missed == ()
    # at N = 31 the square pixels' envelope dims the window's corners: that plate misses
    assert result.square_pixels_missed and record.square_pixels_goals_met is False
    assert list(result.square_pixels_missed) == record.square_pixels["missed"]


def test_retrieve_takes_levels_tile_and_seed_from_the_design(tmp_path):
    cfg = tmp_path / "d.toml"
    cfg.write_text("[fabrication]\nlevels = 4\n[learning]\nseed = 3\n")
    psf = _psf_file(tmp_path, targets.compact_blob(5))
    result = retrieve(psf, tmp_path / "out", config=cfg, tile_pixels=21, progress=False)
    assert (result.record.levels, result.record.seed) == (4, 3)
    assert result.retrieval.levels.max() < 4 and result.retrieval.seed == 3
    assert result.record.design["fabrication"]["levels"] == 4


def _refused(tmp_path, psf, **kwargs):
    """Return the InputError that retrieve raises; check that it wrote nothing."""
    out = tmp_path / "out"
    with pytest.raises(InputError) as raised:
        retrieve(psf, out, progress=False, **kwargs)
    assert not out.exists()
    return raised.value


@pytest.mark.parametrize(
    ("psf", "words"),
    [
        (np.full((4, 4), 1 / 16), "odd"),
        (np.full((5, 5), 2 / 25), "sum to 1"),
        (np.where(targets.compact_blob(5) > 0.1, np.nan, targets.compact_blob(5)), "NaN"),
    ],
)
def test_a_bad_psf_raises_an_input_error_naming_the_file(tmp_path, psf, words):
    path = _psf_file(tmp_path, psf, "bad.npy")
    error = _refused(tmp_path, path, tile_pixels=15)
    assert error.source == str(path) and words in error.problem


def test_a_missing_psf_or_one_larger_than_the_tile_names_the_file(tmp_path):
    missing = tmp_path / "missing.npy"
    assert _refused(tmp_path, missing, tile_pixels=15).source == str(missing)
    psf = _psf_file(tmp_path, targets.compact_blob(5))
    error = _refused(tmp_path, psf, tile_pixels=3)
    assert error.source == str(psf) and "exceeds the tile size N = 3" in error.problem


def test_a_psf_learned_for_another_grid_names_its_learn_json(tmp_path):
    cfg = tmp_path / "factor3.toml"
    cfg.write_text("[sensor]\nsuperres_factor = 3\n")
    psf = _psf_file(tmp_path, targets.compact_blob(5))
    learned = tmp_path / "learn.json"
    learned.write_text(json.dumps({"design": design_summary(load_design(cfg))}))
    error = _refused(tmp_path, psf, tile_pixels=21)
    assert error.source == str(learned) and "superres_factor 3 -> 4" in error.problem


@pytest.mark.parametrize(
    ("kwargs", "flag"),
    [
        ({"levels": 6}, "--levels"),
        ({"tile_pixels": 5000}, "--tile-pixels"),
        ({"seed": -1}, "--seed"),
    ],
)
def test_bad_settings_name_the_command_flag_that_sets_them(tmp_path, kwargs, flag):
    psf = _psf_file(tmp_path, targets.compact_blob(5))
    assert _refused(tmp_path, psf, **{"tile_pixels": 15, **kwargs}).source == flag


def test_an_empty_output_folder_is_refused(tmp_path):
    psf = _psf_file(tmp_path, targets.compact_blob(5))
    with pytest.raises(InputError, match="--out: is empty"):
        retrieve(psf, " ", tile_pixels=15, progress=False)
