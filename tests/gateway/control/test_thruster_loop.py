"""The thruster loop's core: allocation and valve timing on learned per-valve wrenches, and every
safety behaviour, on a plant in the test.

The plant is the ring18 layout whose valves really deliver ``W_true`` (nominal off by a gain and a
misalignment); the "gateway" reports ``W_true`` (or something wrong, or nothing, as each test
says), one step late as in the lockstep closed loop.
"""
from __future__ import annotations

import numpy as np
import pytest

from drivers.samples import ThrusterCommand
from gateway.control import ControlError, ThrusterCompensator, ThrusterLoopSettings, ValveWrenches
from gateway.control.thrusters import SigmaDelta, allocate
from gateway.efforts import Alert
from robot_description.thrusters import ThrusterLayout

MS = 1_000_000
LAYOUT = ThrusterLayout.named("ring18", 100.0)
N = LAYOUT.n
NOMINAL = LAYOUT.nominal_wrenches
WRENCH = np.array([60.0, -40.0, 0.0, 0.0, 0.0, 150.0])     # a commanded body wrench, N and N m


def true_wrenches(gain=0.9, tilt_deg=2.0, seed=3):
    rng = np.random.default_rng(seed)
    W = NOMINAL * gain
    lateral = np.cross(LAYOUT.dir, rng.standard_normal((N, 3)))
    lateral /= np.linalg.norm(lateral, axis=1, keepdims=True)
    f = W[:, :3] + np.radians(tilt_deg) * gain * LAYOUT.max_n[:, None] * lateral
    return np.hstack([f, np.cross(LAYOUT.pos_m, f)])


W_TRUE = true_wrenches()


def learned(t_ns, W=W_TRUE, sigma=0.5, good=True, flags=()):
    return ValveWrenches(t_ns, tuple(np.asarray(W, dtype=float).ravel()), (sigma,) * N, good, tuple(flags))


def comp(**kw):
    settings = kw.pop("settings", None) or ThrusterLoopSettings(min_duty=0.0)
    return ThrusterCompensator.for_layout(LAYOUT, min_on=4, settings=settings, **kw)


def bits(v):
    return np.array([(v.valves >> i) & 1 for i in range(N)], dtype=bool)


def run(c, steps, estimate=lambda k: learned(k * MS), wrench=WRENCH, allowed=None):
    """Steps of 1 ms: the commanded wrench at 0, the estimate of each step fed before the valves
    of the next; returns the valve commands and the wrench the plant delivered with them."""
    c.demand(0, wrench, allowed)
    out, delivered = [], []
    for k in range(steps):
        e = estimate(k)
        if e is not None:
            c.estimate(e)
        v = c.valves((k + 1) * MS)
        out.append(v)
        delivered.append(bits(v) @ W_TRUE)
    return out, np.array(delivered)


def test_on_nominal_wrenches_it_allocates_as_the_flight_software():
    from simulator.thrusters import Allocator

    ok = np.ones(N, dtype=bool)
    ok[[3, 4]] = False
    u = Allocator(LAYOUT, 20.0).allocate(WRENCH, ok)
    duty, saturated = allocate(NOMINAL, WRENCH, ok)
    np.testing.assert_allclose(duty, u / LAYOUT.max_n, rtol=0, atol=1e-9)
    assert not saturated and duty[[3, 4]].sum() == 0


def test_sigma_delta_delivers_the_duty_with_the_minimum_on_time():
    m = SigmaDelta(3, min_on=4)
    duty = np.array([0.05, 0.3, 1.0])
    on = np.array([m.step(duty, np.ones(3, dtype=bool)) for _ in range(2000)])
    np.testing.assert_allclose(on.mean(axis=0), duty, rtol=0, atol=4 / 2000 + 1e-12)
    for i in range(2):                               # every opening lasts at least 4 steps
        edges = np.diff(np.concatenate([[0], on[:, i].astype(int), [0]]))
        lengths = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
        assert lengths.min() >= 4
    # a valve that becomes unusable closes at once, minimum on-time or not
    usable = np.array([True, False, True])
    assert not m.step(duty, usable)[1]


def test_learned_wrenches_deliver_the_commanded_wrench_where_the_nominal_ones_miss():
    _, got = run(comp(), 2000)
    _, nominal = run(comp(enabled=False), 2000)
    err = lambda d: np.abs(d[500:].mean(axis=0) - WRENCH)           # noqa: E731
    assert err(got)[:3].max() < 1.0 and err(got)[5] < 3.0            # N, N m over 1.5 s
    assert err(nominal)[:3].max() > 4.0 and err(nominal)[5] > 10.0   # 10 % weak, 2 deg off


def test_not_good_estimates_fall_back_to_the_nominal_allocation_within_one_step_and_resume():
    c = comp()
    bad = range(300, 400)
    out, _ = run(c, 600, lambda k: learned(k * MS, good=k not in bad, flags=() if k not in bad else ("warmup",)))
    assert out[299].closed and not out[300].closed                  # the step after the first bad one
    assert out[300].flags == ("estimate:not-good (warmup)",)
    # nominal: the duties of the allocation on the nominal wrenches
    np.testing.assert_allclose(out[350].duty, allocate(NOMINAL, WRENCH, np.ones(N, dtype=bool))[0], atol=1e-12)
    # closes again after resume_good good estimates, ramping from nominal under the rate limit
    first = next(k for k in range(400, 600) if out[k].closed)
    assert first == 400 + ThrusterLoopSettings().resume_good - 1
    assert "limited:rate" in out[first + 1].flags
    assert [e.state for e in c.events] == ["closed", "open", "closed"]
    assert c.events[1].reason == "estimate:not-good (warmup)"


@pytest.mark.parametrize("W", [np.full((N, 6), np.nan), np.zeros((N, 5))])
def test_a_malformed_estimate_opens_the_loop(W):
    c = comp()
    out, _ = run(c, 20, lambda k: learned(k * MS) if k < 10 else
                 ValveWrenches(k * MS, tuple(W.ravel()), (0.5,) * N, True))
    assert out[9].closed and not out[10].closed


def test_stale_estimates_fall_back_within_one_step():
    c = comp()
    stale_ms = round(ThrusterLoopSettings().stale_s * 1e3)
    out, _ = run(c, 200, lambda k: learned(k * MS) if k < 100 else None)
    # the last estimate at 99 ms: the valves of 99 + stale_s are still closed loop, the next not
    assert out[99 + stale_ms - 1].closed and not out[99 + stale_ms].closed
    assert out[99 + stale_ms].flags == ("stale:efforts",)


def test_a_wrong_estimate_moves_the_wrenches_used_by_a_bounded_amount():
    c = comp()
    wild = NOMINAL.copy()
    wild[:, :3] *= 3.0                                 # three times the thrust: clipped to +25 %
    out, _ = run(c, 50, lambda k: learned(k * MS, W=wild))
    assert "limited:magnitude" in out[-1].flags
    dev = c.used - NOMINAL
    assert np.all(np.abs(dev[:, :3]) <= 0.25 * LAYOUT.max_n[:, None] + 1e-9)
    # ... and at a bounded speed: at most max_rate_per_s of the scale per second of estimates
    c2 = comp()
    run(c2, 10, lambda k: learned(k * MS, W=wild))
    assert np.abs(c2.used - NOMINAL)[:, :3].max() <= 1.0 * 100.0 * 0.005 + 1e-9   # 5 ms closed


def test_an_unlearned_valve_keeps_its_nominal_wrench():
    c = comp()
    est = lambda k: ValveWrenches(k * MS, tuple(W_TRUE.ravel()), (0.5,) * (N - 1) + (12.0,), True)   # noqa: E731
    run(c, 400, est)
    np.testing.assert_array_equal(c.used[-1], NOMINAL[-1])
    np.testing.assert_allclose(c.used[0], W_TRUE[0], atol=1e-9)


def fault(j, kind="stuck closed", t_ns=0):
    code = {"stuck open": 0.0, "leak": 1.0, "stuck closed": 2.0, "partial loss": 3.0, "cleared": 4.0}[kind]
    return Alert("paper_robot", "thruster", f"thruster{j}", "thruster-fault", "critical", "raised", t_ns, t_ns,
                 f"thruster {j}: {kind}", (("thruster", float(j)), ("theta", 1.0), ("stat", 99.0), ("type", code)))


def test_a_faulty_thruster_is_never_fired_until_cleared_closed_loop_or_not():
    c = comp()
    busiest = int(np.argmax(allocate(W_TRUE, WRENCH, np.ones(N, dtype=bool))[0]))
    c.alert(fault(busiest))
    # the gateway flags its efforts fault:thrusters while the fault is active: a fault the loop
    # knows and excludes, so it stays closed
    out, _ = run(c, 300, lambda k: learned(k * MS, good=False, flags=("fault:thrusters",)))
    assert all(v.closed and not bits(v)[busiest] for v in out[10:])
    assert f"fault:thruster{busiest}" in out[-1].flags
    c.enabled = False
    c.estimate(learned(400 * MS, good=False, flags=("warmup",)))        # open loop: still excluded
    assert not any(bits(c.valves(k * MS))[busiest] for k in range(401, 700))
    c.alert(fault(busiest, "cleared", 700 * MS))
    assert any(bits(c.valves(k * MS))[busiest] for k in range(701, 800))


def test_a_thruster_fault_the_loop_cannot_name_opens_it():
    c = comp()
    out, _ = run(c, 50, lambda k: learned(k * MS, good=k < 20, flags=() if k < 20 else ("fault:thrusters",)))
    assert out[19].closed and not out[20].closed


def test_the_keep_out_mask_is_never_crossed():
    ok = np.ones(N, dtype=bool)
    off = np.argsort(allocate(W_TRUE, WRENCH, ok)[0])[-3:]          # the three it would use most
    ok[off] = False
    out, _ = run(comp(), 500, allowed=ok)
    assert not np.any([bits(v)[off] for v in out])


def test_observed_commands_and_late_ones():
    c = comp()
    c.observe(ThrusterCommand(20 * MS, 1, (10.0, 0.0, 0.0), (0.0, 0.0, 5.0)))
    c.observe(ThrusterCommand(10 * MS, 0, (99.0, 0.0, 0.0), (0.0, 0.0, 0.0)))     # older, arriving late
    assert c._demand[1].tolist() == [10.0, 0.0, 0.0, 0.0, 0.0, 5.0]
    with pytest.raises(ControlError, match="no commanded wrench"):
        comp().valves(0)


@pytest.mark.parametrize("kw, says", [({"max_deviation": 0.0}, "max_deviation"), ({"stale_s": float("nan")}, "stale_s"),
                                      ({"resume_good": 0}, "resume_good"), ({"min_duty": 1.0}, "min_duty")])
def test_bad_settings_are_refused(kw, says):
    with pytest.raises(ControlError, match=says):
        ThrusterLoopSettings(**kw)


def test_bad_inputs_are_refused():
    c = comp()
    with pytest.raises(ControlError, match="6 finite numbers"):
        c.demand(0, [1.0, 2.0])
    with pytest.raises(ControlError, match="allowed"):
        c.demand(0, WRENCH, np.ones(3, dtype=bool))
    with pytest.raises(ControlError, match="nominal wrenches"):
        ThrusterCompensator(np.zeros((3, 5)), np.ones(3), lever_m=1.0)


def test_a_wrench_beyond_the_valves_gets_the_smallest_error_closed_loop_and_the_flight_softwares_scaling_open():
    big = WRENCH * 20.0
    ok = np.ones(N, dtype=bool)
    scaled, sat = allocate(W_TRUE, big, ok)
    bounded, sat_b = allocate(W_TRUE, big, ok, bounded=True)
    assert sat and sat_b and bounded.min() >= 0 and bounded.max() <= 1 + 1e-12
    assert np.linalg.norm(bounded @ W_TRUE - big) < np.linalg.norm(scaled @ W_TRUE - big)
    c = comp()
    out, _ = run(c, 30, wrench=big)
    assert out[-1].closed and "saturated" in out[-1].flags
    np.testing.assert_allclose(out[-1].duty, allocate(c.used, big, ok, bounded=True)[0], atol=1e-9)
    c.estimate(learned(99 * MS, good=False))
    assert c.valves(100 * MS).duty == tuple(allocate(NOMINAL, big, ok)[0].tolist())


def test_valves_the_nominal_allocation_leaves_idle_are_not_pulsed_for_small_corrections():
    ok = np.ones(N, dtype=bool)
    exact, _ = allocate(W_TRUE, WRENCH, ok)
    nominal, _ = allocate(NOMINAL, WRENCH, ok)
    small = (exact > 0) & (exact < 0.02) & (nominal < 0.02)
    assert small.any()                                # the exact allocation would pulse them
    out, _ = run(comp(settings=ThrusterLoopSettings()), 300)
    assert out[-1].closed
    assert all(out[-1].duty[i] == 0.0 for i in np.flatnonzero(small))
    assert not any(bits(v)[small].any() for v in out[10:])


def test_a_schedule_is_the_steps_valves_at_once_and_its_look_ahead_is_replaced():
    # the same valves as step by step; the look-ahead is what the next schedule gives when nothing
    # changed, and it leaves the modulator where the schedule's own steps left it
    one, other = comp(), comp()
    for c in (one, other):
        c.demand(0, WRENCH)
        c.estimate(learned(0))
    steps = [one.valves(k * MS).valves for k in range(1, 31)]
    a = other.schedule(MS, 10, MS, lookahead=10)
    assert a.t_ns == MS and a.step_ns == MS and len(a.masks()) == 20
    assert list(a.masks()[:10]) == steps[:10]
    b = other.schedule(11 * MS, 10, MS, lookahead=10)
    assert a.masks()[10:] == b.masks()[:10] and list(b.masks()[:10]) == steps[10:20]
    assert list(other.schedule(21 * MS, 10, MS).masks()) == steps[20:30]
    assert any(steps) and other.schedule(31 * MS, 1, MS).following == ()
    with pytest.raises(ControlError):
        other.schedule(41 * MS, 0, MS)
