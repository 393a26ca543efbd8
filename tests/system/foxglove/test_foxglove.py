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
                 "gateway.efforts.JointEfforts", "gateway.efforts.ThrusterEffort",
                 "drivers.samples.BusHealth", "drivers.samples.DeviceHealth"):
        assert report["schemas"][kind]["messages"] > 0, kind
    assert report["messages"] > 10_000 and report["invalid"] == 0


def test_a_replay_output(session, tmp_path):
    """What bsc replay writes (efforts and samples written straight from rows)."""
    _bsc("replay", str(session), "--out", str(tmp_path / "replay"), "--samples", "--quiet")
    report = check(tmp_path / "replay" / "replay.mcap")
    assert report["schemas"]["gateway.efforts.ThrusterEffort"]["messages"] > 0
    assert report["schemas"]["drivers.samples.JointSample"]["messages"] > 0


def test_the_records_with_named_counts_alerts_and_odd_channels(tmp_path):
    """Health with rejections and nodes, an alert with evidence, frames whose python-can channel
    is none, an integer or text, a plain dict record: each in the form Foxglove takes."""
    import dataclasses

    from drivers.samples import BusHealth, DeviceHealth
    from gateway import codec
    from gateway.commands.record import Recording
    from gateway.efforts import Alert
    from gateway.recorder import Recorder

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
