"""``bsc monitor`` over zenoh: subscribe to efforts, commands and health; publish alerts.

:class:`MonitorService` is given an open zenoh session (it owns only the subscribers and
publishers it declares). Lifecycle, as the gateway service::

    with MonitorService(session, robots="*") as mon:     # subscribers declared
        mon.run(stop_event, duration_s=None, on_tick=print_dashboard)
    # close(): subscribers and publishers undeclared (harmless twice)

Subscriptions: ``bsc/<robots>/efforts/**``, ``bsc/<robots>/sensors/commands/**``,
``bsc/<robots>/health/**`` (``robots`` is one name or a glob chunk such as ``*``), and the alerts
of the other services, ``bsc/<robots>/alerts`` (the gateway's thruster fault detector, another
monitor) and ``bsc/<robots>/commands/status`` (``bsc control``'s loop transitions), from other
sessions only (its own published alerts do not come back): listed with its own (dashboard, alert
log, ``on_alert``), never published again.
Queue semantics: FIFO, bounded (``queue_size``): the friction fit wants every effort sample;
when the monitor falls behind, the NEWEST samples are refused and counted (``dropped``), never
blocking zenoh's callback thread. Samples are processed on the ``run()`` thread, in arrival
order. Alerts go to ``bsc/<robot>/alerts`` (codec payload, attachment ``publish_ns``), to the
``on_alert`` callback, and to the ``gateway.monitor`` logger (and a JSON-lines file if given).
"""
from __future__ import annotations

import collections
import json
import logging
import threading
import time
from dataclasses import asdict
from pathlib import Path
from typing import Callable

from gateway import codec, keys
from gateway.efforts import Alert

from .core import Monitor
from .rules import RuleSet

log = logging.getLogger("gateway.monitor")


class MonitorService:
    def __init__(self, session, robots: str = "*", ruleset: RuleSet | None = None, *,
                 on_alert: Callable[[Alert], None] | None = None, alert_log: str | Path | None = None,
                 tick_s: float = 0.25, queue_size: int = 100_000, publish: bool = True):
        if robots != "*":
            keys.robot_root(robots)                  # validates the name
        self.session = session
        self.robots = robots
        self.monitor = Monitor(ruleset)
        self.on_alert = on_alert
        self.tick_s = tick_s
        self.publish_alerts = publish
        self.alerts: list[Alert] = []           # its own and the other services' (``others`` of them)
        self.others = 0
        self.received = 0
        self.rejected = 0
        self.dropped = 0
        self._queue: collections.deque = collections.deque()
        self._queue_size = queue_size
        self._wake = threading.Event()
        self._lock = threading.Lock()
        self._subs: list = []
        self._pubs: dict[str, object] = {}
        self._log_file = open(alert_log, "a", encoding="utf-8") if alert_log else None  # noqa: SIM115
        self._closed = False

    # --- lifecycle ----------------------------------------------------------------------------------
    def start(self) -> "MonitorService":
        if self._closed:
            raise RuntimeError("the monitor service is closed")
        if not self._subs:
            root = f"{keys.ROOT}/{self.robots}"
            for sub in ("efforts/**", "sensors/commands/**", "health/**"):
                self._subs.append(self.session.declare_subscriber(f"{root}/{sub}", self._on_sample))
            import zenoh

            for sub in ("alerts", "commands/status"):       # the other services' alerts
                self._subs.append(self.session.declare_subscriber(f"{root}/{sub}", self._on_sample,
                                                                  allowed_origin=zenoh.Locality.REMOTE))
        return self

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for s in self._subs + list(self._pubs.values()):
            try:
                s.undeclare()
            except Exception as exc:  # noqa: BLE001 - a session closed first must not mask close()
                log.debug("undeclare: %r", exc)
        self._subs.clear()
        self._pubs.clear()
        if self._log_file is not None:
            self._log_file.close()
            self._log_file = None

    def __enter__(self) -> "MonitorService":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # --- zenoh side ---------------------------------------------------------------------------------
    def _on_sample(self, sample) -> None:
        # zenoh's callback thread: decode, queue, never raise
        try:
            key = str(sample.key_expr)
            obj = codec.decode(sample.payload.to_bytes())
        except Exception:  # noqa: BLE001 - a bad payload is counted, not fatal
            with self._lock:
                self.rejected += 1
            return
        with self._lock:
            if len(self._queue) >= self._queue_size:
                self.dropped += 1
                return
            self._queue.append((key, obj, time.time_ns()))
            self.received += 1
        self._wake.set()

    def _publish(self, alert: Alert) -> None:
        key = keys.alerts(alert.robot)
        pub = self._pubs.get(key)
        if pub is None:
            pub = self._pubs[key] = codec.declare_publisher(self.session, key)
        codec.put(pub, codec.encode(alert))

    # --- processing ---------------------------------------------------------------------------------
    def process_pending(self) -> int:
        """Feed every queued sample to the monitor (on the calling thread); how many."""
        n = 0
        while True:
            with self._lock:
                if not self._queue:
                    self._wake.clear()
                    return n
                key, obj, recv = self._queue.popleft()
            n += 1
            for alert in self.monitor.feed(key, obj, recv):
                self._emit(alert)
            if isinstance(obj, Alert):
                self.others += 1
                self._emit(obj, publish=False)          # another service's

    def tick(self, now_ns: int | None = None) -> None:
        for alert in self.monitor.tick(time.time_ns() if now_ns is None else now_ns):
            self._emit(alert)

    def _emit(self, alert: Alert, publish: bool = True) -> None:
        self.alerts.append(alert)
        level = logging.WARNING if alert.state == "raised" else logging.INFO
        log.log(level, "%s %s %s %s/%s: %s", alert.robot, alert.state, alert.severity, alert.kind, alert.target,
                alert.message)
        if self._log_file is not None:
            self._log_file.write(json.dumps(asdict(alert)) + "\n")
            self._log_file.flush()
        if publish and self.publish_alerts and not self._closed:
            self._publish(alert)
        if self.on_alert is not None:
            self.on_alert(alert)

    def run(self, stop: threading.Event | None = None, duration_s: float | None = None,
            on_tick: Callable[["MonitorService"], None] | None = None) -> None:
        """Process samples as they come and tick every ``tick_s`` until ``stop`` or ``duration_s``."""
        self.start()
        stop = stop or threading.Event()
        end = None if duration_s is None else time.monotonic() + duration_s
        next_tick = time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            if end is not None and now >= end:
                break
            if now >= next_tick:
                self.tick()
                if on_tick is not None:
                    on_tick(self)
                next_tick = now + self.tick_s
            wait = next_tick - time.monotonic()
            if end is not None:
                wait = min(wait, end - time.monotonic())
            if self._wake.wait(max(0.0, wait)):
                self.process_pending()
        self.process_pending()
        if on_tick is not None:
            on_tick(self)
