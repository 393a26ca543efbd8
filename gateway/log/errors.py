"""The log's errors: :class:`LogError`, a log that cannot be used as asked (a time window
outside it, no robot named in it, nothing left of it), and :class:`McapFileError`, a file that
is no readable MCAP log at all (empty, foreign, corrupt). Both are ``ValueError`` with one line
that names the file."""
from __future__ import annotations

from gateway.errors import GatewayError


class LogError(GatewayError, ValueError):
    """A log cannot be used as asked."""


class McapFileError(LogError):
    """The file is not a readable MCAP log (empty, foreign, corrupt before any data)."""
