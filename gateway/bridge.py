"""The gateway service: CAN buses -> one pipeline (drivers + estimator) -> zenoh (and MCAP).

:class:`GatewayService` is given the buses (one per :class:`drivers.wire.BusSpec`, opened by
the caller) and an open zenoh session; it owns only the notifiers, the worker thread and the
publishers it creates. Lifecycle::

    with GatewayService(robot, buses, session) as gw:     # robot: robot_description.Robot   # start(): notifiers + worker running
        gw.run(stop_event)                                  # health every health_period_s
    # close(): notifiers stopped, worker drained, publishers undeclared (harmless twice)

Threads: python-can runs one notifier thread per bus; each only tags the frame with its bus and
puts it on one FIFO queue. ONE worker thread takes frames from that queue, in that order, through
:class:`gateway.pipeline.Pipeline` (drivers, then the estimator) and publishes what comes out:
decoded samples, efforts, health. The recorder (``record=``) gets the raw frames in exactly the
order the pipeline saw them, so ``bsc replay`` reproduces the efforts byte for byte. The queue is
unbounded (the frame rate is bounded by the buses; ``backlog`` is its current length).

Publish time travels as the zenoh attachment ``publish_ns`` (decimal ASCII), so that payloads of
a replay are identical to the live ones.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Mapping

import can

from drivers import wire
from gateway import codec
from gateway.pipeline import Pipeline

log = logging.getLogger(__name__)
_STOP = object()


class GatewayError(Exception):
    """Root of the gateway service's errors."""


class _Tagger(can.Listener):
    __slots__ = ("bus", "put")

    def __init__(self, bus: str, put):
        self.bus, self.put = bus, put

    def on_message_received(self, msg: can.Message) -> None:
        self.put((self.bus, msg))

    def stop(self) -> None:
        """Nothing to release."""


class GatewayService:
    def __init__(self, robot, buses: Mapping[str, can.BusABC], session, *, fd: bool = False,
                 health_period_s: float = 0.5, stale_periods: int = 10, estimate: bool = True,
                 model_robot=None, layout=None, record=None, publish_samples: bool = True):
        if isinstance(robot, wire.WireMap):                # a wire map names a built-in robot
            import robot_description

            robot = robot_description.load(robot.robot)
        wire_map = wire.WireMap.from_robot(robot)
        missing = set(wire_map.buses) - set(buses)
        if missing:
            raise GatewayError(f"no CAN bus given for {', '.join(sorted(missing))}")
        self.wire = wire_map
        self.robot = wire_map.robot
        self.buses = dict(buses)
        self.session = session
        self.fd = fd
        self.health_period_s = health_period_s
        self.recorder = record
        self.publish_samples = publish_samples
        self.pipeline = Pipeline(robot, emit=self._emit, model_robot=model_robot, layout=layout,
                                 fd=fd, estimate=estimate, stale_periods=stale_periods)
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._notifiers: list[can.Notifier] = []
        self._worker: threading.Thread | None = None
        self._publishers: dict[str, object] = {}
        self._lock = threading.Lock()            # the pipeline is used by the worker and by health ticks
        self._closed = False
        self.published = 0
        self.publish_errors = 0

    # --- lifecycle ---------------------------------------------------------------------------

    def start(self) -> "GatewayService":
        if self._closed:
            raise GatewayError("the gateway service is closed")
        if self._worker is None:
            self._worker = threading.Thread(target=self._work, name="bsc-gateway-worker", daemon=True)
            self._worker.start()
            for name, bus in self.buses.items():
                if name in self.wire.buses:
                    self._notifiers.append(can.Notifier(bus, [_Tagger(name, self._queue.put)], timeout=0.1))
        return self

    def run(self, stop: threading.Event | None = None, duration_s: float | None = None) -> None:
        """Publish health every ``health_period_s`` until ``stop`` is set or ``duration_s`` passes."""
        self.start()
        stop = stop or threading.Event()
        end = None if duration_s is None else time.monotonic() + duration_s
        while True:
            wait = self.health_period_s if end is None else min(self.health_period_s, end - time.monotonic())
            if wait <= 0 or stop.wait(wait):
                break
            self.on_tick()
        self.publish_health()

    def drain(self, timeout: float = 30.0) -> bool:
        """Wait until every frame received so far went through the pipeline."""
        done = threading.Event()
        self._queue.put(done)
        return done.wait(timeout)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for n in self._notifiers:
            n.stop()
        self._notifiers.clear()
        if self._worker is not None:
            self._queue.put(_STOP)
            self._worker.join(30.0)
        with self._lock:
            pubs, self._publishers = list(self._publishers.values()), {}
        for p in pubs:
            try:
                p.undeclare()
            except Exception as exc:  # noqa: BLE001 - a session closed first must not mask close()
                log.debug("undeclare: %r", exc)

    def __enter__(self) -> "GatewayService":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # --- the worker --------------------------------------------------------------------------

    def _work(self) -> None:
        get, feed, rec = self._queue.get, self.pipeline.feed, self.recorder
        while True:
            item = get()
            if item is _STOP:
                with self._lock:
                    self.pipeline.flush()
                return
            if isinstance(item, threading.Event):
                item.set()
                continue
            bus, msg = item
            with self._lock:
                if rec is not None:
                    rec.record_can(bus, msg, int(msg.timestamp * 1e9))
                self._frame_ns = int(msg.timestamp * 1e9)
                feed(bus, msg)

    @property
    def backlog(self) -> int:
        return self._queue.qsize()

    # --- hooks -------------------------------------------------------------------------------

    def on_tick(self) -> None:
        """Called on the ``run()`` thread every health period: publishes health."""
        self.publish_health()

    # --- publishing --------------------------------------------------------------------------

    _frame_ns = 0

    def _emit(self, key: str, obj) -> None:
        if self.recorder is not None:
            self.recorder.record(key, obj, self._frame_ns)
        if self.publish_samples or "/sensors/" not in key:
            self.publish(key, obj)

    def publish(self, key: str, obj) -> None:
        if self._closed:
            return
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publishers[key] = self.session.declare_publisher(key)
        try:
            pub.put(codec.encode(obj), attachment=str(time.time_ns()).encode())
            self.published += 1
        except Exception as exc:  # noqa: BLE001 - a closing session must not kill the worker
            self.publish_errors += 1
            log.debug("put %s: %r", key, exc)

    def health(self, now_ns: int | None = None) -> list:
        """Snapshots of every bus and device (also resets the measured-load window)."""
        now = time.time_ns() if now_ns is None else now_ns
        with self._lock:
            return self.pipeline.health(now)

    def publish_health(self) -> None:
        if self._closed:
            return
        from gateway import keys

        for h in self.health():
            with self._lock:
                self._emit(keys.for_sample(self.robot, h), h)
