"""learn.json: its one reader and writer (doe.records.learn), round trip and refusals."""

import json

import pytest

from doe.infra.errors import InputError
from doe.records.learn import LEARN_JSON, LearnRecord, read_learn, write_learn

RECORD = {  # what `doefab learn` writes, abridged where it is long
    "config": {"psf": "learned", "steps": 3, "kernel_size": 11, "init": None},
    "design": {"name": "sun2020", "sensor": {"superres_factor": 4, "pixel_pitch_um": 150.0}},
    "images": {"source": "imgs", "count": 2},
    "steps": 3,
    "seconds": 0.512,
    "final_loss": 0.125,
    "final_psnr_db": 17.5,
    "seed": 0,
    "device": "cpu",
    "versions": {"torch": "2.5.1", "numpy": "2.1.3", "python": "3.12.7", "doefab": "0.1.0"},
    "files": {"model.pt": "ab" * 32, "psf.npy": "cd" * 32},
}


def test_a_record_round_trips_in_the_bytes_written_before(tmp_path):
    path = tmp_path / LEARN_JSON
    write_learn(path, RECORD)
    # indented, key-sorted JSON and a newline: the bytes learn.json always had
    assert path.read_text() == json.dumps(RECORD, indent=2, sort_keys=True) + "\n"
    record = read_learn(path)
    assert record.design == RECORD["design"] and record.files == RECORD["files"]
    assert (record.steps, record.seconds, record.seed, record.device) == (3, 0.512, 0, "cpu")
    assert (record.final_loss, record.final_psnr_db) == (0.125, 17.5)
    assert record.config == RECORD["config"] and record.images == RECORD["images"]
    assert record.versions == RECORD["versions"] and record.to_dict() == RECORD
    again = tmp_path / "again.json"
    write_learn(again, record)  # a record writes what it was read from
    assert again.read_bytes() == path.read_bytes()


def test_a_record_is_a_copy_of_what_it_was_made_from():
    data = json.loads(json.dumps(RECORD))
    record = LearnRecord.from_dict(data)
    data["design"]["sensor"]["superres_factor"] = 3
    assert record.design["sensor"]["superres_factor"] == 4
    record.to_dict()["files"].clear()
    assert record.files == RECORD["files"]


@pytest.mark.parametrize(
    "data, expected",
    [
        ({"design": 3}, {"design": None}),  # a hand-edited record: nothing to compare
        ({}, {"design": None, "files": None, "steps": None}),  # files: none in old records
        ({"seconds": None}, {"seconds": None}),  # doefab run moved the seconds out
        ({"final_psnr_db": None}, {"final_psnr_db": None}),  # undefined: written as null
        ({"steps": True, "device": 4, "files": []}, {"steps": None, "device": None}),
    ],
)
def test_a_partial_or_odd_record_is_read_with_none_where_a_key_is_unusable(
    tmp_path, data, expected
):
    path = tmp_path / LEARN_JSON
    path.write_text(json.dumps(data))
    record = read_learn(path)
    for key, value in expected.items():
        assert getattr(record, key) == value, key
    assert record.to_dict() == data  # kept whole: written back as it was


def test_non_finite_figures_are_written_as_null(tmp_path):
    path = tmp_path / LEARN_JSON
    write_learn(path, {**RECORD, "final_psnr_db": float("nan")})
    assert json.loads(path.read_text())["final_psnr_db"] is None
    assert read_learn(path).final_psnr_db is None


@pytest.mark.parametrize(
    "text, reason",
    [
        (None, "no such file"),
        ("{not json", "not readable JSON"),
        ("[1, 2]", "expected a JSON object, got list"),
    ],
)
def test_a_file_that_is_no_record_is_refused_naming_it(tmp_path, text, reason):
    path = tmp_path / "model" / LEARN_JSON
    path.parent.mkdir()
    if text is not None:
        path.write_text(text)
    with pytest.raises(InputError, match=reason) as refused:
        read_learn(path)
    assert str(refused.value).startswith(f"{path}: ")
