"""Shared test helpers."""

import functools
import json

import numpy as np
import pytest
from hypothesis import settings

from doe.design import preset_names

# The same examples on every run, so that CI passes or fails on the code alone (a
# random draw once found a case of a test's own flawed property); no deadline, as a
# loaded 2-core machine runs some examples slowly. ``--hypothesis-profile=default``
# explores afresh.
settings.register_profile("doefab", derandomize=True, deadline=None)
settings.load_profile("doefab")


@pytest.fixture(autouse=True, scope="session")
def small_held_out_images():
    """Score every ``learn`` of the tests on one 48 x 48 held-back image, not the three photos.

    ``learn`` scores its model and the no-plate model on the embedded held-out photos
    (about 0.2 s a model, SSIM of 0.6 Mpx); the tests train dozens of tiny models.
    tests/psf_learn/test_heldout.py scores the photos themselves.
    """
    import psf_learn.images as imgio

    with pytest.MonkeyPatch.context() as mp:  # for the module-scoped trainings too
        mp.setattr(imgio, "held_out_images", _small_held_out)
        yield


@pytest.fixture(autouse=True, scope="session")
def no_camera_budget():
    """Build the tests' fab packages without the report's camera budget (about 1.5 s of CPU
    a build; the suite builds some 70). Tests of the section ask for ``camera_budget_on``."""
    import fab.package.build as build

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(build, "CAMERA_BUDGET", False)
        yield


@pytest.fixture
def camera_budget_on(monkeypatch):
    """Build fab packages as ``doefab fab`` does by default: with the camera budget."""
    import fab.package.build as build

    monkeypatch.setattr(build, "CAMERA_BUDGET", True)


@functools.cache
def _small_held_out_image():
    from psf_learn.images import dead_leaves

    return dead_leaves(48, np.random.default_rng(1), n_disks=60)


def _small_held_out():
    """(names, images) of one small held-back image (made once)."""
    return ["dead_leaves:held"], [_small_held_out_image()]


def _refuse(token):
    raise ValueError(f"not JSON: {token}")


@pytest.fixture
def saved_figures(monkeypatch):
    """Return the list that every matplotlib figure saved during the test is appended to."""
    from matplotlib.figure import Figure

    saved, save = [], Figure.savefig
    monkeypatch.setattr(
        Figure, "savefig", lambda fig, *a, **k: saved.append(fig) or save(fig, *a, **k)
    )
    return saved


@pytest.fixture
def sigmas_match_spread():
    """Return check(fit, window, sigma, runs, seed, values, sigmas): fit ``runs`` copies of
    ``window`` with Gaussian noise of ``sigma`` added (``fit(noisy)``), and assert that the
    median 1-sigma the fits quote (``sigmas(fit)``) is within 1.5 times the spread of
    their ``values(fit)``."""

    def check(fit, window, sigma, runs, seed, values, sigmas):
        rng = np.random.default_rng(seed)
        fits = [fit(window + rng.normal(0, 1, window.shape) * sigma) for _ in range(runs)]
        spread = np.std([values(f) for f in fits], axis=0)
        quoted = np.median([sigmas(f) for f in fits], axis=0)
        assert np.all((quoted > spread / 1.5) & (quoted < spread * 1.5)), (quoted, spread)

    return check


def _window_from_contract(levels, n_levels, k):
    """The contract's window powers, written out literally (the oracle for the model)."""
    n = levels.shape[0]
    f = np.fft.fft2(np.exp(2j * np.pi * levels / n_levels)) / n**2
    out = np.empty((k, k))
    for i in range(k):
        for j in range(k):
            out[i, j] = abs(f[(i - k // 2) % n, (j - k // 2) % n]) ** 2
    return out


@pytest.fixture
def window_from_contract():
    """Return window(levels, n_levels, k): CONVENTIONS.md's window powers, written out."""
    return _window_from_contract


@pytest.fixture
def colour_at():
    """Return colour(ax, x, y, space="data"): the RGB drawn at (x, y) of a figure's axes.

    ``space`` "axes" takes (x, y) as fractions of the axes, (0, 0) the lower left.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    drawn = {}

    def colour(ax, x, y, space="data"):
        fig = ax.figure
        if id(fig) not in drawn:
            canvas = FigureCanvasAgg(fig)
            canvas.draw()
            drawn[id(fig)] = np.asarray(canvas.buffer_rgba())[..., :3].astype(int)
        pixels = drawn[id(fig)]
        to_display = ax.transData if space == "data" else ax.transAxes
        col, row = to_display.transform((x, y))  # display y grows upwards
        return pixels[pixels.shape[0] - 1 - int(row), int(col)]

    return colour


@pytest.fixture
def read_strict_json():
    """Return a reader of a JSON file that refuses NaN and Infinity, as strict readers do."""
    return lambda path: json.loads(path.read_text(), parse_constant=_refuse)


@pytest.fixture(params=preset_names())
def preset(request):
    """Each embedded preset's name in turn: a test that takes it runs once per preset."""
    return request.param
