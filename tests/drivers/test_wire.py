"""The DBC contract: completeness, agreement with the code's Structs, ids per robot, bus budget."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import cantools
import pytest
from hypothesis import given, settings, strategies as st

import robot_description
from drivers import frames, wire

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("kind", ["arm", "spacecraft"])
def test_every_message_has_sender_cycle_and_bus(kind):
    db = cantools.database.load_file(str(wire.DBC_FILES[kind]))
    assert db.dbc.attributes["BscBus"].value == kind
    assert db.dbc.attributes["Baudrate"].value == 1_000_000
    for m in db.messages:
        assert len(m.senders) == 1 and m.senders[0] in {n.name for n in db.nodes}, m.name
        assert m.cycle_time and m.cycle_time > 0, m.name
        assert not m.is_extended_frame and m.frame_id < 0x800
        assert m.comment, m.name


def test_paper_robot_ids_per_arm():
    wm = wire.WireMap.from_robot(robot_description.load("paper_robot"))
    assert list(wm.buses) == ["arm0", "arm1", "spacecraft"]
    arm = wm.buses["arm0"]
    assert {0x200, 0x201, 0x300, 0x301, 0x100} <= arm.ids
    assert 0x302 not in arm.ids and 0x101 not in arm.ids
    assert wm.bus_of("arm1/" + wm.buses["arm1"].joints[1]) == "arm1"
    assert wm.joint_index("arm1/" + wm.buses["arm1"].joints[1]) == 1
    assert wm.bus_of("imu") == "spacecraft"


def test_three_arm_ids():
    wm = wire.WireMap.from_robot(robot_description.load("three_arm"))
    assert len(wm.buses) == 4
    for name in [b for b in wm.buses if b != "spacecraft"]:
        assert {0x300, 0x301, 0x302, 0x100} <= wm.buses[name].ids and 0x303 not in wm.buses[name].ids


def test_too_many_joints_is_an_error():
    with pytest.raises(wire.WireError):
        wire.arm_ids(wire.MAX_JOINTS + 1)


def test_frame_bits_formula():
    # DEVICES.md: 8 bytes -> 135 bits worst case; 0 bytes -> 47 + 8 = 55
    assert wire.frame_bits(8) == 135
    assert wire.frame_bits(0) == 55
    assert wire.fd_frame_time_s(8) < wire.frame_bits(8) / 1e6


def test_budget_paper_robot_fits_three_arm_does_not():
    paper = wire.budget(wire.WireMap.from_robot(robot_description.load("paper_robot")))
    for rows in paper.values():
        assert sum(r.load for r in rows) <= wire.LOAD_LIMIT
    three = wire.budget(wire.WireMap.from_robot(robot_description.load("three_arm")))
    assert sum(r.load for r in three["left"]) > wire.LOAD_LIMIT
    three_fd = wire.budget(wire.WireMap.from_robot(robot_description.load("three_arm")), fd=True)
    assert all(sum(r.load for r in rows) <= wire.LOAD_LIMIT for rows in three_fd.values())


def _field_values(lay: wire.Layout):
    out = []
    for bits, signed, scale in zip(lay.bits, lay.signed, lay.scales):
        lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
        out.append(st.integers(lo, hi))
    return st.tuples(*out)


@pytest.mark.parametrize("kind", ["arm", "spacecraft"])
@settings(max_examples=30, deadline=None)
@given(data=st.data())
def test_structs_agree_with_cantools(kind, data):
    """Raw ints packed by the code's Struct decode in cantools to raw*factor, and back."""
    db = wire.database(kind)
    for fid, lay in wire.layouts(kind).items():
        raw = data.draw(_field_values(lay))
        payload = lay.pack_raw(raw)
        ref = db.decode_message(fid, payload, decode_choices=False, scaling=False)
        assert tuple(ref[s] for s in lay.signals) == raw
        assert lay.raw(payload) == raw
        values, _ = frames.decode_fields(lay, payload)
        scaled = db.decode_message(fid, payload, decode_choices=False)
        for s, v in zip(lay.signals, values):
            assert scaled[s] == pytest.approx(v, rel=1e-12, abs=1e-12)


def _bsc(*args):
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-m", "gateway.cli", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=120)


def test_budget_command_paper_robot():
    r = _bsc("budget")
    assert r.returncode == 0, r.stderr
    assert "arm0" in r.stdout and "OVER" not in r.stdout


def test_budget_command_three_arm_flags_and_offers_fd():
    r = _bsc("budget", "--robot", "three_arm")
    assert r.returncode == 0, r.stderr
    assert "OVER" in r.stdout and "--fd" in r.stdout
    r = _bsc("budget", "--robot", "three_arm", "--fd")
    assert "OVER" not in r.stdout
