"""Property-based tests: every bad configuration or contract file is an InputError."""

import io

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from doe.design import _SCHEMA, _read_preset, parse_design
from doe.errors import InputError
from doe.files import check_levels, check_psf, load_npy

values = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**6), 10**6),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.lists(st.floats(allow_nan=True), max_size=3),
)
fields = st.sampled_from([(s, k) for s, keys in _SCHEMA.items() for k in keys])


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(fields, values)
def test_config_parser_accepts_or_refuses_with_input_error(field, value):
    section, key = field
    raw = _read_preset("sun2020")
    raw[section] = dict(raw[section], **{key: value})
    if value is None:
        del raw[section][key]
    try:
        parse_design(raw, "fuzz.toml")
    except InputError as e:
        assert "fuzz.toml" in str(e)


arrays = st.builds(
    lambda shape, dtype, seed: np.random.default_rng(seed).normal(size=shape).astype(dtype),
    st.lists(st.integers(0, 6), min_size=0, max_size=3).map(tuple),
    st.sampled_from([np.float64, np.float32, np.int32, np.uint8, np.complex64]),
    st.integers(0, 2**16),
)


@settings(max_examples=200, deadline=None)
@given(arrays)
def test_psf_validation_never_passes_a_contract_violation(a):
    try:
        psf = check_psf(a, "psf.npy")
    except InputError:
        return
    assert psf.dtype == np.float64 and psf.ndim == 2 and psf.shape[0] % 2 == 1
    assert np.all(psf >= 0) and abs(psf.sum() - 1) < 1e-12


@settings(max_examples=200, deadline=None)
@given(arrays, st.sampled_from([2, 4, 8]))
def test_levels_validation_never_passes_a_contract_violation(a, n_levels):
    try:
        lev = check_levels(a, n_levels, "levels.npy")
    except InputError:
        return
    assert lev.dtype == np.uint8 and lev.shape[0] == lev.shape[1]
    assert lev.size == 0 or lev.max() < n_levels


@settings(max_examples=100, deadline=None)
@given(st.binary(max_size=300))
def test_npy_reader_refuses_garbage_bytes(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("npy") / "x.npy"
    path.write_bytes(data)
    try:
        load_npy(path)
    except InputError as e:
        assert str(path) in str(e)


def test_npy_reader_refuses_truncated_file(tmp_path):
    buf = io.BytesIO()
    np.save(buf, np.ones((11, 11)))
    path = tmp_path / "psf.npy"
    path.write_bytes(buf.getvalue()[:-50])
    try:
        load_npy(path)
    except InputError as e:
        assert str(path) in str(e)
    else:
        raise AssertionError("a truncated .npy was accepted")


def test_npy_reader_names_an_npz_archive_and_a_file_that_is_no_npy(tmp_path):
    # An .npz was "a float array, got dtype <U3" (its key names); a text file got
    # numpy's advice to pass allow_pickle=True.
    np.savez(tmp_path / "psf.npz", psf=np.ones((3, 3)))
    (tmp_path / "psf.npy").write_text("0.1 0.2 0.3\n")
    with pytest.raises(InputError, match=r"psf\.npz: is an \.npz archive"):
        load_npy(tmp_path / "psf.npz")
    with pytest.raises(InputError, match=r"psf\.npy: is not a \.npy file") as e:
        load_npy(tmp_path / "psf.npy")
    assert "pickle" not in str(e.value)
