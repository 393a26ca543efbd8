"""Thruster modulation and allocation."""
from __future__ import annotations

import math

import numpy as np
import pytest

from simulator import scenario
from simulator.thrusters import PWPFM, Allocator, Layout, ThrusterErrors


@pytest.mark.parametrize("demand", [0.1, 0.2, 0.35, 0.5, 0.75, 0.9])
def test_pwpfm_duty_cycle_tracks_demand_on_average(demand):
    pw = scenario.load().cfg.thrusters.pwpfm
    mod = PWPFM(1, 1e-3, pw.km, pw.tau_s, pw.u_on, pw.u_off, pw.min_on_s)
    on = np.array([mod.step(np.array([demand]))[0] for _ in range(20_000)])
    duty = on[2000:].mean()
    assert abs(duty - demand) < 0.03, duty
    # it is pulses, not a continuous valve
    assert 0 < duty < 1 and np.count_nonzero(np.diff(on.astype(int)) == 1) > 10


def test_pwpfm_minimum_impulse_bit():
    pw = scenario.load().cfg.thrusters.pwpfm
    mod = PWPFM(1, 1e-3, pw.km, pw.tau_s, pw.u_on, pw.u_off, pw.min_on_s)
    on = np.array([mod.step(np.array([0.15]))[0] for _ in range(5000)]).astype(int)
    edges = np.flatnonzero(np.diff(on)) + 1
    runs = np.diff(edges)[on[edges[:-1]] == 1]
    assert runs.size and runs.min() >= round(pw.min_on_s / 1e-3)


def _alloc():
    cfg = scenario.load().cfg.thrusters
    layout = Layout.from_config(cfg)
    return layout, Allocator(layout, cfg.keepout_deg)


def test_allocation_never_fires_toward_the_target():
    layout, alloc = _alloc()
    center, radius = np.array([7.0, 0.0, 0.0]), 3.0
    rng = np.random.default_rng(0)
    for _ in range(200):
        yaw = rng.uniform(-0.5, 0.5)
        R = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
        p = rng.normal(0, 0.3, 3)
        allowed = alloc.allowed(R, p, center, radius)
        u = alloc.allocate(rng.normal(0, [80, 80, 20, 20, 20, 300]), allowed)
        assert np.all(u >= 0) and np.all(u <= layout.max_n + 1e-9)
        fired = u > 1e-9
        # independent check: every firing plume points away from the target disk
        for i in np.flatnonzero(fired):
            pos = p + R @ layout.pos_m[i]
            exhaust = -(R @ layout.dir[i])
            to_t = center - pos
            ang = math.acos(float(exhaust @ to_t) / np.linalg.norm(to_t))
            assert ang > math.radians(20) + math.asin(radius / np.linalg.norm(to_t))


def test_allocation_meets_a_feasible_demand():
    layout, alloc = _alloc()
    allowed = np.ones(layout.n, dtype=bool)
    w = np.array([30.0, -40.0, 5.0, 2.0, -3.0, 150.0])
    u = alloc.allocate(w, allowed)
    assert np.allclose(layout.B @ u, w, atol=0.5)


def test_backing_away_from_target_uses_the_canted_thrusters():
    layout, alloc = _alloc()
    allowed = alloc.allowed(np.eye(3), np.zeros(3), np.array([7.0, 0, 0]), 3.0)
    assert not allowed.all()                        # some thrusters are masked by the cone
    u = alloc.allocate(np.array([-50.0, 0, 0, 0, 0, 0]), allowed)
    assert (layout.B @ u)[0] == pytest.approx(-50.0, abs=0.5)


@pytest.mark.parametrize("steps", [1, 7, 20])
def test_pwpfm_chunk_equals_step_by_step(steps):
    """``run`` (closed-form filter between switches) gives the valves of repeated ``step``."""
    pw = scenario.load().cfg.thrusters.pwpfm
    rng = np.random.default_rng(3)
    a = PWPFM(18, 1e-3, pw.km, pw.tau_s, pw.u_on, pw.u_off, pw.min_on_s)
    b = PWPFM(18, 1e-3, pw.km, pw.tau_s, pw.u_on, pw.u_off, pw.min_on_s)
    for _ in range(3000 // steps):
        demand = np.where(rng.random(18) < 0.4, rng.random(18), 0.0)
        chunk = a.run(demand, steps)
        ref = np.array([b.step(demand).copy() for _ in range(steps)])
        assert np.array_equal(chunk, ref)
        assert np.array_equal(a.on, b.on) and np.array_equal(a.on_steps, b.on_steps)
        assert np.allclose(a.f, b.f, rtol=0, atol=1e-12)


def test_thruster_errors_chunk_equals_step_by_step():
    cfg = scenario.load().cfg.thrusters
    layout = Layout.from_config(cfg)
    rng = np.random.default_rng(4)
    a = ThrusterErrors(layout, cfg, np.random.default_rng(5), 1e-3)
    b = ThrusterErrors(layout, cfg, np.random.default_rng(5), 1e-3)
    stuck = np.zeros((20, layout.n), dtype=int)
    stuck[5:, 2], stuck[12:, 4] = 1, -1
    factor = np.ones((20, layout.n))
    factor[8:, 1] = 0.5
    for _ in range(50):
        cmd = rng.random((20, layout.n)) < 0.5
        valves, thrust = a.run(cmd, factor, stuck)
        for j in range(20):
            b.stuck, b.degrade = stuck[j], factor[j]
            v = b.valves(cmd[j])
            assert np.array_equal(valves[j], v)
            assert np.allclose(thrust[j], b.thrust(v), rtol=1e-12, atol=1e-12)
    assert np.allclose(a.dT, b.dT, rtol=1e-9)
