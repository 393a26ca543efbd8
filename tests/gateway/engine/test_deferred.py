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


def test_a_call_a_sink_does_not_take_is_neither_made_nor_copied():
    """A recorder told not to record raw frames (a replay's) takes no frames and, without the
    frame tree, no sample events: its stand-in has neither, so the session makes no such call and
    the writer copies nothing for it. Told to, it takes them."""
    from gateway.engine.deferred import _stand_type

    quiet = RecorderSink(object(), frames=False, transforms=False, rows=True, offline=True)
    full = RecorderSink(object(), frames=True, transforms=True, rows=True, offline=True)
    for name in ("frame", "frames", "sample_events"):
        assert not quiet.takes(name) and full.takes(name)
        assert name not in vars(_stand_type(quiet)) and name in vars(_stand_type(full))
    for name in ("sample_rows", "effort_rows", "valve_rows", "emit"):
        assert quiet.takes(name) and name in vars(_stand_type(quiet))
    assert not Sink().takes("frames") and not Objects().takes("frames") and Objects().takes("emit")


def test_the_session_calls_frames_only_on_sinks_that_take_them(frames):
    class Counting(Sink):
        def __init__(self, take):
            self.take, self.n = take, 0

        def frames(self, buses, rows, log_ns):
            self.n += len(rows)

        def takes(self, method):
            return self.take if method == "frames" else super().takes(method)

    yes, no = Counting(True), Counting(False)
    import robot_description

    with Session(robot_description.load(None), [yes, no]) as ses:
        from drivers.kernel import columns_from_messages

        rows = columns_from_messages([(ses.buses.index(b), m) for b, m in frames[:500]])
        ses.feed_frames(rows)
    assert yes.n == 500 and no.n == 0
