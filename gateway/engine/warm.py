"""Compile (or load from numba's on-disk cache) every kernel the session engine runs.

The first use of a compiled kernel in a fresh installation costs its compilation (about a
minute for the estimator on a loaded two-core machine; from the cache, well under a second).
``python -m gateway.engine.warm`` does it once, ahead of time: after an install, or before a
run whose first epochs must not wait (the SocketCAN tier compiles this way on the host, for the
VM's CPU, because compiling under emulation would take a quarter of an hour).

It runs synthetic frames of the paper robot through a :class:`Session` and through the live
gateway's own receive paths (SocketCAN and ``udp_multicast`` datagrams read straight into rows,
the direct mode's backlog, the recorder's and publisher's JSON written from rows): numba compiles
a kernel once per argument types, so every path that calls a kernel differently must run here.
The kernels do not depend on the robot, so every robot then starts at once.
``tests/gateway/engine/test_warm.py`` checks that a gateway run after this compiles nothing.
"""
from __future__ import annotations

import sys
import time


def frames(n_steps: int = 120):
    """``(bus, can.Message)`` of ``n_steps`` 1 kHz steps of the paper robot: every device, every
    frame type the drivers decode, wall-clock-free timestamps (ms from 0)."""
    from drivers import frames as fr
    from drivers.samples import ImuSample, JointSample, ThrusterCommand, TorqueCommand, ValveCommand, WrenchSample

    out = []
    for k in range(n_steps):
        t = k * 1_000_000
        c = k & 0xFF

        def add(bus, msgs):
            for m in msgs:
                m.timestamp = t / 1e9
                out.append((bus, m))

        for arm in ("arm0", "arm1"):
            add(arm, fr.encode_wrench(WrenchSample(arm, t, c, (1.0, -2.0, 3.0), (0.1, 0.2, -0.3))))
            for j, name in enumerate(("j1", "j2")):
                add(arm, [fr.encode_joint(JointSample(f"{arm}/{name}", t, c, 0.1 * j, 0.01), j)])
            if k % 2 == 0:
                add(arm, fr.encode_torque_commands([TorqueCommand(f"{arm}/j1", t, c, 1.0),
                                                    TorqueCommand(f"{arm}/j2", t, c, -1.0)]))
        if k % 2 == 1:
            add("spacecraft", fr.encode_imu(ImuSample(t, c, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.01), (0.01, 0.0, 0.0))))
        if k % 10 == 0:
            add("spacecraft", fr.encode_thruster(ThrusterCommand(t, c, (1.0, 0.0, 0.0), (0.0, 0.0, 0.5), 0b11)))
        add("spacecraft", [fr.encode_valves(ValveCommand(t, c, 0b11 if k % 3 else 0))])
        if k % 100 == 0:
            add("spacecraft", [fr.encode_heartbeat(0x20, c)])
    return out


def warm() -> float:
    """Run every kernel once, on every path that calls it with its own argument types: a
    session fed one frame at a time (replay, the demo, a simulated series) and the live
    gateway's and an offline replay's (:func:`_gateway`). Returns the wall time it took, s."""
    import robot_description
    from gateway.engine import Session

    t0 = time.perf_counter()
    robot = robot_description.load("paper_robot")
    with Session(robot) as ses:
        for bus, msg in frames():
            ses.feed(bus, msg)
    _gateway(robot, frames(360))
    return time.perf_counter() - t0


class _NullPublisher:
    def put(self, payload, **kwargs) -> None:
        pass

    def undeclare(self) -> None:
        pass


class _NullZenoh:
    """Stands in for a zenoh session: the gateway's payloads are encoded, then go nowhere."""

    def declare_publisher(self, key, **kwargs):
        return _NullPublisher()


def _batches(start: int, stop: int):
    """``(i, j)`` slices of ``start..stop`` of 1, 2, 5, 13 and 16 frames in turn: what arrives
    together varies, and a field of one row types differently in numba from one of several."""
    sizes, k = (1, 2, 5, 13, 16), 0
    while start < stop:
        j = min(stop, start + sizes[k % len(sizes)])
        yield start, j
        start, k = j, k + 1


def _gateway(robot, msgs) -> None:
    """The live gateway's own code on ``msgs``, as :class:`gateway.bridge.GatewayService` builds
    it (its recorder and publisher sinks take rows: the JSON kernels): a third through the
    threads mode's ``feed_messages``, a third each as SocketCAN and ``udp_multicast`` datagrams
    read by :class:`drivers.receive.BusReader` and merged by the direct mode's backlog."""
    import socket
    import tempfile
    from pathlib import Path

    import can
    from can.interfaces.socketcan.socketcan import build_can_frame
    from can.interfaces.udp_multicast.utils import pack_message

    from drivers import wire
    from drivers.receive import BusReader
    from gateway.bridge import DRAIN_MAX, GatewayService
    from gateway.log.recorder import Recorder

    names = list(wire.WireMap.from_robot(robot).buses)
    with tempfile.TemporaryDirectory(prefix="bsc-warm-") as tmp, \
            Recorder(Path(tmp) / "warm.mcap") as rec:
        buses = {n: can.Bus(interface="virtual", channel=f"bsc-warm-{n}-{id(rec)}") for n in names}
        gw = GatewayService(robot, buses, _NullZenoh(), record=rec)
        try:
            third = len(msgs) // 3
            st = gw.bus_state
            for i, j in _batches(0, third):            # threads mode: what arrived together
                gw._process([(st[b], m) for b, m in msgs[i:j]])
            gw.publish_health()
            for kind, pack, part in (("socketcan", build_can_frame, msgs[third:2 * third]),
                                     ("udp", pack_message, msgs[2 * third:])):
                pairs = {n: socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM) for n in names}
                try:
                    readers = {n: BusReader(pairs[n][0], gw._backlog.index[n], kind) for n in names}
                    for i, j in _batches(0, len(part)):
                        stamps = {n: [] for n in names}
                        for b, m in part[i:j]:
                            pairs[b][1].send(pack(m))
                            stamps[b].append(round(m.timestamp * 1e9))
                        for n in names:                # the firmware's stamps, not the read time
                            rows = readers[n].read(DRAIN_MAX)
                            rows["t_ns"] = stamps[n]
                            gw._backlog.append(n, rows)
                        gw._process_rows(gw._backlog.take(len(gw._backlog), all_read=True))
                finally:
                    for a, b in pairs.values():
                        a.close()
                        b.close()
                gw.publish_health()
            gw._final_flush()
        finally:
            gw.close()
            for b in buses.values():
                b.shutdown()
        if gw.pipeline_errors:
            raise RuntimeError(f"warm: the gateway's pipeline failed on {gw.pipeline_errors} batches (see the log)")
        # offline replay of what it recorded: frames read from the chunks into rows
        from gateway.replay import replay_offline

        rec.close()
        replay_offline(Path(tmp) / "warm.mcap", Path(tmp) / "replay", robot=robot.name)


if __name__ == "__main__":
    print(f"bsc kernels ready in {warm():.1f} s", file=sys.stderr)
