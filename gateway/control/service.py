"""``bsc control`` over zenoh: the joint loop (:class:`JointCompensator`) between the gateway and the
robot's drives, and the thruster loop (:class:`ThrusterCompensator`) between the gateway and the
robot's valves.

:class:`ControlService` is given an open zenoh session (it owns only what it declares)::

    with ControlService(session, robot, layout=layout) as ctl:   # subscribers and publishers declared
        ctl.run(stop_event, duration_s=None)
    # close(): undeclared (harmless twice)

Subscriptions: ``bsc/<robot>/efforts/joints/**`` (the gateway's estimates) and
``bsc/<robot>/sensors/commands/torque/**`` (the outer loop's desired torques, as the gateway
observed them on the arm buses); with a thruster ``layout``, also ``bsc/<robot>/efforts/valves``
(the thruster filter's learned per-valve wrenches), ``bsc/<robot>/sensors/commands/thrusters``
(the outer loop's commanded wrench, observed on the spacecraft bus) and ``bsc/<robot>/alerts``
(the fault detector's ``thruster-fault`` alerts). Publications, only under
``bsc/<robot>/commands/**`` (the controller role's key space, deploy/zenoh/router.json5): each
arm's :class:`DriveCommand` on ``commands/drives/<arm>`` every time the arm's desired torques are
complete (the outer loop's rate); on each newer commanded wrench a :class:`ThrusterValves` on
``commands/thrusters``, the valves of the steps until the next one (``block_steps`` steps of
``step_ns``, from one step after the commanded wrench's time) and, as a look-ahead the next
schedule replaces, of as many steps again (so a schedule that arrives late leaves the valves no
gap); the loops' transitions (open/closed,
a thruster excluded) as :class:`gateway.efforts.Alert` records on ``commands/status``.

The valves are commanded only while the commanded wrench carries the flight software's keep-out
mask (``THRUSTER_CMD_ALLOWED``, :attr:`ThrusterCommand.allowed`): a thruster it excludes is never
fired. A commanded wrench without one gets no schedule (the robot's valves keep the flight
software's), raised once as ``compensation-keepout-unknown`` and cleared when a mask comes back.

Samples are handled on zenoh's callback threads at once, each loop under its own lock (the joint
core costs microseconds, a valve schedule 0.3-1 ms: it must not hold up a drive command; a queue
would only add delay): latest-wins by
construction, the cores keep only the newest estimates and commands. A bad payload is counted
(``rejected``), never raised. Staleness is judged on the sensor clock the efforts and commands
share: when the gateway stops, the next desired torques (commanded wrench) find no fresh estimate
and the command goes out open loop (on the nominal allocation).
"""
from __future__ import annotations

import logging
import threading
import time

from drivers.samples import ThrusterCommand, TorqueCommand
from gateway import codec, keys
from gateway.control.joints import JointCompensator, JointLoopSettings, LoopEvent
from gateway.control.messages import encode_drive_command, encode_thruster_valves
from gateway.control.thrusters import LOOP as THRUSTER_LOOP, ThrusterCompensator, ThrusterLoopSettings
from gateway.efforts import Alert, JointEfforts, ValveWrenches

KEEPOUT_RULE = "compensation-keepout-unknown"
"""The alert rule of commanded wrenches without the keep-out mask: no valve command meanwhile."""

log = logging.getLogger("gateway.control")


def valve_timing() -> tuple[int, int]:
    """(step_ns, block_steps) of the thruster loop's schedules, from the wire: a valve command is
    good for one valve-command period (THRUSTER_VALVE_CMD, 1 ms); a schedule covers one
    commanded-wrench period (THRUSTER_CMD, 10 ms), until the next commanded wrench."""
    from drivers import wire

    lay = wire.layouts("spacecraft")
    step = lay[wire.VALVE_CMD_ID].cycle_ms * 1_000_000
    return step, max(1, lay[wire.THRUSTER_FORCE_ID].cycle_ms * 1_000_000 // step)


class ControlService:
    """``layout`` (a :class:`robot_description.thrusters.ThrusterLayout`, the gateway's): run the
    thruster loop too, its valves opened at least ``valve_min_on_s`` at a time (the valves' minimum
    impulse bit); None: the joints only. ``enabled=False`` (``--open-loop``): the desired torques
    pass through, and no valve command is published (the robot's valves keep the flight
    software's)."""

    def __init__(self, session, robot, settings: JointLoopSettings | None = None, *, enabled: bool = True,
                 layout=None, thruster_settings: ThrusterLoopSettings | None = None, valve_min_on_s: float = 0.004):
        self.session, self.robot = session, robot
        self.name = robot.name
        keys.robot_root(self.name)                  # validates the name
        self.core = JointCompensator.for_robot(robot, settings, enabled=enabled)
        self.step_ns, self.block_steps = valve_timing()
        self.thrusters: ThrusterCompensator | None = None
        if layout is not None and enabled:
            min_on = max(1, round(valve_min_on_s * 1e9 / self.step_ns))
            self.thrusters = ThrusterCompensator.for_layout(layout, min_on=min_on, settings=thruster_settings)
        self._demand_ns: int | None = None          # the commanded wrench of the latest schedule
        self._keepout_known: bool | None = None     # the latest commanded wrench carried a keep-out mask
        self.valves_withheld = 0                    # commanded wrenches without one: no valve command
        self._received = {"joints": 0, "thrusters": 0}
        self.rejected = 0
        self.published = {"closed": 0, "open": 0}
        self.valves_published = {"closed": 0, "open": 0}
        self.alerts: list[Alert] = []
        self._lock = threading.Lock()               # the joint loop's
        self._thr_lock = threading.Lock()           # the thruster loop's: a schedule never holds up a drive command
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
            subs = [f"{root}/efforts/joints/**", f"{root}/sensors/commands/torque/**"]
            if self.thrusters is not None:
                self._pubs[THRUSTER_LOOP] = codec.declare_publisher(self.session, keys.thruster_valves(self.name))
                subs += [keys.valve_wrenches(self.name), keys.thruster_command(self.name), keys.alerts(self.name)]
            for key in subs:
                self._subs.append(self.session.declare_subscriber(key, self._on_sample))
        return self

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        with self._lock, self._thr_lock:
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

    @property
    def received(self) -> int:
        """Samples taken by the loops."""
        return sum(self._received.values())

    def feed(self, obj) -> None:
        """One decoded sample (an estimate, an observed command or an alert) through the cores;
        publishes the arm's drive command when its desired torques are complete, the valves until
        the next commanded wrench on each newer commanded wrench. The two loops have a lock each."""
        if isinstance(obj, (JointEfforts, TorqueCommand)) or self.thrusters is None:
            with self._lock:
                if self._closed:
                    return
                self._received["joints"] += 1
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
            return
        thr = self.thrusters
        with self._thr_lock:
            if self._closed:
                return
            self._received["thrusters"] += 1
            if isinstance(obj, ValveWrenches):
                thr.estimate(obj)
            elif isinstance(obj, ThrusterCommand):
                if self._demand_ns is None or obj.t_ns > self._demand_ns:
                    self._demand_ns = obj.t_ns
                    if self._keepout_known is not (obj.allowed >= 0):
                        self._keepout_known = obj.allowed >= 0
                        self._transition(LoopEvent(THRUSTER_LOOP, obj.t_ns,
                                                   "keep-out" if self._keepout_known else "no-keep-out", ""))
                    if obj.allowed < 0:
                        # without the flight software's keep-out mask the loop could fire a thruster
                        # whose plume it keeps off the target: no valve command; the robot's valves
                        # keep the flight software's (docs/control.md)
                        self.valves_withheld += 1
                        return
                    thr.observe(obj)
                    v = thr.schedule(obj.t_ns + self.step_ns, self.block_steps, self.step_ns,
                                     lookahead=self.block_steps)
                    codec.put(self._pubs[THRUSTER_LOOP], encode_thruster_valves(v))
                    self.valves_published["closed" if v.closed else "open"] += 1
            elif isinstance(obj, Alert):
                thr.alert(obj)
            for event in thr.take_events():
                self._transition(event)

    def _transition(self, e: LoopEvent) -> None:
        thruster = e.arm == THRUSTER_LOOP
        if e.state in ("no-keep-out", "keep-out"):
            if e.state == "keep-out" and self.valves_withheld == 0:
                return                              # known from the start: nothing to say
            raised = e.state == "no-keep-out"
            alert = Alert(self.name, "thruster", e.arm, KEEPOUT_RULE, "warning" if raised else "info",
                          "raised" if raised else "cleared", e.t_ns, e.t_ns,
                          "thrusters: no valve commands, the commanded wrench carries no keep-out mask "
                          "(THRUSTER_CMD_ALLOWED); the robot's flight software times its valves" if raised else
                          "thrusters: the keep-out mask is on the wire again; valve commands resume")
        elif e.state == "fault":                      # a thruster the fault detector named: never fired
            alert = Alert(self.name, "thruster", e.arm, "compensation-thruster-excluded", "warning", "raised",
                          e.t_ns, e.t_ns, f"thrusters: {e.reason}")
        else:
            opened = e.state == "open"
            what = ("nominal allocation" if opened else "learned wrenches again") if thruster else \
                ("open loop" if opened else "closed again")
            alert = Alert(self.name, "thruster" if thruster else "actuator", e.arm, "compensation-open-loop",
                          "warning" if opened else "info", "raised" if opened else "cleared", e.t_ns, e.t_ns,
                          f"{e.arm}: compensation {what} ({e.reason})")
        self.alerts.append(alert)
        log.log(logging.WARNING if alert.state == "raised" else logging.INFO, "%s", alert.message)
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
