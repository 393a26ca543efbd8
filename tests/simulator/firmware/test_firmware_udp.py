"""The firmware and the drivers in two processes over python-can ``udp_multicast``, inside a
private network namespace (multicast stays on its loopback): the same comparison as over the
virtual bus. Skipped, with the reason, where a namespace cannot be made (not root, no iproute2)."""
from __future__ import annotations

import os
import pickle
import shutil
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from firmware_rig import assert_clean_health, check_against_readings, snapshot
from simulator import scenario
from simulator.engine import Simulation

CHILD = Path(__file__).with_name("_udp_child.py")
ROOT = Path(__file__).resolve().parents[3]
DURATION_S = 1.0


def _ip(*args):
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)


@pytest.fixture
def netns():
    if shutil.which("ip") is None:
        pytest.skip("no iproute2 `ip` command: cannot make a private network namespace")
    name = f"bsc-fw-{uuid.uuid4().hex[:8]}"
    r = _ip("netns", "add", name)
    if r.returncode != 0:
        pytest.skip(f"cannot create a network namespace (needs root / CAP_SYS_ADMIN): {r.stderr.strip()}")
    try:
        for cmd in (("link", "set", "lo", "up"), ("link", "set", "lo", "multicast", "on"),
                    ("route", "replace", "224.0.0.0/4", "dev", "lo")):
            r = _ip("netns", "exec", name, "ip", *cmd)
            assert r.returncode == 0, f"ip {' '.join(cmd)} in {name}: {r.stderr}"
        yield name
    finally:
        _ip("netns", "delete", name)


@pytest.mark.netns
def test_two_processes_over_udp_multicast(netns, tmp_path):
    name = "capture"
    sim = Simulation(scenario.load(name, {"duration_s": DURATION_S}))
    readings = [snapshot(sim.step()) for _ in range(sim.n_steps)]      # the same run, deterministic
    groups = ",".join(f"239.74.163.{i + 1}" for i in range(len(sim.robot.arms) + 1))
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", PYTHONDONTWRITEBYTECODE="1",
               PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    exe = ["ip", "netns", "exec", netns, sys.executable, str(CHILD)]
    out = tmp_path / "received.pickle"
    rx = subprocess.Popen([*exe, "receive", name, str(DURATION_S), groups, str(out)], cwd=ROOT, env=env,
                          stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert rx.stdout.readline().strip() == "ready", rx.stderr.read()
        tx = subprocess.run([*exe, "send", name, str(DURATION_S), groups], cwd=ROOT, env=env,
                            capture_output=True, text=True, timeout=120)
        assert tx.returncode == 0, tx.stderr
        _, err = rx.communicate(tx.stdout, timeout=60)
        assert rx.returncode == 0, err
    finally:
        if rx.poll() is None:
            rx.kill()
            rx.wait()
    got = pickle.loads(out.read_bytes())
    assert got["seen"] == got["expected"], "frames lost between the processes"
    # udp_multicast stamps frames at reception, so the samples carry host time, not sim time
    n = check_against_readings(sim.robot, readings, got["samples"], stamps=False)
    assert n["arm0"] == 1000 and n["imu"] == 500
    assert_clean_health(got["health"])
    for bus, h in got["bus_health"].items():
        assert h.frames == got["expected"][bus] and h.rejected == ()
