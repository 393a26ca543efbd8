"""The monitor's logic without transport: decoded samples in, alert transitions out.

:class:`Monitor` keeps one tracker per robot and joint / thruster axis / device / bus, updates
metrics as samples arrive (:meth:`Monitor.feed`) and runs the rules on every metric update;
:meth:`Monitor.tick` evaluates what needs no sample (stream staleness on the monitor's clock).
The zenoh service (:mod:`.service`) and the tests drive it the same way.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

from drivers.samples import BusHealth, DeviceHealth, ThrusterCommand, TorqueCommand
from gateway.efforts import Alert, JointEfforts, ThrusterEffort

from .rules import RuleEngine, RuleSet, load_rules
from .trackers import AxisTracker, DeviceTracker, JointTracker

log = logging.getLogger(__name__)
AXES = ("fx", "fy", "fz", "mx", "my", "mz")
STREAM_STALE_S = 1.0       # an effort/command stream is listed as stale in the dashboard after this


def torque_limits(robot: str) -> dict[str, float]:
    """Joint torque limits of a robot known to robot_description (``{}`` if it is not)."""
    try:
        import robot_description

        r = robot_description.load(robot)
    except Exception as exc:  # noqa: BLE001 - an unknown robot only loses the fraction metric
        log.info("robot %s: no torque limits (%s); friction_fraction unavailable", robot, exc)
        return {}
    return {name: float(lim) for name, lim in zip(r.joint_names, r.effort_limit)}


@dataclass
class RobotState:
    joints: dict[str, JointTracker] = field(default_factory=dict)
    axes: dict[str, AxisTracker] = field(default_factory=dict)
    devices: dict[str, DeviceTracker] = field(default_factory=dict)
    buses: dict[str, float] = field(default_factory=dict)
    streams: dict[str, int] = field(default_factory=dict)     # stream -> last receive time (monitor clock)
    last_efforts_t_ns: int = 0
    limits: dict[str, float] | None = None
    flags: tuple[str, ...] = ()
    others: dict[tuple[str, str], Alert] = field(default_factory=dict)   # (rule, target) -> raised by others


class Monitor:
    """Feed it ``(key, sample)`` pairs; it returns alert transitions as they happen."""

    def __init__(self, ruleset: RuleSet | None = None, limits=torque_limits):
        self.ruleset = ruleset or load_rules()
        self.engine = RuleEngine(self.ruleset.rules)
        self.robots: dict[str, RobotState] = {}
        self._limits = limits
        self.recent: list[Alert] = []       # the last alert transitions, newest last
        self.counts = {"samples": 0, "not_good": 0, "ignored": 0}

    def _robot(self, robot: str) -> RobotState:
        st = self.robots.get(robot)
        if st is None:
            st = self.robots[robot] = RobotState()
            st.limits = self._limits(robot) if self._limits else {}
        return st

    def feed(self, key: str, obj, recv_ns: int | None = None) -> list[Alert]:
        parts = key.split("/")
        if len(parts) < 3 or parts[0] != "bsc":
            self.counts["ignored"] += 1
            return []
        robot = parts[1]
        st = self._robot(robot)
        self.counts["samples"] += 1
        if isinstance(obj, Alert):
            self._other(st, obj)
            return []
        if recv_ns is not None:
            st.streams["/".join(parts[2:5]) if parts[2] == "efforts" else "/".join(parts[2:4])] = recv_ns
        s = self.ruleset.monitor
        out: list[Alert] = []
        if isinstance(obj, JointEfforts):
            st.last_efforts_t_ns = max(st.last_efforts_t_ns, obj.t_ns)
            if not obj.good or len(obj.commanded_nm) != len(obj.joints):
                self.counts["not_good"] += 1
                st.flags = obj.flags
                return out
            st.flags = ()
            for name, cmd, est, rate in zip(obj.joints, obj.commanded_nm, obj.full_nm, obj.rate_rad_s):
                tr = st.joints.get(name)
                if tr is None:
                    tr = st.joints[name] = JointTracker(s.tau_s, s.v_min_rad_s, (st.limits or {}).get(name))
                tr.add(obj.t_ns, cmd, est, rate)
                out += self._evaluate(robot, "actuator", name, tr.metrics(s.min_weight_s), obj.t_ns)
        elif isinstance(obj, ThrusterEffort):
            st.last_efforts_t_ns = max(st.last_efforts_t_ns, obj.t_ns)
            if not obj.good or obj.commanded_t_ns == 0:
                self.counts["not_good"] += 1
                return out
            est = (*obj.force_n, *obj.moment_nm)
            cmd = (*obj.commanded_force_n, *obj.commanded_moment_nm)
            for axis, e, c in zip(AXES, est, cmd):
                tr = st.axes.get(axis)
                if tr is None:
                    tr = st.axes[axis] = AxisTracker(s.tau_s)
                tr.add(obj.t_ns, e, c)
                out += self._evaluate(robot, "thruster", axis, tr.metrics(s.min_weight_s), obj.t_ns)
        elif isinstance(obj, DeviceHealth):
            tr = st.devices.get(obj.device)
            if tr is None:
                tr = st.devices[obj.device] = DeviceTracker()
            tr.add(obj)
            out += self._evaluate(robot, "sensor", obj.device, tr.metrics(), obj.t_ns)
        elif isinstance(obj, BusHealth):
            st.buses[obj.bus] = obj.load
            out += self._evaluate(robot, "sensor", f"bus/{obj.bus}", {"bus_load": obj.load}, obj.t_ns)
        elif isinstance(obj, (TorqueCommand, ThrusterCommand)):
            pass                 # only their arrival matters (stream staleness)
        else:
            self.counts["ignored"] += 1
        return out

    def _other(self, st: RobotState, a: Alert) -> None:
        """An alert another service raised or cleared (the gateway's fault detector on
        ``bsc/<robot>/alerts``, ``bsc control``'s transitions on ``commands/status``): shown
        among the robot's active alerts while raised, never judged again here."""
        self.counts["others"] = self.counts.get("others", 0) + 1
        if a.state == "raised":
            st.others[(a.rule, a.target)] = a
        else:
            st.others.pop((a.rule, a.target), None)
        self.recent = (self.recent + [a])[-50:]

    def tick(self, now_ns: int) -> list[Alert]:
        """Stream staleness on the monitor's clock (receive times given to :meth:`feed`)."""
        out: list[Alert] = []
        for robot, st in self.robots.items():
            for stream, t in st.streams.items():
                if stream.startswith("efforts/"):
                    out += self._evaluate(robot, "sensor", stream, {"staleness_s": (now_ns - t) / 1e9}, now_ns)
        return out

    def _evaluate(self, robot: str, kind: str, target: str, metrics: dict[str, float], t_ns: int) -> list[Alert]:
        out = []
        ev = {k: v for k, v in metrics.items() if isinstance(v, float) and math.isfinite(v)}
        for metric, value in metrics.items():
            out += self.engine.update(robot, kind, target, metric, value, t_ns, ev)
        if out:
            self.recent = (self.recent + out)[-50:]
        return out

    def snapshot(self, now_ns: int | None = None) -> dict:
        """Everything the dashboard shows, as plain data."""
        s = self.ruleset.monitor
        snap = {}
        for robot, st in sorted(self.robots.items()):
            snap[robot] = {
                "joints": {n: t.metrics(s.min_weight_s) for n, t in sorted(st.joints.items())},
                "axes": {a: st.axes[a].metrics(s.min_weight_s) for a in AXES if a in st.axes},
                "devices": {d: t.metrics() for d, t in sorted(st.devices.items())},
                "buses": dict(sorted(st.buses.items())),
                "streams": {k: ((now_ns - v) / 1e9 if now_ns else float("nan")) for k, v in sorted(st.streams.items())},
                "flags": st.flags,
                "active": sorted([f"{rule}:{target}" for (r, rule, target) in self.engine.active() if r == robot]
                                 + [f"{rule}:{target}" for rule, target in st.others]),
            }
        return snap
