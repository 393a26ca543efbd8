"""Running estimates converge to known friction / efficiency; the Monitor routes samples to rules."""
from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.samples import BusHealth, DeviceHealth
from gateway import keys
from gateway.efforts import JointEfforts, ThrusterEffort
from gateway.monitor.core import Monitor
from gateway.monitor.dashboard import render
from gateway.monitor.rules import Rule, RuleSet
from gateway.monitor.trackers import AxisTracker, JointTracker


def test_joint_tracker_converges_and_forgets():
    rng = np.random.default_rng(0)
    tr = JointTracker(tau_s=5.0, limit_nm=300.0)
    t = 0
    for fc in (90.0, 150.0):
        for i in range(6000):                          # 60 s at 100 Hz per phase
            t += 10_000_000
            v = 0.3 * math.sin(i / 50)
            cmd = rng.normal(0, 100)
            r = fc * np.sign(v) + 6.0 * v + rng.normal(0, 2)
            tr.add(t, cmd, cmd - r, v)
        m = tr.metrics()
        assert m["friction_nm"] == pytest.approx(fc, abs=2.0)
        assert m["friction_fraction"] == pytest.approx(fc / 300.0, abs=0.01)
        assert abs(m["offset_nm"]) < 1.5


def test_joint_tracker_needs_motion_both_ways():
    tr = JointTracker(tau_s=5.0)
    for i in range(1000):
        tr.add(i * 10_000_000, 10.0, 0.0, 0.2)
    assert math.isnan(tr.metrics()["friction_nm"])


def test_axis_tracker_efficiency_and_weak_axis():
    rng = np.random.default_rng(1)
    fx, mx = AxisTracker(tau_s=5.0), AxisTracker(tau_s=5.0)
    for i in range(3000):
        t = (i + 1) * 10_000_000
        c = rng.normal(0, 50)
        fx.add(t, 0.7 * c + 2.0, c)
        mx.add(t, rng.normal(0, 1), rng.normal(0, 1))
    assert fx.metrics()["efficiency"] == pytest.approx(0.7, abs=1e-6)
    assert math.isnan(mx.metrics()["efficiency"])


def test_monitor_routes_health_and_bus_load_to_rules():
    rules = (Rule("loss", "sensor", "loss_rate", 0.01, 0.002), Rule("load", "sensor", "bus_load", 0.7, 0.6))
    mon = Monitor(RuleSet(rules), limits=None)
    dev = lambda t, samples, lost: DeviceHealth("arm0", "arm0", t, samples, lost, 0, (), t, False)  # noqa: E731
    assert mon.feed(keys.device_health("r1", "arm0"), dev(1, 1000, 0)) == []
    out = mon.feed(keys.device_health("r1", "arm0"), dev(2, 1900, 100))     # 100 of 1000 lost
    assert [(a.robot, a.kind, a.target, a.rule) for a in out] == [("r1", "sensor", "arm0", "loss")]
    out = mon.feed(keys.bus_health("r2", "arm1"), BusHealth("arm1", 3, 10, (), 0.85))
    assert [(a.robot, a.target, a.state) for a in out] == [("r2", "bus/arm1", "raised")]
    text = render(mon.snapshot(10), mon.recent)
    assert "== r1" in text and "== r2" in text and "bus/arm1" in text and "raised" in text


def test_monitor_ignores_estimates_that_are_not_good():
    mon = Monitor(RuleSet((Rule("f", "actuator", "friction_nm", 1.0, 0.5),)), limits=None)
    je = JointEfforts("arm0", 1, ("arm0/j1",), (0.0,), (0.0,), (500.0,), 1, (0.3,), False, ("warmup",))
    assert mon.feed(keys.joint_efforts("r", "arm0"), je) == []
    assert mon.counts["not_good"] == 1
    te = ThrusterEffort(1, (0.0,) * 3, (0.0,) * 3, (1.0,) * 3, (1.0,) * 3, 0, 0, True)
    mon.feed(keys.thruster_effort("r"), te)                               # no command yet: skipped
    assert mon.counts["not_good"] == 2
