"""Change detection and attribution across sessions, on per-session values with known faults."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gateway.analysis import collect_sessions
from gateway.analysis.change import Detector, analyze_series, cusum_track
from gateway.analysis.session import AxisFit, JointFit, SessionFeatures

from .synth import write_session

ROOT = Path(__file__).resolve().parents[3]
JOINTS = ("arm0/j1", "arm0/j2", "arm1/j1", "arm1/j2")


def features(k, rng, *, coulomb=None, offset=None, eff=None, quiet=None):
    coulomb, offset, eff, quiet = coulomb or {}, offset or {}, eff or {}, quiet or {}
    s = SessionFeatures(f"/x/session_{k:04d}.mcap", "bot", k, k, k + 1,
                        arms={"arm0": ["arm0/j1", "arm0/j2"], "arm1": ["arm1/j1", "arm1/j2"]})
    for j in JOINTS:
        s.joints[j] = JointFit(j, coulomb.get(j, 90.0) + rng.normal(0, 0.5), 8.0,
                               offset.get(j, 0.0) + rng.normal(0, 0.5), 8.0, 1000, 500, 500, True)
    for a in ("fx", "fy", "fz", "mx", "my", "mz"):
        weak = a in ("fz", "mx", "my")
        s.axes[a] = AxisFit(a, float("nan") if weak else eff.get(a, 0.9) + rng.normal(0, 0.01), 0.0, 50.0, 5.0, 1000,
                            not weak, quiet.get(a, 0.0) + rng.normal(0, 1.0), 100)
    return s


def series(n, onset, fault, seed=0):
    rng = np.random.default_rng(seed)
    return [features(k, rng, **(fault(k - onset + 1) if k >= onset else {})) for k in range(n)]


def kinds(result):
    return [(f.kind, f.target, f.session_index) for f in result.findings if f.state == "raised"]


def test_healthy_series_raises_nothing():
    for seed in range(20):
        assert analyze_series(series(30, 99, None, seed)).findings == []


def test_friction_growth_is_an_actuator_fault_on_that_joint():
    res = analyze_series(series(12, 4, lambda s: {"coulomb": {"arm0/j2": 90.0 + 15.0 * s}}))
    got = kinds(res)
    assert [(k, t) for k, t, _ in got] == [("actuator", "arm0/j2")]
    assert got[0][2] - 4 <= 1            # a 5-sigma first step: CUSUM h = 5 needs at most one more session
    ev = res.findings[0].to_json()["evidence"]
    assert ev["arm0/j2.coulomb_nm.baseline"] == pytest.approx(90.0, abs=1.0)
    assert ev["arm0/j2.coulomb_nm.cusum"] > ev["threshold_h"]


def test_thruster_loss_is_a_thruster_fault():
    res = analyze_series(series(12, 4, lambda s: {"eff": {"fx": 0.8, "mz": 0.85}}))
    got = kinds(res)
    assert all(k == "thruster" for k, _, _ in got)
    assert {t for _, t, _ in got} == {"fx", "mz"} and min(i for _, _, i in got) <= 5


def test_efficiency_rise_is_not_a_thruster_fault():
    res = analyze_series(series(12, 4, lambda s: {"eff": {"fx": 0.9 + 0.02 * s}}))
    assert kinds(res) == []


def test_ft_bias_is_a_sensor_fault_of_its_arm_not_an_actuator_fault():
    res = analyze_series(series(12, 4, lambda s: {"offset": {"arm0/j1": -5.0 * s, "arm0/j2": 30.0 * s},
                                                  "coulomb": {"arm0/j2": 90.0 - 1.0 * s},
                                                  "quiet": {"fx": 7.0 * s, "mz": -5.0 * s}}))
    got = kinds(res)
    assert got and all(k == "sensor" for k, _, _ in got)
    assert ("sensor", "arm0", 4) in got
    assert not any(t == "imu" for _, t, _ in got)


def test_momentum_inconsistency_alone_points_at_the_imu():
    res = analyze_series(series(10, 4, lambda s: {"quiet": {"fx": 10.0 * s}}))
    assert kinds(res)[0][:2] == ("sensor", "imu")


def test_alert_clears_when_the_fault_goes_away():
    res = analyze_series(series(14, 4, lambda s: {"coulomb": {"arm1/j1": 130.0}} if s <= 3 else {}))
    states = [(f.state, f.target) for f in res.findings]
    assert states == [("raised", "arm1/j1"), ("cleared", "arm1/j1")]


def test_cusum_skips_unidentifiable_sessions_and_respects_direction():
    det = Detector("d", "coulomb_nm", "actuator", "up", 1.0, 0.0, 0.5, 4.0)
    tr = cusum_track(det, "j", [10, float("nan"), 10, 10, 5, 5, 5, 5, 20])
    assert tr.mu == 10 and tr.baseline_n == 3
    assert tr.alarm == [False] * 8 + [True]        # the drops never alarm an "up" detector


def write_series(tmp_path, n, onset, **fault):
    paths = []
    for k in range(n):
        kw = fault if k >= onset else {}
        # written in reverse so that file order is NOT time order
        paths.append(write_session(tmp_path / f"z{n - k:02d}.mcap", k, seed=k, n=1500, **kw))
    return paths


def test_collect_sessions_orders_by_series_metadata(tmp_path):
    write_series(tmp_path, 4, 99)
    files = collect_sessions([tmp_path])
    assert [f.name for f in files] == ["z04.mcap", "z03.mcap", "z02.mcap", "z01.mcap"]


def test_bsc_analyze_json_and_report_as_a_user_runs_it(tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    coulomb = {"arm0/j1": 90.0, "arm0/j2": 90.0, "arm1/j1": 90.0, "arm1/j2": 140.0}
    write_series(logs, 6, 4, coulomb=coulomb)
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-m", "gateway.cli", "analyze", str(logs), "--json", "--workers", "2",
                          "--report", str(tmp_path / "rep")], capture_output=True, text=True, env=env, cwd=ROOT,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    lines = [json.loads(x) for x in out.stdout.splitlines()]
    assert [(a["kind"], a["target"], a["state"], a["session"]) for a in lines] == \
        [("actuator", "arm1/j2", "raised", "z02")]
    assert set(lines[0]) >= {"session", "kind", "target", "severity", "evidence"}
    assert (tmp_path / "rep" / "report.md").read_text().count("arm1/j2") >= 1
    assert (tmp_path / "rep" / "friction.png").stat().st_size > 1000
    text = subprocess.run([sys.executable, "-m", "gateway.cli", "analyze", str(logs), "--workers", "1"],
                          capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
    assert text.returncode == 0 and "friction per joint" in text.stdout and "actuator" in text.stdout


def test_bsc_analyze_errors_are_one_line(tmp_path):
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-m", "gateway.cli", "analyze", str(tmp_path / "nope")],
                         capture_output=True, text=True, env=env, cwd=ROOT, timeout=120)
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and "no such file" in out.stderr


def test_bias_leaking_into_the_friction_fit_is_not_an_actuator_fault():
    # as measured through the real pipeline: offset +30 N m per session, Coulomb +3.5 N m per session
    res = analyze_series(series(10, 4, lambda s: {"offset": {"arm0/j1": -5.0 * s, "arm0/j2": 30.0 * s},
                                                  "coulomb": {"arm0/j2": 90.0 + 3.5 * s}}))
    got = kinds(res)
    assert got == [("sensor", "arm0", 4)]


def test_real_friction_growth_during_a_bias_is_still_an_actuator_fault():
    res = analyze_series(series(10, 4, lambda s: {"offset": {"arm0/j1": -5.0 * s, "arm0/j2": 30.0 * s},
                                                  "coulomb": {"arm0/j2": 90.0 + 20.0 * s}}))
    got = kinds(res)
    assert ("sensor", "arm0", 4) in got and any(k == "actuator" and t == "arm0/j2" for k, t, _ in got)


def test_truncated_and_foreign_logs_in_a_series(tmp_path):
    """A session cut short is analysed from its intact part (as bsc replay does), with a note,
    and keeps its place in time order; a file that is not a log is skipped with one readable
    reason, never a raw library message."""
    from gateway.analysis import run

    paths = write_series(tmp_path, 4, 99)                  # z04 (first) .. z01 (last)
    whole = run([tmp_path], workers=1)[0].sessions
    cut = paths[1]                                          # the second session in time order
    data = cut.read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    (tmp_path / "notes.mcap").write_text("hello")
    result, skipped = run([tmp_path], workers=1)
    assert [s.name for s in result.sessions] == [s.name for s in whole] == ["z04", "z03", "z02", "z01"]
    got = {s.name: s for s in result.sessions}
    note = got["z03"].notes
    assert len(note) == 1 and "is truncated" in note[0] and "analysing the" in note[0]
    assert 0 < got["z03"].counts["joint_efforts"] < {s.name: s for s in whole}["z03"].counts["joint_efforts"]
    assert skipped == [f"{tmp_path / 'notes.mcap'}: not an MCAP file (bad magic bytes b'hello')"]
