"""The root of the drivers' errors (python-can's ``CanError`` is the model): every error the
drivers raise on purpose derives from :class:`DriverError` and from the builtin it mixes in
(``ValueError`` for bad bytes and bad options), so callers catch either."""


class DriverError(Exception):
    """Root of the drivers' exceptions."""
