"""bsc monitor over loopback zenoh: a growing friction residual raises one alert, then clears it.

zenoh: explicit loopback endpoints, multicast scouting off. Synchronisation is on conditions
(events set by subscribers, counters), never on sleeps.
"""
from __future__ import annotations

import math
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import zenoh

from gateway import codec, keys
from gateway.efforts import Alert, JointEfforts
from gateway.monitor.rules import load_rules
from gateway.monitor.service import MonitorService
from gateway.zenoh_config import make_config
from support import free_port

ROOT = Path(__file__).resolve().parents[3]
ROBOT = "paper_robot"          # built in: torque limits known (arm0/j2: 300 N m)
RULES = """
[monitor]
tau_s = 1.0
min_weight_s = 0.5
[[rule]]
name = "joint-friction-high"
kind = "actuator"
metric = "friction_fraction"
raise = 0.45
clear = 0.40
hold_s = 1.0
clear_hold_s = 1.0
severity = "warning"
"""


def efforts(t_ns: int, i: int, fc_j2: float) -> JointEfforts:
    v = (0.3 * math.sin(i / 20), 0.4 * math.cos(i / 15))
    cmd = (50.0 * math.sin(i / 7), 30.0 * math.cos(i / 5))
    fc = (180.0, fc_j2)
    est = tuple(c - f * math.copysign(1.0, w) - 5.0 * w for c, f, w in zip(cmd, fc, v))
    return JointEfforts("arm0", t_ns, ("arm0/j1", "arm0/j2"), est, est, cmd, t_ns, v, True)


class Alerts:
    def __init__(self):
        self.got: list[Alert] = []
        self.lock = threading.Lock()
        self.raised, self.cleared = threading.Event(), threading.Event()

    def __call__(self, sample):
        a = codec.decode(sample.payload.to_bytes())
        with self.lock:
            self.got.append((a, sample.attachment.to_bytes() if sample.attachment else None))
        (self.raised if a.state == "raised" else self.cleared).set()


@pytest.fixture
def sessions():
    ep = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(make_config(listen=[ep])) as a, zenoh.open(make_config(connect=[ep])) as b:
        yield a, b


def test_growing_friction_raises_one_alert_then_clears(sessions, tmp_path):
    pub_s, mon_s = sessions
    rules_file = tmp_path / "rules.toml"
    rules_file.write_text(RULES)
    col = Alerts()
    sub = pub_s.declare_subscriber(keys.alerts(ROBOT), col)
    pub = pub_s.declare_publisher(keys.joint_efforts(ROBOT, "arm0"))
    stop = threading.Event()
    log = tmp_path / "alerts.jsonl"
    with MonitorService(mon_s, "*", load_rules(rules_file), alert_log=log) as svc:
        runner = threading.Thread(target=svc.run, args=(stop,))
        runner.start()
        try:
            # link up: the monitor has seen a sample (t = 0 is harmless: one sample, no estimate)
            seen = threading.Event()
            for _ in range(200):
                pub.put(codec.encode(efforts(0, 0, 90.0)))
                if svc.received > 0 or seen.wait(0.02):
                    break
            assert svc.received > 0, "monitor never received a sample"
            t, i = 1_000_000_000, 0
            phases = [(90.0, 600), (150.0, 600), (90.0, 900)]     # 30 %, 50 %, 30 % of 300 N m at 100 Hz
            for p, (fc, n) in enumerate(phases):
                for _ in range(n):
                    pub.put(codec.encode(efforts(t, i, fc)), attachment=str(t).encode())
                    t += 10_000_000
                    i += 1
                if p == 1:
                    assert col.raised.wait(20), "no alert raised while friction was at 50 %"
            assert col.cleared.wait(20), "alert not cleared after friction went back to 30 %"
        finally:
            stop.set()
            runner.join(10)
            sub.undeclare()
            pub.undeclare()
    got = [a for a, _ in col.got]
    assert [(a.state, a.kind, a.target, a.rule) for a in got] == [
        ("raised", "actuator", "arm0/j2", "joint-friction-high"),
        ("cleared", "actuator", "arm0/j2", "joint-friction-high")]
    raised, cleared = got
    ev = dict(raised.evidence)
    assert 0.45 < ev["friction_fraction"] < 0.52 and ev["raise"] == 0.45 and ev["clear"] == 0.40
    assert 140 < ev["friction_nm"] < 155
    # since: the first crossing, at least hold_s before the alert, and after the step to 150 N m
    assert 7.0e9 <= raised.since_ns <= raised.t_ns - 1.0e9
    assert cleared.since_ns == raised.since_ns and cleared.t_ns > 13.0e9 and cleared.severity == "info"
    assert all(att is not None and int(att) > 0 for _, att in col.got)
    assert len(log.read_text().splitlines()) == 2
    assert len(svc.alerts) == 2 and svc.others == 0        # its own alerts do not come back to it


def test_bsc_monitor_cli_runs_for_a_duration(tmp_path):
    ep = f"tcp/127.0.0.1:{free_port()}"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-m", "gateway.cli", "monitor", "--listen", ep, "--duration", "1",
                          "--once"], capture_output=True, text=True, env=env, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "bsc monitor" in out.stdout and "waiting for" in out.stdout
    assert "0 alert(s) raised" in out.stderr


def test_bsc_monitor_bad_rules_file_is_one_line(tmp_path):
    bad = tmp_path / "r.toml"
    bad.write_text("[[rule]]\nname='x'\n")
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-m", "gateway.cli", "monitor", "--rules", str(bad), "--duration", "1"],
                         capture_output=True, text=True, env=env, cwd=ROOT, timeout=120)
    assert out.returncode == 2 and "missing key" in out.stderr and out.stderr.count("\n") == 1


def test_the_other_services_alerts_are_listed_and_never_published_again(sessions, tmp_path):
    """The gateway's thruster fault (bsc/<robot>/alerts) and bsc control's transitions
    (commands/status) show among the robot's active alerts and in the alert log while raised;
    the monitor does not publish them again, and its own alerts do not come back to it."""
    from gateway.monitor.dashboard import render
    from support import subscribed, wait_until

    pub_s, mon_s = sessions
    fault = Alert(ROBOT, "thruster", "thruster7", "thruster-fault", "critical", "raised", 3_000_000_000,
                  3_000_000_000, "thruster 7: stuck open (size 0.88 of nominal thrust)", (("thruster", 7.0),))
    keepout = Alert(ROBOT, "thruster", "thrusters", "compensation-keepout-unknown", "warning", "raised",
                    3_100_000_000, 3_100_000_000, "thrusters: no valve commands")
    log = tmp_path / "alerts.jsonl"
    pubs = {k: pub_s.declare_publisher(k) for k in (keys.alerts(ROBOT), keys.control_status(ROBOT))}
    stop = threading.Event()
    with MonitorService(mon_s, "*", alert_log=log) as svc:
        runner = threading.Thread(target=svc.run, args=(stop,))
        runner.start()
        try:
            for k in pubs:
                subscribed(pub_s, k)
            # two keys, two subscriptions: their relative order is not guaranteed, so one at a time
            pubs[keys.alerts(ROBOT)].put(codec.encode(fault))
            wait_until(lambda: svc.others == 1, "the thruster fault listed")
            pubs[keys.control_status(ROBOT)].put(codec.encode(keepout))
            wait_until(lambda: svc.others == 2, "the two alerts listed")
            active = svc.monitor.snapshot()[ROBOT]["active"]
            assert active == ["compensation-keepout-unknown:thrusters", "thruster-fault:thruster7"]
            text = render(svc.monitor.snapshot(), svc.alerts)
            assert "2 active alert(s)" in text and "thruster 7: stuck open" in text
            cleared = Alert(ROBOT, "thruster", "thruster7", "thruster-fault", "info", "cleared", 5_000_000_000,
                            3_000_000_000, "thruster 7: cleared")
            pubs[keys.alerts(ROBOT)].put(codec.encode(cleared))
            wait_until(lambda: svc.others == 3, "the clearing listed")
            assert svc.monitor.snapshot()[ROBOT]["active"] == ["compensation-keepout-unknown:thrusters"]
        finally:
            stop.set()
            runner.join(10)
            for p in pubs.values():
                p.undeclare()
    assert [a.rule for a in svc.alerts] == ["thruster-fault", "compensation-keepout-unknown", "thruster-fault"]
    assert not svc._pubs                                   # published nothing: none of them was its own
    assert len(log.read_text().splitlines()) == 3
