"""Sinks every caller of a :class:`~gateway.engine.Session` needs."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .session import Sink


class RecorderSink(Sink):
    """Everything a session emits, and (``frames=True``) the raw frames it was fed, to a
    :class:`gateway.log.recorder.Recorder`, each under the log time the session gives it.

    Frames given as rows are recorded as python-can would have given them, with the bus's
    ``channels[bus]``. Live (default), a message the recorder refuses (its queue full: the disk is behind) is
    counted by the recorder and the session goes on. ``offline=True`` (a replay, a simulated
    series: nothing is real time) waits for the disk instead, and a refusal is an error.

    ``transforms`` (default on): the robot's frame tree from its IMU and joint samples, as
    ``foxglove.FrameTransforms`` on ``/tf`` at 50 Hz of log time, and its URDF on
    ``/robot_description`` (:class:`gateway.log.foxglove.TransformWriter`), whether or not the
    session records its samples: Foxglove's 3D panel then draws the robot moving.
    """

    BACKPRESSURE_EVERY = 4096        # messages between two looks at the recorder's queue

    def __init__(self, recorder, *, frames: bool = True, offline: bool = False, channels=None,
                 rows: bool = False, transforms: bool = True):
        self.recorder, self.record_frames, self.offline = recorder, frames, offline
        self.transforms = transforms
        self._tf = None                         # (session, TransformWriter), made on the first rows
        self.rows = rows                        # samples and efforts as rows: JSON written from them
        self.channels = dict(channels or {})    # bus -> its channel, recorded with frames given as rows
        self._n = 0

    def takes(self, method: str) -> bool:
        """Raw frames only when told to record them, sample events only for the frame tree."""
        if method in ("frame", "frames"):
            return self.record_frames
        if method == "sample_events":
            return self.transforms
        return super().takes(method)

    def _put(self, ok: bool, what: str, n: int = 1) -> None:
        if self.offline:
            if not ok:
                from gateway.log.recorder import RecorderError

                raise RecorderError(f"the recorder refused {what}: {self.recorder.error or self.recorder.stats}")
            self._n += n
            if self._n >= self.BACKPRESSURE_EVERY:
                self._n = 0
                rec = self.recorder
                if rec.queue_depth > rec.queue_size // 2:
                    rec.flush()

    def sample_events(self, session, events: np.ndarray, log_ns: np.ndarray) -> None:
        if not self.transforms:
            return
        tf = self._tf
        if tf is None or tf[0] is not session:
            from gateway.log.foxglove import TransformWriter

            from .tfjson import TransformJson

            tf = self._tf = (session, TransformWriter(self.recorder, session.pipeline.robot, encoder=TransformJson))
        n, refused = tf[1].rows(events, log_ns, session.pipeline.drivers.joint_names)
        if n:
            self._put(not refused, f"{refused} of {n} transforms", n)

    def frame(self, bus: str, msg, log_ns: int) -> None:
        if self.record_frames:
            self._put(self.recorder.record_can(bus, msg, log_ns), f"a frame of bus {bus}")

    def frames(self, buses: Sequence[str], frames: np.ndarray, log_ns: np.ndarray) -> None:
        if not self.record_frames or not len(frames):
            return
        # in the order given (the order they were fed): a replay feeds the file's order, so a
        # batch merged across buses is written run by run, never bus by bus
        bus_of = frames["bus"]
        cuts = [0, *(np.flatnonzero(bus_of[1:] != bus_of[:-1]) + 1).tolist(), len(frames)]
        for a, b in zip(cuts[:-1], cuts[1:]):
            name = buses[int(bus_of[a])]
            refused = self.recorder.record_can_rows(name, frames[a:b], log_ns[a:b], self.channels.get(name))
            self._put(not refused, f"frames of bus {name}", b - a)

    def emit(self, key: str, obj, log_ns: int) -> None:
        self._put(self.recorder.record(key, obj, log_ns), key)

    # rows (``rows=True``): the records written straight from them (encoded once by the session)
    def sample_rows(self, session, events: np.ndarray, log_ns: np.ndarray) -> None:
        self._record_rows(session.sample_encoded, session.sample_messages, events, log_ns,
                          lambda i: session.pipeline.drivers.to_samples(events[i:i + 1])[0])

    def effort_rows(self, session, rows: np.ndarray, log_ns: np.ndarray) -> None:
        self._record_rows(session.effort_encoded, session.effort_messages, rows, log_ns,
                          lambda i: session.encoders().effort_object(rows, i))

    def valve_rows(self, session, rows: np.ndarray, log_ns: np.ndarray) -> None:
        self._record_rows(session.valve_encoded, session.valve_messages, rows, log_ns,
                          lambda i: session.encoders().valve_object(rows, i))

    def _record_rows(self, encoded, messages, rows: np.ndarray, log_ns: np.ndarray, object_of) -> None:
        """Offline (a replay, a simulated series), a batch as one block of records (no Python
        step per message, here or in the recorder's thread); live, and with a value that is not
        finite in it, message by message (a live batch is an epoch or two: a block gains nothing)."""
        block = getattr(self.recorder, "record_encoded_block", None) if self.offline else None
        enc = encoded(rows) if block is not None else None
        if enc is None or enc.failed.any():
            self._record(messages(rows), log_ns, object_of)
            return
        n = len(enc.which)
        refused = block(enc.topics, enc.classes, enc.which, enc.data, enc.offsets, log_ns[enc.row])
        self._put(not refused, f"{refused} of {n} records", n)

    def _record(self, messages, log_ns: np.ndarray, object_of) -> None:
        rec, logs = self.recorder, log_ns.tolist()
        batch = []
        for i, (key, cls, data, k) in enumerate(messages):
            if data is None:                  # a value that is not finite: the object's own encoding
                self._put(rec.record(key, object_of(i), logs[k]), key)
            else:
                batch.append((key, cls, data, logs[k]))
        if batch:
            refused = rec.record_encoded_many(batch)
            self._put(not refused, f"{refused} of {len(batch)} records", len(batch))
