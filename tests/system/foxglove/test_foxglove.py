"""bsc logs as Foxglove reads them: Foxglove's MCAP library for Node (@mcap/core) reads every
kind of log bsc writes, every schema is one Foxglove's JSON-schema loader takes, and every message
validates against its schema (ajv); foxglove.* schemas against the published ones.

Needs node and the npm packages of ``tests/system/foxglove`` (``.ci/foxglove-tier.sh`` installs them with
``npm ci`` and runs these tests; CI runs that tier after the main suite). Without them the tests
are skipped with that reason."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import can
import pytest

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]
READY = shutil.which("node") is not None and (HERE / "node_modules" / "@mcap" / "core").is_dir()

if not READY and os.environ.get("BSC_FOXGLOVE_TIER"):
    raise RuntimeError("the Foxglove tier needs node and tests/system/foxglove/node_modules "
                       "(npm ci --prefix tests/system/foxglove)")

pytestmark = [pytest.mark.foxglove,
              pytest.mark.skipif(not READY, reason="needs node and tests/system/foxglove/node_modules: "
                                                   "run .ci/foxglove-tier.sh (npm ci)")]


def check(path: Path) -> dict:
    out = subprocess.run(["node", str(HERE / "check_mcap.mjs"), str(path)], capture_output=True, text=True,
                         timeout=600)
    assert out.stdout, out.stderr
    report = json.loads(out.stdout)
    assert out.returncode == 0 and report["ok"], json.dumps(report["problems"], indent=1)
    return report


def _bsc(*args: str) -> None:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-m", "gateway.cli", *args], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    """A session made the real way: the simulator's firmware frames through the drivers and the
    estimator, recorded with its raw frames, samples, efforts and health."""
    out = tmp_path_factory.mktemp("series")
    _bsc("sim", "--series", "healthy", "--sessions", "1", "--duration", "1", "--out", str(out), "--quiet")
    return out / "session_0000.mcap"


def test_a_recorded_session(session):
    report = check(session)
    for kind in ("bsc.CanFrame", "drivers.samples.WrenchSample", "drivers.samples.ImuSample",
                 "gateway.efforts.JointEfforts", "gateway.efforts.ThrusterEffort", "gateway.efforts.ValveWrenches",
                 "drivers.samples.BusHealth", "drivers.samples.DeviceHealth"):
        assert report["schemas"][kind]["messages"] > 0, kind
    assert report["messages"] > 10_000 and report["invalid"] == 0
    _check_robot_tree(report, "paper_robot", seconds=1.0)


def _check_robot_tree(report: dict, robot: str, seconds: float) -> None:
    """The 3D panel's inputs: foxglove.FrameTransforms at 50 Hz (checked against the published
    schema), one tree rooted at world whose frames are the URDF's links, the URDF in the log."""
    import robot_description

    links = sorted(j.child for j in robot_description.urdf_joints(robot_description.load(robot).urdf))
    n = report["schemas"]["foxglove.FrameTransforms"]["messages"]
    assert abs(n - 50 * seconds) <= 2 and report["schemas"]["foxglove.FrameTransforms"]["invalid"] == 0
    tf = report["tf"]
    assert tf["roots"] == ["world"] and tf["urdf_messages"] == 1
    assert tf["frames"] == sorted([*links, "spacecraft", "world"])
    assert tf["urdf_links"] == sorted([*links, "spacecraft"])
    assert tf["transforms"] == n * (len(links) + 1)          # every joint and the attitude, every time


def test_a_replay_output(session, tmp_path):
    """What bsc replay writes (efforts and samples written straight from rows)."""
    _bsc("replay", str(session), "--out", str(tmp_path / "replay"), "--samples", "--quiet")
    report = check(tmp_path / "replay" / "replay.mcap")
    assert report["schemas"]["gateway.efforts.ThrusterEffort"]["messages"] > 0
    assert report["schemas"]["gateway.efforts.ValveWrenches"]["messages"] > 0
    assert report["schemas"]["drivers.samples.JointSample"]["messages"] > 0
    _check_robot_tree(report, "paper_robot", seconds=1.0)


def test_the_records_with_named_counts_alerts_and_odd_channels(tmp_path):
    """Health with rejections and nodes, an alert with evidence, frames whose python-can channel
    is none, an integer or text, a plain dict record: each in the form Foxglove takes."""
    import dataclasses

    from drivers.samples import BusHealth, DeviceHealth
    from gateway import codec
    from gateway.commands.record import Recording
    from gateway.efforts import Alert
    from gateway.log.recorder import Recorder

    path = tmp_path / "odd.mcap"
    with Recorder(path) as rec:
        rec.record("bsc/r/health/device/imu", DeviceHealth("imu", "spacecraft", 5, 10, 2, 1,
                                                           (("dlc", 1), ("late", 3)), 4, False))
        rec.record("bsc/r/health/bus/arm0", BusHealth("arm0", 5, 9, (("unknown_id", 2),), 0.4, (("ft", 5),)))
        alert = Alert("r", "sensor", "imu", "sensor-stale", "critical", "raised", 5, 7,
                      "sensor imu: staleness_s = 0.7 > 0.5", (("staleness_s", 0.7), ("raise", 0.5)))
        recording = Recording(rec, {}, None, None)          # bsc record's path: also a foxglove.Log line
        recording.on_payload("bsc/r/alerts", codec.encode(alert))
        recording.on_payload("bsc/r/alerts", codec.encode(dataclasses.replace(alert, state="cleared", t_ns=9)))
        for i, ch in enumerate((None, 0, "can0", ["a", "list"])):
            rec.record_can("arm0", can.Message(timestamp=1 + i, arbitration_id=0x100 + i, data=b"\x01\x02",
                                               channel=ch))
        rec.record("bsc/r/note", {"text": "free-form", "n": 3}, log_time_ns=9)
    report = check(path)
    assert report["schemas"]["gateway.efforts.Alert"]["messages"] == 2
    assert report["schemas"]["foxglove.Log"]["messages"] == 2        # checked against the published schema too
    assert report["schemas"]["bsc.CanFrame"]["messages"] == 4


def test_the_checker_catches_a_frame_tree_foxglove_would_not_draw(tmp_path):
    """The checks above can fail: a foxglove.FrameTransforms schema that is not the published
    one, a transform the published schema refuses (no rotation.w), a frame with two parents,
    a tree with two roots, a URDF link with no frame."""
    from gateway.log.foxglove import (FRAME_TRANSFORMS_SCHEMA, ROBOT_DESCRIPTION_SCHEMA, ROBOT_DESCRIPTION_TOPIC,
                                      TF_TOPIC)
    from gateway.log.recorder import Recorder

    def tf(parent, child, **rotation):
        return {"timestamp": {"sec": 1, "nsec": 0}, "parent_frame_id": parent, "child_frame_id": child,
                "translation": {"x": 0.0, "y": 0.0, "z": 0.0}, "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, **rotation}}

    good = tmp_path / "good.mcap"
    bad = tmp_path / "bad.mcap"
    for path, schema, transforms in (
            (good, FRAME_TRANSFORMS_SCHEMA, [tf("world", "spacecraft", w=1.0), tf("spacecraft", "imu", w=1.0)]),
            (bad, {**FRAME_TRANSFORMS_SCHEMA, "required": []},
             [tf("world", "spacecraft"), tf("spacecraft", "imu", w=1.0), tf("other", "imu", w=1.0)])):
        with Recorder(path) as rec:
            rec.add_channel(TF_TOPIC, schema)
            rec.add_channel(ROBOT_DESCRIPTION_TOPIC, ROBOT_DESCRIPTION_SCHEMA)
            urdf = ('<robot name="r"><link name="spacecraft"/><link name="imu"/>'
                    + ('<link name="arm"/>' if path == bad else "") + "</robot>")
            rec.record(ROBOT_DESCRIPTION_TOPIC, {"data": urdf, "robot": "r"}, log_time_ns=1)
            rec.record(TF_TOPIC, {"transforms": transforms}, log_time_ns=1)
    check(good)
    out = subprocess.run(["node", str(HERE / "check_mcap.mjs"), str(bad)], capture_output=True, text=True, timeout=120)
    report = json.loads(out.stdout)
    assert out.returncode == 1 and not report["ok"]
    problems = "\n".join(report["problems"])
    for expected in ("foxglove.FrameTransforms: differs from the published schema",
                     "published schema: data/transforms/0/rotation must have required property 'w'",
                     "frame imu has two parents", "2 roots", "URDF link arm is no frame of /tf"):
        assert expected in problems, (expected, problems)
