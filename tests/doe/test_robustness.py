"""Property-based tests: every bad configuration or contract file is an InputError."""

import io
import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from doe.design import _SCHEMA, _read_preset, parse_design
from doe.infra.errors import InputError
from doe.infra.files import check_levels, check_psf, load_npy

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


json_values = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**3), 10**3),
    st.integers(10**300, 10**400),  # past any float: int() of it fine, float() overflows
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=6),
    st.lists(st.integers(-2, 20), max_size=3),
    st.dictionaries(st.sampled_from(["a", "exposure_order", "etch_depth_nm"]), st.integers(0, 3)),
)


def _fab_folder(tmp, manifest):
    """A fab folder of a random 8-level N = 15 tile, its target and ``manifest``."""
    from doe.fraunhofer import simulate_levels
    from doe.infra.files import save_npy

    levels = np.random.default_rng(0).integers(0, 8, (15, 15)).astype(np.uint8)
    save_npy(tmp / "levels.npy", levels)
    save_npy(tmp / "target_psf.npy", simulate_levels(levels, 8, 5)[0])
    (tmp / "fab_manifest.json").write_text(json.dumps(manifest))
    return tmp


VERIFY_MANIFEST = {
    "levels": 8,
    "kernel_size": 5,
    "lattice_pitch_um": 37.5,
    "pixel_pitch_nm": 4990,
    "levels_file": "levels.npy",
    "target_psf_file": "target_psf.npy",
    "masks": [
        {"name": "M1_deep", "etch_depth_nm": 717.6, "exposure_order": 1},
        {"name": "M2_mid", "etch_depth_nm": 358.8, "exposure_order": 2},
    ],
    "acceptance": {"correlation_min": 0.99, "rmse_max": 0.01},
}


@settings(
    max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.sampled_from([*VERIFY_MANIFEST, "masks.0.etch_depth_nm", "masks.1.etch_depth_nm",
                        "masks.1.exposure_order"]), json_values)  # fmt: skip
def test_verify_reads_a_design_folder_it_can_use_or_refuses_it(tmp_path_factory, key, value):
    # Each value either makes a design verify can use or an InputError naming the file;
    # "eight", -1, 1e400 and an 11 x 11 target beside kernel_size 9 once went further.
    from fab.verify.design_ref import read_design_dir

    manifest = json.loads(json.dumps(VERIFY_MANIFEST))
    where, _, field = key.partition(".")
    if field:
        index, name = field.split(".")
        manifest[where][int(index)][name] = value
    else:
        manifest[key] = value
    folder = _fab_folder(tmp_path_factory.mktemp("fab"), manifest)
    try:
        d = read_design_dir(folder)
    except InputError as e:
        assert str(folder) in str(e)
        return
    n = d.levels.shape[0]
    assert d.n_levels in (2, 4, 8, 16, 32, 64, 128, 256) and d.levels.max() < d.n_levels
    assert 1 <= d.kernel_size <= n and d.kernel_size % 2 == 1
    assert np.isfinite(d.lattice_pitch) and d.lattice_pitch > 0
    assert all(np.isfinite(depth) and depth > 0 for depth in d.etch_depths)  # errors' scale
    assert d.acceptance is None or isinstance(d.acceptance, dict)
    assert d.target_psf is None or d.target_psf.shape == (d.kernel_size, d.kernel_size)
    pitch = d.mask_pixel_pitch
    assert pitch is None or (np.isfinite(pitch) and pitch > 0)


MESH_MANIFEST = {
    "levels": 8,
    "level_step_nm": 179.4,
    "pixel_pitch_nm": 4990.0,
    "tile_pixels": 15,
    "tiles": [4, 4],
    "array_origin_nm": [0.0, 0.0],
    "levels_file": "levels.npy",
    "substrate_thickness_mm": 0.5,
}


@settings(
    max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.sampled_from(list(MESH_MANIFEST)), json_values)
def test_mesh_reads_a_fab_folder_it_can_build_or_refuses_it(tmp_path_factory, key, value):
    from fab.mesh.build import read_fab_dir

    manifest = {**MESH_MANIFEST, key: value}
    folder = _fab_folder(tmp_path_factory.mktemp("fab"), manifest)
    try:
        relief, info = read_fab_dir(folder)
    except InputError as e:
        assert str(folder) in str(e)
        return
    numbers = [relief.step, relief.pitch, relief.thickness, *info["origin_mm"], *info["tiles"]]
    assert all(np.isfinite(numbers)) and relief.step > 0 and relief.pitch > 0
    assert relief.thickness > (relief.n_levels - 1) * relief.step
    assert all(isinstance(t, int) and t >= 1 for t in info["tiles"])
