"""The root of the drivers' errors (python-can's ``CanError`` is the model): every error the
drivers raise on purpose derives from :class:`DriverError` and from the builtin it mixes in
(``ValueError`` for bad bytes and bad options), so callers catch either. As the gateway's
errors, ``option`` names the parameter at fault (a command line adds its flag)."""
from __future__ import annotations


class DriverError(Exception):
    """Root of the drivers' exceptions. ``option``: the parameter at fault, if one is."""

    option: str | None = None

    def __init__(self, *args: object, option: str | None = None):
        super().__init__(*args)
        if option is not None:
            self.option = option
