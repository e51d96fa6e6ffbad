"""Range checks of command-line flags that argparse alone lets through."""

import argparse

import pytest

from doe.infra import flags
from doe.infra.errors import InputError


def test_a_count_is_a_whole_number_of_at_least_one():
    assert flags.count("3") == 3
    for text, problem in (("0", "at least 1"), ("-2", "at least 1"), ("2.5", "whole number")):
        with pytest.raises(argparse.ArgumentTypeError, match=problem):
            flags.count(text)


@pytest.mark.parametrize("check", [flags.positive, flags.non_negative, flags.seed])
def test_nan_and_infinity_are_refused_naming_the_flag(check):
    for value in (float("nan"), float("inf")):
        with pytest.raises(InputError, match="--x: must be a finite number"):
            check("--x", value)
    assert check("--x", None) is None and check("--x", 1.5) == 1.5
