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
    """What a session's output goes to. Override what you use; the base does nothing."""

    def frame(self, bus: str, msg: can.Message, log_ns: int) -> None:
        """One raw frame as received (live), before it is decoded."""

    def frames(self, buses: Sequence[str], frames: np.ndarray, log_ns: np.ndarray) -> None:
        """Raw frames as :data:`drivers.kernel.FRAME_DTYPE` rows (``bus`` indexes ``buses``)."""

    def emit(self, key: str, obj, log_ns: int) -> None:
        """A decoded sample, an effort or a health snapshot, under its zenoh key."""


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
        # pipeline_factory: a stand-in with Pipeline's interface (tests of what runs around it)
        self.pipeline = pipeline_factory(robot, emit=self._emit, model_robot=model_robot, layout=layout, fd=fd,
                                         estimate=estimate, settings=settings, timing=timing, samples=samples)
        self.name = self.pipeline.name
        self.buses = self.pipeline.buses
        self.health_period_ns = health_period_ns
        self.log_offset_ns = log_offset_ns
        self._next_health: int | None = None
        self.last_ns: int | None = None          # the last frame's time (frame clock)
        self.last_log_ns: int | None = None
        self._closed = False

    def _emit(self, key: str, obj) -> None:
        log_ns = self.pipeline.log_ns
        for s in self.sinks:
            s.emit(key, obj, log_ns)

    # -- input ---------------------------------------------------------------------------------
    def feed(self, bus: str, msg: can.Message, log_ns: int | None = None) -> None:
        """One live frame; ``log_ns`` defaults to its timestamp plus the offset."""
        t = round(msg.timestamp * 1e9)
        log = t + self.log_offset_ns if log_ns is None else log_ns
        for s in self.sinks:
            s.frame(bus, msg, log)
        self.pipeline.log_ns = log
        self.pipeline.feed(bus, msg, log_ns=log)
        self._after(t, log)

    def feed_frames(self, frames: np.ndarray, log_ns: np.ndarray | None = None) -> None:
        """Frames as rows (``bus`` indexes :attr:`buses`), in arrival order; ``log_ns`` (one per
        frame) defaults to their timestamps plus the offset."""
        if not len(frames):
            return
        if log_ns is None:
            log_ns = frames["t_ns"] + self.log_offset_ns
        for s in self.sinks:
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
