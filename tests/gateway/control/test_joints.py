"""The joint loop's core: tracking, limits and every safety behaviour, on a plant in the test.

The plant is one arm of two joints with Coulomb friction: the joint delivers ``applied -
friction``; the "gateway" estimates it exactly (or wrongly, or not at all, as each test says)
one step later, as the lockstep closed loop does.
"""
from __future__ import annotations

import numpy as np
import pytest

from drivers.samples import TorqueCommand
from gateway.control import ControlError, DriveCommand, JointCompensator, JointLoopSettings
from gateway.control.messages import decode_drive_command, encode_drive_command
from gateway.keys import drive_command
from gateway.efforts import JointEfforts

JOINTS = ("arm0/j1", "arm0/j2")
LIMIT = np.array([600.0, 300.0])
FRICTION = np.array([180.0, 90.0])          # 30 % of the limits
MS = 1_000_000


def effort(t_ns, actual, good=True, flags=()):
    return JointEfforts("arm0", t_ns, JOINTS, tuple(map(float, actual)), tuple(map(float, actual)), (), 0,
                        (0.0, 0.0), good, tuple(flags))


class Plant:
    """Desired torques from an outer loop, friction against them, one step of delay."""

    def __init__(self, comp: JointCompensator, desired=lambda t: np.array([200.0, -100.0])):
        self.comp, self.desired_of = comp, desired
        self.applied = None
        self.log: list[tuple[int, DriveCommand, np.ndarray]] = []

    def actual(self, applied):
        return applied - FRICTION * np.sign(applied)

    def step(self, k, estimate=None, good=True, flags=()):
        """Step k: the drives apply the last command; the gateway reports the actual torque (or
        ``estimate(actual)``); the compensator sees the desired torque and commands."""
        t = k * MS
        d = self.desired_of(t)
        self.comp.desired("arm0", t, d)
        applied = d if self.applied is None else self.applied
        act = self.actual(applied)
        est = act if estimate is None else estimate(act)
        if est is not False:
            self.comp.estimate(effort(t, est, good, flags))
        cmd = self.comp.command("arm0", t)
        self.applied = np.array(cmd.torque_nm)
        self.log.append((k, cmd, act))
        return cmd, act


def comp(**kw):
    return JointCompensator([("arm0", JOINTS)], [LIMIT], JointLoopSettings(**kw) if kw else None)


def test_friction_is_compensated_and_the_actual_torque_tracks_the_desired():
    p = Plant(comp())
    for k in range(300):
        cmd, act = p.step(k)
    assert cmd.closed and cmd.flags == ()
    np.testing.assert_allclose(act, [200.0, -100.0], atol=1e-6)           # tracks within 1e-6 N m
    np.testing.assert_allclose(cmd.correction_nm, FRICTION * [1, -1], atol=1e-6)


def test_open_loop_until_enough_good_estimates_then_the_correction_ramps_under_the_rate_limit():
    s = JointLoopSettings(resume_good=5, max_rate_per_s=50.0)
    p = Plant(JointCompensator([("arm0", JOINTS)], [LIMIT], s))
    cmds = [p.step(k)[0] for k in range(60)]
    assert [c.closed for c in cmds[:4]] == [False] * 4 and cmds[4].closed
    assert all(c.correction_nm == (0.0, 0.0) and c.torque_nm == c.desired_nm for c in cmds[:4])
    # at most max_rate * limit * dt per 1 ms step: 50 * 600 * 1e-3 = 30 N m on j1
    steps = np.diff([c.correction_nm for c in cmds[4:]], axis=0)
    assert np.all(np.abs(steps) <= 50.0 * LIMIT * 1e-3 + 1e-9)
    assert "limited:rate" in cmds[6].flags


@pytest.mark.parametrize("bad", [
    {"good": False, "flags": ("warmup",)},
    {"good": True, "flags": ("stale:arm0/j2",)},
    {"good": False, "flags": ()},
    {"estimate": lambda a: np.array([np.nan, a[1]])},
])
def test_a_not_good_estimate_falls_back_to_open_loop_at_the_next_command(bad):
    p = Plant(comp())
    for k in range(100):
        cmd, _ = p.step(k)
    assert cmd.closed and abs(cmd.correction_nm[0]) > 100
    cmd, _ = p.step(100, **bad)
    assert not cmd.closed
    assert cmd.torque_nm == cmd.desired_nm and cmd.correction_nm == (0.0, 0.0)
    assert cmd.flags and cmd.flags[0].startswith("estimate:not-good")
    assert p.comp.take_events()[-1].state == "open"


def test_stale_estimates_fall_back_to_open_loop_within_one_step_and_resume_when_good_again():
    s = JointLoopSettings(stale_s=0.005, resume_good=3)
    p = Plant(JointCompensator([("arm0", JOINTS)], [LIMIT], s))
    for k in range(100):
        p.step(k)
    # the gateway goes silent: the first command beyond stale_s after the last estimate is open
    out = [p.step(k, estimate=lambda a: False)[0] for k in range(100, 110)]
    closed = [c.closed for c in out]
    assert closed[:5] == [True] * 5 and closed[5:] == [False] * 5     # 105 ms - 99 ms > 5 ms
    assert out[5].flags == ("stale:efforts",) and out[5].torque_nm == out[5].desired_nm
    # estimates come back: closed again after resume_good of them, from a zero correction
    back = [p.step(k)[0] for k in range(110, 400)]
    assert [c.closed for c in back[:3]] == [False, False, True]
    assert abs(back[2].correction_nm[0]) <= 100.0 * 600 * 1e-3 + 1e-9
    np.testing.assert_allclose(p.log[-1][2], [200.0, -100.0], atol=1e-6)
    states = [e.state for e in p.comp.take_events()]
    assert states == ["closed", "open", "closed"]


def test_a_wrong_estimate_that_passes_as_good_moves_the_command_by_at_most_the_magnitude_limit():
    # an F/T sensor fault the gateway does not see: the estimate is 1000 N m too low on j1
    p = Plant(comp(max_correction=0.3))
    worst = 0.0
    for k in range(500):
        cmd, _ = p.step(k, estimate=lambda a: a - [1000.0, 0.0])
        worst = max(worst, abs(cmd.torque_nm[0] - cmd.desired_nm[0]))
        assert abs(cmd.torque_nm[0]) <= LIMIT[0]
    assert worst == pytest.approx(0.3 * 600)
    assert "limited:magnitude" in cmd.flags


def test_the_command_saturates_at_the_torque_limit_and_the_integral_does_not_wind_up():
    # the outer loop asks for the limit: the friction cannot be compensated, the drive saturates
    desired = lambda t: np.array([600.0 if t < 200 * MS else 100.0, 0.0])    # noqa: E731
    p = Plant(comp(), desired)
    for k in range(200):
        cmd, act = p.step(k)
        assert abs(cmd.torque_nm[0]) <= 600.0
    assert "saturated" in cmd.flags
    integral = p.comp.arms["arm0"].integral[0]
    assert integral <= 0.5 * 600 + 1e-9
    # once the outer loop asks for less, the actual torque settles on it (within 1e-3 N m) within 50 ms (no wound-up
    # integral to unwind); the step itself moves the correction at most at the rate limit
    out = [p.step(k) for k in range(200, 400)]
    corr = [c.correction_nm[0] for c, _ in out]
    assert np.all(np.abs(np.diff(corr)) <= 100.0 * 600 * 1e-3 + 1e-9)
    np.testing.assert_allclose([a[0] for _, a in out[50:]], 100.0, atol=1e-3)


def test_disabled_is_the_same_path_always_open():
    p = Plant(JointCompensator([("arm0", JOINTS)], [LIMIT], enabled=False))
    for k in range(50):
        cmd, _ = p.step(k)
        assert not cmd.closed and cmd.torque_nm == cmd.desired_nm and cmd.flags == ("disabled",)


def test_observed_torque_commands_are_assembled_per_arm_and_time():
    c = comp()
    assert c.observe(TorqueCommand("arm0/j1", 2 * MS, 1, 10.0)) is None
    assert c.observe(TorqueCommand("arm9/j1", 2 * MS, 1, 10.0)) is None          # not ours
    assert c.observe(TorqueCommand("arm0/j2", 2 * MS, 1, -5.0)) == "arm0"
    cmd = c.command("arm0")
    assert cmd.t_ns == 2 * MS and cmd.desired_nm == (10.0, -5.0) and not cmd.closed


def test_bad_input_gets_a_clear_error():
    c = comp()
    with pytest.raises(ControlError, match="no desired torque"):
        c.command("arm0")
    with pytest.raises(ControlError, match="no arm 'arm7'"):
        c.desired("arm7", 0, [0.0, 0.0])
    with pytest.raises(ControlError, match="2 desired torques"):
        c.desired("arm0", 0, [0.0])
    with pytest.raises(ControlError, match="kp must be"):
        JointLoopSettings(kp=-1.0)
    with pytest.raises(ControlError, match="resume_good"):
        JointLoopSettings(resume_good=0)
    with pytest.raises(ControlError, match="torque limit"):
        JointCompensator([("arm0", JOINTS)], [[600.0]])


def test_drive_command_payload_round_trips_and_bad_payloads_are_refused():
    cmd = DriveCommand("arm0", 5, JOINTS, (1.0, 2.5), (0.5, 2.0), (0.5, 0.5), True, ("limited:rate",))
    assert decode_drive_command(encode_drive_command(cmd)) == cmd
    assert drive_command("paper_robot", "arm0") == "bsc/paper_robot/commands/drives/arm0"
    for bad in (b"nope", b"[]", b'{"type":"DriveCommand","v":1}',
                encode_drive_command(cmd).replace(b'"torque_nm":[1.0,2.5]', b'"torque_nm":[1.0]'),
                encode_drive_command(cmd).replace(b'"closed":true', b'"closed":1')):
        with pytest.raises(ControlError):
            decode_drive_command(bad)
    with pytest.raises(ControlError):
        encode_drive_command(DriveCommand("arm0", 5, JOINTS, (float("nan"), 0.0), (0, 0), (0, 0), True))


def test_an_estimate_implying_friction_that_drives_the_joint_opens_the_loop_and_holds_it_open():
    # an F/T bias the gateway does not flag: the estimate of j1 is 400 N m too high while j1 turns
    # forward, so the friction it implies (applied - estimated actual) pushes the joint along
    s = JointLoopSettings(plausible_steps=10, plausible_hold_s=0.05)
    c = JointCompensator([("arm0", JOINTS)], [LIMIT], s)
    d = np.array([200.0, -100.0])

    def feed(k, bias, rate=(0.3, -0.2)):
        t = k * MS
        c.desired("arm0", t, d)
        act = d + (c.arms["arm0"].correction if c.arms["arm0"].closed else 0) - FRICTION * np.sign(rate)
        est = act + [bias, 0.0]
        c.estimate(JointEfforts("arm0", t, JOINTS, tuple(est), tuple(est), (), 0, rate, True))
        return c.command("arm0", t)

    for k in range(100):
        assert feed(k, 0.0).closed or k < 5                  # plausible: friction against the motion
    out = [feed(k, 400.0) for k in range(100, 120)]
    assert [o.closed for o in out[:9]] == [True] * 9 and not out[9].closed      # 10 in a row
    assert out[9].flags == ("estimate:implausible (arm0/j1)",) and out[9].torque_nm == tuple(d)
    # held open for plausible_hold_s even though the estimates are plausible again
    back = [feed(k, 0.0) for k in range(120, 200)]
    first_closed = next(i for i, o in enumerate(back) if o.closed)
    assert 120 + first_closed >= 109 + 50
    # a joint that does not move is not judged (stiction: any friction within +-static is possible)
    for k in range(200, 300):
        assert feed(k, 400.0, rate=(0.0, 0.0)).closed
