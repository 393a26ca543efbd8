"""``bsc sim`` with the CAN options, run as a user runs it (a subprocess)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]


def _bsc(*args, tmp):
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    # as the `bsc` entry point calls it (``-m gateway.cli`` would load gateway.cli twice)
    main = "import sys; from gateway.cli import main; sys.exit(main())"
    return subprocess.run([sys.executable, "-c", main, "sim", "--duration", "0.05", "--no-plots",
                           "--quiet", "--out", str(tmp), *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=120)


def test_sim_sends_on_virtual_buses_with_faults(tmp_path):
    r = _bsc("--interface", "virtual", "--channel", "bsc-cli-test", "--drop-rate", "0.2",
             "--silent", "arm1/j1:0.01:0.02", "--counter-jump", "imu:0.02:3", "--fault-seed", "4", tmp=tmp_path)
    assert r.returncode == 0, r.stderr
    s = json.loads((tmp_path / "summary.json").read_text())
    assert (tmp_path / "truth.npz").is_file()
    can = s["can"]
    assert can["channels"] == {"arm0": "bsc-cli-test-arm0", "arm1": "bsc-cli-test-arm1",
                               "spacecraft": "bsc-cli-test-spacecraft"}
    assert can["frames_sent"]["arm0"] > 150 and can["faults_injected"]["drop"] > 0
    assert can["faults_per_device"]["arm1/j1"]["silent"] == 20
    assert can["faults_per_device"]["imu"]["jump"] == 3
    assert "sent on virtual (lockstep)" in r.stdout


def test_sim_without_interface_is_unchanged(tmp_path):
    r = _bsc(tmp=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "can" not in json.loads((tmp_path / "summary.json").read_text())


def test_sim_can_errors_are_one_line(tmp_path):
    for args, words in ((("--drop-rate", "0.1"), "need --interface"),
                        (("-i", "virtual", "--silent", "arm0:soon"), "DEVICE:START_S:DURATION_S"),
                        (("-i", "virtual", "--silent", "arm7:0:1"), "no device 'arm7'"),
                        (("-i", "virtual", "--drop-rate", "2"), "probability"),
                        (("-i", "virtual", "-c", "arm0=a"), "missing arm1, spacecraft"),
                        (("-i", "no_such_interface",), "cannot open the CAN buses"),
                        (("-i", "virtual", "--rt-priority", "10"), "needs --realtime"),
                        (("-i", "virtual", "--realtime", "--rt-priority", "100"), "1-99")):
        r = _bsc(*args, tmp=tmp_path)
        assert r.returncode == 2, (args, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1 and words in r.stderr, (args, r.stderr)


def test_sim_realtime_reports_its_pacing(tmp_path):
    """``--realtime`` says how late its steps went out, printed and in summary.json; with
    ``--rt-priority`` it runs at SCHED_FIFO (where allowed) or says in one line why it cannot."""
    r = _bsc("--interface", "virtual", "--channel", "bsc-cli-rt", "--realtime", tmp=tmp_path)
    assert r.returncode == 0, r.stderr
    pc = json.loads((tmp_path / "summary.json").read_text())["can"]["pacing"]
    assert pc["steps"] == 50 and pc["period_us"] == 1000.0
    assert 0 <= pc["p50_us"] <= pc["p99_us"] <= pc["max_us"] and 0 <= pc["late_steps"] <= 50
    assert "real-time pacing: steps sent p50" in r.stdout
    r = _bsc("--interface", "virtual", "--channel", "bsc-cli-rt", "--realtime", "--rt-priority", "5", tmp=tmp_path)
    allowed = os.geteuid() == 0          # root here; elsewhere it depends on CAP_SYS_NICE / rlimits
    if r.returncode == 0:
        assert json.loads((tmp_path / "summary.json").read_text())["can"]["pacing"]["steps"] == 50
    else:
        assert not allowed and r.returncode == 2 and "CAP_SYS_NICE" in r.stderr, r.stderr
