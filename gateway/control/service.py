"""``bsc control`` over zenoh: the joint loop (:class:`JointCompensator`) between the gateway and the
robot's drives.

:class:`ControlService` is given an open zenoh session (it owns only what it declares)::

    with ControlService(session, robot) as ctl:         # subscribers and publishers declared
        ctl.run(stop_event, duration_s=None)
    # close(): undeclared (harmless twice)

Subscriptions: ``bsc/<robot>/efforts/joints/**`` (the gateway's estimates) and
``bsc/<robot>/sensors/commands/torque/**`` (the outer loop's desired torques, as the gateway
observed them on the arm buses). Publications, only under ``bsc/<robot>/commands/**`` (the
controller role's key space, deploy/zenoh/router.json5): each arm's :class:`DriveCommand` on
``commands/drives/<arm>`` every time the arm's desired torques are complete (the outer loop's
rate), and the loop's transitions (open/closed) as :class:`gateway.efforts.Alert` records on
``commands/status``.

Samples are handled on zenoh's callback thread under one lock, at once (the core costs
microseconds; a queue would only add delay): latest-wins by construction, the core keeps only
the newest estimate and desired torques. A bad payload is counted (``rejected``), never raised.
Staleness is judged on the sensor clock the efforts and commands share: when the gateway stops,
the next desired torques find no fresh estimate and the command goes out open loop.
"""
from __future__ import annotations

import logging
import threading
import time

from drivers.samples import TorqueCommand
from gateway import codec, keys
from gateway.control.joints import JointCompensator, JointLoopSettings, LoopEvent
from gateway.control.messages import encode_drive_command
from gateway.efforts import Alert, JointEfforts

log = logging.getLogger("gateway.control")


class ControlService:
    def __init__(self, session, robot, settings: JointLoopSettings | None = None, *, enabled: bool = True):
        self.session, self.robot = session, robot
        self.name = robot.name
        keys.robot_root(self.name)                  # validates the name
        self.core = JointCompensator.for_robot(robot, settings, enabled=enabled)
        self.received = 0
        self.rejected = 0
        self.published = {"closed": 0, "open": 0}
        self.alerts: list[Alert] = []
        self._lock = threading.Lock()
        self._subs: list = []
        self._pubs: dict[str, object] = {}
        self._closed = False

    # --- lifecycle ----------------------------------------------------------------------------------
    def start(self) -> "ControlService":
        if self._closed:
            raise RuntimeError("the control service is closed")
        if not self._subs:
            for a in self.robot.arms:
                self._pubs[a.name] = codec.declare_publisher(self.session, keys.drive_command(self.name, a.name))
            self._pubs["status"] = codec.declare_publisher(self.session, keys.control_status(self.name))
            root = keys.robot_root(self.name)
            for key in (f"{root}/efforts/joints/**", f"{root}/sensors/commands/torque/**"):
                self._subs.append(self.session.declare_subscriber(key, self._on_sample))
        return self

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        with self._lock:
            for s in self._subs + list(self._pubs.values()):
                try:
                    s.undeclare()
                except Exception as exc:  # noqa: BLE001 - a session closed first must not mask close()
                    log.debug("undeclare: %r", exc)
            self._subs.clear()
            self._pubs.clear()

    def __enter__(self) -> "ControlService":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # --- the loop -----------------------------------------------------------------------------------
    def _on_sample(self, sample) -> None:
        # zenoh's callback thread: decode, feed the core, publish; never raise
        try:
            obj = codec.decode(sample.payload.to_bytes())
        except Exception:  # noqa: BLE001 - a bad payload is counted, not fatal
            with self._lock:
                self.rejected += 1
            return
        self.feed(obj)

    def feed(self, obj) -> None:
        """One decoded sample (an estimate or an observed command) through the core; publishes
        the arm's drive command when its desired torques are complete."""
        with self._lock:
            if self._closed:
                return
            self.received += 1
            if isinstance(obj, JointEfforts):
                self.core.estimate(obj)
            elif isinstance(obj, TorqueCommand):
                arm = self.core.observe(obj)
                if arm is not None:
                    cmd = self.core.command(arm)
                    codec.put(self._pubs[arm], encode_drive_command(cmd))
                    self.published["closed" if cmd.closed else "open"] += 1
            for event in self.core.take_events():
                self._transition(event)

    def _transition(self, e: LoopEvent) -> None:
        opened = e.state == "open"
        alert = Alert(self.name, "actuator", e.arm, "compensation-open-loop", "warning" if opened else "info",
                      "raised" if opened else "cleared", e.t_ns, e.t_ns,
                      f"{e.arm}: compensation {'open loop' if opened else 'closed again'} ({e.reason})")
        self.alerts.append(alert)
        log.log(logging.WARNING if opened else logging.INFO, "%s", alert.message)
        codec.put(self._pubs["status"], codec.encode(alert))

    def run(self, stop: threading.Event | None = None, duration_s: float | None = None) -> None:
        """Serve until ``stop`` is set or ``duration_s`` has passed (the work happens on zenoh's
        callback threads)."""
        self.start()
        stop = stop or threading.Event()
        end = None if duration_s is None else time.monotonic() + duration_s
        while not stop.is_set():
            wait = 0.5 if end is None else min(0.5, end - time.monotonic())
            if wait <= 0:
                break
            stop.wait(wait)
