"""Corner contacts: the counts, the pixel checks, the repair and the retrieval without them."""

import numpy as np
import pytest

from doe import retrieval, targets
from doe.goals import Goal
from doe.infra.cli import main
from doe.infra.files import read_psf
from doe.mask_rules import contacts_at, corner_contacts, pixel_is_clean
from doe.quantisation import coordinate_descent
from doe.retrieve import retrieve
from doe.rule_finish import repair_corners
from fab.package.masks import masks_from_levels


def brute_force_contacts(levels, n_levels, periodic):
    """Count the checkerboard 2 x 2 blocks of each mask of fab's own split, pixel by pixel."""
    counts = []
    for mask in masks_from_levels(levels, n_levels, level_step=1e-7):
        b, n_rows, n_cols = mask.bitmap, *mask.bitmap.shape
        count = 0
        last_r, last_c = (n_rows, n_cols) if periodic else (n_rows - 1, n_cols - 1)
        for r in range(last_r):
            for c in range(last_c):
                p, a = b[r, c], b[r, (c + 1) % n_cols]
                q, d = b[(r + 1) % n_rows, c], b[(r + 1) % n_rows, (c + 1) % n_cols]
                count += bool(p == d and a == q and p != a)
        counts.append(count)
    return tuple(counts)


@pytest.mark.parametrize("n_levels", [2, 4, 8, 16])
@pytest.mark.parametrize("periodic", [True, False])
def test_corner_contacts_match_a_pixel_by_pixel_count_of_the_masks(n_levels, periodic):
    rng = np.random.default_rng(n_levels)
    levels = rng.integers(0, n_levels, (13, 17)).astype(np.uint8)
    counts = corner_contacts(levels, n_levels, periodic)
    assert counts == brute_force_contacts(levels, n_levels, periodic)
    assert len(counts) == n_levels.bit_length() - 1 and sum(counts) > 0


def test_a_checkerboard_of_two_levels_touches_at_every_corner_of_the_masks_they_differ_in():
    # levels 5 (code 2 = 010) and 6 (code 1 = 001): M2 and M3 each etch one colour
    board = np.where(np.add.outer(np.arange(6), np.arange(6)) % 2, 5, 6).astype(np.uint8)
    assert corner_contacts(board, 8) == (0, 36, 36)
    assert corner_contacts(board, 8, periodic=False) == (0, 25, 25)
    # an odd period breaks the checkerboard across the tile's edge
    assert corner_contacts(board[:5, :5], 8) == (0, 16, 16)


def test_the_pixel_checks_agree_with_a_recount():
    rng = np.random.default_rng(1)
    q = rng.integers(0, 8, (9, 9))
    for _ in range(200):
        r, c, v = rng.integers(0, 9), rng.integers(0, 9), rng.integers(0, 8)
        moved = q.copy()
        moved[r, c] = v
        blocks = [((r + dr) % 9, (c + dc) % 9) for dr in (-1, 0) for dc in (-1, 0)]
        rolled = [np.roll(moved, (-br, -bc), axis=(0, 1))[:2, :2] for br, bc in blocks]
        expected = any(sum(corner_contacts(b, 8, periodic=False)) for b in rolled)
        assert pixel_is_clean(q, r, c, v, 8) == (not expected)
        assert contacts_at(q, np.array(r), np.array(c), np.array(v), 8).any() == expected


@pytest.mark.parametrize("n_levels", [2, 16])
def test_repair_leaves_no_contact_in_noise(n_levels):
    target = targets.paper_gaussian(7)
    for seed in range(3):
        noise = np.random.default_rng(seed).integers(0, n_levels, (19, 19)).astype(np.uint8)
        fixed = repair_corners(noise, target, Goal.of(target), n_levels, 10.0, 0.81)
        assert sum(corner_contacts(fixed, n_levels)) == 0 < sum(corner_contacts(noise, n_levels))
        assert fixed.dtype == np.uint8 and fixed.max() < n_levels


def test_the_constrained_descent_keeps_a_clean_map_clean_and_improves_it():
    target = targets.asymmetric(7)
    start = np.zeros((21, 21), np.uint8)
    start[5:12, 3:9] = 3  # a clean map, far from the target
    moved = coordinate_descent(start, target, 4, sweeps=2, shifts=None, no_corners=True)
    assert (moved != start).sum() > 20
    assert corner_contacts(moved, 4) == (0, 0)


def _small_design(folder, body):
    path = folder / "design.toml"
    path.write_text(f'name = "small"\n{body}')
    return path


BK7 = '[optics]\nwavelength_nm = 532.0\n[material]\nname = "bk7"\n'
"""A 532 nm plate in BK7 (with the levels and feature size each test sets)."""


@pytest.mark.parametrize(
    ("body", "n_levels", "target"),
    [
        (
            BK7 + "[fabrication]\nlevels = 4\naperture_mm = 12.7\nfeature_size_um = 20.0\n",
            4,
            "paper_gaussian",
        ),
        ("[fabrication]\nlevels = 16\nfeature_size_um = 24.5\n", 16, "asymmetric"),
    ],
)
def test_a_retrieved_tile_has_no_corner_contact_in_any_mask(tmp_path, body, n_levels, target):
    psf = tmp_path / "psf.npy"
    np.save(psf, targets.make_target(target, 11))
    result = retrieve(psf, tmp_path / "out", config=_small_design(tmp_path, body), progress=False)
    levels = np.load(tmp_path / "out" / "levels.npy")
    masks = n_levels.bit_length() - 1
    assert result.record.levels == n_levels and levels.shape == (35, 35)
    assert brute_force_contacts(levels, n_levels, periodic=True) == (0,) * masks
    assert result.record.corner_contacts == {"allowed": False, "per_mask": [0] * masks}
    assert result.goals_met


def test_allowing_corner_contacts_keeps_the_unconstrained_search(tmp_path, monkeypatch):
    def no_repair(*args, **kwargs):
        raise AssertionError("the repair ran although the design allows corner contacts")

    monkeypatch.setattr("doe.quantisation.repair_corners", no_repair)
    psf = tmp_path / "psf.npy"
    np.save(psf, targets.asymmetric(11))
    body = BK7 + "[fabrication]\nlevels = 4\nfeature_size_um = 20.0\nallow_corner_contacts = true\n"
    config = _small_design(tmp_path, body)
    result = retrieve(psf, tmp_path / "out", config=config, tile_pixels=21, progress=False)
    free = retrieval.retrieve_phase(read_psf(psf), 21, 4, allow_corner_contacts=True)
    np.testing.assert_array_equal(result.retrieval.levels, free.levels)
    counts = corner_contacts(free.levels, 4)
    assert sum(counts) > 0
    assert result.record.corner_contacts == {"allowed": True, "per_mask": list(counts)}


@pytest.mark.parametrize(
    ("value", "message"),
    [("1", "must be true or false, got 1"), ('"yes"', "must be true or false, got 'yes'")],
)
def test_a_bad_allow_corner_contacts_exits_2_naming_the_file_and_key(
    tmp_path, capsys, value, message
):
    path = _small_design(tmp_path, f"[fabrication]\nallow_corner_contacts = {value}\n")
    assert main(["config", "show", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert str(path) in err and "[fabrication] allow_corner_contacts" in err and message in err
