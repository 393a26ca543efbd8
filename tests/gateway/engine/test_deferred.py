"""A session's sinks run by a writer thread (gateway/engine/deferred.py): the same calls in the
same order with the same data, rows the caller reuses copied, a sink's error raised in the
session's thread."""
from __future__ import annotations

import numpy as np
import pytest

from gateway.engine import Session, Sink
from gateway.engine.deferred import deferred
from gateway.engine.sinks import RecorderSink


class Tape(Sink):
    """Every call with a snapshot of its arguments (rows as bytes)."""

    rows = True

    def __init__(self):
        self.calls = []

    def _keep(self, name, *args):
        self.calls.append((name, *(a.tobytes() if isinstance(a, np.ndarray) else a for a in args)))

    def sample_rows(self, session, events, log_ns):
        self._keep("sample_rows", events, log_ns)

    def effort_rows(self, session, rows, log_ns):
        self._keep("effort_rows", rows, log_ns)

    def valve_rows(self, session, rows, log_ns):
        self._keep("valve_rows", rows, log_ns)

    def emit(self, key, obj, log_ns):
        self._keep("emit", key, repr(obj), log_ns)


class Objects(Sink):
    """A sink of objects (rows False): what it is handed, in order."""

    def __init__(self):
        self.got = []

    def emit(self, key, obj, log_ns):
        self.got.append((key, repr(obj), log_ns))


def _feed(sinks, frames):
    import robot_description

    with Session(robot_description.load(None), sinks, health_period_ns=200_000_000) as ses:
        for k in range(0, len(frames), 700):
            ses.feed_messages(frames[k:k + 700])


@pytest.fixture(scope="module")
def frames():
    from gateway.engine.warm import frames as warm_frames

    return warm_frames(600)              # (bus, can.Message) of 600 steps of the paper robot


def test_the_same_calls_in_the_same_order(frames):
    direct, obj_direct = Tape(), Objects()
    _feed([direct, obj_direct], frames)
    tape, obj = Tape(), Objects()
    with deferred([tape, obj], depth=2, batch=3) as sinks:
        assert [s.rows for s in sinks] == [True, False]
        _feed(sinks, frames)
    kinds = {c[0] for c in direct.calls}
    assert {"sample_rows", "effort_rows", "valve_rows", "emit"} <= kinds   # every kind of call was there
    assert tape.calls == direct.calls
    assert obj.got == obj_direct.got and obj.got


def test_rows_reused_by_the_caller_are_copied():
    class Keep(Sink):
        rows = True

        def __init__(self):
            self.seen = []

        def effort_rows(self, session, rows, log_ns):
            self.seen.append(rows)

    keep = Keep()
    buf = np.arange(6, dtype=np.int64)
    with deferred([keep], batch=100) as (stand,):
        stand.effort_rows(None, buf, buf)
        buf[:] = -1                                  # the caller's next use of its buffer
    assert keep.seen[0].tolist() == [0, 1, 2, 3, 4, 5]


def test_a_sink_error_reaches_the_session_thread():
    class Broken(Sink):
        def emit(self, key, obj, log_ns):
            raise OSError("disk full")

    written = []

    class Later(Sink):
        def emit(self, key, obj, log_ns):
            written.append(obj)

    with pytest.raises(OSError, match="disk full") as err:      # its own type: what callers handle
        with deferred([Broken(), Later()], batch=1) as (stand, later):
            for k in range(1000):
                stand.emit("k", k, k)
                later.emit("k", k, k)
    assert any("writer thread" in n for n in err.value.__notes__)
    assert len(written) < 1000                                  # it stopped: nothing more written


def test_a_recorder_behind_a_writer_thread_writes_what_it_writes_directly(frames, tmp_path):
    from gateway.log.recorder import Recorder
    from gateway.log.reader import iter_file_order

    def record(path, defer):
        with Recorder(path) as rec:
            sink = RecorderSink(rec, frames=False, offline=True, rows=True)
            if defer:
                with deferred([sink]) as sinks:
                    _feed(sinks, frames)
            else:
                _feed([sink], frames)
        out = {}
        for t, _, m in iter_file_order(path, lambda t, s: True):
            out.setdefault(t, []).append((m.log_time, bytes(m.data)))
        return out

    a, b = record(tmp_path / "direct.mcap", False), record(tmp_path / "deferred.mcap", True)
    assert a == b and any("/efforts/" in t for t in a)
