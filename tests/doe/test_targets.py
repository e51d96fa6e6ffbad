"""Named target PSFs: the PSF contract, orientation, seeded sets."""

import numpy as np
import pytest

from doe import targets


@pytest.mark.parametrize("name", list(targets.TARGETS))
@pytest.mark.parametrize("k", [5, 11])
def test_targets_satisfy_the_psf_contract(name, k):
    t = targets.make_target(name, k)
    assert t.shape == (k, k) and t.dtype == np.float64
    assert np.all(t >= 0) and t.sum() == pytest.approx(1.0, abs=1e-12)


def test_paper_gaussian_is_centred_with_the_paper_sigma():
    t = targets.paper_gaussian(11)
    assert t.argmax() == 60
    # ratio of neighbour to centre of a sampled Gaussian is exp(-1 / (2 sigma^2))
    assert t[5, 6] / t[5, 5] == pytest.approx(np.exp(-0.5 / targets.PAPER_SIGMA**2), rel=1e-12)


@pytest.mark.parametrize(
    "make, problem",
    [
        (lambda: targets.gaussian(10), "K odd"),  # no centre pixel for the axis
        (lambda: targets.gaussian(11, sigma=0), "no light"),  # was all NaN
        (lambda: targets.random_dots(11, count=0), "no light"),
        (lambda: targets.square(11, 4), "odd side"),  # was half a pixel off the axis
    ],
)
def test_a_target_that_breaks_the_contract_is_refused(make, problem):
    with pytest.raises(ValueError, match=problem):
        make()


def test_a_gaussian_with_a_non_positive_sigma_x_is_refused():
    # catches sigma_x left unchecked: a negative one would be squared into a valid PSF
    for sx in (0.0, -1.0):
        with pytest.raises(ValueError, match="sigmas > 0"):
            targets.gaussian(11, 1.0, sigma_x=sx)


def test_gaussian_axes_rotation_and_centre_follow_the_sensor_orientation():
    # catches sigma_x applied along y, a clockwise rotation and a centre of the wrong sign;
    # neighbour ratios of a sampled Gaussian are exp(-d^2 / (2 sigma^2)) along each axis
    t = targets.gaussian(11, sigma=0.7, sigma_x=2.2)
    assert t[5, 7] / t[5, 5] == pytest.approx(np.exp(-0.5 * (2 / 2.2) ** 2), rel=1e-12)
    assert t[7, 5] / t[5, 5] == pytest.approx(np.exp(-0.5 * (2 / 0.7) ** 2), rel=1e-12)
    # turned 45 degrees counter-clockwise on the sensor (rows grow downwards): the long
    # axis runs to the upper right, where (row 3, column 7) lies sqrt(8) along it
    t = targets.gaussian(11, sigma=0.5, sigma_x=3.0, angle=np.pi / 4)
    assert t[3, 7] / t[5, 5] == pytest.approx(np.exp(-0.5 * 8 / 3.0**2), rel=1e-12)
    assert t[7, 7] / t[5, 5] == pytest.approx(np.exp(-0.5 * 8 / 0.5**2), rel=1e-12)
    # centre (y, x) = (1, -2): one row down, two columns left of the axis
    t = targets.gaussian(11, 1.0, centre=(1.0, -2.0))
    assert np.unravel_index(t.argmax(), t.shape) == (6, 3)


def test_square_and_two_lobes_sit_where_their_parameters_say():
    # catches a square shifted by one and lobes placed separation / 2 along each axis
    lit = np.argwhere(targets.square(11, 5) > 0)
    assert lit.min(axis=0).tolist() == [3, 3] and lit.max(axis=0).tolist() == [7, 7]
    # separation 4 sqrt(2) on the diagonal: lobes at (-2, -2) and (+2, +2) from the axis
    t = targets.two_lobes(11, separation=4 * np.sqrt(2), sigma=0.8, ratio=0.6)
    peaks = np.argsort(t.ravel())[-2:]
    assert sorted(np.unravel_index(i, t.shape) for i in peaks) == [(3, 3), (7, 7)]
    assert t[7, 7] / t[3, 3] == pytest.approx(0.6, rel=1e-9)


def test_random_dots_draw_every_count_from_3_to_9():
    # catches a drawn count range that stops at 8 (the docstring's 3-9 dots)
    counts = {int((targets.random_dots(11, seed=s) > 0).sum()) for s in range(60)}
    assert counts == set(range(3, 10))


def test_unknown_target_is_refused():
    with pytest.raises(ValueError, match="unknown target"):
        targets.make_target("nope")


def _assert_psf_contract(t, name):
    """An 11 x 11 float64 PSF, non-negative, sum 1 (CONVENTIONS.md)."""
    assert t.shape == (11, 11) and t.dtype == np.float64, name
    assert np.all(t >= 0) and t.sum() == pytest.approx(1.0, abs=1e-12), name


def test_robustness_set_is_varied_seeded_and_satisfies_the_contract():
    one, two = targets.robustness_set(11), targets.robustness_set(11)
    assert len(one) >= 20
    for name, t in one.items():
        _assert_psf_contract(t, name)
        np.testing.assert_array_equal(t, two[name])  # seeded: the same set every call
    lit = {name: int((t > 0).sum()) for name, t in one.items()}
    assert all(3 <= lit[n] <= 9 for n in one if n.startswith("dots"))
    assert lit["dots_3"] == 3 and lit["dots_9"] == 9
    # hard flat tops: every lit element equal, zero outside
    for name in ("disc_r2", "disc_r2.5", "square_3x3", "square_5x5", "square_7x7"):
        t = one[name]
        np.testing.assert_allclose(t[t > 0], 1.0 / lit[name], rtol=1e-12)
    assert lit["square_3x3"] == 9 and lit["square_7x7"] == 49 and lit["disc_r2"] == 13


def test_drawn_set_is_seeded_varied_and_satisfies_the_contract():
    one, again, other = targets.drawn_set(7), targets.drawn_set(7), targets.drawn_set(8)
    assert len(one) == 34 and list(one) == list(other)
    for name, t in one.items():
        _assert_psf_contract(t, name)
        np.testing.assert_array_equal(t, again[name])  # the seed fixes the set
        if not name.startswith(("disc", "rectangle")):  # hard edges on a lattice may agree
            assert not np.array_equal(t, other[name]), name  # another seed draws anew
    compact = [n for n in one if targets.efficiency_floor(n) == 0.90]
    assert len(compact) == 8 and all(n.startswith(("compact_blob", "near_delta")) for n in compact)
    assert all(3 <= (one[n] > 0).sum() <= 9 for n in one if n.startswith("dots"))


def test_shape_set_satisfies_the_contract_and_reads_upright():
    shapes = targets.shape_set(11)
    assert len(shapes) == 19
    for name, t in shapes.items():
        _assert_psf_contract(t, name)
        assert targets.efficiency_floor(name) == 0.85, name
    lit = {name: int((t > 0).sum()) for name, t in shapes.items()}
    assert lit["bar_full_width"] == 11 and lit["square_outline"] == 24 and lit["checkerboard"] == 61
    # CONVENTIONS orientation: rows grow downwards, so an upright L has its foot below the
    # centre row and its stem left of the centre column, and an F its arms to the right
    ell = shapes["L_stroke1"]
    assert ell[8, 2:9].all() and ell[2:9, 2].all() and not ell[2, 8] and not ell[8, 1]
    f = shapes["F_stroke2"]
    assert f[:, 2:4].sum() > f[:, 7:9].sum() > 0 and f[1, 8] > 0 and f[9, 8] == 0
    for name in ("triangle", "hexagon", "cross", "donut", "airy"):  # mirror-symmetric shapes
        np.testing.assert_allclose(shapes[name], shapes[name][:, ::-1], atol=1e-15, err_msg=name)
    with pytest.raises(ValueError, match="K >= 9"):
        targets.shape_set(7)


def test_efficiency_floor_is_090_on_compact_kernels_only():
    assert targets.efficiency_floor("near_delta_0.3") == targets.efficiency_floor("paper_gaussian")
    assert targets.efficiency_floor("compact_blob") == 0.90
    assert targets.efficiency_floor("sparse_dots") == targets.efficiency_floor("disc_r2") == 0.85


def test_random_dots_differ_by_seed_and_keep_their_count():
    a, b = targets.random_dots(11, seed=1, count=5), targets.random_dots(11, seed=2, count=5)
    assert (a > 0).sum() == (b > 0).sum() == 5
    assert not np.array_equal(a > 0, b > 0)
