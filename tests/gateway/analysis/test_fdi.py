"""Thruster faults within one recorded session (gateway/analysis/fdi.py, ``bsc analyze LOG``), on
simulated capture sessions made by the real path (simulator -> firmware -> CAN frames -> drivers
and estimator -> MCAP, harness/fdi.py), judged against the simulator's truth.

Four short sessions: healthy (no alarm), thruster 5 stuck open and thruster 2 stuck closed
(named with the type within 0.5 s of the onset, size within 0.05 of the truth's thrust), and
thruster 2 losing 30 % of its thrust (named a partial loss within 2 s, size within 0.05). The
offline filter's inputs are the live estimator's own (its wrenches agree to 1e-9). The scenario
family with every thruster and random onsets is the benchmark's (benchmarks/bench_fdi.py)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gateway.analysis.fdi import _decode, _layout_and_robot, analyze_thrusters, detect, event_stream
from harness.fdi import FaultCase, judge, record_many

ROOT = Path(__file__).resolve().parents[3]
ONSET = 3.0
CASES = {
    "healthy": FaultCase(duration_s=5.0),
    "open5": FaultCase(duration_s=5.0, thruster=5, fault="stuck_open", onset_s=ONSET),
    "closed2": FaultCase(duration_s=5.0, thruster=2, fault="stuck_closed", onset_s=ONSET),
    "loss2": FaultCase(duration_s=5.5, thruster=2, fault="loss", onset_s=ONSET, factor=0.7),
}


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    return record_many(CASES, tmp_path_factory.mktemp("fdi"))


def test_healthy_session_raises_nothing(sessions):
    res = analyze_thrusters(sessions["healthy"])
    assert res.alarms == []
    assert res.updates > 0.9 * len(res.imu_t_ns)          # the filter learnt throughout
    # margin: the largest statistics stay well below the thresholds
    from gateway.estimator.fdi import FdiSettings

    s = FdiSettings()
    late = res.imu_t_ns - res.t0_ns > s.warmup_s * 1e9
    assert res.stat[late, 0].max() < s.h_short / 4 and res.stat[late, 2].max() < 0.75 * s.h_long


@pytest.mark.parametrize("name", ["open5", "closed2"])
def test_stuck_valve_named_within_half_a_second(sessions, name):
    case = CASES[name]
    v = judge(case, sessions[name])
    assert v.named, v.alarms
    assert 0 < v.delay_s <= 0.5
    assert v.theta == pytest.approx(v.theta_true, abs=0.05)
    assert v.false_alarms == 0, v.alarms
    if case.fault == "stuck_closed":        # it shows once commanded: that first command before the alarm
        assert 0.0 <= v.commanded_from_s < v.delay_s


def test_partial_loss_named_with_its_size(sessions):
    case = CASES["loss2"]
    v = judge(case, sessions["loss2"])
    assert v.commanded_duty > 0.5              # thruster 2 fires most of the time in the capture task
    assert v.named, v.alarms
    assert 0 < v.delay_s <= 2.0
    assert v.theta == pytest.approx(v.theta_true, abs=0.05)
    assert v.false_alarms == 0, v.alarms


def test_offline_filter_has_the_live_estimators_inputs(sessions):
    """The detector's filter runs on the steps and IMU samples the live estimator used: on a
    healthy session (nothing held) it ends where the estimator's own filter ends."""
    src = sessions["healthy"]
    ctx, rob, layout = _layout_and_robot(src)
    samples, efforts, core = _decode(src, ctx, rob, layout)
    _, _, kf = detect(event_stream(samples, efforts, core), core, layout)
    assert kf.updates == core.kf.updates
    assert np.abs(kf.x - core.kf.x).max() <= 1e-9 * np.abs(core.kf.x).max()


def test_bsc_analyze_names_the_thruster(sessions):
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-m", "gateway.cli", "analyze", str(sessions["closed2"]), "--json",
                          "--quiet", "--workers", "1"], capture_output=True, text=True, cwd=ROOT, env=env,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    alerts = [json.loads(line) for line in out.stdout.splitlines() if line.strip()]
    fdi = [a for a in alerts if a["rule"] == "thruster-fault"]
    assert [(a["kind"], a["target"], a["evidence"]["fault"], a["severity"]) for a in fdi] == \
        [("thruster", "thruster2", "stuck closed", "critical")]
    assert ONSET < fdi[0]["evidence"]["t_s"] <= ONSET + 0.5
    text = subprocess.run([sys.executable, "-m", "gateway.cli", "analyze", str(sessions["healthy"]), "--quiet",
                           "--workers", "1"], capture_output=True, text=True, cwd=ROOT, env=env, timeout=300)
    assert text.returncode == 0 and "alerts: none" in text.stdout, text.stdout + text.stderr
