"""Compile (or load from numba's on-disk cache) every kernel the session engine runs.

The first use of a compiled kernel in a fresh installation costs its compilation (about a
minute for the estimator on a loaded two-core machine; from the cache, well under a second).
``python -m gateway.engine.warm`` does it once, ahead of time: after an install, or before a
run whose first epochs must not wait (the SocketCAN tier compiles this way on the host, for the
VM's CPU, because compiling under emulation would take a quarter of an hour).

It runs a few hundred synthetic frames of the paper robot through a :class:`Session`; the kernels
do not depend on the robot, so every robot then starts at once.
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
    """Run every kernel once; returns the wall time it took, s."""
    import robot_description
    from gateway.engine import Session

    t0 = time.perf_counter()
    with Session(robot_description.load("paper_robot")) as ses:
        for bus, msg in frames():
            ses.feed(bus, msg)
    return time.perf_counter() - t0


if __name__ == "__main__":
    print(f"bsc kernels ready in {warm():.1f} s", file=sys.stderr)
