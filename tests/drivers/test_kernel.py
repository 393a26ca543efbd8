"""drivers.kernel.DriverCore against the Python drivers it replaces: the same frames into both
(the Python side as gateway.pipeline.Pipeline runs it: one BusDispatcher per bus), then the same
sample objects in the same order (== and repr, so float bits and bool/int types too), the same
health snapshots at several points, the same bus time to the last bit. Traffic: the simulator's
firmware clean and with every fault knob, the fuzzer's valid/mutated/random frames (with and
without clock jumps), long silences under the three SourceTiming modes. And the kernel's own
promise: any split of a batch gives the same events and the same state.
"""
from __future__ import annotations

import copy
import dataclasses
import random
import sys
from pathlib import Path

import can
import numpy as np
import pytest

ROOT = str(Path(__file__).resolve().parents[2])
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)       # benchmarks/ is not an installed package
from benchmarks import fuzz_drivers  # noqa: E402
from drivers import devices, kernel, wire  # noqa: E402
from drivers.health import DEFAULT_TIMING, SourceTiming  # noqa: E402

MS = 1_000_000


# --- the two sides -------------------------------------------------------------------------------

class Reference:
    """The Python drivers of every bus of a wire map, fed as Pipeline feeds them."""

    def __init__(self, wm: wire.WireMap, fd: bool, timing: SourceTiming):
        self.samples: list = []
        self.buses = []
        for spec in wm.buses.values():
            mon, drv = devices.listeners_for(spec, self.samples.append, fd, timing)
            self.buses.append((mon, drv, devices.BusDispatcher(mon, drv).feed))

    def feed(self, pairs) -> None:
        buses = self.buses
        for b, m in pairs:
            buses[b][2](m)

    def health(self, now_ns: int):
        return ([mon.health(now_ns) for mon, _, _ in self.buses],
                [h for _, drv, _ in self.buses for d in drv for h in d.health(now_ns)])

    def busy_s(self) -> list[float]:
        return [mon.counters.busy_s for mon, _, _ in self.buses]


def check_same(wm, pairs, fd=False, timing=DEFAULT_TIMING, pieces=4, probes=(0, 5 * MS, 2_000 * MS)):
    """Feed ``pairs`` to both sides in ``pieces`` calls; after each, the new samples and the health
    at the last frame's time plus each of ``probes`` must be identical. Returns (core, reference)."""
    ref, core = Reference(wm, fd, timing), kernel.DriverCore(wm, fd, timing)
    cols = kernel.columns_from_messages(pairs)
    cuts = np.linspace(0, len(pairs), pieces + 1).astype(int)
    for a, b in zip(cuts, cuts[1:]):
        n0 = len(ref.samples)
        ref.feed(pairs[a:b])
        events = core.feed(cols[a:b])
        got, want = core.to_samples(events), ref.samples[n0:]
        assert len(got) == len(want)
        assert got == want
        assert repr(got) == repr(want)              # float bits, bool vs int
        check_frame_index(events, cols[a:b])
        t_last = int(cols["t_ns"][b - 1]) if b > a else 0
        for dt in probes:
            assert core.health(t_last + dt) == ref.health(t_last + dt), f"health at +{dt} ns after frame {b}"
        assert core.state().bus["busy_s"][:-1].tolist() == ref.busy_s()
    return core, ref


def check_frame_index(events, cols) -> None:
    """``frame`` is the frame that completed the sample: one of the device's ids, and for a
    one-frame sample its timestamp."""
    ids = {kernel.WRENCH: {wire.FT_A_ID, wire.FT_B_ID}, kernel.IMU: set(range(0x400, 0x440)),
           kernel.THRUSTER: {0x180, 0x181, 0x182, 0x184}, kernel.VALVE: {wire.VALVE_CMD_ID}}
    for e in events:
        f = cols[e["frame"]]
        kind = int(e["kind"])
        if kind in ids:
            assert int(f["can_id"]) in ids[kind]
        elif kind == kernel.JOINT:
            assert wire.JOINT_STATE_BASE <= int(f["can_id"]) < wire.JOINT_STATE_BASE + wire.MAX_JOINTS
        else:
            assert wire.TORQUE_CMD_BASE <= int(f["can_id"]) < wire.TORQUE_CMD_BASE + 3
        if kind in (kernel.JOINT, kernel.TORQUE, kernel.VALVE):
            assert int(f["t_ns"]) == int(e["t_ns"])
        assert int(f["data"][0]) == int(e["counter"])


# --- traffic ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def readings():
    """Simulated readings of the two robots, 250 steps each (cycled, re-stamped, for longer runs)."""
    from simulator import scenario
    from simulator.engine import Simulation

    out = {}
    for robot, name in (("paper_robot", "capture"), ("three_arm", "three_arm")):
        sim = Simulation(scenario.load(name, {"duration_s": 0.25}))
        out[robot] = (sim.robot, [copy.deepcopy(sim.step()) for _ in range(sim.n_steps)])
    return out


def firmware_pairs(robot, readings, steps: int, fd: bool = False, faults=None, slow: float = 1.0):
    """(bus index, msg) of ``steps`` firmware steps (the readings cycled, step k stamped k ms);
    ``slow``: the receiver's stamps run that many times the simulated time (a slow source; the
    IMU's own time_us keeps the simulated time)."""
    from simulator import firmware

    fw = firmware.Firmware(robot, fd=fd, faults=faults)
    index = {name: b for b, name in enumerate(fw.wire.buses)}
    out = []
    for k in range(steps):
        r = dataclasses.replace(readings[k % len(readings)], t_ns=k * MS)
        out += fw.frames(r)
    out += fw.flush()
    if slow != 1.0:
        for _, m in out:
            m.timestamp = round(m.timestamp * 1e9 * slow) / 1e9
    return fw, [(index[b], m) for b, m in out]


def fuzz_pairs(wm: wire.WireMap, n: int, seed: int, clock_jumps: bool = False):
    """benchmarks/fuzz_drivers.py's campaign as (bus index, msg): valid, mutated and random
    frames, buses in turn. ``clock_jumps``: every frame restamped on a clock that mostly advances
    by a fraction of a period and sometimes jumps (beyond the resync limit, or backwards)."""
    r = random.Random(seed)
    kinds = [k for k, w in fuzz_drivers.MIX for _ in range(w)]
    specs = list(wm.buses.values())
    streams = [[fuzz_drivers.valid_stream(s, r), sorted(s.ids), 0] for s in specs]
    out, t = [], 10**12
    for i in range(n):
        b = i % len(specs)
        st = streams[b]
        kind = kinds[r.randrange(len(kinds))]
        if kind == "random":
            msg = fuzz_drivers.random_frame(r)
        else:
            msg = st[0][st[2]]
            st[2] = (st[2] + 1) % len(st[0])
            if kind == "mutated":
                for _ in range(r.choice((1, 1, 1, 2, 3))):
                    msg = fuzz_drivers._MUT[r.randrange(len(fuzz_drivers._MUT))][1](msg, r, st[1])
        if clock_jumps:
            u = r.random()
            t += (r.randrange(50_000, 400_000) if u < 0.99 else
                  r.choice((150 * MS, 300 * MS, 2_560 * MS, 10**10, -50 * MS)))
            msg = fuzz_drivers._copy(msg, timestamp=t / 1e9)
        out.append((b, msg))
    return out


def _wire(robot) -> wire.WireMap:
    return wire.WireMap.from_robot(robot)


def edge_map() -> wire.WireMap:
    """The widest and narrowest arms the contract allows (8 joints = 3 command frames; 1 joint)."""
    buses = {arm: wire.BusSpec(name=arm, kind="arm", arm=arm, joints=tuple(f"j{i}" for i in range(n)),
                               ids=wire.arm_ids(n))
             for arm, n in (("wide", wire.MAX_JOINTS), ("narrow", 1))}
    buses[wire.SPACECRAFT_BUS] = wire.BusSpec(name=wire.SPACECRAFT_BUS, kind="spacecraft", ids=wire.SPACECRAFT_IDS)
    return wire.WireMap(robot="edge_robot", buses=buses)


# --- firmware traffic ----------------------------------------------------------------------------

CASES = [("paper_robot", False), ("three_arm", False), ("three_arm", True)]


@pytest.mark.parametrize("robot,fd", CASES, ids=[f"{r}-{'fd' if f else 'classic'}" for r, f in CASES])
def test_clean_firmware_traffic(readings, robot, fd):
    rob, rs = readings[robot]
    _, pairs = firmware_pairs(rob, rs, 250, fd=fd)
    core, ref = check_same(_wire(rob), pairs, fd=fd)
    assert len(ref.samples) > 2000
    _, devs = core.health(250 * MS)
    assert all(h.lost == 0 and h.rejected == () and not h.stale for h in devs)


@pytest.mark.parametrize("robot,fd", CASES, ids=[f"{r}-{'fd' if f else 'classic'}" for r, f in CASES])
def test_firmware_traffic_with_faults(readings, robot, fd):
    from simulator import firmware

    rob, rs = readings[robot]
    arm = rob.arms[0].name
    joint = f"{rob.arms[-1].name}/{rob.arms[-1].joint_names[-1]}"
    faults = firmware.Faults(drop_rate=0.03, duplicate_rate=0.03, reorder_rate=0.03, corrupt_rate=0.03,
                             bad_dlc_rate=0.03, seed=11, from_s=0.02, until_s=0.55,
                             silent=((arm, 0.1, 0.05), ("imu", 0.3, 0.04), (joint, 0.4, 0.03)),
                             counter_jumps=((joint, 0.2, 5), ("thrusters", 0.35, 3), (arm, 0.45, 126)))
    fw, pairs = firmware_pairs(rob, rs, 600, fd=fd, faults=faults)
    core, ref = check_same(_wire(rob), pairs, fd=fd, pieces=6)
    _, devs = core.health(600 * MS)
    rejected = {k for h in devs for k, _ in h.rejected}
    assert rejected == {"late", "duplicate", "incomplete", "dlc"}          # not vacuous
    assert sum(h.lost for h in devs) > 150


def test_fd_frames_on_a_classic_core(readings):
    """FD traffic into drivers configured classic: every device frame is fd_on_classic."""
    rob, rs = readings["paper_robot"]
    _, pairs = firmware_pairs(rob, rs, 60, fd=True)
    core, ref = check_same(_wire(rob), pairs, fd=False, pieces=2)
    assert not ref.samples
    buses, devs = core.health(60 * MS)
    assert all(dict(h.rejected)["fd_on_classic"] > 0 for h in devs)
    assert all(dict(h.rejected)["fd_on_classic"] > 0 for h in buses)       # heartbeats


def test_through_the_pipeline(readings):
    """gateway.pipeline.Pipeline (estimate=False) emits what to_samples gives, and its health list
    is health_list's, object for object."""
    from gateway.pipeline import Pipeline

    rob, rs = readings["three_arm"]
    _, pairs = firmware_pairs(rob, rs, 120)
    emitted = []
    pipe = Pipeline(rob, emit=lambda key, obj: emitted.append(obj), estimate=False)
    core = kernel.DriverCore(pipe.wire)
    assert core.bus_names == tuple(pipe.buses)
    for b, m in pairs:
        pipe.feed(pipe.buses[b], m)
    assert core.to_samples(core.feed(kernel.columns_from_messages(pairs))) == emitted
    for now in (60 * MS, 119 * MS, 130 * MS, 10**10):
        assert core.health_list(now) == pipe.health(now)


# --- fuzzed frames -------------------------------------------------------------------------------

FUZZ = [("paper_robot", False, False), ("three_arm", True, False), ("edge_robot", False, False),
        ("edge_robot", True, True), ("paper_robot", False, True)]


@pytest.mark.parametrize("robot,fd,jumps", FUZZ, ids=[f"{r}-{'fd' if f else 'classic'}{'-jumps' if j else ''}"
                                                      for r, f, j in FUZZ])
def test_fuzzed_and_mutated_frames(robot, fd, jumps):
    wm = edge_map() if robot == "edge_robot" else fuzz_drivers.wire_map_for(robot)
    pairs = fuzz_pairs(wm, 15_000, seed=len(robot) * 7 + fd + 2 * jumps, clock_jumps=jumps)
    timings = [DEFAULT_TIMING, SourceTiming(rate=None), SourceTiming(rate=0.25)] if jumps else [DEFAULT_TIMING]
    for timing in timings:
        core, ref = check_same(wm, pairs, fd=fd, timing=timing, pieces=5)
        assert len(ref.samples) > 1000
        buses, devs = core.health(10**13)
        reasons = {k for h in buses + devs for k, _ in h.rejected}
        assert len(reasons) >= 8, reasons                  # nearly every rejection path is taken


# --- long silences, the three SourceTiming modes ---------------------------------------------

SILENCES = [(1.0, "rate 1"), (1.0, "unknown"), (3.0, "declared"), (3.0, "unknown"), (3.0, "rate 1")]


@pytest.mark.parametrize("slow,mode", SILENCES, ids=[f"slow{s:g}-{m}" for s, m in SILENCES])
def test_long_silences(readings, slow, mode):
    """Devices silent for 30..700 periods (beyond RESYNC_PERIODS and beyond the 8-bit counter's
    range) from a source at real time or 3x slower, the rate declared (1 or 1/slow) or unknown;
    health probed inside the silences (staleness) and after them."""
    from simulator import firmware

    rob, rs = readings["paper_robot"]
    faults = firmware.Faults(silent=(("arm0", 0.10, 0.03), ("arm0/j1", 0.15, 0.28), ("arm1", 0.20, 0.70),
                                     ("imu", 0.25, 0.60), ("valves", 0.30, 0.26), ("thrusters", 0.05, 1.30),
                                     ("arm1/torque_cmd", 0.40, 0.30)),
                             counter_jumps=(("arm0/j2", 0.9, 100),))
    _, pairs = firmware_pairs(rob, rs, 1600, faults=faults, slow=slow)
    rate = {"rate 1": 1.0, "declared": 1 / slow, "unknown": None}[mode]
    timing = SourceTiming(rate=rate)
    core, ref = check_same(_wire(rob), pairs, timing=timing, pieces=8, probes=(0, 20 * MS, 400 * MS))
    _, devs = core.health(round(1600 * MS * slow))
    lost = {h.device: (h.lost, h.lost_at_least) for h in devs}
    if rate == 1 / slow:                    # the rate is known and right: every silence exact
        assert lost["arm1"] == (700, False) and lost["imu"] == (300, False) and lost["arm0/j1"] == (280, False)
    if rate is None:
        assert lost["imu"] == (300, False)     # the IMU's own clock
        assert lost["arm1"][1] is True          # a lower bound, and said so


def test_resync_by_device_clock_and_staleness_knob():
    """Hand-made IMU traffic: silences of 1..1000 periods read from time_us whatever the stamps say;
    a time_us behind the last one is a late sample; stale_periods is followed."""
    from drivers import frames
    from drivers.samples import ImuSample

    wm = fuzz_drivers.wire_map_for("paper_robot")
    sc = list(wm.buses).index(wire.SPACECRAFT_BUS)
    pairs, k, t = [], 0, 0
    rnd = random.Random(4)
    for outage in (0, 1, 127, 128, 255, 256, 257, 1000, 0, 0):
        k += outage
        t += 5_000 * MS if outage else 0         # a silence for every timing below: the device clock decides
        for _ in range(20):
            msgs = frames.encode_imu(ImuSample(0, k & 0xFF, (1.0, 0.0, 0.0, 0.0), (0.1, 0.0, 0.0), (0.0, 0.0, 1.0)),
                                     time_us=(k * 2000) & 0xFFFFFFFF)
            t += rnd.choice((2 * MS, 7 * MS, 250 * MS))
            for m in msgs:
                m.timestamp = t / 1e9
            pairs += [(sc, m) for m in msgs]
            k += 1
    stale = [(sc, m) for m in frames.encode_imu(ImuSample(0, (k - 30) & 0xFF, (1.0, 0, 0, 0), (0, 0, 0), (0, 0, 0)),
                                                 time_us=((k - 30) * 2000))]
    for _, m in stale:
        m.timestamp = (t + 500 * MS) / 1e9
    pairs += stale
    for timing in (SourceTiming(rate=None, stale_periods=3), SourceTiming(rate=0.5, stale_periods=50), DEFAULT_TIMING):
        core, _ = check_same(wm, pairs, timing=timing, pieces=7, probes=(0, 5 * MS, 7 * MS, 101 * MS, 199 * MS))
        imu = core.health(t)[1][core.device_names.index("imu")]
        assert imu.lost == 1 + 127 + 128 + 255 + 256 + 257 + 1000 and not imu.lost_at_least
        assert dict(imu.rejected) == {"late": 1}


def test_the_thruster_commands_optional_keep_out_frame():
    """THRUSTER_CMD_ALLOWED (0x184) is optional: a stream without it completes on three frames
    (allowed -1); its first 0x184 after its sample completed is dropped, uncounted; from then on
    it is required (lost: the sample is incomplete). Kernel and Python drivers agree."""
    from drivers import frames
    from drivers.samples import ThrusterCommand

    wm = fuzz_drivers.wire_map_for("paper_robot")
    sc = list(wm.buses).index(wire.SPACECRAFT_BUS)
    mask = 0x00000FF3
    # (counter, allowed, where 0x184 goes: "first" / "last" / "lost")
    plan = [(0, -1, None), (1, -1, None), (2, -1, None), (3, mask, "last"), (4, mask, "first"),
            (5, mask, "last"), (6, mask, "lost"), (7, mask, "first"), (8, -1, None), (9, mask, "first")]
    pairs = []
    for c, allowed, where in plan:
        msgs = frames.encode_thruster(ThrusterCommand(0, c, (10.0, 0.0, -1.0), (0.0, 2.0, 0.0), 0b101, False, allowed))
        if where == "last":
            msgs = msgs[1:] + msgs[:1]
        elif where == "lost":
            msgs = msgs[1:]
        for m in msgs:
            m.timestamp = (1 + c) * 10 * MS / 1e9
        pairs += [(sc, m) for m in msgs]
    core, _ = check_same(wm, pairs, pieces=5)
    got = [s for s in core.to_samples(kernel.DriverCore(wm).feed(kernel.columns_from_messages(pairs)))
           if isinstance(s, ThrusterCommand)]
    # 3: completed before its 0x184; 6: its 0x184 lost; 8: no 0x184 once it is required
    assert [(s.counter, s.allowed) for s in got] == [(0, -1), (1, -1), (2, -1), (3, -1), (4, mask),
                                                      (5, mask), (7, mask), (9, mask)]
    h = core.health(10**10)[1][core.device_names.index("thrusters")]
    assert dict(h.rejected) == {"incomplete": 2} and h.lost == 2


def test_resync_rounding_ties_and_a_repeated_counter():
    """Python's round() (half to even) in the resync count, and the corner where the counter did
    not move over 100..128 periods: the sample is kept after a silence, so it is a new one and
    the counter went round once (255 lost), never 0 lost."""
    from drivers import frames
    from drivers.samples import JointSample

    wm = fuzz_drivers.wire_map_for("paper_robot")
    # (counter, ms): steps - d = 128 -> 0.5 -> 0; d = 0 over 110 periods -> n = 256; steps - d = 384 -> 1.5 -> 2
    seq = [(0, 0), (1, 1), (73, 201), (73, 311), (83, 705), (84, 706)]
    pairs = []
    for c, ms in seq:
        m = frames.encode_joint(JointSample("arm0/j1", ms * MS, c, 0.5, -0.25), 0)
        m.timestamp = ms / 1e3
        pairs.append((0, m))
    core, _ = check_same(wm, pairs, pieces=len(seq))
    j1 = core.health(706 * MS)[1][core.device_names.index("arm0/j1")]
    assert (j1.samples, j1.lost, j1.rejected) == (6, 71 + 255 + 521, ())


# --- batch-size independence and state ----------------------------------------------------------

def _feed_split(core: kernel.DriverCore, cols, sizes):
    events, a = [], 0
    for n in sizes:
        ev = core.feed(cols[a:a + n]).copy()
        ev["frame"] += a
        events.append(ev)
        a += n
    assert a == len(cols)
    return np.concatenate(events) if events else np.zeros(0, kernel.EVENT_DTYPE)


def _splits(n: int, seed: int):
    rnd = random.Random(seed)
    chunks = []
    while sum(chunks) < n:
        chunks.append(min(rnd.choice((0, 1, 2, 3, 13, 50, 700, 4000)), n - sum(chunks)))
    return {"one call": [n], "one at a time": [1] * n, "random chunks": chunks}


@pytest.mark.parametrize("source", ["firmware faults", "fuzz jumps", "torque heavy"])
def test_batch_size_independence(readings, source):
    from simulator import firmware

    if source == "firmware faults":
        rob, rs = readings["three_arm"]
        wm = _wire(rob)
        _, pairs = firmware_pairs(rob, rs, 300, faults=firmware.Faults(
            drop_rate=0.05, duplicate_rate=0.05, reorder_rate=0.05, bad_dlc_rate=0.05, seed=3,
            silent=(("imu", 0.1, 0.12),)))
    elif source == "fuzz jumps":
        wm = edge_map()
        pairs = fuzz_pairs(wm, 6000, seed=9, clock_jumps=True)
    else:                          # 3 events per frame: more than the first output buffer holds
        wm = edge_map()
        pairs = [(0, can.Message(arbitration_id=wire.TORQUE_CMD_BASE + (k % 2), is_extended_id=False,
                                 data=bytes([k // 2 & 0xFF, 0x7F, 0xFF, 0, 1, 0x80, 1]), timestamp=k * 1e-3))
                 for k in range(3000)]
    cols = kernel.columns_from_messages(pairs)
    results = {}
    for name, sizes in _splits(len(cols), seed=len(source)).items():
        core = kernel.DriverCore(wm, timing=SourceTiming(rate=None))
        events = _feed_split(core, cols, sizes)
        results[name] = (events.tobytes(), core.state().bus.tobytes(), core.state().dev.tobytes(),
                         core.health(int(cols["t_ns"].max()) + 3 * MS))
    first = results.pop("one call")
    assert len(first[0]) > 1000 * kernel.EVENT_DTYPE.itemsize
    for name, got in results.items():
        assert got == first, name


def test_state_snapshot_and_restore(readings):
    rob, rs = readings["paper_robot"]
    _, pairs = firmware_pairs(rob, rs, 100)
    cols = kernel.columns_from_messages(pairs)
    core = kernel.DriverCore(_wire(rob))
    half = len(cols) // 2 + 1                        # mid-assembly of some multi-frame sample
    core.feed(cols[:half])
    saved = core.state()
    again = core.feed(cols[half:]).copy()
    after = core.state()
    core.restore(saved)
    assert np.array_equal(core.feed(cols[half:]), again)
    assert core.state().bus.tobytes() == after.bus.tobytes() and core.state().dev.tobytes() == after.dev.tobytes()
    with pytest.raises(ValueError, match="another wire map"):
        kernel.DriverCore(edge_map()).restore(saved)


# --- columns and edges ---------------------------------------------------------------------------

def test_columns_from_messages_layout():
    msgs = [(1, can.Message(arbitration_id=0x123, data=bytes(range(12)), is_fd=True, bitrate_switch=True,
                            timestamp=1.25, is_extended_id=False)),
            (0, can.Message(arbitration_id=0x1ABCDEF, is_extended_id=True, is_remote_frame=True, dlc=3,
                            timestamp=2e-9)),
            (2, can.Message(arbitration_id=-5, data=b"\x01", dlc=300, is_error_frame=True, is_extended_id=False,
                            check=False))]
    cols = kernel.columns_from_messages(msgs)
    assert cols.dtype == kernel.FRAME_DTYPE and cols.dtype.itemsize == 80
    assert cols["t_ns"].tolist() == [1_250_000_000, 2, 0]
    assert cols["can_id"].tolist() == [0x123, 0x1ABCDEF, 0xFFFFFFFF]
    assert cols["bus"].tolist() == [1, 0, 2]
    assert cols["flags"].tolist() == [kernel.FLAG_FD | kernel.FLAG_BRS, kernel.FLAG_EXTENDED | kernel.FLAG_REMOTE,
                                      kernel.FLAG_ERROR]
    assert cols["dlc"].tolist() == [12, 3, 255] and cols["length"].tolist() == [12, 0, 1]
    assert cols["data"][0].tolist() == list(range(12)) + [0] * 52 and cols["data"][2].tolist() == [1] + [0] * 63
    with pytest.raises(ValueError, match="not a CAN frame"):
        kernel.columns_from_messages([(0, can.Message(data=bytes(300), check=False))])
    with pytest.raises(ValueError, match="bus index"):
        kernel.columns_from_messages([(256, can.Message())])


def test_unknown_bus_and_empty_batches():
    wm = fuzz_drivers.wire_map_for("paper_robot")
    core = kernel.DriverCore(wm)
    assert len(core.feed(np.zeros(0, kernel.FRAME_DTYPE))) == 0
    cols = kernel.columns_from_messages([(7, can.Message(arbitration_id=wire.VALVE_CMD_ID, data=bytes(5)))] * 3)
    assert len(core.feed(cols)) == 0 and core.unknown_bus == 3
    assert all(h.frames == 0 for h in core.health(0)[0])
    with pytest.raises(TypeError, match="FRAME_DTYPE"):
        core.feed(np.zeros(3, np.int64))


def test_tables():
    core = kernel.DriverCore(edge_map())
    assert core.bus_names == ("wide", "narrow", "spacecraft")
    assert core.arm_names == ("wide", "narrow")
    assert core.joint_names == tuple(f"wide/j{i}" for i in range(8)) + ("narrow/j0",)
    assert core.device_names == ("wide", *(f"wide/j{i}" for i in range(8)), "wide/torque_cmd/0", "wide/torque_cmd/1",
                                 "wide/torque_cmd/2", "narrow", "narrow/j0", "narrow/torque_cmd", "imu", "thrusters",
                                 "valves")
