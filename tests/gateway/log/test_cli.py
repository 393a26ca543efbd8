"""``bsc info`` and ``bsc recover`` as a user runs them (subprocesses)."""
from __future__ import annotations

import json

import can

from drivers.samples import WrenchSample
from gateway.log.recorder import Recorder


def _log(path, gap_at: int | None = None):
    with Recorder(path, chunk_size=4096) as rec:
        rec.add_session_context(urdf_text="<robot/>", zenoh_keys={"w": "bsc/w"}, software="t")
        t = 1_000_000_000
        for i in range(500):
            t += 10_000_000 if i != gap_at else 2_500_000_000      # 100 Hz, one 2.5 s hole
            rec.record_can("ft0", can.Message(timestamp=t / 1e9, arbitration_id=5, data=b"\1"))
            rec.record("/samples/wrench/arm0",
                       WrenchSample("arm0", t, i, (0.0, 0.0, 1.0), (0.0, 0.0, 0.0)))
    return rec


def test_info_text_and_json(tmp_path, bsc):
    path = tmp_path / "run.mcap"
    _log(path, gap_at=200)
    proc = bsc("info", path)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert "complete (valid summary and footer)" in out
    assert "/can/ft0" in out and "/samples/wrench/arm0" in out
    assert "gaps > 1 s:" in out and "2.500 s" in out
    assert "bsc.recording" in out and "robot.urdf" in out

    proc = bsc("info", "--json", "--gap-s", "0.5", path)
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    assert info["complete"] is True and info["message_count"] == 1000
    chans = {c["topic"]: c for c in info["channels"]}
    ft = chans["/can/ft0"]
    assert ft["count"] == 500 and abs(ft["max_gap_s"] - 2.5) < 1e-9
    assert len(ft["gaps"]) == 1 and ft["gaps_total"] == 1
    assert 50 < ft["rate_hz"] < 100
    assert info["metadata"]["zenoh.keys"] == {"w": "bsc/w"}
    assert [a["name"] for a in info["attachments"]] == ["robot.urdf"]


def test_truncated_info_then_recover(tmp_path, bsc):
    path = tmp_path / "run.mcap"
    _log(path)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size * 2 // 3])
    proc = bsc("info", cut)
    assert proc.returncode == 0 and "truncated" in proc.stdout
    assert f"bsc recover {cut}" in proc.stdout
    assert json.loads(bsc("info", "--json", cut).stdout)["complete"] is False

    proc = bsc("recover", cut)
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "cut.recovered.mcap"
    assert f"wrote {out}" in proc.stdout
    info = json.loads(bsc("info", "--json", out).stdout)
    assert info["complete"] is True and 0 < info["message_count"] < 1000
    assert "bsc.recover" in info["metadata"] and "robot.urdf" in {a["name"] for a in info["attachments"]}


def test_recover_of_a_complete_file_is_a_copy(tmp_path, bsc):
    path = tmp_path / "ok.mcap"
    _log(path)
    proc = bsc("recover", path, "-o", tmp_path / "copy.mcap")
    assert proc.returncode == 0 and "already complete" in proc.stdout
    assert json.loads(bsc("info", "--json", tmp_path / "copy.mcap").stdout)["message_count"] == 1000


def test_bad_gap_option(tmp_path, bsc):
    path = tmp_path / "ok.mcap"
    _log(path)
    proc = bsc("info", "--gap-s", "0", path)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
