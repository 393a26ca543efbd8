"""The root of the gateway's errors: every error it raises on purpose (a bad log, a bad rules file,
a recording that failed, the service's own) derives from :class:`GatewayError` and from the
builtin it mixes in (``ValueError`` for bad input, ``OSError`` for a recording that cannot be
written), so callers catch either. The command line turns these into one line and exit status 2;
anything else is a bug and shows as one.

Messages name what is wrong in the library's terms (a start time, a bus map, the robot), never a
command-line flag: ``option`` names the parameter at fault, and a command line adds its own flag
for it (``gateway.cli``: ``bsc replay: error: ...: not an integer (hex as 0x200) [--can-id]``)."""
from __future__ import annotations


class GatewayError(Exception):
    """Root of the gateway's exceptions. ``option``: the parameter at fault, if one is."""

    option: str | None = None

    def __init__(self, *args: object, option: str | None = None):
        super().__init__(*args)
        if option is not None:
            self.option = option
