"""Simulated degradation series end to end: simulator -> firmware -> CAN frames -> Pipeline -> MCAP
-> bsc analyze, the path every series is made by.

Checked: no alarm on the healthy series, the friction growth found on its joint and the F/T
drift reported as a sensor fault, both at the onset session. The sessions are as short and as
few as that allows (5 sessions, onset 3; 6 s: in shorter ones the capture task does not move
every joint both ways, so friction is not identifiable), and the degraded series take their
sessions before the onset from the healthy series (the same runs: see
``test_sessions_before_the_onset_are_the_healthy_ones``). The thruster loss, visible in 2 s
sessions, is checked through the command line by the last test.
"""
from __future__ import annotations

import json

import pytest

from gateway import analysis
from harness.series import SERIES, default_onset, session_toml, write_series

N = 5
DURATION_S = 6.0


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    out = {}
    healthy: list = []
    for name in ("healthy", "friction-growth", "ft-bias-drift"):
        d = tmp_path_factory.mktemp(name)
        first = SERIES[name].onset(N) or 0
        paths = healthy[:first] + write_series(name, N, d, duration_s=DURATION_S, progress=False, workers=2,
                                                first=first)
        healthy = healthy or paths
        res, skipped = analysis.run(paths, workers=2)
        assert not skipped and [s.index for s in res.sessions] == list(range(N))
        out[name] = (res, json.loads((d / "series.json").read_text()))
    return out


def raised(res):
    return [(f.session_index, f.kind, f.target) for f in res.findings if f.state == "raised"]


@pytest.mark.slow
def test_healthy_series_has_no_false_alarm(results):
    assert raised(results["healthy"][0]) == []


@pytest.mark.slow
def test_friction_growth_detected_on_the_joint_at_the_onset(results):
    res, truth = results["friction-growth"]
    got = raised(res)
    assert got and all(k == "actuator" and t == truth["expected_target"] for _, k, t in got)
    assert got[0][0] == truth["onset_session"] == 3


@pytest.mark.slow
def test_ft_drift_is_a_sensor_fault_not_an_actuator_fault(results):
    res, truth = results["ft-bias-drift"]
    got = raised(res)
    assert got and all(k == "sensor" for _, k, _ in got)
    assert got[0][2] == truth["expected_target"] == "arm0"
    assert got[0][0] == truth["onset_session"] == 3


def _run_lines(toml: str) -> list[str]:
    """What a session runs: its scenario without the comment and the name."""
    return [ln for ln in toml.splitlines() if not ln.startswith(("#", "name ="))]


def test_sessions_before_the_onset_are_the_healthy_ones():
    for spec in SERIES.values():
        onset = spec.onset(N)
        for k in range(N if onset is None else onset):
            assert _run_lines(session_toml(spec, k, N, DURATION_S)) == \
                _run_lines(session_toml(SERIES["healthy"], k, N, DURATION_S))
        if onset is not None:
            assert _run_lines(session_toml(spec, onset, N, DURATION_S)) != \
                _run_lines(session_toml(SERIES["healthy"], onset, N, DURATION_S))


def test_series_table_and_session_files():
    assert set(SERIES) == {"healthy", "friction-growth", "thruster-loss", "ft-bias-drift"}
    assert default_onset(6) == 3 and default_onset(12) == 4
    with pytest.raises(ValueError):
        default_onset(4)
    toml = session_toml(SERIES["friction-growth"], 5, 6, 8.0)
    assert '[friction.per_joint]\n"arm0/j2" = 0.6' in toml and "seed = 1005" in toml
    assert "per_joint" not in session_toml(SERIES["friction-growth"], 1, 6, 8.0)
    with pytest.raises(ValueError, match="no series"):
        write_series("nope", 3, "/tmp/never")


def test_bsc_sim_series_through_the_real_pipeline_then_bsc_analyze(tmp_path):
    """As a user runs it: `bsc sim --series` (firmware -> CAN frames -> drivers + estimator, raw
    frames recorded) then `bsc analyze --json`. Short sessions (2 s) still show a thruster loss."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[3]
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    out = tmp_path / "tl"

    def bsc(*args):
        return subprocess.run([sys.executable, "-m", "gateway.cli", *args], capture_output=True, text=True,
                              env=env, cwd=root, timeout=600)

    r = bsc("sim", "--series", "thruster-loss", "--sessions", "5", "--duration", "2", "--workers", "2",
            "--out", str(out), "--quiet")
    assert r.returncode == 0, r.stderr
    assert "from session 3" in r.stdout
    truth = json.loads((out / "series.json").read_text())
    assert truth["onset_session"] == 3
    again = bsc("sim", "--series", "thruster-loss", "--sessions", "5", "--out", str(out), "--quiet")
    assert again.returncode == 2 and "--overwrite" in again.stderr and again.stderr.count("\n") == 1
    r = bsc("analyze", str(out), "--json", "--workers", "2", "--quiet")
    assert r.returncode == 0, r.stderr
    alerts = [json.loads(x) for x in r.stdout.splitlines()]
    raised = [(a["session_index"], a["kind"]) for a in alerts if a["state"] == "raised"]
    assert raised and all(k == "thruster" for _, k in raised)
    assert min(i for i, _ in raised) == 3                 # at the onset, not before
    assert {a["target"] for a in alerts} <= {"fx", "fy", "mz"}
