"""Helpers shared by the test modules (import as ``from support import ...``: pytest puts the
tests folder on ``sys.path``). Nothing here knows one package's internals."""
from __future__ import annotations

import time
from typing import Callable

from gateway.zenoh_config import free_port  # noqa: F401 - the one loopback port helper, for the tests


def wait_until(cond: Callable[[], bool], what: str, timeout_s: float = 30.0, poll_s: float = 0.005) -> None:
    """Poll ``cond`` until it holds; fail with ``what`` after ``timeout_s`` (a hang becomes a
    failure; on a busy machine a condition, never a fixed sleep, says when to go on)."""
    end = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > end:
            raise AssertionError(f"timed out after {timeout_s} s: {what}")
        time.sleep(poll_s)


def subscribed(publishing_session, key: str, timeout_s: float = 30.0) -> None:
    """Until ``publishing_session`` knows a subscriber matching ``key`` (puts before reach nobody)."""
    from gateway.codec import wait_for_subscriber

    if not wait_for_subscriber(publishing_session, key, timeout_s):
        raise AssertionError(f"no subscriber for {key} reached the publishing session in {timeout_s} s")
