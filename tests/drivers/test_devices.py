"""The drivers: malformed frames rejected by reason, fault injection counted exactly, random
frames never raise, and the same drivers over python-can's virtual bus under a Notifier."""
from __future__ import annotations

import threading
import uuid

import can
import pytest
from hypothesis import given, settings, strategies as st

from drivers import devices, frames, wire
from drivers.samples import ImuSample, JointSample, ThrusterCommand, TorqueCommand, WrenchSample

H = bytes.fromhex
ARM = wire.BusSpec(name="arm0", kind="arm", arm="arm0", joints=("j1", "j2"), ids=wire.arm_ids(2))
SC = wire.BusSpec(name="spacecraft", kind="spacecraft", ids=wire.SPACECRAFT_IDS)


class Rig:
    """The listeners of one bus, fed directly (the pure tier)."""

    def __init__(self, spec, fd=False):
        self.samples = []
        self.monitor, self.drivers = devices.listeners_for(spec, self.samples.append, fd=fd)

    def feed(self, *msgs):
        for m in msgs:
            self.monitor.on_message_received(m)
            for d in self.drivers:
                d.on_message_received(m)

    def device(self, name):
        for d in self.drivers:
            for c in d.counters():
                if c.device == name:
                    return c
        raise KeyError(name)

    def all_rejections(self):
        out = dict(self.monitor.counters.rejected)
        for d in self.drivers:
            for c in d.counters():
                for k, v in c.rejected.items():
                    out[k] = out.get(k, 0) + v
        return out


def msg(i, data, t=1.0, **kw):
    return can.Message(arbitration_id=i, data=data, timestamp=t, is_extended_id=kw.pop("ext", False), check=False, **kw)


def wrench(c, fx=1.0):
    return frames.encode_wrench(WrenchSample("arm0", 0, c, (fx, 0.0, 0.0), (0.0, 0.0, 0.0)))


GOOD_A = H("05 00 0014 FFD8 003C")

MALFORMED = [
    ("error frame", msg(0, b"", is_error_frame=True), "error_frame"),
    ("29-bit id", msg(0x200, GOOD_A, ext=True), "extended_id"),
    ("unknown id", msg(0x123, b"\x00"), "unknown_id"),
    ("unused joint slot", msg(0x305, H("00 00 00000000 0000")), "unknown_id"),
    ("short F/T", msg(0x200, GOOD_A[:7]), "dlc"),
    ("long F/T B", msg(0x201, GOOD_A), "dlc"),
    ("empty joint", msg(0x300, b""), "dlc"),
    ("dlc disagrees with data", can.Message(arbitration_id=0x300, data=H("00 00 00000000 0000"), dlc=5,
                                            is_extended_id=False, check=False), "dlc"),
    ("remote F/T", msg(0x200, b"", is_remote_frame=True, dlc=8), "remote_frame"),
    ("FD joint on classic", msg(0x300, H("00 00 00000000 0000"), is_fd=True), "fd_on_classic"),
    ("FD 64-byte torque", msg(0x100, bytes(64), is_fd=True), "fd_on_classic"),
    ("short heartbeat", msg(0x701, b"\x00"), "dlc"),
    ("remote heartbeat", msg(0x701, b"", is_remote_frame=True), "remote_frame"),
]


@pytest.mark.parametrize("name,frame,reason", MALFORMED, ids=[m[0] for m in MALFORMED])
def test_malformed_frame_rejected_with_reason(name, frame, reason):
    rig = Rig(ARM)
    rig.feed(frame)
    assert rig.samples == []
    assert rig.all_rejections() == {reason: 1}
    assert rig.monitor.counters.frames == 1


def test_fd_frames_accepted_when_bus_is_fd():
    rig = Rig(ARM, fd=True)
    rig.feed(*frames.encode_wrench(WrenchSample("arm0", 0, 1, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0)), fd=True))
    assert len(rig.samples) == 1 and rig.all_rejections() == {}


def test_halves_in_any_order_and_t_ns_from_the_first_frame():
    rig = Rig(ARM)
    a, b = wrench(3)
    a.timestamp, b.timestamp = 2.0, 1.5
    rig.feed(b, a)
    assert len(rig.samples) == 1 and rig.samples[0].t_ns == 1_500_000_000   # the first frame's time


def test_dropped_frame_counts_incomplete_and_lost():
    rig = Rig(ARM)
    f = [wrench(c) for c in range(6)]
    rig.feed(*f[0], *f[1], f[2][0], *f[3], *f[4], *f[5])  # B of sample 2 dropped
    dev = rig.device("arm0")
    assert [s.counter for s in rig.samples] == [0, 1, 3, 4, 5]
    assert dev.rejected == {"incomplete": 1} and dev.lost == 1 and dev.samples == 5


def test_dropped_whole_samples_count_lost():
    rig = Rig(ARM)
    for c in (0, 1, 4, 5, 9):
        rig.feed(*wrench(c))
    dev = rig.device("arm0")
    assert dev.lost == 2 + 3 and dict(dev.rejected) == {}


def test_duplicated_frames_and_samples_counted():
    rig = Rig(ARM)
    a, b = wrench(0)
    rig.feed(a, a, b)           # frame repeated inside one sample
    rig.feed(*wrench(1), *wrench(1))  # whole sample repeated
    dev = rig.device("arm0")
    assert [s.counter for s in rig.samples] == [0, 1]
    assert dev.rejected == {"duplicate": 2} and dev.lost == 0


def test_reordered_samples_counted_late():
    rig = Rig(ARM)
    js = [frames.encode_joint(JointSample("arm0/j1", 0, c, 0.1 * c, 0.0), 0) for c in range(5)]
    rig.feed(js[0], js[1], js[3], js[2], js[4])
    dev = rig.device("arm0/j1")
    assert [s.counter for s in rig.samples] == [0, 1, 3, 4]
    assert dev.rejected == {"late": 1} and dev.lost == 1


def test_counter_wraps_without_loss():
    rig = Rig(ARM)
    for c in list(range(250, 256)) + list(range(0, 5)):
        rig.feed(frames.encode_joint(JointSample("arm0/j2", 0, c, 0.0, 0.0), 1))
    dev = rig.device("arm0/j2")
    assert dev.samples == 11 and dev.lost == 0 and not dev.rejected


def test_imu_partial_and_mismatched_samples_dropped():
    rig = Rig(SC)
    imu = [frames.encode_imu(ImuSample(0, c, (1.0, 0.0, 0.0, 0.0), (0.0,) * 3, (0.0,) * 3)) for c in range(3)]
    rig.feed(*imu[0][:5], *imu[1])        # sample 0 lacks its acceleration frame
    rig.feed(*imu[2][:3], imu[1][3], *imu[2][3:])  # a stray part of sample 1 inside sample 2
    dev = rig.device("imu")
    # sample 0 (no accel), sample 2's first half (interrupted by the stray part), the stray part;
    # sample 2's second half is still pending, not yet counted
    assert [s.counter for s in rig.samples] == [1]
    assert dev.rejected == {"incomplete": 3}


def test_thruster_and_torque_commands_decode():
    rig = Rig(SC)
    rig.feed(*frames.encode_thruster(ThrusterCommand(0, 4, (1.0, 2.0, 3.0), (0.5, 0.0, 0.0), valves=0x81)))
    assert rig.samples == [ThrusterCommand(1_000_000_000 * 0, 4, (1.0, 2.0, 3.0), (0.5, 0.0, 0.0), 0x81)]
    rig = Rig(ARM)
    rig.feed(*frames.encode_torque_commands([TorqueCommand("arm0/j1", 0, 2, 10.0),
                                             TorqueCommand("arm0/j2", 0, 2, -1e6)]))
    assert [(s.device, s.torque_nm, s.saturated) for s in rig.samples] == [
        ("arm0/j1", 10.0, False), ("arm0/j2", -32767 * 0.05, True)]


def test_health_faults_saturation_and_stale():
    rig = Rig(ARM)
    rig.feed(frames.encode_joint(JointSample("arm0/j1", 1_000_000_000, 0, 0.0, 100.0, status=0x01), 0))
    [h] = [h for d in rig.drivers for h in d.health(1_000_000_000) if h.device == "arm0/j1"]
    assert h.faults == 0x01 and h.saturated == 1 and h.samples == 1 and not h.stale
    [h] = [h for d in rig.drivers for h in d.health(1_100_000_000) if h.device == "arm0/j1"]
    assert h.stale        # 10 periods of 1 ms passed
    [h2] = [h for d in rig.drivers for h in d.health(0) if h.device == "arm0/j2"]
    assert h2.stale and h2.samples == 0


def test_heartbeats_and_measured_load():
    rig = Rig(ARM)
    rig.monitor.health(0)
    rig.feed(frames.encode_heartbeat(1, 0, 0x05), frames.encode_heartbeat(0x10, 0, 0x80))
    h = rig.monitor.health(1_000_000)       # 1 ms later: two 75-bit frames
    assert dict(h.nodes) == {"FT": 0x05, "DRIVE_J0": 0x80}
    assert h.load == pytest.approx(2 * 75e-6 / 1e-3)


frame_st = st.builds(
    lambda i, data, ext, err, rtr, fd, dlc: can.Message(arbitration_id=i, data=data, is_extended_id=ext,
                                                        is_error_frame=err, is_remote_frame=rtr, is_fd=fd,
                                                        dlc=dlc, check=False),
    st.one_of(st.sampled_from(sorted(wire.arm_ids(3) | wire.SPACECRAFT_IDS)), st.integers(0, 0x1FFFFFFF)),
    st.one_of(st.binary(max_size=64), st.none()), st.booleans(), st.booleans(), st.booleans(), st.booleans(),
    st.one_of(st.none(), st.integers(-5, 70)))


@settings(max_examples=400, deadline=None)
@given(st.lists(frame_st, max_size=30))
def test_random_frames_never_raise(msgs):
    for spec in (ARM, SC):
        rig = Rig(spec)
        rig.feed(*msgs)
        assert rig.monitor.counters.frames == len(msgs)


# --- integration: virtual bus under a Notifier --------------------------------------------------

@pytest.fixture
def buses():
    ch = f"bsc-test-{uuid.uuid4().hex}"
    tx = can.Bus(interface="virtual", channel=ch, receive_own_messages=False, ignore_config=True)
    rx = can.Bus(interface="virtual", channel=ch, receive_own_messages=False, ignore_config=True)
    with tx, rx:
        yield tx, rx


def test_drivers_under_notifier_over_virtual_bus(buses):
    tx, rx = buses
    got, done = [], threading.Event()

    def sink(s):
        got.append(s)
        if len(got) == 3 * 20:
            done.set()

    monitor, drivers = devices.listeners_for(ARM, sink)
    notifier = can.Notifier(rx, [monitor, *drivers], timeout=0.05)
    try:
        for c in range(20):
            for m in wrench(c):
                tx.send(m)
            tx.send(msg(0x7FF, b"junk"))
            tx.send(msg(0x200, b"\x01"))
            for j in range(2):
                tx.send(frames.encode_joint(JointSample(f"arm0/j{j + 1}", 0, c, 0.01 * c, 0.0), j))
        assert done.wait(5.0), f"only {len(got)} samples"
    finally:
        notifier.stop()
    assert sum(isinstance(s, WrenchSample) for s in got) == 20
    assert {s.device for s in got if isinstance(s, JointSample)} == {"arm0/j1", "arm0/j2"}
    assert monitor.counters.rejected == {"unknown_id": 20}
    assert drivers[0].dev.rejected["dlc"] == 20 and drivers[0].dev.rejected["incomplete"] == 0
    assert monitor.counters.frames == 20 * 6
    assert all(d.errors == 0 for d in drivers)
