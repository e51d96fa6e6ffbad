"""Range checks of numeric command-line flags, shared by every subcommand.

argparse's ``type=float`` accepts "nan" and "inf", and ``value <= 0`` is False for
NaN, so a bare comparison lets NaN through to the numerics. These checks refuse
anything that is not a finite number in range, naming the flag (exit code 2).
``None`` (a flag not given) passes through.
"""

import argparse
import math

from doe.infra.errors import InputError


def positive(flag, value):
    """Return ``value`` if it is None or a finite number > 0, else raise InputError."""
    if value is not None and not (math.isfinite(value) and value > 0):
        raise InputError(flag, f"must be a finite number > 0, got {value:g}")
    return value


def non_negative(flag, value):
    """Return ``value`` if it is None or a finite number >= 0, else raise InputError."""
    if value is not None and not (math.isfinite(value) and value >= 0):
        raise InputError(flag, f"must be a finite number >= 0, got {value:g}")
    return value


# Seeds reach torch.manual_seed, which takes a signed 64-bit integer.
SEED_MAX = 2**63 - 1
# Expected counts per pixel: numpy's Poisson draws stop near 1e19; no SPAD comes near.
PHOTONS_MAX = 1e12
# Training budgets: a million minutes is two years; a larger one is a typing error
# (1e308 minutes would overflow the deadline, and only after the data had loaded).
MINUTES_MAX = 1e6
STEPS_MAX = 10**9


def seed(flag, value):
    """Return ``value`` if it is None or a seed 0 .. ``SEED_MAX``, else raise InputError."""
    non_negative(flag, value)
    if value is not None and value > SEED_MAX:
        raise InputError(flag, f"must be at most 2^63 - 1, got {value}")
    return value


def at_most(flag, value, limit, why):
    """Return ``value`` if it is None or <= ``limit``, else raise InputError saying ``why``."""
    if value is not None and value > limit:
        raise InputError(flag, f"must be at most {limit:g} ({why}), got {value:g}")
    return value


def count(text):
    """argparse ``type`` of a count of at least 1 (bench scripts' repeats and sizes)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value
