"""retrieval.json: its one writer and one reader (doe.records.retrieval)."""

import json
from dataclasses import fields

import numpy as np
import pytest

from doe.infra.errors import InputError
from doe.records.retrieval import (
    RETRIEVAL_JSON,
    RetrievalRecord,
    read_retrieval,
    write_retrieval,
)


def _record():
    quality = {"correlation": 0.99995, "rmse": 0.0042, "efficiency": 0.93}
    return RetrievalRecord(
        continuous=quality,
        quantised={"correlation": None, "rmse": 0.0044, "efficiency": 0.91},
        goals={"correlation_min": 0.9999, "rmse_max": 0.005, "met": True, "missed": []},
        square_pixels={**quality, "goals_met": False, "missed": ["rmse 0.00512 > 0.005"]},
        seconds=12.345,
        seed=0,
        levels=8,
        tile_pixels=175,
        kernel_size=11,
        target_psf="psf.npy",
        target_psf_sha256="0" * 64,
        design={"name": "sun2020", "fabrication": {"levels": 8}},
        versions={"numpy": "2.0", "doefab": "unknown"},
    )


def test_a_record_round_trips_byte_for_byte(tmp_path):
    record = _record()
    write_retrieval(tmp_path / "a.json", record)
    back = read_retrieval(tmp_path / "a.json")
    assert back == record
    assert back.goals_met is True and back.square_pixels_goals_met is False
    write_retrieval(tmp_path / "b.json", back)
    write_retrieval(tmp_path / "c.json", record.as_dict())  # a dict of its keys does too
    written = (tmp_path / "a.json").read_bytes()
    assert (tmp_path / "b.json").read_bytes() == (tmp_path / "c.json").read_bytes() == written
    # indented, keys sorted, one newline at the end: the bytes of doe.infra.files.write_json
    assert written == (json.dumps(record.as_dict(), indent=2, sort_keys=True) + "\n").encode()


def test_an_undefined_correlation_is_written_as_null_and_read_as_none(tmp_path):
    quantised = {"correlation": np.float64("nan"), "rmse": 0.004, "efficiency": 0.9}
    write_retrieval(tmp_path / RETRIEVAL_JSON, RetrievalRecord(quantised=quantised))
    assert '"correlation": null' in (tmp_path / RETRIEVAL_JSON).read_text()
    assert read_retrieval(tmp_path).quantised["correlation"] is None  # a folder names its file


def test_a_partial_record_reads_with_none_for_what_it_lacks(tmp_path):
    path = tmp_path / RETRIEVAL_JSON
    path.write_text(json.dumps({"levels": 4, "design": None, "someone's note": "kept aside"}))
    record = read_retrieval(path)
    assert record == RetrievalRecord(levels=4)
    assert record.goals_met is None and record.square_pixels_goals_met is None
    assert record.as_dict() == {"levels": 4}


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ('{"levels": 8.5}', "'levels' must be a whole number, got 8.5"),
        ('{"levels": "eight"}', "'levels' must be a whole number, got 'eight'"),
        ('{"levels": true}', "'levels' must be a whole number, got True"),
        ('{"kernel_size": [11]}', "'kernel_size' must be a whole number, got [11]"),
        ('{"seconds": "fast"}', "'seconds' must be a number, got 'fast'"),
        ('{"design": []}', "'design' must be a JSON object, got []"),
        ('{"quantised": 0.9}', "'quantised' must be a JSON object, got 0.9"),
        ('{"target_psf": 3}', "'target_psf' must be a string, got 3"),
        ("[]", "expected a JSON object, got list"),
        ('{"levels": 8', "not readable JSON"),
    ],
)
def test_a_malformed_record_is_refused_naming_the_file(tmp_path, content, message):
    path = tmp_path / RETRIEVAL_JSON
    path.write_text(content)
    with pytest.raises(InputError) as raised:
        read_retrieval(path)
    assert raised.value.source == str(path) and message in raised.value.problem


def test_a_missing_record_is_refused_naming_the_file(tmp_path):
    with pytest.raises(InputError) as raised:
        read_retrieval(tmp_path / RETRIEVAL_JSON)
    assert raised.value.source == str(tmp_path / RETRIEVAL_JSON)
    assert raised.value.problem == "no such file"


def test_the_retrieve_stage_writes_a_record_that_reads_back_to_the_same_bytes(tmp_path):
    from doe import targets
    from doe.retrieve import retrieve

    np.save(tmp_path / "psf.npy", targets.compact_blob(5))
    result = retrieve(tmp_path / "psf.npy", tmp_path / "out", tile_pixels=15, progress=False)
    written = tmp_path / "out" / RETRIEVAL_JSON
    record = read_retrieval(written)
    assert record == result.record
    assert all(getattr(record, f.name) is not None for f in fields(record))  # every key set
    assert set(record.as_dict()) == set(json.loads(written.read_text()))  # and no other
    write_retrieval(tmp_path / "again.json", record)
    assert (tmp_path / "again.json").read_bytes() == written.read_bytes()
