"""The root of the gateway's errors: every error it raises on purpose (a bad log, a bad rules file,
a recording that failed, the service's own) derives from :class:`GatewayError` and from the
builtin it mixes in (``ValueError`` for bad input, ``OSError`` for a recording that cannot be
written), so callers catch either. The command line turns these into one line and exit status 2;
anything else is a bug and shows as one."""


class GatewayError(Exception):
    """Root of the gateway's exceptions."""
