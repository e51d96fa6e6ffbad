"""Figures of the optics stage: texts of figures beside their limits, the retrieval figure."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st


@given(
    st.floats(-1e3, 1e3, allow_nan=False),
    st.floats(-1e-6, 1e-6, allow_nan=False),
    st.integers(1, 6),
    st.sampled_from("gf"),
)
def test_value_and_limit_texts_compare_as_the_numbers_do(limit, offset, digits, kind):
    from doe.figures import value_and_limit

    value = limit + offset
    shown, shown_limit = value_and_limit(value, limit, digits, kind)
    assert np.sign(float(shown) - float(shown_limit)) == np.sign(value - limit)
    # never fewer digits than asked: never further from the value than its text with
    # ``digits`` digits (a text's length is no measure: "1e+01" for 11.4999995,
    # "1e-300" beside a limit of 0)
    asked = float(f"{value:.{digits}{kind}}")
    assert abs(float(shown) - value) <= abs(asked - value)


def test_retrieval_figure_shows_row_0_at_the_top_and_column_0_at_the_left(
    tmp_path, saved_figures, colour_at
):
    # Row 0, last column lit in the target, the PSF and the level map: each panel shows
    # it top right on the screen; the PSF panels' axes put it at order (m, n) = (-2, +2).
    from doe.figures import save_retrieval_figure

    psf = np.full((5, 5), 1.0)
    psf[0, 4] = 20.0
    psf /= psf.sum()
    levels = np.zeros((6, 6), np.uint8)
    levels[0, 5] = 7
    quality = {"correlation": 1.0, "rmse": 0.0, "efficiency": 1.0}
    save_retrieval_figure(tmp_path / "r.png", psf, psf, levels, 8, quality)
    corners = {"top right": (0.9, 0.9), "top left": (0.1, 0.9), "bottom right": (0.9, 0.1),
               "bottom left": (0.1, 0.1)}  # fmt: skip
    axes = [ax for ax in saved_figures[-1].axes if ax.images]
    for ax in (axes[0], axes[1], axes[3]):  # target, simulated, level map
        background = colour_at(ax, 0.5, 0.5, space="axes")
        lit = [k for k, p in corners.items()
               if np.abs(colour_at(ax, *p, space="axes") - background).max() > 60]  # fmt: skip
        assert lit == ["top right"], ax.get_title()
    assert np.array_equal(colour_at(axes[0], 2, -2), colour_at(axes[0], 0.9, 0.9, space="axes"))
