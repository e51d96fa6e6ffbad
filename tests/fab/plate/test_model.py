"""Tests of fab.plate.model: the one model of a faulty plate, its two evaluations agree."""

import numpy as np
import pytest

from doe.fraunhofer import level_phase, pixel_envelope
from fab.plate.model import (
    PlateFaults,
    level_plate_model,
    plate_far_field,
    tile_phase,
    window_amplitudes,
)

N, K, L, S = 12, 5, 8, 4


@pytest.fixture(scope="module")
def levels():
    return np.random.default_rng(11).integers(0, L, (N, N)).astype(np.uint8)


def far_field_window(phase):
    m = np.arange(K) - K // 2
    return plate_far_field(phase)(m[:, None], m[None, :])


FAULTS = [
    PlateFaults(),
    PlateFaults(etch_errors=(0.1, -0.2, 0.05)),
    PlateFaults(overlay=((0.0, 0.0), (0.25, -1.5), (-0.75, 0.5))),
    PlateFaults(cd_bias=-0.25, overlay=((0.5, 0.0), (0.0, 0.0), (0.0, 0.25))),
    PlateFaults(etch_errors=(0.0, 0.3, 0.0), cd_bias=0.25, conjugate=True),
]


@pytest.mark.parametrize("faults", FAULTS)
def test_the_window_and_the_sampled_tile_s_far_field_are_one_model(levels, faults):
    # Faults on the sub-sample grid (1/4 mask pixel): the continuous plate's window is the
    # far field of the tile sampled 4 x 4 per mask pixel, envelope of the sub-sample included.
    window = np.abs(window_amplitudes(level_plate_model(levels, L, K), faults)) ** 2
    phase = tile_phase(level_plate_model(levels, L, supersample=S), faults)
    np.testing.assert_allclose(window, far_field_window(phase), rtol=0, atol=1e-14)


def test_a_conjugate_plate_is_the_level_map_l_minus_1_minus_l(levels):
    phase = tile_phase(level_plate_model(levels, L, supersample=1), PlateFaults(conjugate=True))
    expected = level_phase((L - 1) - levels, L)
    np.testing.assert_allclose(np.exp(1j * phase), np.exp(1j * expected), rtol=0, atol=1e-12)


def test_another_level_map_is_made_instead(levels):
    other = np.ascontiguousarray(levels[::-1])
    model = level_plate_model(levels, L, K)
    made = np.abs(window_amplitudes(model, PlateFaults(other_levels=other))) ** 2
    expected = np.abs(window_amplitudes(level_plate_model(other, L, K))) ** 2
    np.testing.assert_allclose(made, expected, rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="N = 12"):
        window_amplitudes(model, PlateFaults(other_levels=np.zeros((8, 8), np.uint8)))


def test_the_continuous_window_carries_the_pixel_envelope(levels):
    window = np.abs(window_amplitudes(level_plate_model(levels, L, K))) ** 2
    env = pixel_envelope(np.arange(K) - K // 2, N)
    contract = far_field_window(level_phase(levels, L))  # square pixels: the envelope too
    np.testing.assert_allclose(window, contract, rtol=0, atol=1e-14)
    assert env.min() < 1  # so the envelope is there to see


@pytest.mark.parametrize(
    "faults, message",
    [
        (PlateFaults(overlay=((1.0, 0.0),)), "overlay must be one"),
        (PlateFaults(etch_errors=(0.1, 0.0)), "etch errors must be one per mask"),
    ],
)
def test_per_mask_faults_are_one_per_mask(levels, faults, message):
    with pytest.raises(ValueError, match=message):
        window_amplitudes(level_plate_model(levels, L, K), faults)
    with pytest.raises(ValueError, match=message):
        tile_phase(level_plate_model(levels, L, supersample=2), faults)


def test_a_sampled_tile_needs_a_supersample(levels):
    with pytest.raises(ValueError, match="supersample"):
        tile_phase(level_plate_model(levels, L), PlateFaults())
