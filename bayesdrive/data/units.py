"""Unit factors to SI. Every reader declares its units; nothing guesses them."""

from bayesdrive.data.errors import DataError

__all__ = ["FOOT_M", "LENGTH_UNITS", "SPEED_UNITS", "to_metres_factor"]

FOOT_M = 0.3048
LENGTH_UNITS = {"m": 1.0, "ft": FOOT_M}
# Factors to m/s of the speed units data come in; validation names a mix-up of them.
SPEED_UNITS = {"m/s": 1.0, "km/h": 1 / 3.6, "ft/s": FOOT_M, "mph": 0.44704}


def to_metres_factor(units: str) -> float:
    """Factor that turns lengths in ``units`` into metres.

    ``units`` is ``m``, ``ft`` or a plain number (the factor itself), for sources converted with a
    wrong factor: e.g. a file "in metres" made with 0.3084 m/ft takes ``0.3048/0.3084``.
    """
    if units in LENGTH_UNITS:
        return LENGTH_UNITS[units]
    try:
        factor = float(units)
    except ValueError:
        raise DataError(
            f"unknown length unit {units!r}: use one of {sorted(LENGTH_UNITS)} or a factor to metres"
        ) from None
    if not factor > 0:
        raise DataError(f"length factor must be positive, got {units!r}")
    return factor
