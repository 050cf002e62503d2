"""The one error type for bad input data."""

__all__ = ["DataError"]


class DataError(ValueError):
    """Input data that cannot be read as it is; the message names the file, row and column."""
