"""Shared test fixtures. Generic: nothing here knows about one package's internals.

``_no_leaked_resources`` (autouse) fails a test that leaves a python-can bus open, a
python-can Notifier thread running, or a zenoh session open. It records what the test created
by wrapping the constructors for the duration of the test only.
"""
from __future__ import annotations

import sys
import threading

import pytest


@pytest.fixture(autouse=True)
def _no_leaked_resources(monkeypatch):
    buses: list = []   # strong references, for the test's duration only: a dropped bus still leaks
    sessions: list = []
    threads_before = set(threading.enumerate())

    can = sys.modules.get("can")
    if can is None:
        try:
            import can  # noqa: F811 - cheap enough, and the tests that matter import it anyway
        except ImportError:
            can = None
    if can is not None:
        orig_init = can.BusABC.__init__

        def tracking_init(self, *a, **kw):
            buses.append(self)
            orig_init(self, *a, **kw)

        monkeypatch.setattr(can.BusABC, "__init__", tracking_init)

    zenoh = sys.modules.get("zenoh")
    if zenoh is not None:
        orig_open = zenoh.open

        def tracking_open(*a, **kw):
            s = orig_open(*a, **kw)
            sessions.append(s)
            return s

        monkeypatch.setattr(zenoh, "open", tracking_open)

    yield

    problems = []
    for t in set(threading.enumerate()) - threads_before:
        if t.is_alive() and "notifier" in t.name.lower():
            t.join(timeout=0.5)
            if t.is_alive():
                problems.append(f"notifier thread still running: {t.name}")
    open_buses = [b for b in list(buses) if not getattr(b, "_is_shutdown", True)]
    for b in open_buses:
        problems.append(f"CAN bus not shut down: {b!r}")
        try:
            b.shutdown()
        except Exception:  # noqa: BLE001 - cleaning up after the failed test
            pass
    buses.clear()
    for s in sessions:
        if not s.is_closed():
            problems.append("zenoh session not closed")
            s.close()
    if problems:
        pytest.fail("resource leak: " + "; ".join(problems))
