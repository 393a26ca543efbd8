"""``bsc record``: raw CAN per bus and every zenoh sample into one MCAP file with its context;
clean stop on SIGTERM; one-line errors."""
from __future__ import annotations

import base64
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
import uuid

import can
import pytest
import zenoh

import robot_description
from drivers import frames, wire
from drivers.samples import JointSample, WrenchSample
from gateway import codec, keys
from gateway.cli import main
from gateway.commands.record import REJECTED_TOPIC, Recording
from gateway.efforts import ThrusterEffort
from gateway.log.recorder import Recorder
from gateway.log.context import read_context, session_context
from gateway.zenoh_config import make_config
from gateway.log import reader, scan

from .conftest import REPO
from support import free_port as _free_port

ROBOT = "paper_robot"


def _until(cond, timeout_s: float = 30.0) -> bool:
    """Wait for a condition another thread makes true (synchronisation, not a timing check)."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def test_recording_can_and_zenoh(tmp_path):
    robot = robot_description.load(ROBOT)
    prefix = f"bsc-rec-{uuid.uuid4().hex}"
    path = tmp_path / "s.mcap"
    ep = f"tcp/127.0.0.1:{_free_port()}"
    names = ["arm0", "spacecraft"]
    rx = {b: can.Bus(interface="virtual", channel=wire.channel_name(prefix, b),
                     ignore_config=True) for b in names}
    tx = {b: can.Bus(interface="virtual", channel=wire.channel_name(prefix, b),
                     ignore_config=True) for b in names}
    sent = {b: [] for b in names}
    samples = [WrenchSample("arm0", 1_000_000 + i, i, (1.0, 2.0, float(i)), (0.5, 0.25, 0.0))
               for i in range(50)]
    effort = ThrusterEffort(5, (1.0, 2.0, 3.0), (0.0, 0.0, 0.1), (0.0,) * 3, (0.0,) * 3, 0, 3,
                            True, ("x",))
    try:
        with zenoh.open(make_config(listen=[ep])) as rec_s, \
                zenoh.open(make_config(connect=[ep])) as pub_s, \
                Recorder(path) as rec:
            rec.add_session_context(**session_context(robot))
            with Recording(rec, rx, rec_s, keys.everything(ROBOT)) as recording:
                for i in range(200):
                    b = names[i % 2]
                    msg = frames.encode_joint(JointSample("arm0/j0", 0, i, 0.1 * i, 0.0), 0) \
                        if b == "arm0" else can.Message(arbitration_id=0x405, data=bytes([i]) * 8,
                                                        is_extended_id=False)
                    tx[b].send(msg)
                    sent[b].append(bytes(msg.data))
                # BLOCK: the test checks the recorder, not zenoh's drop policy for sensor keys
                block = zenoh.CongestionControl.BLOCK
                pub_w = pub_s.declare_publisher(keys.wrench(ROBOT, "arm0"), congestion_control=block)
                pub_e = pub_s.declare_publisher(keys.thruster_effort(ROBOT), congestion_control=block)
                assert _until(lambda: pub_w.matching_status.matching and pub_e.matching_status.matching)
                for s in samples:
                    pub_w.put(codec.encode(s))
                pub_e.put(codec.encode(effort))
                pub_w.put(b"not json at all")                       # undecodable
                pub_w.put(codec.encode(effort))                     # a second type on one key
                assert _until(lambda: sum(recording.frames.values()) == 200
                              and sum(recording.samples.values()) == 51
                              and sum(recording.rejected.values()) == 2), recording.summary()
                pub_w.undeclare()
                pub_e.undeclare()
            lines = recording.summary()
    finally:
        for b in list(rx.values()) + list(tx.values()):
            b.shutdown()
    assert rec.stats.dropped == 0
    assert "CAN frames: 200 (arm0 100, spacecraft 100)" in lines[0]
    assert "undecodable 1" in lines[2] and "type_conflict 1" in lines[2]

    info = scan.inspect(path)
    assert info.complete
    by_topic = {c.topic: c for c in info.channels}
    assert by_topic["/can/arm0"].schema_name == "bsc.CanFrame"
    assert by_topic[keys.wrench(ROBOT, "arm0")].schema_name == "drivers.samples.WrenchSample"
    assert by_topic[keys.thruster_effort(ROBOT)].schema_name == "gateway.efforts.ThrusterEffort"
    assert by_topic[REJECTED_TOPIC].count == 2
    for b in names:
        got = [bytes(m.data) for _, _, m in reader.iter_can_frames(path, buses=[b], log_time_order=True)]
        assert got == sent[b]
    got = [reader.to_dataclass(WrenchSample, m.data)
           for m in reader.read_messages(path, [keys.wrench(ROBOT, "arm0")])]
    assert got == samples
    rej = [m.data for m in reader.read_messages(path, [REJECTED_TOPIC])]
    assert {r["reason"] for r in rej} == {"undecodable", "type_conflict"}
    assert base64.b64decode(next(r for r in rej if r["reason"] == "undecodable")["payload"]) \
        == b"not json at all"
    ctx = read_context(path)
    assert ctx.robot_name == ROBOT and sorted(ctx.buses) == ["arm0", "spacecraft"]
    assert {"robot.urdf", "dbc/bsc_arm.dbc", "dbc/bsc_spacecraft.dbc"} <= set(ctx.attachments)
    assert ctx.metadata["zenoh.keys"]["wrench/arm0"] == keys.wrench(ROBOT, "arm0")
    assert ctx.metadata["bsc.session"]["software"].startswith("bsc ")


def _env():
    return dict(os.environ, OPENBLAS_NUM_THREADS="1",
                PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def test_sigterm_finishes_the_file(tmp_path):
    out = tmp_path / "t.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-m", "gateway.cli", "record", "--robot", ROBOT, "--out", str(out),
         "--interface", "virtual", "--channel", f"bsc-rec-{uuid.uuid4().hex}", "--no-zenoh"],
        cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stdout.readline()          # printed once buses and file are open
        assert first.startswith("bsc record: robot paper_robot"), (first, proc.stderr.read())
        proc.send_signal(signal.SIGTERM)
        rest, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert err == ""
    assert "CAN frames: 0" in rest and f"wrote {out}" in rest
    info = scan.inspect(out)
    assert info.complete
    assert {"bsc.recording", "bsc.session", "zenoh.keys"} <= set(info.metadata)
    assert info.metadata["bsc.session"]["robot"] == ROBOT


def test_duration_zenoh_and_split_naming(tmp_path, capsys):
    out = tmp_path / "z.mcap"
    rc = main(["record", "--robot", ROBOT, "--out", str(out), "--duration", "0.2",
               "--split-size", "1", "--connect", f"tcp/127.0.0.1:{_free_port()}"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "zenoh samples: 0" in cap.out and "zenoh rejected: 0" in cap.out
    first = tmp_path / "z_0000.mcap"
    assert f"wrote {first}" in cap.out
    assert scan.inspect(first).complete
    assert json.loads(json.dumps(read_context(first).metadata["bsc.session"]))["robot"] == ROBOT


def test_record_errors_are_one_line(tmp_path, read_only_dir, capsys):
    existing = tmp_path / "e.mcap"
    existing.write_bytes(b"x")
    cases = [
        (["--out", str(read_only_dir / "x.mcap"), "--no-zenoh", "--interface", "virtual",
          "--channel", "c"], ""),
        (["--out", str(existing)], "--force"),
        (["--out", str(tmp_path / "a.mcap"), "--channel", "c"], "--interface"),
        (["--out", str(tmp_path / "b.mcap"), "--no-zenoh"], "nothing to record"),
        (["--out", str(tmp_path / "c.mcap"), "--robot", "nope"], "no such robot"),
        (["--out", str(tmp_path / "d.mcap"), "--duration", "-1"], "--duration"),
        (["--out", str(tmp_path / "f.mcap"), "--interface", "virtual", "--channel", "a=b"],
         "--channel"),
        (["--out", str(tmp_path / "g" / "h.mcap"), "--no-zenoh", "--interface", "virtual",
          "--channel", "c"], "No such file"),
    ]
    for args, message in cases:
        rc = main(["record", "--robot", ROBOT, *args] if "--robot" not in args
                  else ["record", *args])
        err = capsys.readouterr().err
        assert rc == 2, (args, err)
        assert err.count("\n") == 1 and err.startswith("bsc record: error: "), (args, err)
        assert message in err, (args, err)
    assert existing.read_bytes() == b"x"
    assert not (tmp_path / "a.mcap").exists()


@pytest.mark.skipif(os.geteuid() != 0, reason="mounts a small tmpfs (root)")
def test_a_full_disk_stops_the_recording_at_once_with_one_error(tmp_path):
    """bsc record on a 256 KiB filesystem, fed zenoh samples until it stops: it stops on its own
    as soon as a write fails (not at --duration), prints its summary with the messages and bytes
    really in the file, then one error line, exit 2; bsc recover gets back every message the
    summary says is in the file."""
    import random

    from support import subscribed

    disk = tmp_path / "disk"
    disk.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(disk)], check=True)
    try:
        out, ep = disk / "s.mcap", f"tcp/127.0.0.1:{_free_port()}"
        proc = subprocess.Popen(
            [sys.executable, "-m", "gateway.cli", "record", "--robot", ROBOT, "--out", str(out),
             "--listen", ep, "--duration", "300"],
            cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            first = proc.stdout.readline()
            assert first.startswith("bsc record: robot paper_robot"), (first, proc.stderr.read())
            rnd = random.Random(1)
            key = keys.wrench(ROBOT, "arm0")
            with zenoh.open(make_config(connect=[ep])) as pub_s:
                pub = pub_s.declare_publisher(key)
                subscribed(pub_s, key)
                sent, deadline = 0, time.monotonic() + 120
                while proc.poll() is None and time.monotonic() < deadline:
                    for _ in range(50):
                        pub.put(codec.encode(WrenchSample("arm0", sent, sent & 0xFF,
                                                          tuple(rnd.uniform(-50, 50) for _ in range(3)),
                                                          tuple(rnd.uniform(-5, 5) for _ in range(3)))))
                        sent += 1
                    time.sleep(0.005)
                stopped = proc.poll() is not None
            rest, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        assert stopped, f"still recording after {sent} samples"
        assert proc.returncode == 2, (rest, err)
        assert err.count("\n") == 1 and "No space left on device" in err and "bsc recover" in err, err
        line = next(x for x in rest.splitlines() if x.startswith("bsc record: recorder: "))
        in_file = int(line.split("recorder: ")[1].split()[0])
        size = int(line.split(" bytes")[0].rsplit(" ", 1)[1])
        assert size == out.stat().st_size > 100_000, (line, out.stat().st_size)
        assert "stopped: " in line and "write error " in line
        fixed = scan.recover(out, tmp_path / "fixed.mcap")
        got = sum(1 for _ in reader.read_messages(tmp_path / "fixed.mcap", [key]))
        assert got == fixed.messages == in_file > 100, (got, fixed.messages, in_file)
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)


def test_an_alert_is_also_recorded_as_a_foxglove_log_line(tmp_path):
    """Foxglove's Log panel takes foxglove.Log on any topic: each alert bsc record receives is
    recorded as itself and as a log line at its severity's level (a cleared one at info)."""
    from gateway.efforts import Alert
    from gateway.log.foxglove import ALERT_LOG_TOPIC, LOG_SCHEMA_NAME

    path = tmp_path / "a.mcap"
    alert = Alert(ROBOT, "actuator", "arm0/j2", "joint-friction-high", "critical", "raised", 1_000, 2_500_000_001,
                  "friction 182 N m > 150", (("friction_nm", 182.0),))
    with Recorder(path) as rec:
        recording = Recording(rec, {}, None, None)
        for a in (alert, dataclasses.replace(alert, state="cleared", t_ns=3_000_000_000)):
            recording.on_payload(keys.alerts(ROBOT), codec.encode(a))
    logs = list(reader.read_messages(path, [ALERT_LOG_TOPIC]))
    assert [m.schema_name for m in logs] == [LOG_SCHEMA_NAME] * 2
    assert [m.log_time_ns for m in logs] == [2_500_000_001, 3_000_000_000] and logs[1].data["level"] == 2
    first = logs[0].data
    assert first["timestamp"] == {"sec": 2, "nsec": 500_000_001} and first["level"] == 4
    assert first["name"] == f"bsc/{ROBOT}/actuator/arm0/j2 [joint-friction-high]"
    assert first["message"] == "raised critical: friction 182 N m > 150"
    alerts = list(reader.read_messages(path, [keys.alerts(ROBOT)]))
    assert len(alerts) == len(logs)
