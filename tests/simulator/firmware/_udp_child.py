"""One side of the two-process udp_multicast test (run inside a private network namespace).

    python _udp_child.py send    SCENARIO DURATION_S GROUP,GROUP,...
        runs the firmware in real time on udp_multicast buses (one group and port per bus),
        then prints {bus: frames sent} as JSON.
    python _udp_child.py receive SCENARIO DURATION_S GROUP,GROUP,... OUT.pickle
        opens the same buses with the drivers under Notifiers, prints "ready", reads the
        sender's JSON from stdin, waits until that many frames arrived on every bus (or 20 s),
        and pickles the decoded samples and the health to OUT.
"""
from __future__ import annotations

import json
import pickle
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from firmware_rig import BusRig  # noqa: E402
from simulator import firmware, scenario  # noqa: E402
from simulator.engine import Simulation  # noqa: E402


def main(role: str, name: str, duration_s: str, groups: str, out: str | None = None) -> int:
    sim = Simulation(scenario.load(name, {"duration_s": float(duration_s)}))
    fw = firmware.Firmware(sim.robot)
    chans = dict(zip(fw.wire.buses, groups.split(",")))
    with firmware.open_buses(sim.robot, "udp_multicast", chans) as buses:
        if role == "send":
            firmware.run_on_buses(sim, buses, firmware=fw, realtime=True)
            print(json.dumps(dict(fw.frames_sent)), flush=True)
            return 0
        # a loaded 2-core host can starve the receiver for tens of ms: give each socket room for
        # that (UDP drops silently when the default ~200 kB buffer fills; seen in CI under load)
        import socket
        for bus in buses.values():
            sock = getattr(getattr(bus, "_multicast", None), "_socket", None)
            if sock is not None:
                opt = getattr(socket, "SO_RCVBUFFORCE", socket.SO_RCVBUF)
                try:
                    sock.setsockopt(socket.SOL_SOCKET, opt, 16 << 20)
                except OSError:
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 << 20)
        rig = BusRig(sim.robot, dict(buses))
        try:
            print("ready", flush=True)
            expected = json.loads(sys.stdin.readline())
            seen = rig.wait(expected, timeout=20.0)
        finally:
            rig.stop()
        now = time.time_ns()
        Path(out).write_bytes(pickle.dumps({"expected": expected, "seen": seen, "samples": rig.samples,
                                           "health": rig.health(now), "bus_health": rig.bus_health(now)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(*sys.argv[1:]))
