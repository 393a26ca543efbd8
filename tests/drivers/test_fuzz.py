"""Fuzz tier of the drivers: a short fixed-seed campaign of benchmarks/fuzz_drivers.py.

Random and mutated frames through every listener of every bus of a wire map: no exception may
leave a driver, every decoded sample must hold its invariants, and the campaign must actually
reach every rejection path (otherwise it proves little). The long run is on demand:
``python -m benchmarks.fuzz_drivers --frames 1000000``.
"""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = str(Path(__file__).resolve().parents[2])
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)       # benchmarks/ is not an installed package
from benchmarks import fuzz_drivers  # noqa: E402
from drivers import frames, health, wire  # noqa: E402

FRAMES = 20_000
SEED = 20261122


class _Arm:
    def __init__(self, name, n):
        self.name, self.joint_names = name, tuple(f"j{i}" for i in range(n))


class _Robot:
    """Widest and narrowest arms the wire contract allows (8 joints = 3 command frames; 1 joint)."""
    name = "edge_robot"
    arms = (_Arm("wide", wire.MAX_JOINTS), _Arm("narrow", 1))


def _map(robot: str) -> wire.WireMap:
    return wire.WireMap.from_robot(_Robot()) if robot == "edge_robot" else fuzz_drivers.wire_map_for(robot)


@pytest.mark.parametrize("robot,fd", [("paper_robot", False), ("three_arm", True), ("edge_robot", False)])
def test_no_frame_raises_out_of_a_driver(robot, fd):
    rep = fuzz_drivers.fuzz(_map(robot), FRAMES, seed=SEED, fd=fd)
    assert dict(rep.exceptions) == {}, rep.first_failure
    assert rep.bad_samples == 0
    assert rep.frames == FRAMES and rep.samples > FRAMES // 10       # the decoders got real work
    assert set(rep.mutations) == set(fuzz_drivers.MUTATIONS)
    reasons = {k.split("/", 1)[1] for k in rep.rejected}
    expected = set(health.REASONS) - ({"fd_on_classic"} if fd else set())
    assert expected <= reasons, f"never reached: {sorted(expected - reasons)}"


def test_the_campaign_is_reproducible():
    wm = _map("paper_robot")
    a, b = (fuzz_drivers.fuzz(wm, 3000, seed=7) for _ in range(2))
    assert (a.samples, a.rejected, a.mutations, a.lost) == (b.samples, b.rejected, b.mutations, b.lost)


def test_the_campaign_catches_a_driver_that_raises(monkeypatch):
    """The harness itself can fail: a decoder that raises on some payloads is reported."""
    real = frames.decode_joint

    def fragile(data, device, t_ns):
        if data[2] & 0x80:
            raise ZeroDivisionError("planted")
        return real(data, device, t_ns)

    monkeypatch.setattr(frames, "decode_joint", fragile)
    rep = fuzz_drivers.fuzz(_map("paper_robot"), 5000, seed=SEED)
    assert rep.exceptions and all(k.endswith("ZeroDivisionError") for k in rep.exceptions)
    assert "JointDriver" in rep.first_failure and "planted" in rep.first_failure
