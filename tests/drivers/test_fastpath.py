"""The drivers' fast paths give exactly what the reference code gives: compiled field decoders
against ``decode_fields``, ``frames.builder`` against the dataclass constructor, and one
``BusDispatcher`` per bus against the monitor and drivers each seeing every frame."""
from __future__ import annotations

import dataclasses
import random

import can
import pytest

from drivers import devices, frames, wire
from drivers.samples import (DeviceHealth, ImuSample, JointSample, ThrusterCommand, TorqueCommand, ValveCommand,
                             WrenchSample)


def _payloads(lay: wire.Layout, rnd: random.Random, n: int):
    edge = [0x00, 0x01, 0x7E, 0x7F, 0x80, 0x81, 0xFE, 0xFF]
    for k in range(n):
        if k % 3 == 0:
            yield bytes(rnd.choice(edge) for _ in range(lay.length))
        else:
            yield bytes(rnd.getrandbits(8) for _ in range(lay.length))


@pytest.mark.parametrize("kind", ["arm", "spacecraft"])
def test_compiled_decoders_equal_decode_fields(kind):
    rnd = random.Random(kind)
    for lay in wire.layouts(kind).values():
        fast = frames._compile_fields(lay)
        for data in _payloads(lay, rnd, 2000):
            ref = frames.decode_fields(lay, data)
            got = fast(data)
            assert got == ref, (lay.name, data.hex())
            assert type(got[1]) is type(ref[1]) is bool
            assert [type(x) for x in got[0]] == [type(x) for x in ref[0]], lay.name


def test_checked_decoders_refuse_wrong_lengths():
    for lay in (frames.JOINT_STATE, frames.IMU_QA, frames.VALVE_CMD):
        for n in (0, lay.length - 1, lay.length + 1):
            with pytest.raises(frames.DecodeError, match=f"{n} bytes, expected {lay.length}"):
                frames._checked(lay)(bytes(n))


def test_builder_builds_the_same_objects():
    cases = [(WrenchSample, ("arm0", 5, 7, (1.0, 2.0, 3.0), (0.5, -0.5, 0.0), True, 3)),
             (JointSample, ("arm0/j1", 1, 2, 0.25, -0.125, False, 0)),
             (ImuSample, (9, 1, (1.0, 0.0, 0.0, 0.0), (0.1, 0.2, 0.3), (1.0, 2.0, 3.0), False, 0x300)),
             (TorqueCommand, ("arm1/j2", 4, 3, -2.5, True)),
             (ThrusterCommand, (6, 8, (1.0, 0.0, 0.0), (0.0, 0.0, 0.5), 0x3F, False, 0xFF0)),
             (ValveCommand, (7, 9, 0x20009)),
             (DeviceHealth, ("imu", "spacecraft", 1, 2, 3, 4, (("dlc", 1),), 5, True, 6, 7, True))]
    for cls, values in cases:
        make = frames.builder(cls)
        assert make is not cls, cls.__name__
        a, b = make(*values), cls(*values)
        assert type(a) is cls and a == b and hash(a) == hash(b) and repr(a) == repr(b)
        with pytest.raises(dataclasses.FrozenInstanceError):
            a.t_ns = 0


def test_builder_falls_back_when_it_does_not_fit():
    @dataclasses.dataclass(frozen=True)
    class NoSlots:
        x: int

    @dataclasses.dataclass(frozen=True, slots=True)
    class Checked:
        x: int

        def __post_init__(self):
            if self.x < 0:
                raise ValueError("negative")

    assert frames.builder(NoSlots) is NoSlots
    assert frames.builder(Checked) is Checked
    assert frames.builder(int) is int


def _random_frames(spec: wire.BusSpec, n: int, seed: int):
    """Valid traffic of the bus, mutated: wrong ids, lengths, flags, counters, duplicates."""
    rnd = random.Random(seed)
    lays = wire.layouts(spec.kind)
    ids = sorted(spec.ids) + [0x7FF, 0x000, 0x123, wire.HEARTBEAT_BASE + 99]
    out = []
    for k in range(n):
        i = rnd.choice(ids)
        lay = lays.get(i)
        length = lay.length if lay is not None else rnd.randrange(9)
        data = bytearray(rnd.getrandbits(8) for _ in range(length))
        if data and rnd.random() < 0.8:
            data[0] = (k // 7) & 0xFF                 # counters that mostly advance
        u = rnd.random()
        kw = {"is_extended_id": False}
        if u < 0.03:
            data = data[:rnd.randrange(len(data) + 1)]
        elif u < 0.05:
            kw["is_remote_frame"] = True
        elif u < 0.07:
            kw["is_fd"] = True
        elif u < 0.09:
            kw["is_error_frame"] = True
        elif u < 0.11:
            kw["is_extended_id"] = True
        msg = can.Message(arbitration_id=i, data=bytes(data), timestamp=1.0 + k * 1e-4, check=False, **kw)
        if rnd.random() < 0.02:
            msg.dlc = rnd.randrange(16)
        out.append(msg)
        if rnd.random() < 0.02:
            out.append(msg)
    return out


@pytest.mark.parametrize("fd", [False, True])
@pytest.mark.parametrize("spec", [
    wire.BusSpec(name="arm0", kind="arm", arm="arm0", joints=("j1", "j2"), ids=wire.arm_ids(2)),
    wire.BusSpec(name="arm2", kind="arm", arm="arm2", joints=tuple(f"j{i}" for i in range(5)), ids=wire.arm_ids(5)),
    wire.BusSpec(name="spacecraft", kind="spacecraft", ids=wire.SPACECRAFT_IDS)], ids=lambda s: getattr(s, "name", s))
def test_dispatcher_equals_every_listener_seeing_every_frame(spec, fd):
    msgs = _random_frames(spec, 9000, seed=len(spec.ids) * 2 + fd)
    ref_out, fast_out = [], []
    ref_mon, ref_drv = devices.listeners_for(spec, ref_out.append, fd=fd)
    mon, drv = devices.listeners_for(spec, fast_out.append, fd=fd)
    dispatch = devices.BusDispatcher(mon, drv)
    assert dispatch.feed == dispatch._feed                   # the merged path, not the fallback
    for m in msgs:
        ref_mon.on_message_received(m)
        for d in ref_drv:
            d.on_message_received(m)
        dispatch.feed(m)
    assert fast_out == ref_out and len(ref_out) > 100
    assert mon.health(10**10) == ref_mon.health(10**10)
    assert [h for d in drv for h in d.health(10**10)] == [h for d in ref_drv for h in d.health(10**10)]
    assert mon.counters.busy_s == ref_mon.counters.busy_s


def test_dispatcher_falls_back_for_a_subclassed_listener():
    spec = wire.BusSpec(name="spacecraft", kind="spacecraft", ids=wire.SPACECRAFT_IDS)
    seen = []

    class Spy(devices.ValveCommandDriver):
        def on_message_received(self, msg):
            seen.append(msg.arbitration_id)
            super().on_message_received(msg)

    mon, drv = devices.listeners_for(spec, lambda s: None)
    drv[-1] = Spy(lambda s: None)
    dispatch = devices.BusDispatcher(mon, drv)
    assert dispatch.feed == dispatch._feed_each
    dispatch.feed(can.Message(arbitration_id=wire.VALVE_CMD_ID, data=bytes(5), is_extended_id=False))
    assert seen == [wire.VALVE_CMD_ID]
