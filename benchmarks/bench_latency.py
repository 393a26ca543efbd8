"""End-to-end latency of the gateway: ``python -m benchmarks.bench_latency [--seconds S] [--json]``
(a benchmark, not a test; method and measured figures in docs/latency.md).

What is measured (issue #4): the time from the arrival at the gateway of the LAST CAN frame that
completed an estimate's inputs to the arrival of that estimate's efforts at a zenoh subscriber in
another process. Target: p50 <= 300 us, p99 <= 1 ms at nominal rates on the 2-core machine.

Processes, all on this host:

- **sender**: the capture scenario's sensor firmware (``simulator.firmware.Firmware``: the frames
  ``run_on_buses`` sends, 13.4 k frames/s on three buses), pre-generated in lockstep, then sent in
  real time: step ``k`` at ``k`` ms on the monotonic clock. ``--pacing burst`` (default): a step's
  frames back to back, as ``run_on_buses(realtime=True)`` does; ``--pacing wire``: each bus's
  frames spaced by their worst-case 1 Mbit/s wire time. ``--source firmware`` runs the simulator
  live instead (``run_on_buses(realtime=True)``). The sender stands for the robot's hardware, so it
  runs at real-time priority when allowed (it sleeps most of the time).
- **gateway**: :class:`gateway.bridge.GatewayService` built as ``bsc gateway`` builds it (python-can
  buses; the direct receive mode, where the one worker thread polls the buses' sockets and runs
  drivers + estimator, or ``--receive threads``: one notifier thread per bus feeding the worker; a
  zenoh peer session listening on a loopback port; the heap frozen after start-up), timed by its own
  hooks (:class:`gateway.bridge.Probe`: frames received, each batch fed, health ticks) and by probe
  sinks around its outputs (``Session.add_sink``; ``--bare``: those only). The benchmark replaces
  nothing of the service.
  ``--topology split`` measures the alternative: the gateway process runs the drivers only
  (``estimate=False``, samples published on zenoh) and an **estimator** process subscribes to the
  samples, runs :class:`gateway.estimator.core.EstimatorCore` in its zenoh callback (one sample
  per call, as the gateway feeds it) and publishes the efforts.
- **subscriber**: a zenoh session connected to the process that publishes the efforts, subscribed
  to ``bsc/<robot>/efforts/**`` (``--subscribe all``: everything, as a recorder does), stamping each
  sample with ``time.time_ns()`` first thing in its callback.

Clocks: CAN frames travel over python-can ``udp_multicast`` inside a private network namespace
(root needed; the namespace's loopback carries the multicast and the zenoh TCP, nothing leaves
it). python-can stamps each datagram with the kernel's receive time (``SO_TIMESTAMPNS``,
CLOCK_REALTIME): that is ``msg.timestamp``, the frame's arrival. An effort is emitted
synchronously while the frame that completed its epoch is being fed (its log time is that frame's
stamp), so the completing frame's arrival is known at emit time; in the split
topology it is the ``t_ns`` of the sample whose arrival completed the epoch (a sample's ``t_ns`` is
its last frame's stamp). The subscriber stamps with CLOCK_REALTIME too (same host). Without root,
the frames go over loopback UDP unicast instead (``--transport loopback``: a small ``can.BusABC``
here with the same msgpack datagrams and kernel receive stamps as ``udp_multicast``).

Reported: the distribution (p50, p90, p99, p99.9, max, count), the stages of the completing
frame's path (arrival -> a gateway thread has received it -> the pipeline starts on it -> effort
emitted -> ``put`` returned -> subscriber), every frame's queue wait and worker time, the CPU of every thread group
of every process over the sending window, GC pauses and health ticks in the gateway, the
gateway's frame accounting (drops when its bounded queue overflows), the load average and the
host's CPU use, and the verdict. ``--slowdown K`` sends K times slower than real time: a
diagnostic of the latency floor when the gateway is not saturated (not the nominal rate).

``figures(quick=False)`` returns the headline rows for ``python -m benchmarks``.
"""
from __future__ import annotations

import argparse
import contextlib
import gc
import json
import os
import pickle
import select
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

from gateway.zenoh_config import free_port

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parents[1]
TARGET_P50_US = 300.0
TARGET_P99_US = 1000.0
WARMUP_S = 1.0                  # efforts whose completing frame came in the first second are not counted
SCENARIO = "capture"
GROUP_BASE = "239.74.163."      # one multicast group per bus (docs/firmware.md)
RCVBUF = 16 << 20               # as tests/simulator/firmware/_udp_child.py: a starved reader must not lose frames
SO_TIMESTAMPNS = 35
SO_RCVBUFFORCE = 33             # Linux; not exported by Python's socket module
QUICK_SECONDS = 4.0


# --- the fallback CAN transport: loopback UDP unicast ------------------------------------------

def _loopback_bus_class():
    import can
    from can.interfaces.udp_multicast.utils import unpack_message

    class _LoopbackBus(can.BusABC):
        """One CAN bus as a UDP socket on 127.0.0.1 (receive side). Same datagrams as python-can's
        ``udp_multicast`` (msgpack), same kernel receive stamp (SO_TIMESTAMPNS)."""

        def __init__(self, channel="loopback", port: int = 0, **kw):
            super().__init__(channel=channel, **kw)
            self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            _big_rcvbuf(self.sock)
            self.sock.bind(("127.0.0.1", port))
            self.port = self.sock.getsockname()[1]
            self._anc = socket.CMSG_SPACE(struct.calcsize("@ll"))

        def _recv_internal(self, timeout):
            r, _, _ = select.select([self.sock], [], [], timeout)
            if not r:
                return None, False
            data, anc, _, _ = self.sock.recvmsg(4096, self._anc)
            ts = time.time()
            for level, kind, cdata in anc:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                    sec, nsec = struct.unpack("@ll", cdata[:struct.calcsize("@ll")])
                    ts = sec + nsec * 1e-9
            return unpack_message(data, replace={"timestamp": ts}, check=True), False

        def fileno(self) -> int:                          # pollable, as udp_multicast is
            return self.sock.fileno()

        def send(self, msg, timeout=None):
            raise NotImplementedError("receive side only")

        def shutdown(self):
            super().shutdown()
            self.sock.close()

    return _LoopbackBus


def _big_rcvbuf(sock) -> None:
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, RCVBUF)       # root: past net.core.rmem_max
    except OSError:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF)


# --- helpers of the children --------------------------------------------------------------------

def _lines():
    """stdin lines (the parent drives the children with one word per line)."""
    for line in sys.stdin:
        yield line.strip()


def _say(obj) -> None:
    print(json.dumps(obj), flush=True)


def _wait_for(word: str) -> None:
    for line in _lines():
        if line == word:
            return


def _set_timer_slack(ns: int = 1000) -> None:
    """Let this process's sleeps end within ~1 us (default slack 50 us) so the pacing is exact."""
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(29, ns, 0, 0, 0)      # PR_SET_TIMERSLACK


def _robot():
    import robot_description
    from robot_description.thrusters import ThrusterLayout
    from simulator import scenario

    scn = scenario.load(SCENARIO)
    return robot_description.load(scn.robot), ThrusterLayout.from_config(scn.cfg.thrusters)


class _Pauses:
    """GC pauses of this process (``gc.callbacks``): (start ns, duration ns, generation)."""

    def __init__(self):
        self.items: list[tuple[int, int, int]] = []
        self._t0 = 0
        gc.callbacks.append(self._on_gc)

    def _on_gc(self, phase, info):
        if phase == "start":
            self._t0 = time.time_ns()
        else:
            self.items.append((self._t0, time.time_ns() - self._t0, info["generation"]))


# --- sender -------------------------------------------------------------------------------------

def _frames_schedule(seconds: float, pacing: str, slowdown: float = 1.0):
    """[(send offset s, bus, message)] for ``seconds`` of the capture scenario's firmware; steps
    ``slowdown`` times further apart (the wire spacing inside a step is kept)."""
    from drivers import wire
    from simulator import firmware, scenario
    from simulator.engine import Simulation

    sim = Simulation(scenario.load(SCENARIO, {"duration_s": seconds}))
    fw = firmware.Firmware(sim.robot)
    out = []
    while sim.k < sim.n_steps:
        r = sim.step()
        t0 = r.t_ns * 1e-9 * slowdown
        busy: dict[str, float] = {}
        for bus, msg in fw.frames(r):
            if pacing == "wire":                        # a frame is whole when its last bit is on the wire
                busy[bus] = busy.get(bus, 0.0) + wire.frame_time_s(msg.dlc)
                out.append((t0 + busy[bus], bus, msg))
            else:
                out.append((t0, bus, msg))
    out.sort(key=lambda x: x[0])                         # stable: a step's order per bus is kept
    return sim, fw, out


def _sender_priority() -> str:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
        return "SCHED_FIFO 10"
    except (OSError, AttributeError):
        return "default priority (real-time not allowed)"


def role_sender(a) -> int:
    from simulator import firmware

    _set_timer_slack()
    prio = _sender_priority()
    chans = json.loads(a.channels)                       # bus -> group (multicast) or port (loopback)
    if a.source == "firmware":
        from simulator import scenario
        from simulator.engine import Simulation

        sim = Simulation(scenario.load(SCENARIO, {"duration_s": a.seconds}))
        fw, sched = firmware.Firmware(sim.robot), None
    else:
        sim, fw, sched = _frames_schedule(a.seconds, a.pacing, a.slowdown)
    with contextlib.ExitStack() as stack:
        buses = None
        if a.transport == "multicast":
            buses = stack.enter_context(firmware.open_buses(sim.robot, "udp_multicast", chans))
            senders = {b: (lambda m, bus=bus: bus.send(m, timeout=firmware.SEND_TIMEOUT_S)) for b, bus in buses.items()}
        else:
            from can.interfaces.udp_multicast.utils import pack_message

            sock = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
            senders = {b: (lambda m, port=int(p): sock.sendto(pack_message(m), ("127.0.0.1", port)))
                       for b, p in chans.items()}
        _say({"ready": True, "priority": prio})
        _wait_for("go")
        start_wall = time.time_ns()
        late: list[float] = []
        sent = 0
        if sched is None:
            if buses is None:
                raise SystemExit("--source firmware needs --transport multicast")
            firmware.run_on_buses(sim, buses, firmware=fw, realtime=True)
            sent = sum(fw.frames_sent.values())
        else:
            t0 = time.perf_counter() + 0.01
            step_t = None
            for off, bus, msg in sched:
                d = t0 + off - time.perf_counter()
                if d > 0:
                    time.sleep(d)
                elif off != step_t:
                    late.append(-d)
                step_t = off
                msg.timestamp = time.time()
                senders[bus](msg)
                sent += 1
        wall = (time.time_ns() - start_wall) * 1e-9
        late_us = sorted(x * 1e6 for x in late) or [0.0]
        _say({"sent": sent, "start_ns": start_wall, "wall_s": wall, "late_sends": len(late),
              "late_p99_us": late_us[int(0.99 * (len(late_us) - 1))], "late_max_us": late_us[-1]})
    return 0


# --- gateway ------------------------------------------------------------------------------------

def _open_buses(names, transport):
    import can

    from drivers.wire import udp_port

    buses = {}
    for i, name in enumerate(names):
        if transport == "multicast":
            bus = can.Bus(interface="udp_multicast", channel=GROUP_BASE + str(i + 1), port=udp_port(i),
                          ignore_config=True)
            sock = getattr(getattr(bus, "_multicast", None), "_socket", None)
            if sock is not None:
                _big_rcvbuf(sock)
        else:
            bus = _loopback_bus_class()(channel=f"lo-{name}")
        buses[name] = bus
    return buses


def role_gateway(a) -> int:
    import zenoh

    from drivers.wire import WireMap
    from gateway.bridge import GatewayService, Probe
    from gateway.config import GatewayConfig
    from gateway.commands.gateway import freeze_heap
    from gateway.zenoh_config import make_config

    if a.switch_interval:
        sys.setswitchinterval(a.switch_interval)
    if a.nice:
        os.nice(a.nice)                                   # before any thread starts: they inherit it
    robot, layout = _robot()
    tn = time.time_ns
    wakes: dict[int, int] = {}
    frames: list[tuple[int, int, int, int]] = []         # arrival, received, pipeline starts, fed
    efforts: list[tuple] = []                            # key, t_ns, then the stamps named below
    cur = [0, 0, 0]
    pauses = _Pauses()
    with contextlib.ExitStack() as stack:
        buses = _open_buses(list(WireMap.from_robot(robot).buses), a.transport)
        for bus in buses.values():
            stack.callback(bus.shutdown)
        conf = make_config(connect=[a.endpoint]) if a.router else make_config(listen=[a.endpoint])
        session = stack.enter_context(zenoh.open(conf))
        config = GatewayConfig().updated(service={"estimate": not a.no_estimate, "publish_samples": not a.no_samples},
                                         can={"receive": a.receive})
        gw = GatewayService(robot, buses, session, config, layout=layout)
        from gateway import keys as _keys
        from gateway.engine import Sink

        effort_keys = ([_keys.joint_efforts(robot.name, a.name) for a in robot.arms]
                       + [_keys.thruster_effort(robot.name)])
        batch_wake: dict[int, int] = {}                   # arrival ns -> received, this batch
        emitted: list = []                                # (rows' t_ns, their completing frames' stamps, t)

        class Before(Sink):                               # probes around the gateway's own sinks
            rows = True

            def effort_rows(self, ses, rows, log_ns):
                emitted.append((rows["t_ns"].tolist(), log_ns.tolist(), tn()))

        class After(Sink):
            rows = True

            def effort_rows(self, ses, rows, log_ns):
                t = tn()
                t_rows, arrs, t0 = emitted.pop()
                for t_ns, arr in zip(t_rows, arrs):
                    for key in effort_keys:
                        if a.bare:
                            efforts.append((key, t_ns, arr, t0, t))
                        else:
                            efforts.append((key, t_ns, arr, batch_wake.get(arr, 0), cur[2], t0, t))

        gw.engine.add_sink(Before(), first=True)
        gw.engine.add_sink(After())
        if a.bare:
            names = ["frame arrival", "effort emitted", "put returned"]
        else:
            names = ["frame arrival", "received by a gateway thread", "pipeline starts on it", "effort emitted",
                     "put returned"]

        class Ticks(Probe):                               # the gateway's own hooks: nothing replaced
            def ticked(self, start, end):
                ticks.append((start, end - start, -1))

        class Timing(Ticks):
            def received(self, bus, stamps):
                t = tn()
                for arr in stamps:
                    wakes[arr] = t

            def feeding(self, stamps):
                t = cur[2] = tn()
                batch_wake.clear()
                for arr in stamps:
                    batch_wake[arr] = wakes.pop(arr, t)

            def fed(self, stamps):
                t, end = cur[2], tn()
                for arr in stamps:                        # the worker's time, shared by the batch
                    frames.append((arr, batch_wake.get(arr, t), t, t + (end - t) // len(stamps)))

        ticks: list[tuple[int, int, int]] = []
        gw.probe = Ticks() if a.bare else Timing()
        stop = threading.Event()
        drain: dict = {}
        freeze_heap()                                     # as bsc gateway does before it runs
        with gw:
            tids = gw.thread_ids()
            _say({"ready": True, "ports": {n: getattr(b, "port", None) for n, b in buses.items()}, "tids": {
                "python main (health)": [threading.get_native_id()], "python worker": tids["worker"],
                "python notifiers": tids["notifiers"]}})

            def wait_stop():
                _wait_for("stop")
                t = time.monotonic()                      # the backlog left when the frames stopped
                drain["backlog_frames"] = gw.backlog
                drain["ok"] = gw.drain(120.0)
                drain["s"] = time.monotonic() - t
                drain["tasks"] = _tasks(os.getpid())      # CPU of every thread once every frame is through
                stop.set()
            threading.Thread(target=wait_stop, daemon=True).start()
            gw.run(stop)
            dump = {"frames": frames, "efforts": efforts, "stamp_names": names, "stats": dict(gw.engine.stats),
                    "published": gw.published, "publish_errors": gw.publish_errors,
                    "service": dict(getattr(gw, "stats", {}) or {}), "drain": drain,
                    "pauses": pauses.items + ticks, "switch_interval_s": sys.getswitchinterval(),
                    "receive": gw.receive}
        Path(a.out).write_bytes(pickle.dumps(dump))
    _say({"done": True})
    return 0


def role_estimator(a) -> int:
    """The split topology's second process: samples from zenoh -> EstimatorCore -> efforts on zenoh."""
    import zenoh

    from gateway import codec, keys
    from gateway.estimator.core import EstimatorCore, sample_rows
    from gateway.zenoh_config import make_config

    if a.switch_interval:
        sys.setswitchinterval(a.switch_interval)
    if a.nice:
        os.nice(a.nice)
    robot, layout = _robot()
    name = robot.name
    tn = time.time_ns
    efforts: list[tuple] = []
    cur = [0, 0]
    pubs: dict = {}
    lock = threading.Lock()
    pauses = _Pauses()
    with zenoh.open(make_config(connect=[a.endpoint], listen=[a.listen])) as session:
        def out(effort):
            key = keys.for_sample(name, effort)
            t = tn()
            pub = pubs.get(key)
            if pub is None:
                pub = pubs[key] = session.declare_publisher(key)
            pub.put(codec.encode(effort), attachment=str(tn()).encode())
            efforts.append((key, effort.t_ns, cur[0], cur[1], t, tn()))

        est = EstimatorCore(robot, layout=layout)

        def on_sample(s):
            t = tn()
            try:
                obj = codec.decode(s.payload.to_bytes())
            except codec.CodecError:
                return
            with lock:
                cur[0], cur[1] = obj.t_ns, t
                rows = est.feed(sample_rows([obj], est.joint_index, est.arm_index))
                if len(rows):
                    for effort in est.efforts(rows):
                        out(effort)

        sub = session.declare_subscriber(keys.sensors(name), on_sample)
        time.sleep(0.3)                                   # the subscription reaches the gateway
        _say({"ready": True, "tids": {"python main": [threading.get_native_id()]}})
        _wait_for("stop")
        sub.undeclare()
        with lock:
            dump = {"efforts": list(efforts), "pauses": pauses.items,
                    "stamp_names": ["frame arrival", "estimator process has the sample", "effort emitted",
                                    "put returned"],
                    "stats": {"epochs": est.epochs, "good_epochs": est.good, "late_samples": est.late}}
    Path(a.out).write_bytes(pickle.dumps(dump))
    _say({"done": True})
    return 0


def role_subscriber(a) -> int:
    import zenoh

    from gateway import codec, keys
    from gateway.zenoh_config import make_config

    tn = time.time_ns
    rx = []

    def on_sample(s):
        t = tn()
        att = s.attachment
        rx.append((t, str(s.key_expr), s.payload.to_bytes(), att.to_bytes() if att is not None else b""))

    robot, _ = _robot()
    key = keys.everything(robot.name) if a.subscribe == "all" else keys.efforts(robot.name)
    with zenoh.open(make_config(mode="client" if a.router else "peer", connect=[a.endpoint])) as session:
        sub = session.declare_subscriber(key, on_sample)
        time.sleep(0.3)                                   # the subscription reaches the publisher
        _say({"ready": True})
        _wait_for("stop")
        sub.undeclare()
    out = []
    for t, k, payload, att in list(rx):
        if "/efforts/" in k:
            obj = codec.decode(payload)
            out.append((k, obj.t_ns, t, int(att) if att else 0, bool(obj.good)))
    Path(a.out).write_bytes(pickle.dumps({"rx": out, "samples_received": len(rx)}))
    _say({"done": True})
    return 0


def role_router(a) -> int:
    import zenoh

    from gateway.zenoh_config import make_config

    with zenoh.open(make_config(mode="router", listen=[a.endpoint])):
        _say({"ready": True})
        _wait_for("stop")
    _say({"done": True})
    return 0


ROLES = {"sender": role_sender, "gateway": role_gateway, "estimator": role_estimator,
         "subscriber": role_subscriber, "router": role_router}


# --- the parent ---------------------------------------------------------------------------------

def _ip(*args):
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)


@contextlib.contextmanager
def private_netns():
    """A private network namespace with multicast on its loopback (as tests/simulator/firmware/test_firmware_udp.py);
    yields its name, or None when one cannot be made (not root, no iproute2)."""
    if shutil.which("ip") is None or os.geteuid() != 0:
        yield None
        return
    name = f"bsc-lat-{uuid.uuid4().hex[:8]}"
    if _ip("netns", "add", name).returncode != 0:
        yield None
        return
    try:
        for cmd in (("link", "set", "lo", "up"), ("link", "set", "lo", "multicast", "on"),
                    ("route", "replace", "224.0.0.0/4", "dev", "lo")):
            r = _ip("netns", "exec", name, "ip", *cmd)
            if r.returncode != 0:
                raise RuntimeError(f"ip {' '.join(cmd)} in {name}: {r.stderr.strip()}")
        yield name
    finally:
        _ip("netns", "delete", name)


class _Child:
    def __init__(self, role: str, prefix: list[str], args: list[str], env: dict):
        self.role = role
        self.p = subprocess.Popen([*prefix, sys.executable, "-m", "benchmarks.bench_latency", "--role", role, *args],
                                  cwd=ROOT, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True)

    def read(self, timeout: float = 120.0) -> dict:
        r, _, _ = select.select([self.p.stdout], [], [], timeout)
        line = self.p.stdout.readline() if r else ""
        if not line:
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.p.wait(5 if r else 0.1)
            state = f"exited ({self.p.returncode})" if self.p.poll() is not None else "timed out"
            self.p.kill()
            raise RuntimeError(f"{self.role} process {state}; stderr: {self.p.stderr.read()[-3000:]}")
        return json.loads(line)

    def tell(self, word: str) -> None:
        self.p.stdin.write(word + "\n")
        self.p.stdin.flush()

    def kill(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
        self.p.wait()


def _tasks(pid: int) -> dict[int, tuple[str, int]]:
    """tid -> (thread name, CPU clock ticks) of every thread of ``pid``."""
    out = {}
    with contextlib.suppress(OSError):
        for tid in os.listdir(f"/proc/{pid}/task"):
            with contextlib.suppress(OSError, ValueError, IndexError):
                raw = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
                comm = raw[raw.index("(") + 1:raw.rindex(")")]
                f = raw[raw.rindex(")") + 2:].split()
                out[int(tid)] = (comm, int(f[11]) + int(f[12]))
    return out


def _thread_cores(before: dict, after: dict, wall_s: float, named: dict[int, str]) -> dict[str, float]:
    """Cores used per thread group over the window: the named Python threads, the rest by name."""
    tick = os.sysconf("SC_CLK_TCK")
    groups: dict[str, float] = {}
    for tid, (comm, t1) in after.items():
        g = named.get(tid) or comm
        groups[g] = groups.get(g, 0.0) + (t1 - before.get(tid, (comm, 0))[1]) / tick / wall_s
    return {k: round(v, 3) for k, v in sorted(groups.items(), key=lambda kv: -kv[1]) if v >= 0.005}


def _tree() -> dict:
    """The commit measured and the files modified in the working tree (figures depend on them)."""
    def git(*args):
        with contextlib.suppress(Exception):
            r = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=10)
            return r.stdout.rstrip() if r.returncode == 0 else None
    status = git("status", "--porcelain", "--untracked-files=no") or ""
    return {"commit": (git("rev-parse", "--short", "HEAD") or "unknown"),
            "modified": sorted(line[3:] for line in status.splitlines() if line.strip())}


def _host_cpu():
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    return sum(v), v[3] + v[4]          # total, idle + iowait


def measure(seconds: float = 10.0, *, pacing: str = "burst", subscribe: str = "efforts", transport: str = "auto",
            topology: str = "one", router: bool = False, source: str = "pregen", bare: bool = False,
            switch_interval: float = 0.0, nice: int = 0, slowdown: float = 1.0, samples: bool = True,
            receive: str = "auto", progress=None) -> dict:
    """Run the processes for ``WARMUP_S + seconds`` of frames; return the raw records and context."""
    say = progress or (lambda s: None)
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", PYTHONDONTWRITEBYTECODE="1",
               PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    split = topology == "split"
    with contextlib.ExitStack() as stack:
        ns = None
        if transport in ("auto", "multicast"):
            ns = stack.enter_context(private_netns())
            if ns is None and transport == "multicast":
                raise RuntimeError("--transport multicast needs a private network namespace (root and iproute2)")
        transport = "multicast" if ns else "loopback"
        prefix = ["ip", "netns", "exec", ns] if ns else []
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bsc-lat-")))
        ep, ep2 = (("tcp/127.0.0.1:7447", "tcp/127.0.0.1:7448") if ns else
                   (f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"))
        children: dict[str, _Child] = {}

        def start(role, *args):
            children[role] = _Child(role, prefix, list(args), env)
            return children[role]

        si = ((["--switch-interval", str(switch_interval)] if switch_interval else [])
              + (["--nice", str(nice)] if nice else []))
        total = WARMUP_S + seconds
        try:
            if router:
                start("router", "--endpoint", ep).read()
            gw = start("gateway", "--endpoint", ep, "--transport", transport, "--out", str(tmp / "gateway.pickle"),
                       *["--bare"] * bare, *["--router"] * router, *["--no-estimate"] * split,
                       *["--no-samples"] * (not samples), "--receive", receive, *si)
            ready = gw.read()
            if split:
                est = start("estimator", "--endpoint", ep, "--listen", ep2, "--out", str(tmp / "estimator.pickle"), *si)
                est_ready = est.read()
            sub = start("subscriber", "--endpoint", ep2 if split else ep, "--subscribe", subscribe,
                        "--out", str(tmp / "subscriber.pickle"), *["--router"] * router)
            from drivers.wire import WireMap

            names = list(WireMap.from_robot(_robot()[0]).buses)
            chans = ({b: GROUP_BASE + str(i + 1) for i, b in enumerate(names)} if transport == "multicast"
                     else ready["ports"])
            tx = start("sender", "--seconds", str(total), "--pacing", pacing, "--source", source,
                       "--transport", transport, "--channels", json.dumps(chans), "--slowdown", str(slowdown))
            sub.read()
            sender_ready = tx.read(300)
            say(f"sending {total * slowdown:.0f} s of frames ({transport}, {pacing} pacing, {topology} process"
                f"{'es' if split else ''})")
            named = {tid: g for g, tids in ready["tids"].items() for tid in tids if tid}
            if split:
                named_est = {tid: g for g, tids in est_ready["tids"].items() for tid in tids}
            pids = {r: c.p.pid for r, c in children.items()}
            load0, cpu0, w0 = os.getloadavg(), _host_cpu(), time.monotonic()
            tasks0 = {r: _tasks(p) for r, p in pids.items()}
            tx.tell("go")
            sent = tx.read(total * slowdown + 120)
            tasks1 = {r: _tasks(p) for r, p in pids.items()}
            load1, cpu1, wall = os.getloadavg(), _host_cpu(), time.monotonic() - w0
            gw.tell("stop")                                  # the gateway drains its queue first
            gw.read(300)
            time.sleep(0.5)                                  # the last efforts reach the subscriber
            for role in ("estimator", "subscriber", "router"):
                if role in children:
                    children[role].tell("stop")
                    children[role].read(120)
            for c in children.values():
                c.p.wait(60)
        finally:
            for c in children.values():
                c.kill()
        dumps = {r: pickle.loads((tmp / f"{r}.pickle").read_bytes())
                 for r in ("gateway", "estimator", "subscriber") if (tmp / f"{r}.pickle").exists()}
    busy = 1.0 - (cpu1[1] - cpu0[1]) / max(1, cpu1[0] - cpu0[0])
    cores = {r: _thread_cores(tasks0[r], tasks1[r], wall,
                              named if r == "gateway" else named_est if r == "estimator" else {}) for r in pids}
    return {**dumps, "sender": sent, "cores": cores, "gateway_tasks0": tasks0["gateway"], "gateway_named": named,
            "config": {"seconds": seconds, "warmup_s": WARMUP_S, "pacing": pacing, "subscribe": subscribe,
                       "transport": transport, "topology": topology, "router": router, "source": source,
                       "bare": bare, "switch_interval_s": dumps["gateway"]["switch_interval_s"],
                       "receive": dumps["gateway"].get("receive"),
                       "slowdown": slowdown, "gateway_nice": nice, "zenoh": ep, "cpus": os.cpu_count(),
                       "sender_priority": sender_ready.get("priority"), "tree": _tree()},
            "load": {"before": [round(x, 2) for x in load0], "after": [round(x, 2) for x in load1],
                     "host_cpu_busy": round(busy, 3)}}


def _pct(x, qs=(50, 90, 99, 99.9)):
    import numpy as np

    x = np.asarray(x, dtype=float)
    if x.size == 0:
        return {"count": 0}
    out = {f"p{q:g}": float(np.percentile(x, q)) for q in qs}
    out.update(max=float(x.max()), mean=float(x.mean()), count=int(x.size))
    return out


def analyse(raw: dict) -> dict:
    import numpy as np

    cfg, tx = raw["config"], raw["sender"]
    g, s = raw["gateway"], raw["subscriber"]
    src = raw.get("estimator", g)                     # whoever emitted the efforts
    t_start = tx["start_ns"] + int(WARMUP_S * cfg["slowdown"] * 1e9)
    t_end = tx["start_ns"] + int(tx["wall_s"] * 1e9)
    rx = {(k, t): (trecv, good) for k, t, trecv, _pub, good in s["rx"]}
    names = src["stamp_names"]
    rows, keys_, lost, good, early = [], [], 0, 0, 0
    for key, t_ns, *stamps in src["efforts"]:
        if not (t_start <= stamps[0] <= t_end):
            early += stamps[0] < t_start
            continue
        hit = rx.get((key, t_ns))
        if hit is None:
            lost += 1
            continue
        good += hit[1]
        rows.append((*stamps, hit[0]))
        keys_.append(key.rsplit("/", 1)[-1])
    if not rows:
        raise RuntimeError("no effort matched between the gateway and the subscriber")
    a = np.array(rows, dtype=np.int64)
    e2e = (a[:, -1] - a[:, 0]) / 1e3
    res: dict = {"end_to_end_us": _pct(e2e)}
    k_arr = np.array(keys_)
    res["by_key_us"] = {k: _pct(e2e[k_arr == k], (50, 99)) for k in sorted(set(keys_))}
    sec = (a[:, 0] - t_start) // 1_000_000_000
    per_s = [float(np.percentile(e2e[sec == k], 50)) for k in np.unique(sec) if (sec == k).sum() >= 50]
    res["p50_per_second_us"] = [round(x) for x in per_s]
    stages = {}
    full = [*names, "subscriber callback"]
    for i in range(len(full) - 1):
        d = a[:, i + 1] - a[:, i]
        if a[:, i].all() and a[:, i + 1].all():
            stages[f"{full[i]} -> {full[i + 1]}"] = _pct(d / 1e3)
    ie = names.index("effort emitted")
    stages["effort emitted -> subscriber callback (codec, zenoh hop)"] = _pct((a[:, -1] - a[:, ie]) / 1e3)
    res["stages_us"] = stages
    fr = np.array(g["frames"], dtype=np.int64).reshape(-1, 4)
    fr = fr[(fr[:, 0] >= t_start) & (fr[:, 0] <= t_end)]
    if len(fr):
        f_arr, f_wake, f_deq, f_done = fr.T
        span = (t_end - t_start) * 1e-9
        res["frames"] = {
            "count": int(len(fr)), "rate_per_s": round(len(fr) / span),
            "arrival -> received us": _pct((f_wake - f_arr) / 1e3, (50, 99)),
            "queue wait us": _pct((f_deq - f_wake) / 1e3, (50, 99)),
            "worker wall time per frame us": _pct((f_done - f_deq) / 1e3, (50, 99)),
            # wall time the worker spent on the frames of one second (> 1: it cannot keep up)
            "worker s per s of frames": round(float((f_done - f_deq).sum()) * 1e-9 / span, 3)}
    res["efforts"] = {"measured": len(rows), "lost": lost, "good": good, "pipeline": g["stats"],
                      "published": g["published"], "publish_errors": g["publish_errors"]}
    if "estimator" in raw:
        res["efforts"]["estimator"] = raw["estimator"]["stats"]
    res["cores"] = {r: {"total": round(sum(v.values()), 3), **v} for r, v in raw["cores"].items()}
    res["sender"] = {k: tx[k] for k in ("sent", "late_sends", "late_p99_us", "late_max_us")}
    drain = dict(g.get("drain", {}))
    tasks1 = drain.pop("tasks", None)
    res["drain"] = drain
    if tasks1 and raw.get("gateway_tasks0") is not None:
        # CPU the gateway's Python threads spent on all the frames (sending + drain), per frame and
        # per second of nominal traffic: one interpreter (one GIL) can give at most 1 core-second
        tick = os.sysconf("SC_CLK_TCK")
        t0 = {int(k): v for k, v in raw["gateway_tasks0"].items()}
        named = {int(k): v for k, v in raw["gateway_named"].items()}
        py = {}
        for tid, (comm, t) in tasks1.items():
            grp = named.get(int(tid))
            if grp:
                py[grp] = py.get(grp, 0.0) + (t - t0.get(int(tid), (comm, 0))[1]) / tick
        n = max(1, g["stats"]["frames"])
        rate = tx["sent"] / tx["wall_s"] * cfg["slowdown"]            # frames per second at the nominal rate
        res["python_work"] = {"frames": n, "cpu_s": {k: round(v, 2) for k, v in py.items()},
                              "us_per_frame": round(sum(py.values()) / n * 1e6, 1),
                              "core_s_per_s_at_nominal": round(sum(py.values()) / n * rate, 3)}
    svc = g.get("service") or {}
    res["service"] = {k: svc[k] for k in ("received", "processed", "dropped", "peak_backlog", "max_backlog",
                                          "overflow_episodes") if k in svc}
    pz: dict = {}
    for role in ("gateway", "estimator"):
        for start, dur, gen in raw.get(role, {}).get("pauses", []):
            if t_start <= start <= t_end:
                name = f"{role} " + ("health tick" if gen < 0 else f"gc gen{gen}")
                n, tot, mx = pz.get(name, (0, 0.0, 0.0))
                pz[name] = (n + 1, tot + dur / 1e3, max(mx, dur / 1e3))
    res["pauses_us"] = {k: {"count": n, "mean": round(t / n, 1), "max": round(m, 1)}
                        for k, (n, t, m) in sorted(pz.items())}
    p = res["end_to_end_us"]
    res["saturated"] = bool(res["service"].get("dropped") or (
        len(per_s) >= 3 and per_s[-1] > 2 * TARGET_P99_US and per_s[-1] > 3 * per_s[0]))
    res["target"] = {"p50_us": TARGET_P50_US, "p99_us": TARGET_P99_US,
                     "p50_ok": p["p50"] <= TARGET_P50_US, "p99_ok": p["p99"] <= TARGET_P99_US}
    res["target"]["met"] = res["target"]["p50_ok"] and res["target"]["p99_ok"] and cfg["slowdown"] == 1
    res["config"], res["load"] = cfg, raw["load"]
    return res


def report(res: dict) -> str:
    c, ld, p = res["config"], res["load"], res["end_to_end_us"]
    out = [f"gateway end-to-end latency: {c['topology']} process{'es' if c['topology'] == 'split' else ''}, "
           f"{c['transport']} CAN, {c['pacing']} pacing, source {c['source']}, subscriber on {c['subscribe']}"
           f"{', via a zenoh router' if c['router'] else ''}, receive {c.get('receive')}; "
           f"{c['seconds']:g} s measured after {c['warmup_s']:g} s "
           f"warm-up; {c['cpus']} cores",
           f"load average before {ld['before']}, after {ld['after']}; host CPU busy {100 * ld['host_cpu_busy']:.0f} %",
           f"tree: commit {c['tree']['commit']}" + (f", modified {', '.join(c['tree']['modified'])}"
                                                    if c['tree']['modified'] else ", clean"),
           "", "last frame arrival -> subscriber callback (us):",
           "  " + "  ".join(f"{k} {p[k]:.0f}" for k in ("p50", "p90", "p99", "p99.9", "max")) + f"  count {p['count']}",
           "  per key: " + ", ".join(f"{k} p50 {v['p50']:.0f} p99 {v['p99']:.0f}" for k, v in res["by_key_us"].items()),
           f"  p50 per measured second: {res['p50_per_second_us']}",
           "", f"{'stages of the completing frame (us)':<72} {'p50':>8} {'p90':>8} {'p99':>8} {'max':>9}"]
    for k, v in res["stages_us"].items():
        out.append(f"  {k:<70} {v['p50']:8.0f} {v['p90']:8.0f} {v['p99']:8.0f} {v['max']:9.0f}")
    fr = res.get("frames")
    if fr:
        out += ["", f"every frame ({fr['rate_per_s']} frames/s): arrival -> received p50 "
                f"{fr['arrival -> received us']['p50']:.0f} p99 {fr['arrival -> received us']['p99']:.0f} us; "
                f"queue wait p50 {fr['queue wait us']['p50']:.0f} p99 {fr['queue wait us']['p99']:.0f} us; "
                f"worker wall time per frame p50 {fr['worker wall time per frame us']['p50']:.0f} mean "
                f"{fr['worker wall time per frame us']['mean']:.0f} us; the worker spent "
                f"{fr['worker s per s of frames']:.2f} s on each second of frames"]
    e, tx, d = res["efforts"], res["sender"], res["drain"]
    out += [f"efforts measured {e['measured']}, lost {e['lost']}, good {e['good']}; pipeline {e['pipeline']}"
            + (f"; estimator {e['estimator']}" if "estimator" in e else ""),
            "CPU while sending (cores, per process and thread group):"]
    for role, v in res["cores"].items():
        out.append(f"  {role:<10} {v['total']:.2f}: " + ", ".join(f"{k} {x:.2f}" for k, x in v.items() if k != "total"))
    out.append(f"sender ({c['sender_priority']}): {tx['sent']} frames, {tx['late_sends']} sent late (p99 "
               f"{tx['late_p99_us']:.0f} us, max {tx['late_max_us']:.0f} us)")
    pw = res.get("python_work")
    if pw:
        out.append(f"Python (GIL) work in the gateway: {pw['us_per_frame']:.0f} us of CPU per frame ("
                   + ", ".join(f"{k} {v:.1f} s" for k, v in pw["cpu_s"].items()) + f" for {pw['frames']} frames) = "
                   f"{pw['core_s_per_s_at_nominal']:.2f} core-seconds per second at the nominal rate "
                   "(one interpreter: at most 1)")
    if res["pauses_us"]:
        out.append("pauses (us): " + "; ".join(f"{k} {v['count']}x mean {v['mean']:.0f} max {v['max']:.0f}"
                                               for k, v in res["pauses_us"].items()))
    out.append(f"gateway backlog when the frames stopped: {d.get('backlog_frames')} frames, drained in "
               f"{d.get('s', 0):.2f} s" + ("; " + ", ".join(f"{k} {v}" for k, v in res["service"].items())
                                          if res["service"] else ""))
    if res["saturated"]:
        out.append("SATURATED: the gateway did not keep up with the frame rate (its queue grew for the whole run "
                   "or overflowed): the figures measure a backlog, not a steady state")
    if c.get("gateway_nice"):
        out.append(f"experiment: gateway process at nice {c['gateway_nice']}")
    if c["switch_interval_s"] != 0.005:
        out.append(f"experiment: gateway switch interval {c['switch_interval_s'] * 1e3:g} ms")
    if c["slowdown"] != 1:
        out.append(f"NOT the nominal rate: frames sent {c['slowdown']:g}x slower than real time (diagnostic)")
    t = res["target"]
    out += ["", f"target p50 <= {t['p50_us']:.0f} us: {'met' if t['p50_ok'] else 'MISSED'} ({p['p50']:.0f} us); "
            f"p99 <= {t['p99_us']:.0f} us: {'met' if t['p99_ok'] else 'MISSED'} ({p['p99']:.0f} us)"]
    return "\n".join(out)


def figures(quick: bool = False) -> list[dict]:
    """Headline rows for ``python -m benchmarks`` (quick: 4 s measured, 12-15 s in all)."""
    res = analyse(measure(QUICK_SECONDS if quick else 10.0))      # a failure raises: the suite reports it
    p, c, ld = res["end_to_end_us"], res["config"], res["load"]
    note = (f"{c['transport']} CAN, {c['pacing']} pacing, {p['count']} efforts, load {ld['before'][0]:.1f}"
            + (", gateway saturated" if res["saturated"] else ""))
    rows = [
        {"name": "end-to-end latency p50", "value": p["p50"], "unit": "us", "target": "<= 300",
         "ok": p["p50"] <= TARGET_P50_US, "note": note},
        {"name": "end-to-end latency p99", "value": p["p99"], "unit": "us", "target": "<= 1000",
         "ok": p["p99"] <= TARGET_P99_US, "note": note},
        {"name": "end-to-end latency p99.9", "value": p["p99.9"], "unit": "us", "target": None, "ok": None},
        {"name": "end-to-end latency max", "value": p["max"], "unit": "us", "target": None, "ok": None},
    ]
    st = res["stages_us"]
    compute = "pipeline starts on it -> effort emitted"
    if compute in st:
        rows.append({"name": "completing frame into the pipeline -> efforts emitted p50 (drivers + estimator epoch)",
                     "value": st[compute]["p50"], "unit": "us", "target": None, "ok": None})
    hop = "effort emitted -> subscriber callback (codec, zenoh hop)"
    rows.append({"name": "effort emitted -> subscriber callback p50 (zenoh hop)", "value": st[hop]["p50"],
                 "unit": "us", "target": None, "ok": None})
    pw = res.get("python_work")
    if pw:
        rows.append({"name": "gateway Python (one GIL) work at the nominal frame rate",
                     "value": pw["core_s_per_s_at_nominal"], "unit": "core-s/s", "target": None, "ok": None,
                     "note": f"{pw['us_per_frame']:.0f} us CPU per frame; above 1 one process cannot keep up"})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_latency", description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="measured seconds, after 1 s of warm-up (default 10)")
    ap.add_argument("--json", action="store_true", help="print the result as JSON")
    ap.add_argument("--pacing", choices=("burst", "wire"), default="burst",
                    help="a step's frames back to back (default, as the firmware's real-time mode) or at CAN wire time")
    ap.add_argument("--subscribe", choices=("efforts", "all"), default="efforts",
                    help="what the subscriber takes: the efforts (default) or everything, like a recorder")
    ap.add_argument("--topology", choices=("one", "split"), default="one",
                    help="one gateway process (default, as bsc gateway) or drivers and estimator in two processes")
    ap.add_argument("--transport", choices=("auto", "multicast", "loopback"), default="auto",
                    help="CAN transport: udp_multicast in a private netns (auto when root) or loopback UDP")
    ap.add_argument("--source", choices=("pregen", "firmware"), default="pregen",
                    help="pre-generated frames (default) or the simulator running live")
    ap.add_argument("--router", action="store_true", help="gateway and subscriber meet at a zenoh router process")
    ap.add_argument("--bare", action="store_true", help="only the emit wrapper in the gateway (no per-frame stages)")
    ap.add_argument("--receive", choices=("auto", "threads"), default="auto",
                    help="the gateway's receive mode (GatewayService receive=; auto: direct on these buses)")
    ap.add_argument("--no-samples", action="store_true",
                    help="the gateway publishes efforts and health only, not every decoded sample "
                         "(bsc gateway --no-samples)")
    ap.add_argument("--slowdown", type=float, default=1.0, metavar="K",
                    help="diagnostic: send the frames K times slower than real time (not the nominal rate)")
    ap.add_argument("--switch-interval", type=float, default=0.0, metavar="S",
                    help="experiment: sys.setswitchinterval(S) in the gateway process (Python's default 5 ms)")
    ap.add_argument("--nice", type=int, default=0, metavar="N",
                    help="experiment: the gateway (and estimator) process at nice N, e.g. -10 (root for N < 0)")
    # the children (internal)
    ap.add_argument("--role", choices=tuple(ROLES), help=argparse.SUPPRESS)
    ap.add_argument("--endpoint", help=argparse.SUPPRESS)
    ap.add_argument("--listen", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    ap.add_argument("--channels", help=argparse.SUPPRESS)
    ap.add_argument("--no-estimate", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.role:
        return ROLES[a.role](a)
    if a.topology == "split" and (a.router or a.bare):
        ap.error("--topology split takes neither --router nor --bare")
    if a.source == "firmware" and (a.slowdown != 1 or a.pacing != "burst"):
        ap.error("--source firmware sends as run_on_buses(realtime=True) does: no --slowdown, no --pacing wire")
    res = analyse(measure(a.seconds, pacing=a.pacing, subscribe=a.subscribe, transport=a.transport,
                          topology=a.topology, router=a.router, source=a.source, bare=a.bare,
                          switch_interval=a.switch_interval, nice=a.nice, slowdown=a.slowdown,
                          samples=not a.no_samples, receive=a.receive,
                          progress=None if a.json else (lambda s: print(s, file=sys.stderr, flush=True))))
    print(json.dumps(res, indent=1) if a.json else report(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
