"""Masks: level-to-etch mapping, binary-weighted Sellmeier depths, rectangles of a bitmap."""

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from doe.derived import derive
from doe.design import load_design
from fab.package.masks import (
    Mask,
    etch_depth_map,
    levels_from_masks,
    mask_count,
    masks_from_levels,
    min_feature_pixels,
)
from layouts.rectangles import bitmap_rectangles, rectangles_to_bitmap, row_runs

STEP = 179.4e-9


def malitson_fused_silica(wavelength_um):
    """Fused-silica index (Malitson 1965), written out here as an independent oracle."""
    w2 = wavelength_um**2
    terms = ((0.6961663, 0.0684043), (0.4079426, 0.1162414), (0.8974794, 9.896161))
    return np.sqrt(1 + sum(b * w2 / (w2 - c**2) for b, c in terms))


def test_etch_depths_come_from_sellmeier_within_half_a_nanometre():
    design = load_design()
    der = derive(design)
    n = malitson_fused_silica(design.optics.wavelength * 1e6)
    step = design.optics.wavelength / (n - 1) / design.fabrication.levels
    masks = masks_from_levels(np.zeros((4, 4), np.uint8), 8, der.level_step)
    want_nm = [4 * step * 1e9, 2 * step * 1e9, step * 1e9]
    got_nm = [mk.etch_depth * 1e9 for mk in masks]
    assert np.allclose(got_nm, want_nm, atol=0.5)
    assert abs(n - 1.4564) < 1e-3  # the contract's quoted index at 655 nm


def test_deepest_mask_is_exposed_first():
    masks = masks_from_levels(np.zeros((3, 3), np.uint8), 8, STEP)
    assert [mk.exposure_order for mk in masks] == [1, 2, 3]
    assert [mk.steps for mk in masks] == [4, 2, 1]
    assert [mk.name for mk in masks] == ["M1_deep", "M2_mid", "M3_shallow"]
    assert [mk.gds_layer for mk in masks] == [1, 2, 3]  # the manifest's layers (CONVENTIONS.md)
    assert all(mk.gds_datatype == 0 for mk in masks)
    assert masks[0].etch_depth > masks[1].etch_depth > masks[2].etch_depth


@pytest.mark.parametrize("n_levels", [2, 4, 8, 16])
def test_top_level_unetched_and_level_zero_etched_by_every_mask(n_levels):
    levels = np.array([[n_levels - 1, 0]], dtype=np.uint8)
    levels = np.vstack([levels, levels[:, ::-1]])
    masks = masks_from_levels(levels, n_levels, STEP)
    assert len(masks) == mask_count(n_levels)
    for mk in masks:
        assert not mk.bitmap[0, 0] and not mk.bitmap[1, 1]  # level L-1: no glass removed
        assert mk.bitmap[0, 1] and mk.bitmap[1, 0]  # level 0: removed by every mask
    assert np.isclose(etch_depth_map(masks)[0, 1], (n_levels - 1) * STEP)


def test_each_level_has_its_own_binary_code():
    levels = np.arange(8, dtype=np.uint8).reshape(1, 8)
    masks = masks_from_levels(levels, 8, STEP)
    codes = np.stack([mk.bitmap[0] for mk in masks])  # (3, 8): deep, mid, shallow
    # etch code 7 - l in binary, most significant bit (deep) first
    want = np.array([[(7 - lv) >> b & 1 for lv in range(8)] for b in (2, 1, 0)], dtype=bool)
    assert np.array_equal(codes, want)


@settings(max_examples=40, deadline=None)
@given(
    st.sampled_from([2, 4, 8, 16]).flatmap(
        lambda L: st.tuples(
            st.just(L),
            arrays(np.uint8, st.tuples(st.integers(1, 9), st.integers(1, 9)),
                   elements=st.integers(0, L - 1)),
        )
    )
)  # fmt: skip
def test_masks_round_trip_and_depth_sum(args):
    n_levels, levels = args
    masks = masks_from_levels(levels, n_levels, STEP)
    assert np.array_equal(levels_from_masks(masks, n_levels, STEP), levels)
    depth = etch_depth_map(masks)
    assert np.allclose(depth, (n_levels - 1 - levels.astype(float)) * STEP, rtol=0, atol=1e-15)


def test_masks_do_not_alias_or_mutate_the_input():
    levels = np.random.default_rng(1).integers(0, 8, (5, 5)).astype(np.uint8)
    before = levels.copy()
    masks = masks_from_levels(levels, 8, STEP)
    assert np.array_equal(levels, before)
    with pytest.raises(ValueError):
        masks[0].bitmap[0, 0] = True  # read-only: a frozen mask stays frozen
    assert isinstance(masks[0], Mask)


@pytest.mark.parametrize(
    "levels, n_levels",
    [
        (np.array([[8]], np.uint8), 8),
        (np.array([[-1]]), 8),
        (np.zeros((2, 2), np.uint8), 6),
        (np.zeros((2, 2), np.uint8), 1),  # one level: not a single mask
    ],
)
def test_bad_levels_are_refused(levels, n_levels):
    with pytest.raises(ValueError):
        masks_from_levels(levels, n_levels, STEP)


def test_a_levels_map_that_is_not_2d_is_refused():
    with pytest.raises(ValueError, match="levels must be 2-D, got shape"):
        masks_from_levels(np.zeros(4, np.uint8), 8, STEP)


@settings(max_examples=60, deadline=None)
@given(arrays(bool, st.tuples(st.integers(1, 12), st.integers(1, 12))))
def test_rectangles_cover_the_bitmap_exactly_and_are_disjoint(bitmap):
    rects = bitmap_rectangles(bitmap)
    assert np.array_equal(rectangles_to_bitmap(rects, bitmap.shape), bitmap)
    areas = (rects[:, 2] - rects[:, 0]) * (rects[:, 3] - rects[:, 1])
    assert areas.sum() == bitmap.sum()  # equal area + exact cover = no overlap
    assert np.all(areas > 0)


def test_rectangles_merge_identical_runs_vertically():
    b = np.zeros((6, 5), bool)
    b[1:4, 1:3] = True  # one 3 x 2 block
    b[5, :] = True  # one full row
    rects = bitmap_rectangles(b)
    assert sorted(map(tuple, rects.tolist())) == [(0, 5, 5, 6), (1, 1, 3, 4)]
    assert row_runs(b).tolist() == [[1, 1, 3], [2, 1, 3], [3, 1, 3], [5, 0, 5]]


def test_rectangles_merge_runs_of_rows_that_hold_several_runs():
    b = np.zeros((4, 7), bool)
    b[0:3, 0:2] = True  # two 3-row blocks side by side: two rectangles, not six
    b[0:3, 4:7] = True
    b[3, 0:2] = True  # one more run under the left block, one row down: joins it
    assert bitmap_rectangles(b).tolist() == [[0, 0, 2, 4], [4, 0, 7, 3]]  # by c0, c1, r0


def test_rectangles_of_a_checkerboard_are_single_pixels():
    b = (np.add.outer(np.arange(6), np.arange(6)) % 2).astype(bool)
    rects = bitmap_rectangles(b)
    assert len(rects) == b.sum()
    assert np.all(rects[:, 2] - rects[:, 0] == 1) and np.all(rects[:, 3] - rects[:, 1] == 1)


def test_min_feature_counts_periodic_runs():
    b = np.zeros((6, 6), bool)
    assert min_feature_pixels(b) == 6
    b[:, 0] = b[:, 5] = True  # joined across the tile edge: 2 wide, gap 4
    assert min_feature_pixels(b) == 2
    b = np.zeros((6, 6), bool)
    b[1:4, 1:4] = True
    b[2, 2] = False  # a 1-pixel hole
    assert min_feature_pixels(b) == 1


def test_min_feature_sees_a_feature_narrow_along_y():
    # A one-row stripe across the tile is 1 pixel wide (along y) however long it is
    # (along x); the manifest's min_feature_um must say so.
    b = np.zeros((6, 6), bool)
    b[2, :] = True
    assert min_feature_pixels(b) == 1
    assert min_feature_pixels(b.T) == 1


def test_fill_fraction_is_the_etched_share_of_the_tile():
    levels = np.full((2, 4), 7, np.uint8)
    levels[0, :3] = 6  # 3 of 8 pixels one step down: etched by the shallow mask only
    masks = masks_from_levels(levels, 8, STEP)
    assert [mk.fill_fraction for mk in masks] == [0.0, 0.0, 3 / 8]


def test_levels_from_masks_is_uint8_up_to_256_levels():
    # levels.npy is uint8 (CONVENTIONS.md); level 255 of a 256-level tile must survive
    levels = np.arange(256, dtype=np.uint8).reshape(16, 16)
    back = levels_from_masks(masks_from_levels(levels, 256, STEP), 256, STEP)
    assert back.dtype == np.uint8
    assert np.array_equal(back, levels)


def test_levels_from_masks_refuses_masks_that_etch_deeper_than_l_minus_1_steps():
    masks = masks_from_levels(np.zeros((2, 2), np.uint8), 8, STEP)  # every pixel 7 steps deep
    too_deep = [masks[0], masks[1], dataclasses.replace(masks[2], etch_depth=2 * STEP)]
    with pytest.raises(ValueError, match="deeper"):
        levels_from_masks(too_deep, 8, STEP)  # 4 + 2 + 2 = 8 steps: level -1


def test_levels_from_masks_refuses_depths_that_are_not_whole_steps():
    masks = masks_from_levels(np.zeros((2, 2), np.uint8), 8, STEP)
    off = [masks[0], masks[1], dataclasses.replace(masks[2], etch_depth=0.7 * STEP)]
    with pytest.raises(ValueError, match="whole multiples"):
        levels_from_masks(off, 8, STEP)  # 4 + 2 + 0.7 = 6.7 steps
