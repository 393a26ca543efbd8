"""Crash safety: SIGKILL a recording process mid-run, recover the file, count what came back.

"Had written" = the child's last reported ``stats.flushed`` before the kill: messages the
recorder had put into finished chunks and handed to the OS with write(2). A SIGKILL cannot take
those back (the page cache survives the process), so all of them must be recovered; the 99.9 %
bar is the requirement, the test also checks the stronger "all, in order, no holes".
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gateway.log import reader, scan
REPO = Path(__file__).resolve().parents[3]


@pytest.mark.slow
def test_sigkill_mid_run_then_recover(tmp_path):
    path = tmp_path / "killed.mcap"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", PYTHONPATH=str(REPO))
    child = subprocess.Popen([sys.executable, "-m", "tests.gateway.log._crash_child", str(path),
                              "4000"], stdout=subprocess.PIPE, text=True, cwd=REPO, env=env)
    last_flushed = 0
    try:
        assert child.stdout.readline().strip() == "started"
        deadline = time.monotonic() + 30
        for line in child.stdout:               # paced by the child's own reports
            word, *rest = line.split()
            assert word != "refused", line
            last_flushed = int(rest[0])
            if last_flushed >= 6000 or time.monotonic() > deadline:
                break
        child.send_signal(signal.SIGKILL)       # mid-run: a chunk is being filled right now
        child.wait(10)
        # Reports written after the one we stopped reading at are still "had written".
        for line in child.stdout.read().splitlines():
            if line.startswith("flushed"):
                last_flushed = int(line.split()[1])
    finally:
        if child.poll() is None:
            child.kill()
            child.wait(10)
        child.stdout.close()
    assert child.returncode == -signal.SIGKILL
    assert last_flushed >= 6000

    before = scan.inspect(path)
    assert not before.complete                  # killed: no summary, no footer
    report = scan.recover(path, tmp_path / "recovered.mcap")
    assert not report.was_complete
    print(f"had written (flushed) {last_flushed}, recovered {report.messages}")
    assert report.messages >= 0.999 * last_flushed
    assert report.messages >= last_flushed      # in fact nothing flushed is lost
    after = scan.inspect(report.output)
    assert after.complete and after.message_count == report.messages
    assert "robot.urdf" in {a["name"] for a in after.attachments}
    assert {"bsc.recording", "bsc.session", "bsc.recover"} <= set(after.metadata)
    # Every recovered frame is intact and they form one unbroken prefix 0..n-1.
    payloads = [int.from_bytes(m.data, "little")
                for _, _, m in reader.iter_can_frames(report.output, log_time_order=True)]
    assert payloads == list(range(report.messages))
