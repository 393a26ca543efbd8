"""The drivers over real SocketCAN (vcan), fed by a separate sender process.

Runs inside the VM tier (``.ci/vcan-tier.sh``: a stock kernel with vcan0..vcan2 up); skipped with
a reason elsewhere. The paper robot's buses map to ``arm0 -> vcan0, arm1 -> vcan1,
spacecraft -> vcan2``. Each check waits for a condition (every expected sample or error seen),
never for a fixed time; the bounded waits only turn a hang into a failure.
"""
from __future__ import annotations

import dataclasses
import errno
import os
import selectors
import socket
import subprocess
import sys
import threading
from pathlib import Path

import can
import pytest

import _vcan_traffic as traffic
from drivers import devices, wire
from drivers.samples import ImuSample, JointSample, WrenchSample

HERE = Path(__file__).parent
CHANNELS = {"arm0": "vcan0", "arm1": "vcan1", "spacecraft": "vcan2"}
HAVE_VCANS = all(Path(f"/sys/class/net/{ch}").exists() for ch in CHANNELS.values())
needs_vcan = pytest.mark.skipif(not HAVE_VCANS,
                                reason="needs SocketCAN vcan0..vcan2: run .ci/vcan-tier.sh (a VM with vcan)")
N = 300            # samples per device in the main check: a few hundred, seconds in the VM
WAIT_S = 120.0     # a hang becomes a failure after this (Python is ~14x slower in the VM)
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)


def paper_wire_map() -> wire.WireMap:
    """The paper robot's wire map without Pinocchio (kept equal to the description below)."""
    arms = [type("Arm", (), {"name": a, "joint_names": j}) for a, j in traffic.JOINTS.items()]
    return wire.WireMap.from_robot(type("Robot", (), {"name": "paper_robot", "arms": arms}))


def test_stand_in_is_the_paper_robot():
    """Not a vcan test: keeps the hard-coded robot of this tier equal to the real description."""
    import robot_description

    assert wire.WireMap.from_robot(robot_description.load("paper_robot")) == paper_wire_map()


class Watch(can.Listener):
    """Last listener of a notifier: wakes the test after every frame (the drivers have already
    seen it) and counts the errors the notifier reported."""

    def __init__(self, cond: threading.Condition):
        self.cond, self.frames, self.errors = cond, 0, []

    def on_message_received(self, msg):
        with self.cond:
            self.frames += 1
            self.cond.notify_all()

    def on_error(self, exc):
        with self.cond:
            self.errors.append(exc)
            self.cond.notify_all()


class Gateway:
    """Receiving side: one socketcan bus per robot bus, the drivers under a Notifier each."""

    def __init__(self, wm: wire.WireMap):
        self.cond = threading.Condition()
        self.samples: dict[str, list] = {name: [] for name in wm.buses}
        self.buses: dict[str, can.BusABC] = {}
        self.notifiers: list[can.Notifier] = []
        self.monitors, self.drivers, self.watch = {}, {}, {}
        try:
            for name, spec in wm.buses.items():
                # FD-capable socket, classic drivers: FD frames reach the drivers and are rejected
                bus = self.buses[name] = can.Bus(interface="socketcan", channel=CHANNELS[name], fd=True,
                                                 ignore_config=True)
                try:   # room for a whole burst while the notifier thread is slower than the sender
                    bus.socket.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, 8 << 20)
                except OSError:
                    bus.socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
                self.monitors[name], self.drivers[name] = devices.listeners_for(spec, self._sink(name))
                self.watch[name] = Watch(self.cond)
                self.notifiers.append(can.Notifier(bus, [self.monitors[name], *self.drivers[name], self.watch[name]],
                                                   timeout=0.1))
        except BaseException:
            self.close()
            raise

    def _sink(self, name):
        def sink(sample):
            self.samples[name].append(sample)   # under the notifier; Watch notifies after the frame
        return sink

    def wait(self, pred, what: str) -> None:
        with self.cond:
            if not self.cond.wait_for(pred, timeout=WAIT_S):
                pytest.fail(f"timed out waiting for {what}")

    def device(self, name: str):
        for ds in self.drivers.values():
            for d in ds:
                for c in d.counters():
                    if c.device == name:
                        return c
        raise KeyError(name)

    def close(self):
        for n in self.notifiers:
            n.stop()
        for b in self.buses.values():
            b.shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class Sender:
    """The separate sender process (tests/system/vcan/_vcan_traffic.py)."""

    def __init__(self):
        args = [f"{b}={c}" for b, c in CHANNELS.items()]
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(HERE), *filter(None, [os.environ.get("PYTHONPATH")])]))
        self.proc = subprocess.Popen([sys.executable, str(HERE / "_vcan_traffic.py"), *args], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, bufsize=1, env=env)
        self.sel = selectors.DefaultSelector()
        self.sel.register(self.proc.stdout, selectors.EVENT_READ)

    def ask(self, line: str) -> tuple[int, ...]:
        """``(sent, failed)`` frames (``resume``: and the first counter)."""
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        if not self.sel.select(timeout=WAIT_S):
            pytest.fail(f"sender did not answer {line!r}")
        reply = self.proc.stdout.readline().split()
        assert reply[:1] == ["ok"], f"sender: {reply!r} (exit {self.proc.poll()})"
        return tuple(int(x) for x in reply[1:])

    def close(self):
        try:
            if self.proc.poll() is None:
                self.proc.stdin.write("quit\n")
                self.proc.stdin.close()
                self.proc.wait(timeout=WAIT_S)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()
            self.proc.stdout.close()
            self.sel.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _ip_link(channel: str, state: str) -> None:
    subprocess.run(["ip", "link", "set", channel, state], check=True)


def _no_t(sample):
    return dataclasses.replace(sample, t_ns=0)


def _expected(wm: wire.WireMap, name: str, counters: range) -> list:
    """What the same drivers decode from the same frames fed directly (no socket)."""
    out: list = []
    mon, drv = devices.listeners_for(wm.buses[name], out.append)
    for k in counters:
        for m in traffic.sample_messages(name, k):
            mon.on_message_received(m)
            for d in drv:
                d.on_message_received(m)
    return [_no_t(s) for s in out]


def _close_to_sent(got, sent) -> bool:
    """Independent of the drivers: decoded values within half a count of what was encoded."""
    def near(a, b, step):
        return all(abs(x - y) <= step / 2 + 1e-12 for x, y in zip(a, b))
    if isinstance(sent, WrenchSample):
        return near(got.force_n, sent.force_n, 0.05) and near(got.torque_nm, sent.torque_nm, 0.05)
    if isinstance(sent, JointSample):
        return near([got.angle_rad], [sent.angle_rad], 1e-6) and near([got.rate_rad_s], [sent.rate_rad_s], 2.5e-4)
    assert isinstance(sent, ImuSample)
    return (near(got.quat_wxyz, sent.quat_wxyz, 2.0 ** -22) and near(got.rate_rad_s, sent.rate_rad_s, 2.0 ** -14)
            and near(got.accel_m_s2, sent.accel_m_s2, 2.0 ** -13))


@pytest.mark.vcan
@needs_vcan
def test_every_sample_decoded_exactly_over_socketcan():
    wm = paper_wire_map()
    per_cycle = {name: len(traffic.samples_for(name, 0)) for name in wm.buses}
    with Gateway(wm) as gw, Sender() as tx:
        for name in wm.buses:
            assert tx.ask(f"samples {name} 0 {N}") == (N * len(traffic.sample_messages(name, 0)), 0)
        gw.wait(lambda: all(len(gw.samples[n]) >= N * per_cycle[n] for n in wm.buses), "every sample")
        for name in wm.buses:
            got = gw.samples[name]
            assert [_no_t(s) for s in got] == _expected(wm, name, range(N))
            sent = [s for k in range(N) for s in traffic.samples_for(name, k)]
            fed_devices = {getattr(s, "device", "imu") for s in sent}
            assert all(_close_to_sent(g, s) for g, s in zip(got, sent))
            assert all(s.t_ns > 0 for s in got)          # kernel receive timestamps, not the sender's
            bus = gw.monitors[name].counters
            assert bus.frames == N * len(traffic.sample_messages(name, 0))
            assert dict(bus.rejected) == {}
            for d in gw.drivers[name]:
                for c in d.counters():
                    fed = N if c.device in fed_devices else 0       # no command traffic in this test
                    assert (c.device, c.samples, c.lost, dict(c.rejected)) == (c.device, fed, 0, {})
                assert d.errors == 0
            assert gw.watch[name].errors == []


@pytest.mark.vcan
@needs_vcan
def test_error_remote_fd_and_foreign_frames_counted_by_reason():
    wm = paper_wire_map()
    faults = traffic.fault_frames("arm0")
    with Gateway(wm) as gw, Sender() as tx:
        assert tx.ask("faults arm0") == (len(faults), 0)
        assert tx.ask("samples arm0 0 3") == (3 * 4, 0)          # and the bus still works afterwards
        gw.wait(lambda: gw.watch["arm0"].frames >= len(faults) + 12, "the fault frames")
        want: dict[tuple[str, str], int] = {}
        for _, where, reason in faults:
            if reason:
                want[(where, reason)] = want.get((where, reason), 0) + 1
        got = {("bus", r): n for r, n in gw.monitors["arm0"].counters.rejected.items()}
        for d in gw.drivers["arm0"]:
            for c in d.counters():
                got.update({(c.device, r): n for r, n in c.rejected.items()})
        assert got == want
        assert gw.monitors["arm0"].counters.nodes == {wire.layouts("arm")[0x701].sender: 0x05}
        assert [type(s).__name__ for s in gw.samples["arm0"]] == ["WrenchSample", "JointSample", "JointSample"] * 3
        assert gw.watch["arm0"].errors == [] and all(d.errors == 0 for d in gw.drivers["arm0"])


@pytest.mark.vcan
@needs_vcan
def test_bus_down_and_up_is_counted_and_survived():
    """``ip link set vcan1 down``: the receiving socket reports ENETDOWN once (python-can raises
    CanOperationError in recv; the Notifier hands it to every listener's on_error and keeps
    reading), the sender's frames are refused meanwhile, and after ``up`` samples flow again:
    the gap shows as ``lost`` in the health, nothing is rejected, no thread died.

    The devices behave as real ones: their counters go on at the nominal period while the bus
    is down (the outage lasts from tens of ms to seconds, under TCG), so what was lost is the
    counter step, taken exactly from counter and time together (drivers/health.py: beyond 100
    periods away the 8-bit counter alone is ambiguous)."""
    wm = paper_wire_map()
    before, tried, after = 100, 20, 100
    with Gateway(wm) as gw, Sender() as tx:
        assert tx.ask(f"samples arm1 0 {before}") == (4 * before, 0)
        gw.wait(lambda: len(gw.samples["arm1"]) >= 3 * before, "samples before the bus goes down")
        _ip_link("vcan1", "down")
        try:
            gw.wait(lambda: len(gw.watch["arm1"].errors) >= 1, "the notifier to report the bus down")
            assert tx.ask(f"samples arm1 {before} {tried}") == (0, 4 * tried)
        finally:
            _ip_link("vcan1", "up")
        sent, failed, first = tx.ask(f"resume arm1 {after}")
        assert (sent, failed) == (4 * after, 0)
        gap = first - before                      # counters before..first-1 never arrived
        gw.wait(lambda: len(gw.samples["arm1"]) >= 3 * (before + after), "samples after the bus came back")

        errors = gw.watch["arm1"].errors
        assert len(errors) == 1 and isinstance(errors[0], can.CanOperationError)
        assert errors[0].error_code == errno.ENETDOWN
        assert [d.errors for d in gw.drivers["arm1"]] == [1, 1, 1]
        for dev in ("arm1", "arm1/j1", "arm1/j2"):
            c = gw.device(dev)
            assert (dev, c.samples, c.lost, dict(c.rejected)) == (dev, before + after, gap, {})
        # each device's health at its own last sample (receive time): the frames of one step arrive
        # up to tens of ms apart in a slow VM, longer than the 10 ms a 1 kHz device may be quiet
        last = {s.device: s.t_ns for s in gw.samples["arm1"]}
        assert set(last) == {"arm1", "arm1/j1", "arm1/j2"}
        checked = [c.snapshot(last[c.device]) for d in gw.drivers["arm1"] for c in d.counters() if c.device in last]
        assert [(h.device, h.lost, h.last_t_ns, h.stale) for h in checked] == \
            [(h.device, gap, last[h.device], False) for h in checked] and len(checked) == 3
        # the other buses saw nothing and lost nothing
        assert gw.watch["arm0"].errors == [] and gw.watch["spacecraft"].errors == []
        readers = [t for n in gw.notifiers for t in n._readers]
        assert len(readers) == 3 and all(t.is_alive() for t in readers)   # no reader thread died
