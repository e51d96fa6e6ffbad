"""Shared test helpers."""

import json

import pytest
from hypothesis import settings

# The same examples on every run, so that CI passes or fails on the code alone (a
# random draw once found a case of a test's own flawed property); no deadline, as a
# loaded 2-core machine runs some examples slowly. ``--hypothesis-profile=default``
# explores afresh.
settings.register_profile("doefab", derandomize=True, deadline=None)
settings.load_profile("doefab")


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
def read_strict_json():
    """Return a reader of a JSON file that refuses NaN and Infinity, as strict readers do."""
    return lambda path: json.loads(path.read_text(), parse_constant=_refuse)
