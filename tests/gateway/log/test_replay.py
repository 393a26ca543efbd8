"""``bsc replay``: offline determinism, live playback onto virtual CAN and loopback zenoh,
filters, windows, loops, and bad input.

The offline engine is exercised with a stand-in for ``gateway.pipeline.Pipeline`` defined here
(drivers + a toy estimator that, like the real one, mixes buses: arm efforts use the latest IMU
sample). The same determinism test runs against the real pipeline when it exists.
"""
from __future__ import annotations

import dataclasses

import json
import random
import struct
import threading
import time
import uuid
from pathlib import Path

import can
import pytest

import robot_description
from drivers import frames, wire
from drivers.devices import listeners_for
from drivers.samples import ImuSample, JointSample, ThrusterCommand, TorqueCommand, ValveCommand, WrenchSample
from gateway import KERNELS, codec, keys
from gateway import replay as rp
from gateway.log import context, errors, reader, scan
from gateway.cli import main
from gateway.efforts import JointEfforts, ThrusterEffort
from gateway.log.recorder import Recorder
from support import free_port as _free_port

ROBOT = "paper_robot"
PNG = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + bytes(13) + b"\0\0\0\0"


# ----------------------------------------------------------------------------- stand-in pipeline

class StandInPipeline:
    """The ``gateway.pipeline.Pipeline`` contract with the real drivers and a toy estimator.

    Emits every decoded sample; on each F/T sample a ``JointEfforts`` built from the wrench, the
    arm's latest joint samples and the LATEST IMU sample (another bus), so the result depends
    on the order frames of different buses were fed in; on each IMU sample a
    ``ThrusterEffort``. Times come only from the samples' integer ``t_ns``.
    """

    def __init__(self, robot, *, model_robot=None, fd=False, emit, layout=None, **_pipeline_options):
        self.wire = wire.WireMap.from_robot(robot)
        self.robot = self.name = robot.name
        self.buses = list(self.wire.buses)
        self.log_ns = 0                  # set by the session before each feed
        self.stats: dict = {}
        self._emit = emit
        self._listeners = {}
        for name, spec in self.wire.buses.items():
            mon, drivers = listeners_for(spec, self._on_sample, fd)
            self._listeners[name] = [mon, *drivers]
        self._joints: dict[str, JointSample] = {}
        self._imu: ImuSample | None = None
        self._cmd: dict[str, float] = {}

    def feed(self, bus, msg, log_ns=None):
        for listener in self._listeners[bus]:
            listener.on_message_received(msg)

    def feed_frames(self, rows, log_ns=None):
        """Rows as the frames they are (the session engine feeds a replay as rows)."""
        for r in rows:
            f = int(r["flags"])
            msg = can.Message(timestamp=int(r["t_ns"]) / 1e9, arbitration_id=int(r["can_id"]),
                              is_extended_id=bool(f & 1), is_remote_frame=bool(f & 2), is_error_frame=bool(f & 4),
                              is_fd=bool(f & 8), bitrate_switch=bool(f & 16), error_state_indicator=bool(f & 32),
                              dlc=int(r["dlc"]), data=bytes(r["data"][:int(r["length"])]), check=False)
            self.feed(self.buses[int(r["bus"])], msg)

    def flush(self):
        pass

    def health(self, now_ns):
        out = []
        for ls in self._listeners.values():
            out.append(ls[0].health(now_ns))
            for d in ls[1:]:
                out.extend(d.health(now_ns))
        return out

    def _on_sample(self, s):
        self._emit(keys.for_sample(self.robot, s), s)
        if isinstance(s, JointSample):
            self._joints[s.device] = s
        elif isinstance(s, TorqueCommand):
            self._cmd[s.device] = s.torque_nm
        elif isinstance(s, ImuSample):
            self._imu = s
            self._emit(keys.thruster_effort(self.robot), ThrusterEffort(
                t_ns=s.t_ns, force_n=tuple(100.0 * a for a in s.accel_m_s2),
                moment_nm=tuple(10.0 * w for w in s.rate_rad_s), commanded_force_n=(0.0,) * 3,
                commanded_moment_nm=(0.0,) * 3, commanded_t_ns=0, valves=0, good=True))
        elif isinstance(s, WrenchSample):
            spec = self.wire.buses[s.device]
            devs = [f"{s.device}/{j}" for j in spec.joints]
            js = [self._joints.get(d) for d in devs]
            wz = self._imu.rate_rad_s[2] if self._imu is not None else 0.0
            full = tuple(s.torque_nm[i % 3] * (i + 1) + 0.37 * (j.rate_rad_s if j else 0.0)
                         + wz / 3.0 for i, j in enumerate(js))
            self._emit(keys.joint_efforts(self.robot, s.device), JointEfforts(
                arm=s.device, t_ns=s.t_ns, joints=tuple(devs), full_nm=full,
                simplified_nm=tuple(s.torque_nm[i % 3] for i in range(len(devs))),
                commanded_nm=tuple(self._cmd.get(d, 0.0) for d in devs), commanded_t_ns=0,
                rate_rad_s=tuple(j.rate_rad_s if j else 0.0 for j in js),
                good=all(js) and self._imu is not None,
                flags=() if all(js) and self._imu is not None else ("warmup",)))


# ----------------------------------------------------------------------------- sessions

def synthetic_frames(robot, n_ms: int, seed: int = 1, valves: bool = False):
    """``(bus, can.Message)`` in ARRIVAL order for ``n_ms`` ms of a live-like session
    (``valves``: with the valve commands of every millisecond, so the estimator's epochs are whole).

    Timestamps are wall-clock floats with sub-nanosecond digits (as python-can gives them),
    and the spacecraft bus is fed 0.7 ms late relative to the arm buses (two notifier threads),
    so arrival order is not log-time order.
    """
    rnd = random.Random(seed)
    wm = wire.WireMap.from_robot(robot)
    base = 1_767_000_000.0 + rnd.random()
    out = []
    late = []
    for k in range(n_ms):
        t = base + k * 1e-3
        step = []
        for arm, spec in wm.buses.items():
            if spec.arm is None:
                continue
            ts = t + rnd.random() * 2e-4
            for i, j in enumerate(spec.joints):
                step.append((arm, frames.encode_joint(JointSample(
                    f"{arm}/{j}", 0, k, rnd.uniform(-3, 3), rnd.uniform(-1, 1)), i), ts))
            if k % 2 == 0:
                cmds = [TorqueCommand(f"{arm}/{j}", 0, k // 2, rnd.uniform(-5, 5))
                        for j in spec.joints]
                step += [(arm, m, ts) for m in frames.encode_torque_commands(cmds)]
            step += [(arm, m, ts + 1e-5) for m in frames.encode_wrench(WrenchSample(
                arm, 0, k, tuple(rnd.uniform(-50, 50) for _ in range(3)),
                tuple(rnd.uniform(-10, 10) for _ in range(3))))]
        sc = []
        if k % 2 == 0:
            imu = ImuSample(0, k // 2, (1.0, 0.0, 0.0, 0.0),
                            tuple(rnd.uniform(-0.5, 0.5) for _ in range(3)),
                            tuple(rnd.uniform(-0.1, 0.1) for _ in range(3)))
            sc += [(wire.SPACECRAFT_BUS, m, t) for m in frames.encode_imu(imu, time_us=k * 1000)]
        if valves:
            sc.append((wire.SPACECRAFT_BUS, frames.encode_valves(ValveCommand(0, k, 5 if k % 20 < 4 else 0)), t))
        if k % 10 == 0:
            sc += [(wire.SPACECRAFT_BUS, m, t) for m in frames.encode_thruster(ThrusterCommand(
                0, k // 10, (1.0, 0.0, 0.0), (0.0, 0.0, 0.1), valves=5))]
        for bus, m, ts in step + late:
            m.timestamp = ts + rnd.random() * 1e-9
            out.append((bus, m))
        late = sc            # arrives after the next step's arm frames, with an older stamp
    for bus, m, ts in late:
        m.timestamp = ts
        out.append((bus, m))
    return out


def record_live(path: Path, robot, frame_list, pipeline_cls=StandInPipeline):
    """What the live gateway does: record each frame, then feed it, in arrival order; every
    emit recorded under its key. Returns ``[(key, codec payload)]`` of the emits."""
    emitted = []
    with Recorder(path, queue_size=1 << 22) as rec:
        rec.add_session_context(**context.session_context(robot, extra={"mode": "test live"}))

        def emit(key, obj):
            emitted.append((key, codec.encode(obj)))
            assert rec.record(key, obj)

        pipe = pipeline_cls(robot, emit=emit)
        for bus, msg in frame_list:
            assert rec.record_can(bus, msg)
            pipe.feed(bus, msg)
        if hasattr(pipe, "flush"):              # the live gateway flushes when it stops
            pipe.flush()
    assert rec.stats.dropped == 0
    return emitted


def efforts_by_topic(path: Path) -> dict[str, list[bytes]]:
    """Raw MCAP message bytes of every effort channel, in file order."""
    out: dict[str, list[bytes]] = {}
    for topic, _, m in reader.iter_file_order(path, lambda t, s: "/efforts/" in t):
        out.setdefault(topic, []).append(bytes(m.data))
    return out


@pytest.fixture(scope="module")
def robot():
    return robot_description.load(ROBOT)


@pytest.fixture(scope="module")
def session(robot, tmp_path_factory):
    """A live-recorded session: 600 ms, about 7 k frames."""
    path = tmp_path_factory.mktemp("live") / "live.mcap"
    fl = synthetic_frames(robot, 600)
    emitted = record_live(path, robot, fl)
    return path, fl, emitted


@pytest.fixture
def standin(monkeypatch):
    monkeypatch.setattr(rp, "_default_pipeline_factory", lambda: StandInPipeline)


# ----------------------------------------------------------------------------- offline

def test_offline_replay_efforts_are_byte_identical(session, robot, tmp_path):
    path, fl, emitted = session
    report = rp.replay_offline(path, tmp_path / "out", pipeline_factory=StandInPipeline)
    live = efforts_by_topic(path)
    replayed = efforts_by_topic(tmp_path / "out" / rp.OUTPUT_NAME)
    assert set(live) == {keys.joint_efforts(ROBOT, "arm0"), keys.joint_efforts(ROBOT, "arm1"),
                         keys.thruster_effort(ROBOT)}
    assert replayed == live
    n_eff = sum(len(v) for v in live.values())
    assert report.frames_in == len(fl) and report.efforts == n_eff > 1000
    assert 0 < report.good_efforts < report.efforts          # warm-up ones are not good
    assert report.samples == sum(1 for k, _ in emitted if "/sensors/" in k)
    # every other emitted payload too, in order
    got = [(t, codec.encode(reader.to_dataclass(codec.TYPES[s.rsplit(".", 1)[1]],
                                                 json.loads(m.data))))
           for t, s, m in reader.iter_file_order(tmp_path / "out" / rp.OUTPUT_NAME,
                                             lambda t, s: "/health/" not in t)]
    assert got == [(k, p) for k, p in emitted if "/health/" not in k]
    saved = json.loads((tmp_path / "out" / rp.REPORT_NAME).read_text())
    assert saved["frames_in"] == len(fl) and saved["efforts"] == n_eff
    assert saved["speed_x_realtime"] > 0 and saved["recorder"]["dropped"] == 0


def test_log_time_order_would_not_be_deterministic(session, robot):
    """The check above can fail: feeding the same frames in log-time order (not the order they
    were recorded in) changes the efforts, because arm efforts use the latest IMU sample."""
    path, fl, _ = session
    ours, other = [], []
    for order, sink in ((reader.iter_can_frames(path), ours),
                        (reader.iter_can_frames(path, log_time_order=True), other)):
        pipe = StandInPipeline(robot, emit=lambda k, o, sink=sink: sink.append(codec.encode(o))
                               if isinstance(o, JointEfforts) else None)
        for bus, _, msg in order:
            pipe.feed(bus, msg)
    assert len(ours) == len(other) > 0
    assert ours != other


def test_replayed_frames_keep_their_nanosecond_times(session):
    path, fl, _ = session
    got = [(b, round(m.timestamp * 1e9), bytes(m.data)) for b, _, m in reader.iter_can_frames(path)]
    assert got == [(b, round(m.timestamp * 1e9), bytes(m.data)) for b, m in fl]


def test_offline_replay_with_the_real_pipeline(robot, tmp_path):
    pipeline = pytest.importorskip("gateway.pipeline")
    path = tmp_path / "live.mcap"
    record_live(path, robot, synthetic_frames(robot, 400, seed=7), pipeline.Pipeline)
    report = rp.replay_offline(path, tmp_path / "out")        # the default factory: the real one
    live = efforts_by_topic(path)
    assert sum(len(v) for v in live.values()) > 0
    assert efforts_by_topic(tmp_path / "out" / rp.OUTPUT_NAME) == live
    assert report.efforts == sum(len(v) for v in live.values())


def test_offline_output_holds_samples_only_when_asked_and_copies_frames_exactly(robot, tmp_path):
    """Efforts and health by default; ``samples=True`` adds every decoded sample; ``copy_can``
    copies each raw frame record as it was (channel and all), and the efforts stay the same."""
    from gateway.pipeline import Pipeline

    path = tmp_path / "live.mcap"
    emitted = record_live(path, robot, synthetic_frames(robot, 200, seed=3), Pipeline)
    n_samples = sum(1 for k, _ in emitted if "/sensors/" in k)
    live = efforts_by_topic(path)

    def topics(p):
        return [t for t, _, _ in reader.iter_file_order(p, lambda t, s: True)]

    plain = rp.replay_offline(path, tmp_path / "plain")
    out = tmp_path / "plain" / rp.OUTPUT_NAME
    assert plain.samples == 0 and not any("/sensors/" in t or t.startswith("/can/") for t in topics(out))
    assert efforts_by_topic(out) == live

    full = rp.replay_offline(path, tmp_path / "full", samples=True, copy_can=True)
    out = tmp_path / "full" / rp.OUTPUT_NAME
    assert full.samples == n_samples > 0 and sum("/sensors/" in t for t in topics(out)) == n_samples
    assert efforts_by_topic(out) == live

    def frames(p):
        return [(t, m.log_time, bytes(m.data))
                for t, _, m in reader.iter_file_order(p, lambda t, s: t.startswith("/can/"))]

    assert frames(out) == frames(path) and len(frames(path)) == full.frames_in


def _live_log(path, robot, *, kernels=None, nudge=0.0, at=40, old_form=False, valves=True):
    """A live-recorded log (real pipeline) whose ``at``-th JointEfforts has its first full torque
    scaled by ``1 + nudge``, and whose session metadata names ``kernels`` (default: these);
    ``old_form``: samples and efforts written as logs were before the one JSON form (no ``type``
    and ``v``); ``valves=False``: without the learned per-valve wrenches (a log from before the
    gateway published them)."""
    from gateway.pipeline import Pipeline

    frame_list = synthetic_frames(robot, 200, seed=5, valves=True)
    seen = [0]
    with Recorder(path, queue_size=1 << 22) as rec:
        extra = {"kernels": kernels} if kernels is not None else {}
        rec.add_session_context(**context.session_context(robot, extra=extra))

        def emit(key, obj):
            if not valves and key == keys.valve_wrenches(robot.name):
                return
            if isinstance(obj, JointEfforts):
                seen[0] += 1
                if seen[0] == at and nudge:
                    obj = dataclasses.replace(obj, full_nm=(obj.full_nm[0] * (1 + nudge), *obj.full_nm[1:]))
            if old_form:
                from gateway.log.schema import record_of

                obj = {k: v for k, v in record_of(obj).items() if k not in ("type", "v")}
            assert rec.record(key, obj)

        pipe = Pipeline(robot, emit=emit)
        for bus, msg in frame_list:
            assert rec.record_can(bus, msg)
            pipe.feed(bus, msg)
        pipe.flush()
    assert seen[0] > at
    return path


def test_check_finds_the_replay_identical_to_live(robot, tmp_path, capsys):
    from gateway import KERNELS
    from gateway.cli import main

    log = _live_log(tmp_path / "live.mcap", robot)
    assert context.read_context(log).metadata["bsc.session"]["kernels"] == KERNELS
    assert main(["replay", str(log), "--out", str(tmp_path / "out"), "--check", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert f"check: all {efforts_count(log)} efforts byte-identical to the log's (kernels v{KERNELS})" in out
    report = json.loads((tmp_path / "out" / rp.REPORT_NAME).read_text())["check"]
    assert report["ok"] and report["identical"] == report["recorded"] == report["replayed"] > 100
    # the learned per-valve wrenches are among them
    assert len(efforts_by_topic(log)[keys.valve_wrenches(ROBOT)]) >= 15 and report["not_in_log"] == {}


def test_check_of_a_log_from_before_the_valve_wrenches(robot, tmp_path, capsys):
    """A log recorded before the gateway published the learned per-valve wrenches is checked on
    its other efforts, saying that those were not compared."""
    from gateway.cli import main

    log = _live_log(tmp_path / "old.mcap", robot, valves=False)
    assert keys.valve_wrenches(ROBOT) not in efforts_by_topic(log)
    assert main(["replay", str(log), "--out", str(tmp_path / "out"), "--check", "--quiet"]) == 0
    out = capsys.readouterr().out
    n = len(efforts_by_topic(tmp_path / "out" / rp.OUTPUT_NAME)[keys.valve_wrenches(ROBOT)])
    assert f"byte-identical to the log's (kernels v{KERNELS}) ({n} on {keys.valve_wrenches(ROBOT)} not compared" in out
    report = json.loads((tmp_path / "out" / rp.REPORT_NAME).read_text())["check"]
    assert report["ok"] and report["not_in_log"] == {keys.valve_wrenches(ROBOT): n} and n >= 15


def test_check_of_a_log_from_before_the_one_json_form(robot, tmp_path, capsys):
    """A log whose records have no ``type`` and ``v`` (written before the zenoh payload and the log
    message became one form) holds the same efforts: the check finds them identical."""
    from gateway.cli import main

    log = _live_log(tmp_path / "old.mcap", robot, old_form=True)
    first = next(iter(efforts_by_topic(log).values()))[0]
    assert b'"type"' not in first
    assert main(["replay", str(log), "--out", str(tmp_path / "out"), "--check", "--quiet"]) == 0
    report = json.loads((tmp_path / "out" / rp.REPORT_NAME).read_text())["check"]
    assert report["ok"] and report["identical"] == report["recorded"] == report["replayed"] > 100
    replayed = efforts_by_topic(tmp_path / "out" / rp.OUTPUT_NAME)[keys.joint_efforts(ROBOT, "arm0")][0]
    assert replayed.startswith(b'{"type":"JointEfforts","v":1,')


def efforts_count(path):
    return sum(len(v) for v in efforts_by_topic(path).values())


@pytest.mark.parametrize("kernels, nudge, status, says", [
    ("0", 0.0, 0, f"all {{n}} efforts byte-identical to the log's (kernels v0, now v{KERNELS})"),
    ("0", 1e-12, 0, f"came from kernels v0, these are v{KERNELS}: {{n}} byte-identical, 1 within 1e-09 relative, "
                    "none beyond"),
    (None, 1e-12, 3, "1 not byte-identical although the kernels are the same"),
    ("0", 1e-6, 3, f"efforts DIFFER from the log's (kernels v0, now v{KERNELS}): 1 beyond 1e-09 relative; first: "
                   "bsc/paper_robot/efforts/joints/arm"),
])
def test_check_of_a_log_from_other_kernels(robot, tmp_path, capsys, kernels, nudge, status, says):
    """A log from older kernels is compared within 1e-9 relative, with a note naming both versions
    and no failure; beyond that, or any difference under the same kernels, is exit 3 naming the
    first."""
    from gateway.cli import main

    log = _live_log(tmp_path / "live.mcap", robot, kernels=kernels, nudge=nudge)
    assert main(["replay", str(log), "--out", str(tmp_path / "out"), "--check", "--quiet"]) == status
    out = capsys.readouterr().out
    assert says.format(n=efforts_count(log) - (nudge > 0)) in out, out


def test_check_needs_the_whole_log_with_its_own_robot(session, tmp_path, capsys):
    from gateway.cli import main

    assert main(["replay", str(session[0]), "--out", str(tmp_path / "out"), "--check", "--start", "0.1"]) == 2
    err = capsys.readouterr().err
    assert "a check compares with the efforts the log recorded" in err and err.rstrip().endswith("[--check]")


def test_many_logs_replay_on_every_core_each_into_its_own_folder(robot, tmp_path, capsys):
    """Several logs (two of one name in different folders, one damaged): each replays in a worker
    process into its own folder, the same efforts as replaying it alone; the damaged one is
    reported and the others go on; exit 2 for it; replays.json lists every log."""
    from gateway.cli import main

    for day in ("day1", "day2"):
        (tmp_path / "runs" / day).mkdir(parents=True)
    a, b = (tmp_path / "runs" / day / "session.mcap" for day in ("day1", "day2"))
    _live_log(a, robot)
    b.write_bytes(a.read_bytes())
    bad = tmp_path / "runs" / "notes.mcap"
    bad.write_text("not a log")
    out = tmp_path / "out"
    status = main(["replay", str(a), str(b), str(bad), "--out", str(out), "--workers", "2", "--check", "--quiet"])
    text = capsys.readouterr()
    assert status == 2, text
    assert f"{bad}: error: " in text.err and "not an MCAP file" in text.err
    assert "bsc replay: 2 of 3 logs" in text.out and "on 2 processes" in text.out
    for day in ("day1", "day2"):
        got = out / day / "session" / rp.OUTPUT_NAME
        assert efforts_by_topic(got) == efforts_by_topic(a) and efforts_count(a) > 100
        assert "byte-identical" in json.loads((out / day / "session" / rp.REPORT_NAME).read_text())["check"]["summary"]
    index = json.loads((out / "replays.json").read_text())
    assert [(Path(x["source"]).name, x["error"] is None) for x in index["logs"]] == [
        ("session.mcap", True), ("session.mcap", True), ("notes.mcap", False)]


def test_output_folders_of_many_logs():
    assert rp.output_dirs([Path("x/a.mcap"), Path("y/b.mcap")], Path("o")) == [Path("o/a"), Path("o/b")]
    assert rp.output_dirs([Path("/r/d1/s.mcap"), Path("/r/d2/s.mcap")], Path("o")) == [Path("o/d1/s"), Path("o/d2/s")]
    with pytest.raises(rp.ReplayError, match="given twice"):
        rp.output_dirs([Path("/r/s.mcap"), Path("/r/s.mcap")], Path("o"))


def test_live_playback_takes_one_log(session, capsys):
    from gateway.cli import main

    assert main(["replay", str(session[0]), str(session[0]), "--zenoh"]) == 2
    assert "live playback takes one log, not 2" in capsys.readouterr().err


def test_a_replay_that_fails_part_way_leaves_no_complete_looking_output(robot, tmp_path):
    """A corrupt chunk in the middle of a log stops the replay with an error naming bsc recover;
    the output is written under a temporary name and renamed only on success, so no file that
    bsc info calls complete is left, and an earlier output is kept as it was."""
    from mcap.reader import make_reader

    log = _live_log(tmp_path / "live.mcap", robot)
    with open(log, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    mid = chunks[len(chunks) // 2]
    data = bytearray(log.read_bytes())
    at = mid.chunk_start_offset + mid.chunk_length // 2
    data[at:at + 32] = bytes(32)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data)
    out = tmp_path / "out"
    rp.replay_offline(log, out)                                  # an earlier, good output
    before = (out / rp.OUTPUT_NAME).read_bytes()
    with pytest.raises(errors.McapFileError, match="bsc recover"):
        rp.replay_offline(bad, out, overwrite=True)
    assert (out / rp.OUTPUT_NAME).read_bytes() == before
    assert not [p for p in out.iterdir() if p.name.endswith(".part")]
    with pytest.raises(errors.McapFileError, match="bsc recover"):
        rp.replay_offline(bad, tmp_path / "fresh")
    assert not (tmp_path / "fresh" / rp.OUTPUT_NAME).exists()
    assert not [p for p in (tmp_path / "fresh").iterdir() if p.name.endswith(".part")]


def test_offline_cli_filters_and_report(session, tmp_path, capsys, standin):
    path, fl, _ = session
    out = tmp_path / "out"
    rc = main(["replay", str(path), "--out", str(out), "--quiet", "--topic", "/can/arm*",
               "--start", "0.1", "--duration", "0.2"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    t0 = min(round(m.timestamp * 1e9) for _, m in fl)
    lo, hi = t0 + 100_000_000, t0 + 300_000_000
    want = [m for b, m in fl if b != "spacecraft" and lo <= round(m.timestamp * 1e9) < hi]
    report = json.loads((out / "report.json").read_text())
    assert report["frames_in"] == len(want)
    assert "frames" in cap.out and "x real time" in cap.out and "report.json" in cap.out
    assert not any("/thrusters" in k or "/imu" in k for k in report["by_key"]
                   if "/health/" not in k)
    # an existing output needs --force
    rc = main(["replay", str(path), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "--force" in err
    assert main(["replay", str(path), "--out", str(out), "--quiet", "--force",
                 "--can-id", "0x200,0x201"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["frames_in"] == sum(1 for _, m in fl if m.arbitration_id in (0x200, 0x201))


def test_offline_without_a_pipeline_is_one_line(session, tmp_path, capsys, monkeypatch):
    def missing():
        raise rp.ReplayError("offline replay needs gateway.pipeline (test)")

    monkeypatch.setattr(rp, "_default_pipeline_factory", missing)
    rc = main(["replay", str(session[0]), "--out", str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "gateway.pipeline" in err


# ----------------------------------------------------------------------------- live CAN

def _drain(bus) -> list[can.Message]:
    out = []
    while (m := bus.recv(timeout=0)) is not None:
        out.append(m)
    return out


def _rx(prefix: str, buses):
    return {b: can.Bus(interface="virtual", channel=wire.channel_name(prefix, b),
                       ignore_config=True) for b in buses}


def test_live_can_filtered_in_order_with_scaled_timing(session, tmp_path, capsys):
    path, fl, _ = session
    prefix = f"bsc-replay-{uuid.uuid4().hex}"
    rx = _rx(prefix, ["arm0", "arm1", "spacecraft"])
    try:
        rate = 2.0
        rc = main(["replay", str(path), "--interface", "virtual", "--channel", prefix,
                   "--rate", str(rate), "--can-id", "0x200,0x300", "--can-id", "0x421",
                   "--topic", "/can/arm0", "--topic", "/can/spacecraft", "--quiet"])
        cap = capsys.readouterr()
        assert rc == 0, cap.err
        got = {b: _drain(bus) for b, bus in rx.items()}
    finally:
        for bus in rx.values():
            bus.shutdown()
    for b in ("arm0", "spacecraft"):
        want = [(m.arbitration_id, bytes(m.data)) for bb, m in fl
                if bb == b and m.arbitration_id in (0x200, 0x300, 0x421)]
        assert [(m.arbitration_id, bytes(m.data)) for m in got[b]] == want
        assert len(want) > 100
    assert got["arm1"] == []
    sent = [m for b in ("arm0", "spacecraft") for b2, m in fl
            if b2 == b and m.arbitration_id in (0x200, 0x300, 0x421)]
    span = max(m.timestamp for m in sent) - min(m.timestamp for m in sent)
    stamps = [m.timestamp for b in ("arm0", "spacecraft") for m in got[b]]
    took = max(stamps) - min(stamps)
    assert took >= 0.8 * span / rate, (took, span)
    assert took <= span / rate + 30.0
    assert "sent frames" in cap.out


def test_live_can_window_and_bus_map(session, tmp_path, capsys):
    path, fl, _ = session
    ch = f"bsc-replay-{uuid.uuid4().hex}"
    rx = can.Bus(interface="virtual", channel=ch, ignore_config=True)
    try:
        rc = main(["replay", str(path), "--interface", "virtual", "--channel", f"arm1={ch}",
                   "--rate", "0", "--start", "0.25", "--duration", "0.1", "--quiet"])
        assert rc == 0, capsys.readouterr().err
        got = _drain(rx)
    finally:
        rx.shutdown()
    t0 = min(round(m.timestamp * 1e9) for _, m in fl)
    want = [bytes(m.data) for b, m in fl if b == "arm1"
            and t0 + 250_000_000 <= round(m.timestamp * 1e9) < t0 + 350_000_000]
    assert [bytes(m.data) for m in got] == want and len(want) > 100


def test_live_can_loop_until_stopped(session):
    path, fl, _ = session
    ch = f"bsc-replay-{uuid.uuid4().hex}"
    want = [bytes(m.data) for b, m in fl if b == "spacecraft" and m.arbitration_id == 0x182]
    stop = threading.Event()
    got = []

    class Until(can.Listener):
        def on_message_received(self, msg):
            got.append(bytes(msg.data))
            if len(got) >= 2 * len(want) + 3:
                stop.set()

    with can.Bus(interface="virtual", channel=ch, ignore_config=True) as tx, \
            can.Bus(interface="virtual", channel=ch, ignore_config=True) as rx:
        notifier = can.Notifier(rx, [Until()], timeout=0.05)
        try:
            stats = rp.play_can(path, {"spacecraft": tx}, rate=0, loop=True,
                                can_ids=[0x182], stop=stop)
        finally:
            notifier.stop()
    assert stats.loops >= 2 and stats.interrupted
    n = len(got)
    assert got == (want * (n // len(want) + 1))[:n]


# ----------------------------------------------------------------------------- live zenoh


def test_live_zenoh_payloads_byte_identical(session, capsys):
    import zenoh

    from gateway.zenoh_config import make_config

    path, _, emitted = session
    want = [(k, p) for k, p in emitted if "/efforts/" in k or k.endswith("/sensors/imu")]
    got, done = [], threading.Event()

    def on_sample(sample):
        got.append((str(sample.key_expr), sample.payload.to_bytes()))
        if len(got) >= len(want):
            done.set()

    ep = f"tcp/127.0.0.1:{_free_port()}"
    with zenoh.open(make_config(listen=[ep])) as sub_s:
        sub = sub_s.declare_subscriber(f"bsc/{ROBOT}/**", on_sample)
        try:
            rc = main(["replay", str(path), "--zenoh", "--connect", ep, "--rate", "0",
                       "--wait", "30", "--quiet", "--topic", "bsc/*/efforts/**",
                       "--topic", "*/sensors/imu"])
            cap = capsys.readouterr()
            assert rc == 0, cap.err
            assert done.wait(30), f"got {len(got)} of {len(want)}"
        finally:
            sub.undeclare()
    assert "warning" not in cap.err
    for key in {k for k, _ in want}:
        assert [p for k, p in got if k == key] == [p for k, p in want if k == key], key
    assert sorted(got) == sorted(want)


def test_live_zenoh_wait_names_the_keys_nobody_subscribes(session):
    """``--wait`` waits for a subscriber on every key: with one only on the efforts, the rest
    are named in the warning after the wait, and the efforts still all arrive."""
    import zenoh

    from gateway.zenoh_config import make_config

    path, _, emitted = session
    want = [(k, p) for k, p in emitted if "/efforts/" in k]
    got, warned = [], []
    ep = f"tcp/127.0.0.1:{_free_port()}"
    with zenoh.open(make_config(listen=[ep])) as sub_s, zenoh.open(make_config(connect=[ep])) as pub_s:
        sub = sub_s.declare_subscriber(f"bsc/{ROBOT}/efforts/**",
                                       lambda s: got.append((str(s.key_expr), s.payload.to_bytes())))
        try:
            t0 = time.monotonic()
            rp.play_zenoh(path, pub_s, rate=0, wait_s=0.5, warn=warned.append,
                          topics=["bsc/*/efforts/**", "*/sensors/imu"])
            waited = time.monotonic() - t0
            deadline = time.monotonic() + 30
            while len(got) < len(want) and time.monotonic() < deadline:
                time.sleep(0.01)
        finally:
            sub.undeclare()
    assert waited >= 0.5
    assert len(warned) == 1 and "no subscriber within 0.5 s for 1 of " in warned[0], warned
    assert "sensors/imu" in warned[0]
    assert sorted(got) == sorted(want)


# ----------------------------------------------------------------------------- bad input

def _foreign_mcap(path: Path) -> None:
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="someone else")
        sid = w.register_schema("sensor_msgs/Image", "ros2msg", b"uint8[] data")
        cid = w.register_channel("/camera", "cdr", sid)
        w.add_message(cid, 1, b"\x00\x01\x02", 1)
        w.finish()


def _empty_log(path: Path) -> None:
    with Recorder(path):
        pass


BAD = {
    "missing": (lambda p, good: None, "no such file"),
    "empty": (lambda p, good: p.write_bytes(b""), "empty file"),
    "png": (lambda p, good: p.write_bytes(PNG), "not an MCAP file"),
    "text": (lambda p, good: p.write_text("t,v\n1,2\n"), "not an MCAP file"),
    "half header": (lambda p, good: p.write_bytes(good[:20]), "truncated before"),
    "foreign mcap": (lambda p, good: _foreign_mcap(p), "no raw CAN channels"),
    "no messages": (lambda p, good: _empty_log(p), "empty log"),
    "directory": (lambda p, good: p.mkdir(), "directory"),
}


@pytest.mark.parametrize("mode", ["offline", "can", "zenoh"])
@pytest.mark.parametrize("name", list(BAD))
def test_bad_files_give_one_line(name, mode, session, tmp_path, capsys, standin):
    make, message = BAD[name]
    path = tmp_path / "bad.mcap"
    make(path, session[0].read_bytes())
    args = {"offline": ["--out", str(tmp_path / "o")],
            "can": ["--interface", "virtual", "--channel", f"x-{uuid.uuid4().hex}"],
            "zenoh": ["--zenoh"]}[mode]
    rc = main(["replay", str(path), *args, "--quiet"])
    cap = capsys.readouterr()
    if mode == "zenoh" and message == "no raw CAN channels":
        message = "no recorded samples"
    assert rc == 2, cap
    assert cap.err.count("\n") == 1 and cap.err.startswith("bsc replay: error: "), cap.err
    assert message in cap.err and "Traceback" not in cap.err


def test_truncated_log_is_recovered_with_a_warning(session, tmp_path, capsys, standin):
    path, fl, _ = session
    cut = tmp_path / "cut.mcap"
    data = path.read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    rc = main(["replay", str(cut), "--out", str(tmp_path / "o"), "--quiet"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert cap.err.count("\n") == 1 and "truncated" in cap.err and "recovered" in cap.err
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    rec = scan.recover(cut, tmp_path / "r.mcap")
    n = sum(1 for _ in reader.iter_can_frames(rec.output, log_time_order=True))
    assert report["source_recovered"] and report["frames_in"] == n and 0 < n < len(fl)


def test_read_only_output_and_bad_options(session, tmp_path, read_only_dir, capsys, standin):
    path = str(session[0])
    cases = [
        (["--out", str(read_only_dir / "o")], ""),
        (["--out", str(tmp_path / "a"), "--can-id", "zz"], "--can-id"),
        (["--out", str(tmp_path / "b"), "--rate", "-1"], "--rate"),
        (["--out", str(tmp_path / "c"), "--duration", "0"], "--duration"),
        (["--out", str(tmp_path / "d"), "--zenoh"], "one mode"),
        ([], "one mode"),
        (["--interface", "virtual"], "--channel"),
        (["--interface", "virtual", "--channel", "nope=x"], "unknown nope"),
        (["--out", str(tmp_path / "e"), "--robot", "no_such_robot"], "no such robot"),
        (["--out", str(tmp_path / "f"), "--topic", "/can/none"], "--topic"),
        (["--zenoh", "--loop", "--rate", "0"], "--loop"),
        (["--out", str(tmp_path / "g"), "--rt-priority", "10"], "live playback"),
        (["--zenoh", "--rt-priority", "200"], "1-99"),
    ]
    for args, message in cases:
        rc = main(["replay", path, *args, "--quiet"])
        err = capsys.readouterr().err
        assert rc == 2, (args, err)
        assert err.count("\n") == 1 and message in err and "Traceback" not in err, (args, err)


# ----------------------------------------------------------------------------- live timing

class _Capture:
    """Stands in for a python-can bus in live playback: records what is sent and when;
    ``stall_every``: every n-th frame the send takes ``stall_s`` (a host too busy to send)."""

    def __init__(self, name: str, log: list, stall_every: int = 0, stall_s: float = 0.0):
        self.name, self.log, self.stall_every, self.stall_s = name, log, stall_every, stall_s

    def send(self, msg, timeout=None):
        self.log.append((self.name, msg.timestamp, msg.arbitration_id, bytes(msg.data)))
        if self.stall_every and len(self.log) % self.stall_every == 0:
            time.sleep(self.stall_s)


def _chunked(frame_list, run: int = 16) -> list:
    """The order a direct-receive gateway records in: up to ``run`` frames of one bus, then the
    next bus's, and so on (bursts of a few steps per bus, not log-time order)."""
    per_bus: dict[str, list] = {}
    for b, m in frame_list:
        per_bus.setdefault(b, []).append((b, m))
    out = []
    while any(per_bus.values()):
        for b in per_bus:
            out += per_bus[b][:run]
            per_bus[b] = per_bus[b][run:]
    return out


def test_live_can_plays_a_gateway_recording_in_log_time_order(robot, tmp_path):
    fl = synthetic_frames(robot, 200)
    path = tmp_path / "chunked.mcap"
    record_live(path, robot, _chunked(fl))
    log: list = []
    stats = rp.play_can(path, {b: _Capture(b, log) for b in ("arm0", "arm1", "spacecraft")}, rate=0)
    assert stats.total == len(fl) and stats.late == 0                  # rate 0: nothing is due
    times = [t for _, t, _, _ in log]
    assert times == sorted(times)                                      # across buses: log time
    for b in ("arm0", "arm1", "spacecraft"):                           # each bus: as recorded
        assert ([(i, d) for bb, _, i, d in log if bb == b]
                == [(m.arbitration_id, bytes(m.data)) for bb, m in fl if bb == b])


def test_live_can_counts_frames_sent_late(robot, tmp_path, session):
    path = session[0]
    log: list = []
    buses = {b: _Capture(b, log, stall_every=500, stall_s=0.004) for b in ("arm0", "arm1", "spacecraft")}
    stats = rp.play_can(path, buses, rate=2.0, duration_s=0.3)
    assert stats.total == len(log) > 1000
    assert stats.late >= 1 and stats.late_max_us >= 2000.0, (stats.late, stats.late_max_us)
    assert "sent more than 0.5 ms after their recorded time" in stats.line("sent frames")
    quiet = rp.play_can(path, {b: _Capture(b, []) for b in buses}, rate=0, duration_s=0.3)
    assert quiet.late == 0 and "after their recorded time" not in quiet.line("sent frames")


def test_time_ordered_keeps_ties_and_bounds_its_window():
    items = [("a", 30, 1), ("b", 10, 2), ("a", 30, 3), ("b", 20, 4), ("c", 5_000, 5), ("b", 25, 6)]
    # within the window: sorted by time, equal times in recording order
    assert [o for _, _, o in rp._time_ordered(iter(items), window_ns=10_000)] == [2, 4, 6, 1, 3, 5]
    # a message read more than the window after newer ones went out: sent as soon as it is read
    late = [("b", 10, 1), ("a", 5_000, 2), ("a", 7_000, 3), ("b", 20, 4)]
    assert [o for _, _, o in rp._time_ordered(iter(late), window_ns=1_000)] == [1, 2, 4, 3]


def test_several_can_logs_are_replayed_one_at_a_time(tmp_path, capsys):
    """Many MCAP logs replay on every core; CAN logs are imported one at a time (each needs its
    own channel mapping), so several at once is one line naming bsc import."""
    from gateway.cli import main

    logs = [tmp_path / "a.log", tmp_path / "b.log"]
    for p in logs:
        p.write_text("(1.000000) can0 123#01\n")
    assert main(["replay", *map(str, logs), "--out", str(tmp_path / "o"), "--robot", ROBOT,
                 "--bus", "arm0=can0"]) == 2
    assert "CAN logs replay one at a time (or `bsc import` each" in capsys.readouterr().err


def test_a_full_disk_stops_a_replay_with_the_recorders_error(robot, tmp_path, tiny_fs):
    """The output is written by a thread of its own (gateway/engine/deferred.py): a disk that
    fills up still stops the replay with the recorder's own error, in the caller's thread, and
    leaves no complete-looking output."""
    pipeline = pytest.importorskip("gateway.pipeline")
    from gateway.log.recorder import RecorderError

    path = tmp_path / "live.mcap"
    record_live(path, robot, synthetic_frames(robot, 3000, seed=3), pipeline.Pipeline)
    with pytest.raises((RecorderError, OSError)) as err:
        rp.replay_offline(path, tiny_fs / "out", samples=True)
    assert "No space left" in str(err.value) or "ENOSPC" in str(err.value) or err.value.errno == 28
    assert not (tiny_fs / "out" / rp.OUTPUT_NAME).exists()
