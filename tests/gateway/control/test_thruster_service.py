"""bsc control's thruster loop over loopback zenoh: the learned per-valve wrenches, the observed
commanded wrench and the fault detector's alerts in; the valves until the next commanded wrench
and the loop's transitions out, under bsc/<robot>/commands/**.

zenoh: explicit loopback endpoints, multicast scouting off. Synchronisation on conditions with
deadlines, never on sleeps.
"""
from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

import robot_description
from drivers.samples import ThrusterCommand
from gateway import codec, keys
from gateway.control import ThrusterCompensator, ThrusterLoopSettings
from gateway.control.messages import ControlError, ThrusterValves, decode_thruster_valves, encode_thruster_valves
from gateway.control.service import KEEPOUT_RULE, ControlService, valve_timing
from gateway.control.thrusters import mask_bits
from gateway.efforts import Alert, ValveWrenches
from robot_description.thrusters import ThrusterLayout
from support import free_port, subscribed, wait_until

ROOT = Path(__file__).resolve().parents[3]
ROBOT = "paper_robot"
MS = 1_000_000
LAYOUT = ThrusterLayout.load(None)          # the gateway's default layout
N = LAYOUT.n
WRENCH = (60.0, -40.0, 0.0, 0.0, 0.0, 150.0)
SETTINGS = ThrusterLoopSettings(resume_good=3, min_duty=0.0)


def learned():
    """What the valves really deliver: 10 % weak, 2 degrees off."""
    rng = np.random.default_rng(3)
    W = LAYOUT.nominal_wrenches * 0.9
    lateral = np.cross(LAYOUT.dir, rng.standard_normal((N, 3)))
    lateral /= np.linalg.norm(lateral, axis=1, keepdims=True)
    f = W[:, :3] + np.radians(2.0) * 0.9 * LAYOUT.max_n[:, None] * lateral
    return np.hstack([f, np.cross(LAYOUT.pos_m, f)])


W_TRUE = learned()


def keep_out() -> int:
    """The flight software's keep-out mask of the test: every thruster but the two an unrestricted
    allocation of WRENCH uses most (so that the mask changes the schedules)."""
    free = ThrusterCompensator.for_layout(LAYOUT, min_on=4, settings=SETTINGS)
    free.demand(0, WRENCH)
    duty = free.schedule(MS, 10, MS).duty
    out = [int(j) for j in np.argsort(duty)[-2:]]
    assert min(duty[j] for j in out) > 0.0
    return ((1 << N) - 1) & ~sum(1 << j for j in out)


ALLOWED = keep_out()
EXCLUDED = [j for j in range(N) if not (ALLOWED >> j) & 1]


def estimate(t_ns, good=True, flags=()):
    return ValveWrenches(t_ns, tuple(W_TRUE.ravel().tolist()), (0.5,) * N, good, tuple(flags))


def fault(t_ns, j, cleared=False):
    return Alert(ROBOT, "thruster", f"thruster{j}", "thruster-fault", "critical", "raised", t_ns, t_ns,
                 f"thruster {j}: stuck open", (("thruster", float(j)), ("type", 4.0 if cleared else 0.0)))


class Got:
    def __init__(self):
        self.valves, self.status = [], []
        self.lock = threading.Lock()

    def valve(self, sample):
        with self.lock:
            self.valves.append(decode_thruster_valves(sample.payload.to_bytes()))

    def alert(self, sample):
        with self.lock:
            self.status.append(codec.decode(sample.payload.to_bytes()))


def test_valves_until_the_next_commanded_wrench_on_the_learned_wrenches(sessions):
    robot_side, ctl_side = sessions
    got = Got()
    subs = [robot_side.declare_subscriber(keys.thruster_valves(ROBOT), got.valve),
            robot_side.declare_subscriber(keys.control_status(ROBOT), got.alert)]
    names = (keys.valve_wrenches(ROBOT), keys.thruster_command(ROBOT), keys.alerts(ROBOT))
    pubs = {k: codec.declare_publisher(robot_side, k) for k in names}
    robot = robot_description.load(ROBOT)
    step_ns, block = valve_timing()
    assert (step_ns, block) == (MS, 10)             # the DBC: valves every 1 ms, commanded wrench every 10 ms
    # the oracle: the same core fed the same inputs in process
    oracle = ThrusterCompensator.for_layout(LAYOUT, min_on=4, settings=SETTINGS)
    try:
        with ControlService(ctl_side, robot, layout=LAYOUT, thruster_settings=SETTINGS) as ctl:
            assert ctl.thrusters is not None
            for k in pubs:
                subscribed(robot_side, k)
            subscribed(ctl_side, keys.thruster_valves(ROBOT))
            subscribed(ctl_side, keys.control_status(ROBOT))

            def put(key, obj):
                # zenoh orders samples per key, not across keys: each one taken before the next
                n = ctl.received
                codec.put(pubs[key], codec.encode(obj))
                wait_until(lambda: ctl.received > n, f"{key} taken")

            def period(k, est=None, alert=None):
                """One 10 ms period: an estimate (or an alert), then the commanded wrench."""
                t = 10 * k * MS
                for what in (est, alert):
                    if what is not None:
                        put(keys.valve_wrenches(ROBOT) if isinstance(what, ValveWrenches) else keys.alerts(ROBOT),
                            what)
                        oracle.estimate(what) if isinstance(what, ValveWrenches) else oracle.alert(what)
                put(keys.thruster_command(ROBOT), ThrusterCommand(t, k, WRENCH[:3], WRENCH[3:], allowed=ALLOWED))
                oracle.demand(t, WRENCH, mask_bits(ALLOWED, N))
                want = oracle.schedule(t + MS, 10, MS, lookahead=10)
                wait_until(lambda: len(got.valves) >= k + 1, f"valves of period {k}")
                assert got.valves[k] == want
                # the flight software's keep-out, on the wire: an excluded thruster never fires
                assert not any((m >> j) & 1 for m in got.valves[k].masks() for j in EXCLUDED)
                return got.valves[k]

            first = period(0)
            assert not first.closed and first.flags == ("no-estimate",)
            assert first.t_ns == MS and len(first.masks()) == 20 and first.step_ns == MS     # and a look-ahead
            for k in range(1, 4):
                v = period(k, est=estimate(10 * k * MS - MS))
            assert v.closed and "no-estimate" not in v.flags           # the 3rd good estimate closed it
            # an older commanded wrench arriving late is not answered
            n = len(got.valves)
            put(keys.thruster_command(ROBOT), ThrusterCommand(5 * MS, 99, WRENCH[:3], WRENCH[3:], allowed=ALLOWED))
            # a not-good estimate: the next valves on the nominal allocation, the transition published
            v = period(4, est=estimate(39 * MS, good=False, flags=("stale:imu",)))
            assert len(got.valves) == n + 1
            assert not v.closed and v.flags == ("estimate:not-good (stale:imu)",)
            wait_until(lambda: len(got.status) >= 2, "the loop's transitions")
            closed, opened = got.status[:2]
            assert (closed.state, opened.state) == ("cleared", "raised")
            assert opened.kind == "thruster" and opened.target == "thrusters" and opened.t_ns == 39 * MS
            # a thruster the fault detector names is never opened again
            busiest = int(np.argmax(v.duty))
            for k in range(5, 9):
                named = fault(10 * k * MS - MS, busiest) if k == 5 else None
                v = period(k, est=estimate(10 * k * MS - MS), alert=named)
                assert not any((m >> busiest) & 1 for m in v.masks()) and v.duty[busiest] == 0.0
                assert f"fault:thruster{busiest}" in v.flags
            wait_until(lambda: any(a.rule == "compensation-thruster-excluded" for a in got.status), "exclusion")
            # the gateway stops: the first valves more than stale_s after the last estimate (79 ms)
            # are on the nominal allocation
            assert v.closed and period(9).closed
            v = period(10)
            assert not v.closed and v.flags == (f"fault:thruster{busiest}", "stale:efforts")
            assert ctl.rejected == 0 and ctl.valves_published == {"closed": 4, "open": 7}
    finally:
        for s in subs + list(pubs.values()):
            s.undeclare()


def test_no_valve_command_without_the_keep_out_mask(sessions):
    """A commanded wrench without THRUSTER_CMD_ALLOWED (a controller that does not send it, or a
    log from before it existed): no valve command, raised once; the mask back: valves again."""
    _, ctl_side = sessions
    robot = robot_description.load(ROBOT)
    with ControlService(ctl_side, robot, layout=LAYOUT, thruster_settings=SETTINGS) as ctl:
        ctl.feed(ThrusterCommand(0, 0, WRENCH[:3], WRENCH[3:], allowed=ALLOWED))
        assert ctl.valves_published == {"closed": 0, "open": 1} and not ctl.alerts   # known from the start
        for k in (1, 2, 3):
            ctl.feed(ThrusterCommand(10 * k * MS, k, WRENCH[:3], WRENCH[3:]))
        assert ctl.valves_withheld == 3 and sum(ctl.valves_published.values()) == 1
        (a,) = ctl.alerts
        assert (a.rule, a.state, a.target, a.t_ns) == (KEEPOUT_RULE, "raised", "thrusters", 10 * MS)
        assert "THRUSTER_CMD_ALLOWED" in a.message
        ctl.feed(ThrusterCommand(40 * MS, 4, WRENCH[:3], WRENCH[3:], allowed=ALLOWED))
        assert sum(ctl.valves_published.values()) == 2
        assert [(x.rule, x.state, x.t_ns) for x in ctl.alerts[1:]] == [(KEEPOUT_RULE, "cleared", 40 * MS)]
    with ControlService(ctl_side, robot, layout=LAYOUT, thruster_settings=SETTINGS) as ctl:
        ctl.feed(ThrusterCommand(0, 0, WRENCH[:3], WRENCH[3:]))         # unknown from the start
        assert ctl.valves_withheld == 1 and [x.state for x in ctl.alerts] == ["raised"]


def test_open_loop_and_joints_only_command_no_valve(sessions):
    _, ctl_side = sessions
    robot = robot_description.load(ROBOT)
    with ControlService(ctl_side, robot, layout=LAYOUT, enabled=False) as ctl:
        assert ctl.thrusters is None
        ctl.feed(ThrusterCommand(0, 0, WRENCH[:3], WRENCH[3:]))
        assert sum(ctl.valves_published.values()) == 0
    with ControlService(ctl_side, robot) as ctl:
        assert ctl.thrusters is None


def test_valve_commands_are_decoded_strictly():
    v = ThrusterValves(MS, 5, (0.5, 0.0), True, ("limited:rate",), (1, 0, 4), MS)
    assert decode_thruster_valves(encode_thruster_valves(v)) == v and v.masks() == (5, 1, 0, 4)
    good = encode_thruster_valves(v).decode()
    for bad in (good.replace('"duty":[0.5,0.0]', '"duty":[1.5,0.0]'), good.replace('"valves":5', '"valves":-5'),
                good.replace(f'"step_ns":{MS}', '"step_ns":0'), good.replace('"closed":true', '"closed":1'),
                good.replace('"ThrusterValves"', '"DriveCommand"'), "[]", "not json"):
        with pytest.raises(ControlError):
            decode_thruster_valves(bad)


def test_bsc_control_cli_runs_the_thruster_loop_when_asked():
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    for extra, says in ((["--thruster-loop"],
                         "publishing on bsc/paper_robot/commands/drives/**, bsc/paper_robot/commands/thrusters"),
                        ([], "publishing on bsc/paper_robot/commands/drives/**\n")):
        ep = f"tcp/127.0.0.1:{free_port()}"
        out = subprocess.run([sys.executable, "-m", "gateway.cli", "control", "--listen", ep, "--duration", "0.3",
                              *extra], capture_output=True, text=True, env=env, cwd=ROOT, timeout=120)
        assert out.returncode == 0 and says in out.stderr, out.stderr
    out = subprocess.run([sys.executable, "-m", "gateway.cli", "control", "--thruster-loop", "--valve-min-on", "0",
                          "--duration", "1"],
                         capture_output=True, text=True, env=env, cwd=ROOT, timeout=120)
    assert out.returncode == 2 and "--valve-min-on" in out.stderr and out.stderr.count("\n") == 1
