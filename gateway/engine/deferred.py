"""A session's output written by a thread of its own, so an offline run uses both cores.

An offline replay spends about half its time computing (the drivers' and estimator's compiled
kernels, which release the GIL) and half writing what it computed (encoding rows as JSON,
handing records to the recorder). Run in one thread, the two halves take turns on one core.
:func:`deferred` gives the session stand-ins for its sinks: each call the session makes on a
stand-in is queued, with a copy of the rows it passes (the pipeline's row buffers are valid only
until its next call), and a writer thread makes the same calls, in the same order, on the real
sinks. The session computes exactly what it computes without it (the same code, the same order,
on one thread); only where the sinks run changes, so the output is the same bytes.

Health snapshots and alerts are built by the session when it emits them (the state they report is
the state at that moment); only their writing is deferred. An error in a sink is raised in the
session's thread at its next call on a stand-in, or when the ``with`` block ends; the queue is
bounded, so the session runs at most ``depth`` calls ahead of the writer.

A live gateway does not use it: there the sinks publish, and a queue would only add latency.
"""
from __future__ import annotations

import queue
import threading
from contextlib import contextmanager
from typing import Iterator, Sequence

import numpy as np

from .session import Sink

_METHODS = ("sample_rows", "effort_rows", "valve_rows", "sample_events", "frame", "frames", "emit")


def _own(a):
    """``a`` if it is not an array, else a copy the caller may keep: a contiguous structured row
    array copied as bytes (numpy copies a structured array field by field, several times slower)."""
    if not isinstance(a, np.ndarray):
        return a
    if a.dtype.names is not None and a.ndim == 1 and a.flags.c_contiguous:
        return a.view(np.dtype((np.void, a.dtype.itemsize))).copy().view(a.dtype)
    return a.copy()


class _Writer:
    """The queue between the session and the real sinks, and the thread that drains it. Calls are
    handed over in batches of ``batch``: a hand-over wakes the thread, and waking it for each call
    cost more than the call (42 us a call, 2026-11-26)."""

    def __init__(self, depth: int, batch: int):
        self.q: queue.Queue = queue.Queue(maxsize=depth)
        self.batch = batch
        self.pending: list = []
        self.error: BaseException | None = None
        self.stopped = False                  # after an error: nothing more is written
        self.thread = threading.Thread(target=self._run, name="bsc-sink-writer", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while True:
            calls = self.q.get()
            if calls is None:
                return
            if self.error is not None or self.stopped:   # drain without writing, so put never blocks
                continue
            try:
                for sink, name, args in calls:
                    getattr(sink, name)(*args)
            except BaseException as exc:  # noqa: BLE001 - raised in the session's thread
                self.error = exc

    def check(self) -> None:
        """Raise the writer's error here, in the session's thread, as it is (its type is what a
        caller handles: a recorder's ``RecorderError`` stays one), once."""
        exc = self.error
        if exc is not None:
            self.stopped = True               # before the error is taken: the thread writes nothing more
            self.error = None
            exc.add_note("(raised in the writer thread of the session's sinks, gateway/engine/deferred.py)")
            raise exc

    def put(self, sink: Sink, name: str, args: tuple) -> None:
        self.pending.append((sink, name, args))
        if len(self.pending) >= self.batch:
            self.check()
            self.q.put(self.pending)
            self.pending = []

    def close(self) -> None:
        if self.pending:
            self.q.put(self.pending)
            self.pending = []
        self.q.put(None)
        self.thread.join()


class _Stand(Sink):
    """A real sink's stand-in (subclassed per real sink type: the session dispatches on which
    methods a sink's type overrides and on its ``rows``)."""

    def __init__(self, real: Sink, writer: _Writer):
        self.real, self._writer = real, writer


def _queued(name: str):
    def call(self, *args):
        self._writer.put(self.real, name, tuple(_own(a) for a in args))
    call.__name__ = name
    return call


def _stand_type(real: Sink) -> type:
    """The stand-in type of a sink: the methods it takes (:meth:`Sink.takes`) overridden, so the
    session calls the stand-in for those only and nothing is copied for a call the sink would
    ignore. Made per use, not cached: a sink type may be local to a call (a replay's counter), and
    a cache would keep each one."""
    ns: dict = {name: _queued(name) for name in _METHODS if real.takes(name)}
    return type(f"Deferred{type(real).__name__}", (_Stand,), ns)


@contextmanager
def deferred(sinks: Sequence[Sink], depth: int = 8, batch: int = 64) -> Iterator[list[Sink]]:
    """Stand-ins for ``sinks`` whose calls a writer thread makes on the real ones, in order. On
    leaving the block every queued call has been made (the writer's error, if any, raised); the
    rows attribute of each stand-in is its sink's."""
    writer = _Writer(depth, batch)
    stands = []
    for s in sinks:
        st = _stand_type(s)(s, writer)
        st.rows = s.rows
        stands.append(st)
    try:
        yield stands
    finally:
        writer.close()
    writer.check()
