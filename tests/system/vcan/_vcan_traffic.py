"""Deterministic traffic for the SocketCAN tier, and the sender process that puts it on the wire.

The same module serves both sides: the test builds the expected samples with :func:`sample_messages`,
the sender process (``python tests/system/vcan/_vcan_traffic.py CHANNELS``, a separate process as a real
device would be) sends them on real SocketCAN buses. It is driven line by line on stdin::

    samples <bus> <first> <count>   send samples with counters first..first+count-1 of <bus>
    resume <bus> <count>            send <count> samples as a device back from a silence does: its
                                    counter went on at its nominal period meanwhile, so the first
                                    one is the last delivered + the periods elapsed since (wall clock)
    faults <bus>                    send FAULT_FRAMES on <bus>
    quit

and answers each command with one line ``ok <sent> <failed>`` (``failed``: frames the kernel
refused, e.g. ENETDOWN while the interface is down); ``resume`` adds the first counter it used.
Sample values depend only on (bus, counter), so both sides agree without sharing state.
"""
from __future__ import annotations

import errno
import math
import random
import sys
import time

import can

from drivers import frames
from drivers.samples import ImuSample, JointSample, WrenchSample

# The paper robot (checked against robot_description by test_socketcan.py on every host).
JOINTS = {"arm0": ("j1", "j2"), "arm1": ("j1", "j2")}
SPACECRAFT = "spacecraft"


def _rng(bus: str, k: int) -> random.Random:
    return random.Random(f"bsc-vcan/{bus}/{k}")


def samples_for(bus: str, k: int) -> list:
    """The samples one device cycle ``k`` produces on ``bus`` (values well inside the ranges)."""
    r = _rng(bus, k)
    t_ns = 1_000_000 * (k + 1)
    if bus == SPACECRAFT:
        q = [r.uniform(-1, 1) for _ in range(4)]
        n = math.sqrt(sum(x * x for x in q)) or 1.0
        return [ImuSample(t_ns, k & 0xFF, tuple(x / n for x in q), tuple(r.uniform(-1.5, 1.5) for _ in range(3)),
                          tuple(r.uniform(-3.0, 3.0) for _ in range(3)))]
    out = [WrenchSample(bus, t_ns, k & 0xFF, tuple(r.uniform(-200, 200) for _ in range(3)),
                        tuple(r.uniform(-50, 50) for _ in range(3)))]
    for j in JOINTS[bus]:
        out.append(JointSample(f"{bus}/{j}", t_ns, k & 0xFF, r.uniform(-3.0, 3.0), r.uniform(-5.0, 5.0)))
    return out


def sample_messages(bus: str, k: int) -> list[can.Message]:
    """The frames of cycle ``k`` on ``bus``, in the order a device would send them."""
    msgs: list[can.Message] = []
    for s in samples_for(bus, k):
        if isinstance(s, WrenchSample):
            msgs += frames.encode_wrench(s)
        elif isinstance(s, JointSample):
            msgs.append(frames.encode_joint(s, JOINTS[bus].index(s.device.split("/", 1)[1])))
        else:
            msgs += frames.encode_imu(s)
    return msgs


def _m(i: int, data: bytes = b"", **kw) -> can.Message:
    return can.Message(arbitration_id=i, data=data, is_extended_id=kw.pop("ext", False), check=False, **kw)


# Frames a sick or hostile node puts on an arm bus, and what the drivers must count for each:
# (frame, where, reason) with where = "bus" (BusMonitor) or a device name (its DeviceCounters).
def fault_frames(arm: str) -> list[tuple[can.Message, str, str | None]]:
    good_a = frames.wrench_payloads(WrenchSample(arm, 0, 7, (1.0, 2.0, 3.0), (0.1, 0.2, 0.3)))[0][1]
    return [
        (_m(0x004, bytes(8), is_error_frame=True), "bus", "error_frame"),
        (_m(0x200, dlc=8, is_remote_frame=True), arm, "remote_frame"),
        (_m(0x200, good_a, ext=True), "bus", "extended_id"),
        (_m(0x123, b"\x01"), "bus", "unknown_id"),
        (_m(0x300, bytes(8), is_fd=True), f"{arm}/j1", "fd_on_classic"),
        (_m(0x100, bytes(64), is_fd=True, bitrate_switch=True), f"{arm}/torque_cmd", "fd_on_classic"),
        (_m(0x200, good_a[:7]), arm, "dlc"),
        (_m(0x702, dlc=2, is_remote_frame=True), "bus", "remote_frame"),
        (frames.encode_heartbeat(0x01, 3), "bus", None),          # a good heartbeat: node state read
    ]


def _send_all(bus: can.BusABC, msgs: list[can.Message]) -> tuple[int, int]:
    sent = failed = 0
    for m in msgs:
        for attempt in range(200):
            try:
                bus.send(m, timeout=1.0)
                sent += 1
                break
            except can.CanOperationError as exc:
                if exc.error_code == errno.ENOBUFS and attempt < 199:
                    time.sleep(0.001)   # the kernel's queue is full: the receiver is behind
                    continue
                failed += 1
                break
    return sent, failed


def period_s(bus: str) -> float:
    """Nominal period of the samples of ``bus`` (its first frame's cycle time in the DBC)."""
    from drivers import wire

    first = sample_messages(bus, 0)[0].arbitration_id
    return wire.layouts("spacecraft" if bus == SPACECRAFT else "arm")[first].cycle_ms / 1000.0


def serve(channels: dict[str, str]) -> int:
    buses = {name: can.Bus(interface="socketcan", channel=ch, fd=True, ignore_config=True)
             for name, ch in channels.items()}
    delivered: dict[str, tuple[int, float]] = {}      # bus -> (counter, wall time) of its last sample sent

    def send_samples(bus: str, counters) -> tuple[int, int]:
        sent = failed = 0
        for k in counters:                  # one sample at a time: a frame leaves as soon as it is built
            s, f = _send_all(buses[bus], sample_messages(bus, k))
            sent, failed = sent + s, failed + f
            if f == 0:
                delivered[bus] = (k, time.time())
        return sent, failed

    try:
        for line in sys.stdin:
            cmd = line.split()
            if not cmd:
                continue
            if cmd[0] == "quit":
                break
            if cmd[0] == "samples":
                bus, first, count = cmd[1], int(cmd[2]), int(cmd[3])
                print("ok %d %d" % send_samples(bus, range(first, first + count)), flush=True)
            elif cmd[0] == "resume":
                bus, count = cmd[1], int(cmd[2])
                last, at = delivered[bus]
                first = last + max(1, round((time.time() - at) / period_s(bus)))
                print("ok %d %d %d" % (*send_samples(bus, range(first, first + count)), first), flush=True)
            elif cmd[0] == "faults":
                print("ok %d %d" % _send_all(buses[cmd[1]], [f for f, _, _ in fault_frames(cmd[1])]), flush=True)
            else:
                print(f"error unknown command {cmd[0]!r}", flush=True)
    finally:
        for b in buses.values():
            b.shutdown()
    return 0


if __name__ == "__main__":
    # argv: bus=channel pairs, e.g. arm0=vcan0 arm1=vcan1 spacecraft=vcan2
    sys.exit(serve(dict(a.split("=", 1) for a in sys.argv[1:])))
