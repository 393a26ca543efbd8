"""The simulator's sensor firmware and the gateway as two separate processes on vcan0..vcan2,
both through their command lines, as deployed (README: ``bsc gateway --interface socketcan``):

    bsc sim     --interface socketcan -c arm0=vcan0 -c arm1=vcan1 -c spacecraft=vcan2   (lockstep)
    bsc gateway --interface socketcan -c arm0=vcan0 ... --record gw.mcap                (drivers + estimator)

Judged like the in-process bus tiers (tests/simulator/firmware): every sample the gateway published equals
the simulator's reading of the same step within the wire quantization, none missing or extra;
its health counts every frame and sample exactly, nothing lost or rejected. SocketCAN stamps
frames on reception (host clock) and the lockstep firmware runs as fast as the host lets it, far
slower than real time in the VM, so freshness is judged when the stream ended, by the drivers'
own rule (stale after ``stale_periods`` nominal periods) at the pace the stream ran (measured:
the last samples of every device were at most ~0.9 of its period old).

The firmware runs at normal priority and the gateway at nice 19: the firmware stands for devices
with CPUs of their own, the gateway drains its socket buffers (8 MiB in the VM) afterwards. So
the stream runs at the firmware's own pace (~15x slower than real time in the VM), and the
drivers' time-based rules (drivers/health.py: stale after 10 periods, a device silent for over
100 periods is resynchronised by time) see steps ~15 ms apart, not ~50-250 ms as when the two
processes share the vCPU. The test waits for conditions (the gateway's health counting every
frame sent), never for fixed times; the bounded waits only turn a hang into a failure.
"""
from __future__ import annotations

import json
import os
import selectors
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

HERE = Path(__file__).parent
ROOT = HERE.parents[2]
sys.path.insert(0, str(ROOT / "tests" / "simulator" / "firmware"))   # the schedule and comparison of the firmware tests

from firmware_rig import by_device, check_against_readings, snapshot  # noqa: E402
from support import free_port as _free_port  # noqa: E402

CHANNELS = {"arm0": "vcan0", "arm1": "vcan1", "spacecraft": "vcan2"}
HAVE_VCANS = all(Path(f"/sys/class/net/{ch}").exists() for ch in CHANNELS.values())
DURATION_S = 0.1      # 100 steps, ~1350 frames: enough for every device, short in the VM
WAIT_S = 300.0        # a hang becomes a failure after this (Python is ~14x slower in the VM)
STALL_S = 60.0        # the gateway's frame counts standing still this long: a failure


def _bsc(*args) -> list[str]:
    # as the `bsc` entry point calls it (``-m gateway.cli`` would load gateway.cli twice)
    return [sys.executable, "-c", "import sys; from gateway.cli import main; sys.exit(main())", *args]


def _env() -> dict:
    return dict(os.environ, OPENBLAS_NUM_THREADS="1",
                PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))


class GatewayProcess:
    """``bsc gateway`` on the vcans, recording to ``mcap`` and listening for zenoh on ``endpoint``."""

    def __init__(self, tmp: Path, endpoint: str, mcap: Path):
        chans = [a for b, ch in CHANNELS.items() for a in ("-c", f"{b}={ch}")]
        self.err_path = tmp / "gateway.stderr"
        self.err = open(self.err_path, "w")
        # nice: the firmware stands for devices with CPUs of their own, so it must not wait for
        # the gateway on the VM's one vCPU; the gateway catches up from its socket buffers.
        # --source-rate lockstep: `bsc sim` without --realtime runs as fast as the VM lets it, so
        # the kernel's receive stamps do not measure the devices' clocks (drivers/health.py)
        self.proc = subprocess.Popen(
            ["nice", "-n", "19", *_bsc("gateway", "--interface", "socketcan", *chans, "--robot", "paper_robot",
                                       "--source-rate", "lockstep",
                                       "--record", str(mcap), "--listen", endpoint, "--health-period", "0.25")],
            cwd=ROOT, env=_env(), stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=self.err, text=True)
        self.out: list[str] = []

    def stderr(self) -> str:
        self.err.flush()
        return self.err_path.read_text()[-3000:]

    def wait_ready(self) -> None:
        """Until its buses are open (the line ``bsc gateway: robot ...``)."""
        with selectors.DefaultSelector() as sel:
            sel.register(self.proc.stdout, selectors.EVENT_READ)
            deadline = time.monotonic() + WAIT_S
            while time.monotonic() < deadline:
                if sel.select(timeout=1.0):
                    line = self.proc.stdout.readline()
                    if not line:
                        break
                    self.out.append(line)
                    if line.startswith("bsc gateway: robot"):
                        return
                elif self.proc.poll() is not None:
                    break
        pytest.fail(f"bsc gateway did not start (exit {self.proc.poll()}): {''.join(self.out)}{self.stderr()}")

    def stop(self) -> str:
        """SIGTERM (the gateway publishes its last health and closes the recording); its stdout."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            out, _ = self.proc.communicate(timeout=WAIT_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, _ = self.proc.communicate()
            pytest.fail(f"bsc gateway did not stop on SIGTERM: {self.stderr()}")
        self.out.append(out)
        return "".join(self.out)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self.proc.stdout.close()
        self.err.close()


class HealthWatch:
    """zenoh subscriber of the gateway's health: the frames each bus's health has counted."""

    def __init__(self):
        self.frames: dict[str, int] = {}
        self.changed = time.monotonic()          # when a count last moved
        self.cond = threading.Condition()

    def __call__(self, sample) -> None:
        from drivers.samples import BusHealth
        from gateway import codec

        h = codec.decode(sample.payload.to_bytes())
        if isinstance(h, BusHealth):
            with self.cond:
                if self.frames.get(h.bus) != h.frames:
                    self.frames[h.bus] = h.frames
                    self.changed = time.monotonic()
                self.cond.notify_all()

    def wait_for(self, frames: dict[str, int], alive) -> bool:
        """Until every bus counted ``frames[bus]`` (True); False once ``alive()`` is False, no
        count moved for STALL_S (frames lost: they will never come) or WAIT_S passed."""
        deadline = time.monotonic() + WAIT_S
        with self.cond:
            self.changed = time.monotonic()
            while not all(self.frames.get(b, -1) >= n for b, n in frames.items()):
                now = time.monotonic()
                if not alive() or now > deadline or now - self.changed > STALL_S:
                    return False
                self.cond.wait(1.0)
            return True


def read_recording(path: Path) -> dict:
    """The gateway's recording: samples in recording order, the last health of every device
    and bus, the efforts."""
    from drivers.samples import BusHealth, DeviceHealth
    from gateway import codec
    from gateway.efforts import JointEfforts, ThrusterEffort, ValveWrenches
    from gateway.log.reader import iter_file_order
    from gateway.replay import sample_types

    types_ = sample_types()
    out: dict = {"samples": [], "device_health": {}, "bus_health": {}, "efforts": []}
    for topic, schema, m in iter_file_order(path, lambda t, s: s in types_):
        fields = json.loads(m.data)
        obj = codec.decode(json.dumps({"type": types_[schema].__name__, "v": codec.VERSION, **fields}))
        if isinstance(obj, DeviceHealth):
            out["device_health"][obj.device] = obj
        elif isinstance(obj, BusHealth):
            out["bus_health"][obj.bus] = obj
        elif isinstance(obj, (JointEfforts, ThrusterEffort, ValveWrenches)):     # the learned valve wrenches too
            out["efforts"].append(obj)
        else:
            out["samples"].append(obj)
    return out


def _nominal_counters() -> dict:
    """device -> the drivers' DeviceCounters (nominal period, stale_periods) of the paper robot."""
    import robot_description
    from drivers import devices, wire

    wm = wire.WireMap.from_robot(robot_description.load("paper_robot"))
    return {c.device: c for spec in wm.buses.values()
            for d in devices.listeners_for(spec, lambda s: None)[1] for c in d.counters()}


@pytest.mark.vcan
@pytest.mark.skipif(not HAVE_VCANS, reason="needs SocketCAN vcan0..vcan2: run .ci/vcan-tier.sh (a VM with vcan)")
def test_firmware_and_gateway_processes_over_socketcan(tmp_path):
    import zenoh

    from gateway import keys
    from gateway.zenoh_config import make_config
    from simulator import firmware, scenario
    from simulator.engine import Simulation

    endpoint, mcap = f"tcp/127.0.0.1:{_free_port()}", tmp_path / "gateway.mcap"
    watch = HealthWatch()
    gw = GatewayProcess(tmp_path, endpoint, mcap)
    try:
        sim = Simulation(scenario.load("capture", {"duration_s": DURATION_S}))    # while the gateway starts
        robot = sim.robot
        readings = [snapshot(sim.step()) for _ in range(sim.n_steps)]      # the firmware's run, deterministic
        gw.wait_ready()
        assert "(receive: direct)" in gw.out[-1], gw.out[-1]     # socketcan: the worker polls the sockets
        with zenoh.open(make_config(connect=[endpoint])) as session:
            sub = session.declare_subscriber(keys.health(robot.name), watch)
            try:
                chans = [a for b, ch in CHANNELS.items() for a in ("-c", f"{b}={ch}")]
                fw = subprocess.run(
                    _bsc("sim", "--scenario", "capture", "--duration", str(DURATION_S), "--out", str(tmp_path / "sim"),
                         "--no-plots", "--no-compare", "--quiet", "--interface", "socketcan", *chans),
                    cwd=ROOT, env=_env(), stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=WAIT_S)
                assert fw.returncode == 0, fw.stderr
                sent = json.loads((tmp_path / "sim" / "summary.json").read_text())["can"]["frames_sent"]
                assert set(sent) == set(CHANNELS)
                if not watch.wait_for(sent, alive=lambda: gw.proc.poll() is None):
                    pytest.fail(f"the gateway's health counted {watch.frames} frames, the firmware sent {sent} "
                                f"(gateway exit {gw.proc.poll()}): {gw.stderr()}")
            finally:
                sub.undeclare()
        gw.stop()
    finally:
        gw.close()
    assert gw.proc.returncode == 0, gw.stderr()

    rec = read_recording(mcap)
    # every sample equals the simulator's reading of its step, none missing or extra
    n = check_against_readings(robot, readings, rec["samples"], stamps=False)
    steps = sim.n_steps
    assert n["arm0"] == n["arm1/j2"] == n["valves"] == steps and n["imu"] == steps // 2
    assert n[("cmd", "arm0/j1")] == steps // 2 and n["thrusters"] == steps // 10
    # health counts every frame and sample exactly
    for bus, h in rec["bus_health"].items():
        assert (bus, h.frames, h.rejected) == (bus, sent[bus], ()), h
        assert h.nodes and all(state == firmware.HEARTBEAT_OPERATIONAL for _, state in h.nodes), h
    assert set(rec["bus_health"]) == set(CHANNELS)
    got = by_device(rec["samples"])
    counters = _nominal_counters()
    first_joint = {a.name: f"{a.name}/{a.joint_names[0]}" for a in robot.arms}
    assert set(rec["device_health"]) == set(counters)
    for dev, h in rec["device_health"].items():
        key = ("cmd", first_joint[h.bus]) if dev.endswith("/torque_cmd") else dev   # one frame: every joint
        assert (dev, h.samples, h.lost, h.rejected, h.faults) == (dev, len(got[key]), 0, (), 0)
        assert h.last_t_ns == got[key][-1].t_ns, dev
    # fresh when the stream ended, at the pace it ran (real time: pace 1)
    stamps = [s.t_ns for s in rec["samples"]]
    end = max(stamps)
    pace = max(1.0, (end - min(stamps)) / (readings[-1].t_ns - readings[0].t_ns))
    late = {dev: (end - h.last_t_ns) / (counters[dev].period_ns * pace) for dev, h in rec["device_health"].items()}
    assert all(periods <= counters[dev].stale_periods for dev, periods in late.items()), (pace, late)
    # the estimator ran on it; an estimate that is not good says why
    assert rec["efforts"] and all(e.good or e.flags for e in rec["efforts"])
