"""Sinks every caller of a :class:`~gateway.engine.Session` needs."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .session import Sink


class RecorderSink(Sink):
    """Everything a session emits, and (``frames=True``) the raw frames it was fed, to a
    :class:`gateway.recorder.Recorder`, each under the log time the session gives it.

    Frames given as rows are recorded as python-can would have given them, with the bus's
    ``channels[bus]``. Live (default), a message the recorder refuses (its queue full: the disk is behind) is
    counted by the recorder and the session goes on. ``offline=True`` (a replay, a simulated
    series: nothing is real time) waits for the disk instead, and a refusal is an error.
    """

    BACKPRESSURE_EVERY = 4096        # messages between two looks at the recorder's queue

    def __init__(self, recorder, *, frames: bool = True, offline: bool = False, channels=None):
        self.recorder, self.record_frames, self.offline = recorder, frames, offline
        self.channels = dict(channels or {})    # bus -> its channel, recorded with frames given as rows
        self._n = 0

    def _put(self, ok: bool, what: str) -> None:
        if self.offline:
            if not ok:
                from gateway.recorder import RecorderError

                raise RecorderError(f"the recorder refused {what}: {self.recorder.error or self.recorder.stats}")
            self._n += 1
            rec = self.recorder
            if self._n % self.BACKPRESSURE_EVERY == 0 and rec.stats.queue_depth > rec.queue_size // 2:
                rec.flush()

    def frame(self, bus: str, msg, log_ns: int) -> None:
        if self.record_frames:
            self._put(self.recorder.record_can(bus, msg, log_ns), f"a frame of bus {bus}")

    def frames(self, buses: Sequence[str], frames: np.ndarray, log_ns: np.ndarray) -> None:
        if not self.record_frames or not len(frames):
            return
        bus_of = frames["bus"]
        for i, name in enumerate(buses):
            sel = bus_of == i
            if sel.any():
                refused = self.recorder.record_can_rows(name, frames[sel], log_ns[sel], self.channels.get(name))
                self._put(not refused, f"frames of bus {name}")

    def emit(self, key: str, obj, log_ns: int) -> None:
        self._put(self.recorder.record(key, obj, log_ns), key)
