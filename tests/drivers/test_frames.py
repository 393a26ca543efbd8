"""Pure protocol tests: golden byte vectors (written by hand from docs/wire.md, not by the
encoder), encode -> decode round trips within quantization, random payloads never raise."""
from __future__ import annotations

import math

import pytest
from hypothesis import given, settings, strategies as st

from drivers import frames, wire
from drivers.samples import ImuSample, JointSample, ThrusterCommand, TorqueCommand, ValveCommand, WrenchSample

H = bytes.fromhex

# --- golden vectors ----------------------------------------------------------------------------
# FT: 20 counts per N and per N m. Fx 1 N = 20 = 0x0014, Fy -2 N = -40 = 0xFFD8, Fz 3 N = 0x003C;
# Tx 0.1 = 2, Ty 0.25 = 5, Tz -1.5 = -30 = 0xFFE2.
FT_A = H("05 00 0014 FFD8 003C")
FT_B = H("05 0002 0005 FFE2")
# joint: angle 1.5 rad = 1_500_000 = 0x0016E360; rate -0.5 rad/s / 2.5e-4 = -2000 = 0xF830
JOINT = H("07 00 0016E360 F830")
# torque command G0: 100 N m = 2000 = 0x07D0, -50 N m = -1000 = 0xFC18, slot 2 unused
TORQUE = H("01 07D0 FC18 0000")
# IMU, counter 3: time 1 s = 1_000_000 us = 0x000F4240; quaternion w 1.0 = 2^22 = 0x400000,
# x -0.5 = -2^21 = 0xE00000, y 0.25 = 0x100000, z 0; rate 0.5 rad/s = 0.5 * 2^14 = 0x2000,
# -0.25 = 0xF000; accel 1 m/s^2 = 2^13 = 0x2000, -2 = 0xC000, 0.5 = 0x1000
IMU = {0x405: H("03 000F4240"), 0x411: H("03 00000000"), 0x421: H("03 400000 E00000"),
       0x422: H("03 100000 000000"), 0x432: H("03 2000 F000 0000"), 0x434: H("03 2000 C000 1000")}
# thruster, counter 9: Fx 10 N = 200 = 0x00C8, Fz -1 N = -20 = 0xFFEC; My 2 N m = 40 = 0x0028; valves 0b1011
THR = {0x180: H("09 00C8 0000 FFEC"), 0x181: H("09 0000 0028 0000"), 0x182: H("09 0000000B")}


def test_golden_wrench_decode():
    s = frames.decode_wrench(FT_A, FT_B, "arm0", 42)
    assert s == WrenchSample("arm0", 42, 5, (1.0, -2.0, 3.0), (0.1, 0.25, -1.5), False, 0)


def test_golden_wrench_encode():
    s = WrenchSample("arm0", 0, 5, (1.0, -2.0, 3.0), (0.1, 0.25, -1.5))
    assert frames.wrench_payloads(s) == [(0x200, FT_A), (0x201, FT_B)]


def test_golden_wrench_saturates_never_wraps():
    s = WrenchSample("arm0", 0, 5, (5000.0, -2.0, 3.0), (0.1, 0.25, -1e9))
    (ia, a), (ib, b) = frames.wrench_payloads(s)
    assert a == H("05 01 7FFF FFD8 003C")       # status bit0 = overload
    assert b == H("05 0002 0005 8001")
    d = frames.decode_wrench(a, b, "arm0", 0)
    assert d.saturated and d.force_n[0] == 32767 * 0.05 and d.torque_nm[2] == -32767 * 0.05


def test_golden_joint():
    assert frames.joint_payload(JointSample("arm0/j1", 0, 7, 1.5, -0.5), 0) == (0x300, JOINT)
    assert frames.joint_payload(JointSample("arm0/j2", 0, 7, 1.5, -0.5), 1)[0] == 0x301
    assert frames.decode_joint(JOINT, "arm0/j1", 9) == JointSample("arm0/j1", 9, 7, 1.5, -0.5)


def test_golden_torque_commands():
    cmds = [TorqueCommand("a/j1", 0, 1, 100.0), TorqueCommand("a/j2", 0, 1, -50.0)]
    assert frames.torque_payloads(cmds) == [(0x100, TORQUE)]
    out = frames.decode_torque_commands(TORQUE, ["a/j1", "a/j2", None], 5)
    assert out == [TorqueCommand("a/j1", 5, 1, 100.0), TorqueCommand("a/j2", 5, 1, -50.0)]


def test_golden_torque_commands_four_joints_use_two_frames():
    cmds = [TorqueCommand(f"a/j{i}", 0, 2, 0.05 * i) for i in range(4)]
    assert frames.torque_payloads(cmds) == [(0x100, H("02 0000 0001 0002")), (0x101, H("02 0003 0000 0000"))]


def test_golden_imu():
    s = frames.decode_imu(IMU, 11)
    assert s == ImuSample(11, 3, (1.0, -0.5, 0.25, 0.0), (0.5, -0.25, 0.0), (1.0, -2.0, 0.5), False, 0)
    enc = frames.imu_payloads(ImuSample(10**9, 3, (1.0, -0.5, 0.25, 0.0), (0.5, -0.25, 0.0), (1.0, -2.0, 0.5)))
    assert dict(enc) == IMU


def test_golden_thruster():
    s = frames.decode_thruster(THR, 3)
    assert s == ThrusterCommand(3, 9, (10.0, 0.0, -1.0), (0.0, 2.0, 0.0), valves=0b1011)
    assert dict(frames.thruster_payloads(s)) == THR


def test_golden_thruster_with_the_keep_out_mask():
    """0x184 THRUSTER_CMD_ALLOWED: thrusters 0-7 and 31 may fire = 0x800000FF; sent first."""
    parts = {**THR, 0x184: H("09 800000FF")}
    s = frames.decode_thruster(parts, 3)
    assert s == ThrusterCommand(3, 9, (10.0, 0.0, -1.0), (0.0, 2.0, 0.0), valves=0b1011, allowed=0x800000FF)
    assert frames.thruster_payloads(s) == [(0x184, parts[0x184])] + list(THR.items())
    with pytest.raises(frames.DecodeError, match="disagree on the counter"):
        frames.decode_thruster({**THR, 0x184: H("0A 800000FF")}, 3)

# valve commands, counter 0x2A: thrusters 0, 3 and 17 open = bits 0b10_0000_0000_0000_1001 = 0x00020009
VALVES = H("2A 00020009")


def test_golden_valves():
    assert frames.decode_valves(VALVES, 5) == ValveCommand(5, 0x2A, 0x20009)
    assert frames.valves_payload(ValveCommand(5, 0x12A, (1 << 0) | (1 << 3) | (1 << 17))) == (0x183, VALVES)
    with pytest.raises(frames.EncodeError):
        frames.valves_payload(ValveCommand(0, 0, 1 << 32))


def test_golden_heartbeat():
    assert frames.heartbeat_payload(1, 0) == (0x701, H("00 05"))


def test_mismatched_halves_raise_decode_error():
    with pytest.raises(frames.DecodeError):
        frames.decode_wrench(FT_A, H("06 0002 0005 FFE2"), "arm0", 0)


def test_nan_is_refused():
    with pytest.raises(frames.EncodeError):
        frames.wrench_payloads(WrenchSample("a", 0, 0, (math.nan, 0.0, 0.0), (0.0, 0.0, 0.0)))


# --- round trips -------------------------------------------------------------------------------
F = st.floats(-1600, 1600, allow_nan=False)
ctr = st.integers(0, 255)


@settings(max_examples=200, deadline=None)
@given(ctr, st.tuples(F, F, F), st.tuples(F, F, F), st.integers(0, 0xFE))
def test_wrench_round_trip(c, f, t, status):
    status &= ~wire.FT_SAT
    s = WrenchSample("arm0", 0, c, f, t, status=status)
    (_, a), (_, b) = frames.wrench_payloads(s)
    d = frames.decode_wrench(a, b, "arm0", 0)
    assert d.counter == c and d.status & ~wire.FT_SAT == status
    for x, y in zip(f + t, d.force_n + d.torque_nm):
        assert abs(x - y) <= 0.025 + 1e-9
    assert d.saturated == (d.status & wire.FT_SAT != 0)


@settings(max_examples=200, deadline=None)
@given(ctr, st.floats(-2000, 2000), st.floats(-8, 8), st.integers(0, 7))
def test_joint_round_trip(c, angle, rate, j):
    i, p = frames.joint_payload(JointSample("a/j", 0, c, angle, rate), j)
    assert i == 0x300 + j
    d = frames.decode_joint(p, "a/j", 0)
    assert abs(d.angle_rad - angle) <= 0.5e-6 + 1e-12
    assert abs(d.rate_rad_s - rate) <= 1.25e-4 + 1e-12 or d.saturated


unit = st.floats(-1, 1)


@settings(max_examples=200, deadline=None)
@given(ctr, st.tuples(unit, unit, unit, unit), st.tuples(*[st.floats(-1.9, 1.9)] * 3),
       st.tuples(*[st.floats(-3.9, 3.9)] * 3))
def test_imu_round_trip(c, q, w, a):
    s = ImuSample(123_000, c, q, w, a)
    d = frames.decode_imu(dict(frames.imu_payloads(s)), 1)
    assert d.counter == c and not d.saturated
    assert all(abs(x - y) <= 2 ** -23 + 1e-15 for x, y in zip(q, d.quat_wxyz))
    assert all(abs(x - y) <= 2 ** -15 + 1e-15 for x, y in zip(w, d.rate_rad_s))
    assert all(abs(x - y) <= 2 ** -14 + 1e-15 for x, y in zip(a, d.accel_m_s2))


@settings(max_examples=100, deadline=None)
@given(ctr, st.tuples(F, F, F), st.tuples(F, F, F), st.integers(0, 2**32 - 1))
def test_thruster_round_trip(c, f, m, valves):
    d = frames.decode_thruster(dict(frames.thruster_payloads(ThrusterCommand(0, c, f, m, valves))), 0)
    assert d.valves == valves and d.counter == c
    assert all(abs(x - y) <= 0.025 + 1e-9 for x, y in zip(f + m, d.force_n + d.moment_nm))


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-1e6, 1e6), min_size=1, max_size=8), ctr)
def test_torque_round_trip_clamps(taus, c):
    cmds = [TorqueCommand(f"a/j{i}", 0, c, t) for i, t in enumerate(taus)]
    out = []
    for g, (i, p) in enumerate(frames.torque_payloads(cmds)):
        assert i == 0x100 + g
        out += frames.decode_torque_commands(p, [x.device for x in cmds[3 * g:3 * g + 3]] + [None] * 3, 0)
    for cmd, d in zip(cmds, out):
        lim = 32767 * 0.05
        if abs(cmd.torque_nm) >= lim:
            assert d.saturated and abs(d.torque_nm) == pytest.approx(lim)
        else:
            assert abs(d.torque_nm - cmd.torque_nm) <= 0.025 + 1e-9


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(sorted(set(wire.layouts("arm").values()) | set(wire.layouts("spacecraft").values()),
                              key=lambda l: (l.name, l.frame_id))),
       st.binary(min_size=0, max_size=64))
def test_random_payloads_never_raise_anything_but_decode_error(lay, data):
    try:
        values, sat = frames.decode_fields(lay, data)
    except frames.DecodeError:
        assert len(data) != lay.length
    else:
        assert len(values) == len(lay.signals) and all(math.isfinite(v) for v in values)
