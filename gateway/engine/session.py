"""One session: frames in from any source, samples, efforts and health out to sinks.

A :class:`Session` wraps the :class:`gateway.pipeline.Pipeline` (the compiled drivers and
estimator) with what every caller needs around it, once:

- **log time**: every emitted object carries the log time of the frame that produced it (the
  frame's own timestamp, plus ``log_offset_ns``, or the log time a recorded frame had);
- **raw frames**: handed to the sinks that record them (:meth:`Sink.frame` for a live
  ``can.Message``, :meth:`Sink.frames` for rows), before the frame is decoded;
- **health**: every ``health_period_ns`` of frame time (a simulated or replayed session), or when
  the caller asks (:meth:`Session.emit_health`, the live gateway's wall-clock ticks);
- **the end**: :meth:`Session.close` computes the epochs still waiting and emits a last health
  snapshot at the last frame's time.

Sinks see objects in emission order: within one call the samples first, then the efforts they
completed (one frame per call: sample by sample, as the first wave did).
"""
from __future__ import annotations

from typing import Iterable, Sequence

import can
import numpy as np

from drivers.health import DEFAULT_TIMING, SourceTiming
from gateway import keys
from gateway.estimator.core import CoreSettings
from gateway.pipeline import Pipeline
from robot_description import Robot
from robot_description.thrusters import ThrusterLayout


class Sink:
    """What a session's output goes to. Override what you use; the base does nothing.

    A sink with ``rows = True`` takes decoded samples and efforts as rows
    (:meth:`sample_rows`, :meth:`effort_rows`: an output that encodes rows directly, never
    building an object per message), and the learned valve wrenches as rows too if it overrides
    :meth:`valve_rows`; health, alerts (and the valve wrenches otherwise) still come as objects to
    :meth:`emit`.
    """

    rows = False

    def sample_rows(self, session: "Session", events: np.ndarray, log_ns: np.ndarray) -> None:
        """The drivers' event rows (:data:`drivers.kernel.EVENT_DTYPE`) with each one's log time."""

    def effort_rows(self, session: "Session", rows: np.ndarray, log_ns: np.ndarray) -> None:
        """The estimator's effort rows (:func:`gateway.estimator.core.effort_dtype`), each
        one epoch: one :class:`JointEfforts` per arm and a :class:`ThrusterEffort`."""

    def valve_rows(self, session: "Session", rows: np.ndarray, log_ns: np.ndarray) -> None:
        """The thruster filter's learned per-valve wrenches as rows
        (:func:`gateway.estimator.core.valve_dtype`), each one :class:`ValveWrenches`."""

    def sample_events(self, session: "Session", events: np.ndarray, log_ns: np.ndarray) -> None:
        """Every decoded sample's event row with its log time, whether or not the session emits
        samples (``samples=False``): for what a sink derives from them (the recorder's /tf)."""

    def frame(self, bus: str, msg: can.Message, log_ns: int) -> None:
        """One raw frame as received (live), before it is decoded."""

    def frames(self, buses: Sequence[str], frames: np.ndarray, log_ns: np.ndarray) -> None:
        """Raw frames as :data:`drivers.kernel.FRAME_DTYPE` rows (``bus`` indexes ``buses``)."""

    def emit(self, key: str, obj, log_ns: int) -> None:
        """A decoded sample, an effort or a health snapshot, under its zenoh key."""

    def takes(self, method: str) -> bool:
        """Whether this sink does something with calls of ``method`` (one of the methods above):
        by default, whether its type overrides it. A session makes no call, and builds nothing,
        for a sink that does not take it (a recorder told not to record the raw frames)."""
        return getattr(type(self), method) is not getattr(Sink, method)


class Session:
    """The pipeline of one robot between a source of frames and ``sinks``.

    ``health_period_ns``: emit health every this much frame time (None: only when asked and at
    :meth:`close`). ``log_offset_ns`` is added to frame times to make log times (a simulated
    series dates its sessions). ``samples=False`` keeps decoded samples out of the emits. The
    other arguments are :class:`gateway.pipeline.Pipeline`'s (``pipeline_factory`` builds it:
    a stand-in with its interface lets tests look at what runs around it).
    """

    def __init__(self, robot: Robot, sinks: Iterable[Sink] = (), *, model_robot: Robot | None = None,
                 layout: ThrusterLayout | None = None, fd: bool = False, estimate: bool = True,
                 timing: SourceTiming = DEFAULT_TIMING, settings: CoreSettings | None = None,
                 samples: bool = True, health_period_ns: int | None = None, log_offset_ns: int = 0,
                 pipeline_factory=Pipeline):
        self.sinks = list(sinks)
        self.samples = samples
        self._encoders = None
        self._sample_memo = self._effort_memo = self._valve_memo = None
        self._sorted()
        rows = {"on_samples": self._sample_rows, "on_efforts": self._effort_rows, "on_valves": self._valve_rows}
        # pipeline_factory: a stand-in with Pipeline's interface (tests of what runs around it)
        self.pipeline = pipeline_factory(robot, emit=self._emit, model_robot=model_robot, layout=layout, fd=fd,
                                         estimate=estimate, settings=settings, timing=timing,
                                         samples=samples or bool(self._event_sinks), **rows)
        self.name = self.pipeline.name
        self.buses = self.pipeline.buses
        self.health_period_ns = health_period_ns
        self.log_offset_ns = log_offset_ns
        self._next_health: int | None = None
        self.last_ns: int | None = None          # the last frame's time (frame clock)
        self.last_log_ns: int | None = None
        self._closed = False

    def _sorted(self) -> None:
        self._row_sinks = [s for s in self.sinks if s.rows]
        self._object_sinks = [s for s in self.sinks if not s.rows]
        self._valve_row_sinks = [s for s in self._row_sinks if s.takes("valve_rows")]
        self._valve_object_sinks = [s for s in self.sinks if s not in self._valve_row_sinks]
        self._frame_sinks = [s for s in self.sinks if s.takes("frame")]
        self._frames_sinks = [s for s in self.sinks if s.takes("frames")]
        self._event_sinks = [s for s in self.sinks if s.takes("sample_events")]
        if getattr(self, "pipeline", None) is not None:      # a sink added later: the rows it needs
            self.pipeline.emit_samples = self.samples or bool(self._event_sinks)

    def add_sink(self, sink: Sink, *, first: bool = False) -> None:
        """Another output, after the others (``first``: before them; e.g. a probe that times
        what the others do)."""
        self.sinks.insert(0, sink) if first else self.sinks.append(sink)
        self._sorted()

    # -- payloads: encoded once per batch, for every row sink (a zenoh payload and a log message
    #    are the same bytes, gateway.log.schema)
    def sample_encoded(self, events: np.ndarray):
        """A batch of sample events encoded into one buffer (:class:`gateway.engine.encode.Encoded`),
        once whatever the number of sinks that ask (the publisher and the recorder)."""
        return self._encoded("_sample_memo", events, "sample_encoded")

    def effort_encoded(self, rows: np.ndarray):
        """The same for a batch of effort rows."""
        return self._encoded("_effort_memo", rows, "effort_encoded")

    def valve_encoded(self, rows: np.ndarray):
        """The same for a batch of valve rows."""
        return self._encoded("_valve_memo", rows, "valve_encoded")

    def sample_messages(self, events: np.ndarray) -> list:
        """``(key, type, payload, event)`` of a batch of sample events, from :meth:`sample_encoded`."""
        return self._messages("_sample_memo", events, "sample_encoded")

    def effort_messages(self, rows: np.ndarray) -> list:
        """The same for a batch of effort rows."""
        return self._messages("_effort_memo", rows, "effort_encoded")

    def valve_messages(self, rows: np.ndarray) -> list:
        """The same for a batch of valve rows."""
        return self._messages("_valve_memo", rows, "valve_encoded")

    def _encoded(self, memo_name: str, rows: np.ndarray, how: str):
        memo = getattr(self, memo_name)
        if memo is None or memo[0] is not rows:
            memo = [rows, getattr(self.encoders(), how)(rows), None]
            setattr(self, memo_name, memo)
        return memo[1]

    def _messages(self, memo_name: str, rows: np.ndarray, how: str) -> list:
        enc = self._encoded(memo_name, rows, how)
        memo = getattr(self, memo_name)
        if memo[2] is None:
            memo[2] = enc.messages()
        return memo[2]

    def encoders(self):
        """This session's :class:`gateway.engine.encode.RowEncoders` (made on first use)."""
        if self._encoders is None:
            from .encode import RowEncoders

            self._encoders = RowEncoders(self.pipeline)
        return self._encoders

    def _emit(self, key: str, obj) -> None:
        log_ns = self.pipeline.log_ns
        for s in self.sinks:
            s.emit(key, obj, log_ns)

    def _emit_objects(self, key: str, obj) -> None:
        log_ns = self.pipeline.log_ns
        for s in self._object_sinks:
            s.emit(key, obj, log_ns)

    def _sample_rows(self, events: np.ndarray, log_ns: np.ndarray) -> None:
        self._sample_memo = None                 # the rows of this batch, encoded on first ask
        for s in self._event_sinks:
            s.sample_events(self, events, log_ns)
        if not self.samples:
            return
        for s in self._row_sinks:
            s.sample_rows(self, events, log_ns)
        if self._object_sinks:                   # objects built once, for the sinks that want them
            pl = self.pipeline
            for obj, t in zip(pl.drivers.to_samples(events), log_ns.tolist()):
                pl.log_ns = t
                self._emit_objects(pl.key(obj), obj)

    def _effort_rows(self, rows: np.ndarray, log_ns: np.ndarray) -> None:
        self._effort_memo = None
        for s in self._row_sinks:
            s.effort_rows(self, rows, log_ns)
        if self._object_sinks:
            self.pipeline.emit_efforts(rows, log_ns.tolist(), self._emit_objects)

    def _valve_rows(self, rows: np.ndarray, log_ns: np.ndarray) -> None:
        self._valve_memo = None
        for s in self._valve_row_sinks:
            s.valve_rows(self, rows, log_ns)
        if self._valve_object_sinks:
            sinks = self._valve_object_sinks
            pl = self.pipeline

            def emit(key: str, obj) -> None:
                for s in sinks:
                    s.emit(key, obj, pl.log_ns)

            pl.emit_valves(rows, log_ns.tolist(), emit)

    # -- input ---------------------------------------------------------------------------------
    def feed(self, bus: str, msg: can.Message, log_ns: int | None = None) -> None:
        """One live frame; ``log_ns`` defaults to its timestamp plus the offset."""
        t = round(msg.timestamp * 1e9)
        log = t + self.log_offset_ns if log_ns is None else log_ns
        for s in self._frame_sinks:
            s.frame(bus, msg, log)
        self.pipeline.log_ns = log
        self.pipeline.feed(bus, msg, log_ns=log)
        self._after(t, log)

    def feed_messages(self, pairs: Sequence[tuple[str, can.Message]]) -> None:
        """Live frames ``(bus, can.Message)`` that arrived together, in arrival order: one pass
        of the compiled kernels for all of them (a call costs microseconds of dispatch, a frame
        a fraction of one), each frame still going to the sinks that record frames."""
        if not pairs:
            return
        rows, kept = self.pipeline.rows_of(pairs)
        if not len(rows):
            return
        log_ns = rows["t_ns"] + self.log_offset_ns
        logs = log_ns.tolist()
        for s in self._frame_sinks:
            for j, k in enumerate(kept):
                bus, msg = pairs[k]
                s.frame(bus, msg, logs[j])
        self.pipeline.feed_frames(rows, log_ns=log_ns)
        self._after(int(rows["t_ns"][-1]), logs[-1])

    def feed_frames(self, frames: np.ndarray, log_ns: np.ndarray | None = None) -> None:
        """Frames as rows (``bus`` indexes :attr:`buses`), in arrival order; ``log_ns`` (one per
        frame) defaults to their timestamps plus the offset."""
        if not len(frames):
            return
        if log_ns is None:
            log_ns = frames["t_ns"] + self.log_offset_ns
        for s in self._frames_sinks:
            s.frames(self.buses, frames, log_ns)
        self.pipeline.feed_frames(frames, log_ns=log_ns)
        self._after(int(frames["t_ns"][-1]), int(log_ns[-1]))

    def _after(self, t: int, log: int) -> None:
        self.last_ns, self.last_log_ns = t, log
        period = self.health_period_ns
        if period is None:
            return
        nxt = self._next_health
        if nxt is None:
            self._next_health = (t // period + 1) * period
        elif t >= nxt:
            self._next_health = (t // period + 1) * period
            self.emit_health(t, log)

    # -- output --------------------------------------------------------------------------------
    def emit(self, key: str, obj, log_ns: int) -> None:
        """Emit an object of the caller's to every sink (e.g. a health report it completed)."""
        for s in self.sinks:
            s.emit(key, obj, log_ns)

    def emit_health(self, now_ns: int, log_ns: int | None = None) -> list:
        """Emit a health snapshot of every bus and device at ``now_ns`` (frame clock); returns it."""
        out = self.pipeline.health(now_ns)
        log = now_ns + self.log_offset_ns if log_ns is None else log_ns
        name = self.name
        for h in out:
            key = keys.for_sample(name, h)
            for s in self.sinks:
                s.emit(key, h, log)
        return out

    def close(self) -> list:
        """End of input: the epochs still waiting are computed (emitted with the last frame's log
        time) and a last health snapshot is emitted at the last frame's time, which is returned.
        Harmless twice (the second call returns [])."""
        if self._closed:
            return []
        self._closed = True
        if self.last_log_ns is not None:
            self.pipeline.log_ns = self.last_log_ns
        self.pipeline.flush()
        if self.last_ns is None:
            return []
        return self.emit_health(self.last_ns, self.last_log_ns)

    def __enter__(self) -> "Session":
        return self

    def __exit__(self, *exc) -> None:
        if exc[0] is None:
            self.close()

    @property
    def stats(self) -> dict[str, int]:
        return self.pipeline.stats
