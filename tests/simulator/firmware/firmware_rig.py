"""Helpers of the firmware tests: the drivers of a robot fed directly or under Notifiers, and
the comparison of decoded samples with the simulator's readings of the same steps.

The expected schedule is written here from docs/firmware.md (not taken from the firmware):
F/T, joint state and valve commands every step, torque commands every 2 ms and thruster commands every 10 ms
(the controller's latest output), the IMU when it sampled.
"""
from __future__ import annotations

import copy
import math
import threading
from collections import defaultdict

import can
import numpy as np

from drivers import devices, wire
from drivers.health import DEFAULT_TIMING, SourceTiming
from drivers.samples import ImuSample, JointSample, ThrusterCommand, TorqueCommand, ValveCommand, WrenchSample

# half an LSB of each wire field (drivers/frames.py), plus float slack
TOL = {"force": 0.025, "angle": 0.5e-6, "rate": 1.25e-4, "torque": 0.025, "quat": 2.0 ** -23,
       "gyro": 2.0 ** -15, "accel": 2.0 ** -14}
SLACK = 1e-9


def snapshot(readings):
    """A copy of one step's readings (the arrays may be reused by the simulator)."""
    return copy.deepcopy(readings)


class Rig:
    """The monitor and drivers of every bus of a robot, fed directly (``feed``)."""

    def __init__(self, robot, fd: bool = False, timing: SourceTiming = DEFAULT_TIMING):
        self.wire = wire.WireMap.from_robot(robot)
        self.samples: list = []
        self.listeners = {name: devices.listeners_for(spec, self.samples.append, fd=fd, timing=timing)
                          for name, spec in self.wire.buses.items()}

    def feed(self, batch):
        for bus, msg in batch:
            mon, drivers = self.listeners[bus]
            mon.on_message_received(msg)
            for d in drivers:
                d.on_message_received(msg)

    def health(self, now_ns: int, pace: float = 1.0) -> dict:
        """Every device's health at ``now_ns``. ``pace``: wall-clock time per simulated time of
        the stream the drivers saw (1: real time; a lockstep firmware over real CAN in a slow VM
        runs far slower): the drivers' staleness budget of ``stale_periods`` nominal periods
        then counts periods of the stream as it ran."""
        out = {}
        for _, drivers in self.listeners.values():
            for d in drivers:
                for c in d.counters():
                    periods = c.stale_periods
                    c.stale_periods = math.ceil(periods * max(1.0, pace))
                    try:
                        out[c.device] = c.snapshot(now_ns)
                    finally:
                        c.stale_periods = periods
        return out

    def bus_health(self, now_ns: int) -> dict:
        return {name: mon.health(now_ns) for name, (mon, _) in self.listeners.items()}


class _Gate(can.Listener):
    """Counts the frames of one bus; lets the test wait until a number of them arrived."""

    def __init__(self):
        self.n = 0
        self._cv = threading.Condition()

    def on_message_received(self, msg):
        with self._cv:
            self.n += 1
            self._cv.notify_all()

    def wait_for(self, n: int, timeout: float) -> bool:
        with self._cv:
            return self._cv.wait_for(lambda: self.n >= n, timeout)


class BusRig(Rig):
    """The same listeners under one ``can.Notifier`` per bus (the gateway's arrangement)."""

    def __init__(self, robot, buses: dict, fd: bool = False, timing: SourceTiming = DEFAULT_TIMING):
        super().__init__(robot, fd, timing)
        self.gates = {name: _Gate() for name in buses}
        self.notifiers = []
        try:
            for name, bus in buses.items():
                mon, drivers = self.listeners[name]
                self.notifiers.append(can.Notifier(bus, [mon, *drivers, self.gates[name]], timeout=0.05))
        except BaseException:
            self.stop()
            raise

    def wait(self, expected: dict, timeout: float = 20.0) -> dict:
        """Wait until every bus saw ``expected[bus]`` frames; returns the counts seen."""
        for name, n in expected.items():
            self.gates[name].wait_for(n, timeout)
        return {name: g.n for name, g in self.gates.items()}

    def stop(self):
        for n in self.notifiers:
            n.stop()


def by_device(samples) -> dict:
    out = defaultdict(list)
    for s in samples:
        if isinstance(s, ImuSample):
            out["imu"].append(s)
        elif isinstance(s, ThrusterCommand):
            out["thrusters"].append(s)
        elif isinstance(s, TorqueCommand):
            out[("cmd", s.device)].append(s)
        elif isinstance(s, ValveCommand):
            out["valves"].append(s)
        else:
            out[s.device].append(s)
    return out


def expected_streams(robot, readings) -> dict:
    """Device -> [(t_ns, reading)] in send order, from docs/firmware.md's schedule."""
    exp = defaultdict(list)
    names = robot.joint_names
    tau = thr = allowed = None
    for r in readings:
        t = r.t_ns
        if r.torque_cmd is not None:
            tau = np.array(r.torque_cmd)
        if r.thruster_cmd is not None:
            thr = np.array(r.thruster_cmd)
            allowed = sum(1 << i for i, v in enumerate(r.thruster_allowed) if v)
        for k, arm in enumerate(robot.arms):
            exp[arm.name].append((t, r.ft[k]))
            for jn in arm.joint_names:
                dev = f"{arm.name}/{jn}"
                i = names.index(dev)
                exp[dev].append((t, (r.joint_angle[i], r.joint_rate[i])))
                if tau is not None and t % 2_000_000 == 0:
                    exp[("cmd", dev)].append((t, tau[i]))
        if r.imu is not None:
            exp["imu"].append((t, r.imu))
        exp["valves"].append((t, sum(1 << i for i, v in enumerate(r.valves) if v)))
        if thr is not None and t % 10_000_000 == 0:
            mask = sum(1 << i for i, v in enumerate(r.valves) if v)
            exp["thrusters"].append((t, (thr, mask, allowed)))
    return exp


def _close(got, want, tol, what):
    got, want = np.asarray(got, dtype=float), np.asarray(want, dtype=float)
    err = np.max(np.abs(got - want))
    assert err <= tol + SLACK, f"{what}: off by {err:.3g} (> half LSB {tol:.3g}): {got} vs {want}"


def check_against_readings(robot, readings, samples, stamps: bool = True) -> dict:
    """Every decoded sample equals the reading of its step within the wire quantization, none
    is missing or extra, counters run 0, 1, 2, ... per device. ``stamps``: the interface kept
    the frames' timestamps (sample ``t_ns`` = the step's simulated time). Returns the number of
    samples checked per device."""
    exp = expected_streams(robot, readings)
    got = by_device(samples)
    assert set(got) == set(exp), f"devices {sorted(map(str, got))} != {sorted(map(str, exp))}"
    for dev, want in exp.items():
        have = got[dev]
        assert len(have) == len(want), f"{dev}: {len(have)} samples decoded, {len(want)} sent"
        for n, (s, (t, r)) in enumerate(zip(have, want)):
            assert s.counter == n & 0xFF, f"{dev}: sample {n} has counter {s.counter}"
            if stamps:
                assert s.t_ns == t, f"{dev}: sample {n} stamped {s.t_ns} ns, step at {t} ns"
            where = f"{dev} sample {n}"
            if isinstance(s, WrenchSample):
                _close(s.force_n, r[:3], TOL["force"], where + " force")
                _close(s.torque_nm, r[3:], TOL["torque"], where + " torque")
            elif isinstance(s, JointSample):
                _close(s.angle_rad, r[0], TOL["angle"], where + " angle")
                _close(s.rate_rad_s, r[1], TOL["rate"], where + " rate")
            elif isinstance(s, TorqueCommand):
                _close(s.torque_nm, r, TOL["torque"], where)
            elif isinstance(s, ImuSample):
                quat, rate, acc, sat = r
                _close(s.quat_wxyz, quat, TOL["quat"], where + " quaternion")
                _close(s.rate_rad_s, rate, TOL["gyro"], where + " rate")
                _close(s.accel_m_s2, acc, TOL["accel"], where + " acceleration")
                assert s.saturated == bool(sat)
            elif isinstance(s, ValveCommand):
                assert s.valves == r, f"{where}: valves {s.valves:#x} != {r:#x}"
            elif isinstance(s, ThrusterCommand):
                w, mask, allowed = r
                _close(s.force_n, w[:3], TOL["force"], where + " force")
                _close(s.moment_nm, w[3:], TOL["torque"], where + " moment")
                assert s.valves == mask, f"{where}: valves {s.valves:#x} != {mask:#x}"
                assert s.allowed == allowed, f"{where}: keep-out mask {s.allowed} != {allowed:#x}"
    return {dev: len(v) for dev, v in got.items()}


def assert_clean_health(health: dict):
    for dev, h in health.items():
        assert h.lost == 0 and h.rejected == (), f"{dev}: lost {h.lost}, rejected {h.rejected}"
