"""Range checks of numeric command-line flags, shared by every subcommand.

argparse's ``type=float`` accepts "nan" and "inf", and ``value <= 0`` is False for
NaN, so a bare comparison lets NaN through to the numerics. These checks refuse
anything that is not a finite number in range, naming the flag (exit code 2).
``None`` (a flag not given) passes through.
"""

import math

from doe.errors import InputError


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
