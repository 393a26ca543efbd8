"""The gateway service: CAN drivers -> zenoh, samples and health.

:class:`GatewayService` is given the buses (one per :class:`drivers.wire.BusSpec`, opened by
the caller) and an open zenoh session; it owns only the notifiers and publishers it creates.
Lifecycle::

    with GatewayService(wire_map, buses, session) as gw:   # start(): notifiers running
        gw.run(stop_event)                                  # health every health_period_s
    # close(): notifiers stopped, publishers undeclared (harmless twice)

Samples are published from the notifier threads as they are decoded (no queue: zenoh's put
does not block on slow subscribers in the default congestion control "drop"). The estimator
extends the service by overriding :meth:`on_sample` (call ``super().on_sample(sample)`` to keep
publishing) and :meth:`on_tick` (runs on the ``run()`` thread every health period).
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Mapping

import can

from drivers import wire
from drivers.devices import BusMonitor, Driver, listeners_for
from gateway import codec, keys

log = logging.getLogger(__name__)


class GatewayError(Exception):
    """Root of the gateway service's errors."""


class GatewayService:
    def __init__(self, wire_map: wire.WireMap, buses: Mapping[str, can.BusABC], session, *, fd: bool = False,
                 health_period_s: float = 0.5, stale_periods: int = 10):
        missing = set(wire_map.buses) - set(buses)
        if missing:
            raise GatewayError(f"no CAN bus given for {', '.join(sorted(missing))}")
        self.wire = wire_map
        self.robot = wire_map.robot
        self.buses = dict(buses)
        self.session = session
        self.fd = fd
        self.health_period_s = health_period_s
        self.monitors: dict[str, BusMonitor] = {}
        self.drivers: dict[str, list[Driver]] = {}
        for name, spec in wire_map.buses.items():
            self.monitors[name], self.drivers[name] = listeners_for(spec, self.on_sample, fd, stale_periods)
        self._notifiers: list[can.Notifier] = []
        self._publishers: dict[str, object] = {}
        self._lock = threading.Lock()
        self._closed = False
        self.published = 0

    # --- lifecycle ---------------------------------------------------------------------------

    def start(self) -> "GatewayService":
        if self._closed:
            raise GatewayError("the gateway service is closed")
        if not self._notifiers:
            for name, bus in self.buses.items():
                if name in self.monitors:
                    self._notifiers.append(can.Notifier(bus, [self.monitors[name], *self.drivers[name]], timeout=0.1))
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

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for n in self._notifiers:
            n.stop()
        self._notifiers.clear()
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

    # --- hooks -------------------------------------------------------------------------------

    def on_sample(self, sample) -> None:
        """Called on a notifier thread for every decoded sample: publishes it."""
        self.publish(keys.for_sample(self.robot, sample), sample)

    def on_tick(self) -> None:
        """Called on the ``run()`` thread every health period: publishes health."""
        self.publish_health()

    # --- publishing --------------------------------------------------------------------------

    def publish(self, key: str, obj) -> None:
        if self._closed:
            return
        pub = self._publishers.get(key)
        if pub is None:
            with self._lock:
                if self._closed:
                    return
                pub = self._publishers.get(key)
                if pub is None:
                    pub = self._publishers[key] = self.session.declare_publisher(key)
        pub.put(codec.encode(obj))
        self.published += 1

    def health(self, now_ns: int | None = None) -> list:
        """Snapshots of every bus and device (also resets the measured-load window)."""
        now = time.time_ns() if now_ns is None else now_ns
        out = []
        for name in self.wire.buses:
            out.append(self.monitors[name].health(now))
            for d in self.drivers[name]:
                out.extend(d.health(now))
        return out

    def publish_health(self) -> None:
        if self._closed:
            return
        for h in self.health():
            self.publish(keys.for_sample(self.robot, h), h)
