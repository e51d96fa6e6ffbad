"""Shared test helpers."""

import json

import pytest


def _refuse(token):
    raise ValueError(f"not JSON: {token}")


@pytest.fixture
def read_strict_json():
    """Return a reader of a JSON file that refuses NaN and Infinity, as strict readers do."""
    return lambda path: json.loads(path.read_text(), parse_constant=_refuse)
