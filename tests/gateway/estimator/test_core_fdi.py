"""The thruster fault detector in the live estimator (EstimatorCore, Pipeline): on sessions made by
the real path (simulator -> firmware -> CAN frames -> drivers + estimator, recorded as bsc
gateway --record would; harness/fdi.py), thruster 2 stuck closed at 3 s.

Checked against the simulator's truth: one alert on bsc/<robot>/alerts naming thruster 2 stuck
closed within 0.5 s; the thruster efforts carry ``fault:thrusters`` (not good) from the moment
it is raised, and not before; the published thruster wrench from the alarm on stays within 5 %
(band-limited NRMSE, worst axis) of the actual one, where without the detector's model of the
fault it is about 20 %; bsc replay gives the same efforts byte for byte and the same alert. A
healthy session raises nothing and flags nothing."""
from __future__ import annotations


import pytest

from harness.fdi import FaultCase, judge, record_many

ONSET = 3.0
CASES = {"closed2": FaultCase(duration_s=5.0, thruster=2, fault="stuck_closed", onset_s=ONSET),
         "healthy": FaultCase(seed=11, duration_s=5.0)}


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    return record_many(CASES, tmp_path_factory.mktemp("core_fdi"))


def _published(path):
    """(alerts, thruster efforts) the live run recorded."""
    from gateway.log.reader import read_messages

    alerts, thr = [], []
    for m in read_messages(path, None):
        if m.topic.endswith("/alerts"):
            alerts.append(m.data)
        elif m.schema_name == "gateway.efforts.ThrusterEffort":
            thr.append(m.data)
    return alerts, thr


def test_stuck_valve_alert_flag_and_wrench_live(sessions):
    path = sessions["closed2"]
    alerts, thr = _published(path)
    assert [(a["kind"], a["target"], a["rule"], a["severity"], a["state"]) for a in alerts] == \
        [("thruster", "thruster2", "thruster-fault", "critical", "raised")]
    a = alerts[0]
    assert "stuck closed" in a["message"]
    assert ONSET * 1e9 < a["since_ns"] <= a["t_ns"] <= (ONSET + 0.5) * 1e9
    flagged = [e for e in thr if "fault:thrusters" in e["flags"]]
    assert flagged and all(not e["good"] for e in flagged)
    assert min(e["t_ns"] for e in flagged) >= a["since_ns"]
    assert all("fault:thrusters" in e["flags"] for e in thr if e["t_ns"] > a["since_ns"] + 2_000_000)
    v = judge(CASES["closed2"], path)
    assert v.named and 0 < v.delay_s <= 0.5
    assert v.nrmse_published <= 0.05                     # the published wrench models the stuck valve


def test_replay_gives_the_same_efforts_and_alert(sessions, tmp_path):
    from gateway.replay import replay_offline

    rep = replay_offline(sessions["closed2"], tmp_path, check=True)
    assert rep.check["ok"], rep.check
    assert rep.alerts == 1

    def alerts(path):
        from gateway.log.reader import iter_file_order

        return [(t, m.log_time, bytes(m.data)) for t, _, m in iter_file_order(path, lambda t, s: t.endswith("/alerts"))]

    # the same alert at the same log time (its epoch's): the replay feeds batches of thousands of
    # frames, the live gateway a step's frames at a time
    live = alerts(sessions["closed2"])
    assert len(live) == 1 and alerts(tmp_path / "replay.mcap") == live


def test_healthy_session_raises_and_flags_nothing(sessions):
    alerts, thr = _published(sessions["healthy"])
    assert alerts == []
    assert thr and not any("fault:thrusters" in e["flags"] for e in thr)
