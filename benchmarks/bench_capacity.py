"""Whole-system capacity: the simulated firmware in real time, ``bsc gateway --record`` and
``bsc monitor``, each its own process on this machine, at the nominal frame rate for ``--seconds``
(default 60). Target: 0 frames shed by the gateway.

Run: ``python -m benchmarks.bench_capacity [--seconds S]`` or ``bsc bench --only capacity``.
CAN goes over udp_multicast in a private network namespace (loopback, multicast on), so it needs
root and iproute2; the firmware runs at SCHED_FIFO priority 10 (``--rt-priority``). Reported:
frames the gateway received and shed (its last line), the peak of its backlog, epochs and good
epochs, the firmware's late steps, and the monitor's ``sensor-loss`` alerts (a shed run of frames
shows there too).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.bench_latency import private_netns
from gateway.zenoh_config import free_port

ROOT = Path(__file__).resolve().parents[1]
GROUPS = {"arm0": "239.74.163.1", "arm1": "239.74.163.2", "spacecraft": "239.74.163.3"}
_LAST = re.compile(r"received (\d+) frames, dropped (\d+) \(backlog full; peak (\d+) of (\d+)\).*?"
                   r"epochs (\d+), good_epochs (\d+)")


def measure(seconds: float = 60.0, say=print) -> dict:
    with private_netns() as ns:
        if ns is None:
            raise RuntimeError("needs root and iproute2: CAN goes over udp_multicast in a private network namespace")
        with tempfile.TemporaryDirectory(prefix="bsc-capacity-") as tmp:
            tmp = Path(tmp)
            env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
            inside = ["ip", "netns", "exec", ns, sys.executable, "-m", "gateway.cli"]
            channels = [a for b, g in GROUPS.items() for a in ("-c", f"{b}={g}")]
            ep = f"tcp/127.0.0.1:{free_port()}"
            run_for = str(seconds + 120)            # stopped with SIGINT when the firmware is done
            gw = subprocess.Popen(inside + ["gateway", "-i", "udp_multicast", *channels, "--listen", ep,
                                            "--record", str(tmp / "gateway.mcap"), "--duration", run_for],
                                  cwd=ROOT, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True)
            mon = None
            try:
                first = gw.stdout.readline()            # printed once the buses are open
                if "receive" not in first:
                    raise RuntimeError(f"the gateway did not start: {first} {gw.stderr.read()[-2000:]}")
                mon = subprocess.Popen(inside + ["monitor", "--connect", ep, "--duration", run_for,
                                                 "--alert-log", str(tmp / "alerts.jsonl")],
                                       cwd=ROOT, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                       stderr=subprocess.PIPE, text=True)
                say(f"capacity: firmware for {seconds:g} s at the nominal rate, gateway --record and monitor running")
                t0 = time.perf_counter()
                sim = subprocess.run(inside + ["sim", "--scenario", "capture", "--duration", f"{seconds:g}",
                                               "--interface", "udp_multicast", *channels, "--realtime",
                                               "--rt-priority", "10", "--no-plots", "--no-compare", "--quiet",
                                               "--out", str(tmp / "sim")],
                                     cwd=ROOT, env=env, stdin=subprocess.DEVNULL, capture_output=True, text=True,
                                     timeout=3 * seconds + 300)
                wall = time.perf_counter() - t0
                if sim.returncode != 0:
                    raise RuntimeError(f"the firmware failed: {sim.stderr[-2000:]}")
                gw.send_signal(signal.SIGINT)           # its final flush takes what it has received
                out, err = gw.communicate(timeout=300)
            finally:
                for p in (gw, mon):
                    if p is not None and p.poll() is None:
                        p.send_signal(signal.SIGINT)
                        try:
                            p.wait(60)
                        except subprocess.TimeoutExpired:
                            p.kill()
            m = _LAST.search(out)
            if m is None:
                raise RuntimeError(f"the gateway's last line is missing: {out[-1000:]} {err[-1000:]}")
            received, shed, peak, bound, epochs, good = map(int, m.groups())
            summary = json.loads((tmp / "sim" / "summary.json").read_text())["can"]
            alerts = [json.loads(x) for x in (tmp / "alerts.jsonl").read_text().splitlines()] \
                if (tmp / "alerts.jsonl").exists() else []
    return {"seconds": seconds, "wall_s": wall, "sent": sum(summary["frames_sent"].values()),
            "late_steps": summary["pacing"]["late_steps"], "steps": summary["pacing"]["steps"],
            "received": received, "shed": shed, "peak_backlog": peak, "backlog_bound": bound,
            "epochs": epochs, "good_epochs": good,
            "sensor_loss_alerts": sum(a["rule"] == "sensor-loss" and a["state"] == "raised" for a in alerts)}


def figures(quick: bool = False) -> list[dict]:
    from benchmarks.anchors import row

    m = measure(10.0 if quick else 60.0, say=lambda *_: None)
    note = (f"{m['seconds']:g} s: firmware (real time, SCHED_FIFO 10) + bsc gateway --record + bsc monitor, "
            f"processes on this machine; {m['received']} of {m['sent']} frames received, peak backlog "
            f"{m['peak_backlog']} of {m['backlog_bound']}; firmware steps late {m['late_steps']}; "
            f"sensor-loss alerts {m['sensor_loss_alerts']}")
    return [row("whole system at the nominal rate: frames shed", m["shed"], "frames", target="0",
                ok=m["shed"] == 0, note=note),
            row("whole system at the nominal rate: good epochs", 100.0 * m["good_epochs"] / max(1, m["epochs"]), "%",
                note=f"{m['good_epochs']} of {m['epochs']}")]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="how long the firmware runs")
    args = ap.parse_args(argv)
    m = measure(args.seconds)
    print(json.dumps(m, indent=1))
    print(f"target 0 frames shed: {'met' if m['shed'] == 0 else 'MISSED'} ({m['shed']} of {m['received'] + m['shed']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
