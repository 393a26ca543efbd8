"""``python -m gateway.engine.warm`` compiles every kernel the live gateway then runs.

numba compiles a kernel once per argument types, and the SocketCAN tier depends on it: the VM
reads kernels warmed on the host, and one kernel compiled under emulation instead takes minutes
(a gateway that compiled its socket reader there counted no frame while the test waited). So:
in a fresh process, warm, note every compiled signature of every kernel, run the gateway as it
runs on SocketCAN and on ``udp_multicast`` (direct receive of the real wire bytes, recording,
publishing on zenoh over loopback, health), replay what it recorded offline, and find nothing
new compiled.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]

SCRIPT = r"""
import json, socket, sys, tempfile, time
from pathlib import Path

import numba.core.dispatcher


def compiled():
    out = set()
    for name, mod in list(sys.modules.items()):
        if mod is None or not name.split(".")[0] in ("drivers", "gateway", "simulator"):
            continue
        for attr, v in list(vars(mod).items()):
            if isinstance(v, numba.core.dispatcher.Dispatcher):
                out.update(f"{v.py_func.__module__}.{v.py_func.__qualname__}{sig}" for sig in v.signatures)
    return out


from gateway.engine.warm import warm

warm()
before = compiled()

import can
import zenoh
from can.interfaces.socketcan.socketcan import build_can_frame
from can.interfaces.udp_multicast.utils import pack_message

from drivers import wire
from drivers.receive import BusReader
from gateway import bridge
from gateway.config import GatewayConfig

DIRECT = GatewayConfig().updated(can={"receive": "direct"})
from gateway.log.recorder import Recorder
from gateway.zenoh_config import make_config
from simulator import firmware, scenario
from simulator.engine import DT_S, Simulation


class WireBus(can.BusABC):
    # a bus whose socket carries `kind` datagrams: SocketCAN's struct can_frame or python-can's
    # udp_multicast packing, which the gateway reads straight from the socket
    def __init__(self, sock, name, kind):
        self.sock, self.kind = sock, kind
        super().__init__(channel=name)

    def fileno(self):
        return self.sock.fileno()

    def _recv_internal(self, timeout):
        return None, False

    def send(self, msg, timeout=None):
        raise NotImplementedError

    def shutdown(self):
        super().shutdown()
        self.sock.close()


bridge.reader_for = lambda bus, index: BusReader(bus.sock, index, bus.kind)
report = {}
with tempfile.TemporaryDirectory() as tmp:
    for kind, pack in (("socketcan", build_can_frame), ("udp", pack_message)):
        sim = Simulation(scenario.load("capture", {"duration_s": 0.3}))
        fw = firmware.Firmware(sim.robot)
        pairs, buses = {}, {}
        for n in wire.WireMap.from_robot(sim.robot).buses:
            rx, tx = pairs[n] = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
            rx.setsockopt(socket.SOL_SOCKET, 35, 1)          # SO_TIMESTAMPNS, as python-can sets it
            buses[n] = WireBus(rx, n, kind)
        with zenoh.open(make_config(listen=[sys.argv[1]])) as z, Recorder(Path(tmp) / f"{kind}.mcap") as rec, \
                bridge.GatewayService(sim.robot, buses, z, DIRECT, record=rec) as gw:
            sent, t0 = 0, time.monotonic()
            for k in range(sim.n_steps):
                r = sim.step()
                time.sleep(max(0.0, t0 + k * DT_S - time.monotonic()))
                for b, msg in fw.frames(r):
                    pairs[b][1].send(pack(msg))
                    sent += 1
            end = time.monotonic() + 120
            while gw.stats["received"] < sent and time.monotonic() < end:
                time.sleep(0.01)
            assert gw.drain(120)
            gw.publish_health()
            st = gw.stats
        report[kind] = {"sent": sent, "received": st["received"], "processed": st["processed"],
                        "published": gw.published, "errors": gw.pipeline_errors + gw.publish_errors,
                        "recorded": rec.stats.written}
        for rx, tx in pairs.values():
            tx.close()
    from gateway.replay import replay_offline

    r = replay_offline(Path(tmp) / "socketcan.mcap", Path(tmp) / "replay", robot=sim.robot.name, samples=True)
    report["replay"] = {"frames": r.frames_in, "efforts": r.efforts, "samples": r.samples}
report["new"] = sorted(compiled() - before)
print(json.dumps(report))
"""


def test_a_gateway_after_warm_compiles_nothing(tmp_path):
    from support import free_port

    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", SCRIPT, f"tcp/127.0.0.1:{free_port()}"], cwd=ROOT, env=env,
                         stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-4000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    for kind in ("socketcan", "udp"):
        r = report[kind]
        assert r["sent"] > 1000 and r["received"] == r["processed"] == r["sent"], (kind, r)
        assert r["errors"] == 0 and r["published"] > r["sent"] // 4 and r["recorded"] > r["sent"], (kind, r)
    r = report["replay"]
    assert r["frames"] == report["socketcan"]["sent"] and r["efforts"] > 0 and r["samples"] > 0, r
    assert report["new"] == [], "compiled after warm (add their path to gateway/engine/warm.py):\n" + \
        "\n".join(report["new"])
