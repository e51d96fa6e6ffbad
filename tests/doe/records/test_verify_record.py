"""``verify.json``'s record: its one reader and one writer."""

import json

import pytest

from doe.infra.errors import InputError
from doe.infra.files import write_json
from doe.records.verify import VerifyRecord, read_verify, write_verify

REPORT = {
    "pass": False,
    "diagnosis": ["conjugate_plate"],
    "measured_psf_usable": False,
    "lattice_pitch_um": 75.0,
    "design_lattice_pitch_um": 37.5,
    "correlation": float("nan"),
    "notes": ["a note"],
}


def test_write_verify_writes_the_bytes_of_write_json(tmp_path):
    write_json(tmp_path / "expected.json", REPORT)
    write_verify(tmp_path / "verify.json", REPORT)
    expected = (tmp_path / "expected.json").read_bytes()
    assert (tmp_path / "verify.json").read_bytes() == expected
    write_verify(tmp_path / "again.json", read_verify(tmp_path / "verify.json"))
    assert (tmp_path / "again.json").read_bytes() == expected


def test_read_verify_gives_the_fields_other_stages_read(tmp_path):
    write_verify(tmp_path / "verify.json", REPORT)
    record = read_verify(tmp_path / "verify.json")
    assert record.passed is False and record.diagnosis == ["conjugate_plate"]
    assert record.measured_psf_usable is False
    assert record.lattice_pitch_um == 75.0 and record.design_lattice_pitch_um == 37.5
    assert record.data["correlation"] is None  # JSON has no NaN
    assert list(record.data) == sorted(REPORT)


def test_a_report_without_the_fields_reads_them_as_none(tmp_path):
    (tmp_path / "verify.json").write_text(json.dumps({"lattice_pitch_um": "75"}))
    record = read_verify(tmp_path / "verify.json")
    assert record == VerifyRecord(lattice_pitch_um="75", data={"lattice_pitch_um": "75"})
    assert record.measured_psf_usable is None and record.design_lattice_pitch_um is None


@pytest.mark.parametrize("text", ["not json", "[1, 2]"])
def test_a_verify_json_that_is_no_json_object_is_refused_naming_it(tmp_path, text):
    (tmp_path / "verify.json").write_text(text)
    with pytest.raises(InputError) as refused:
        read_verify(tmp_path / "verify.json")
    assert refused.value.source == str(tmp_path / "verify.json")
