"""The closed inner loop in lockstep: simulator -> firmware frames -> session -> compensator -> the
simulator's drives, judged against the simulator's truth."""
from __future__ import annotations

import numpy as np
import pytest

from harness import closed_loop
from simulator import scenario
from simulator.engine import Simulation
from simulator.firmware import Faults


@pytest.fixture(scope="module")
def capture():
    return scenario.load("capture", {"duration_s": 2.0})


@pytest.fixture(scope="module")
def study(capture):
    # the outer loop leaves the drives 30 % of their limits: room to cancel 30 % Coulomb friction
    return closed_loop.closed_loop_study(capture, command_limit=0.7)


def test_compensation_removes_most_of_the_friction_error_with_headroom(study):
    out, traces = study
    # truth: friction makes the end effectors miss; compensation through the gateway wins back at
    # least 90 % of that miss (the issue's stretch target), and the actual joint torques track the
    # desired ones with at least 90 % less RMS error
    ee = out["ee_rms_error_m"]
    assert ee["open_loop"]["overall"] > 1.3 * ee["no_friction"]["overall"]
    assert out["ee_friction_error_removed"]["overall"] >= 0.90
    for arm in traces["open_loop"].meta["arms"]:
        assert out["ee_friction_error_removed"][arm] >= 0.90, arm
    assert out["joint_torque_error_cut"]["overall"] >= 0.90
    for joint in traces["open_loop"].meta["joints"]:
        assert out["joint_torque_error_cut"][joint] >= 0.85, joint
    assert out["pass"]
    assert out["loop"]["transitions"][0]["state"] == "closed"
    assert all(t["state"] == "closed" for t in out["loop"]["transitions"])     # never opened again


def test_the_report_has_the_issues_keys(study):
    out, _ = study
    for case in ("no_friction", "open_loop", "compensated"):
        assert set(out["ee_rms_error_m"][case]) == {"arm0", "arm1", "overall"}
    for case in ("open_loop", "compensated"):
        assert out["joint_torque_rms_error_nm"][case]["overall"] >= 0
        assert set(out["thruster_wrench_rms_error"][case]) == {"force_n", "moment_nm", "per_axis"}
        raw, band = out["thruster_wrench_rms_error_1khz"][case], out["thruster_wrench_rms_error"][case]
        assert raw["force_n"] > band["force_n"]
    assert set(out["thruster_wrench_error_cut"]) == {"force_n", "moment_nm"}


def test_the_thruster_loop_cuts_the_wrench_error_through_the_gateway(study):
    # the valves under the learned wrenches: the band-limited error of actual vs commanded wrench
    # falls against open loop, and against the same valve timing on the nominal wrenches (what the
    # learned wrenches add); the loop closed at once and stayed closed, every step's valves external
    out, _ = study
    w, cut = out["thruster_wrench_rms_error"], out["thruster_wrench_error_cut"]
    # 2 s: 28 % and 37 % (2026-11-26, the learned wrenches in process every epoch); 38 % and 53 % on
    # the ones the gateway publishes every 5 ms (15 % and 33 % every 10 ms)
    assert cut["force_n"] > 0.2 and cut["moment_nm"] > 0.2
    for k in ("force_n", "moment_nm"):
        assert w["compensated"][k] < w["nominal_wrenches"][k]
    loop = out["thruster_loop"]
    # closed after resume_good (5) published estimates, 5 ms apart
    assert [t["state"] for t in loop["transitions"]] == ["closed"] and loop["transitions"][0]["t_s"] < 0.031
    assert loop["late"] == 0 and loop["steps_external"] == loop["commands"]["closed"] + loop["commands"]["open"]


def test_the_closed_loop_is_deterministic(capture):
    sc = capture.replace(duration_s=0.4)
    a, _ = closed_loop.run_compensated(sc)
    b, _ = closed_loop.run_compensated(sc)
    assert np.array_equal(a.arrays["tau_act"], b.arrays["tau_act"])
    assert np.array_equal(a.arrays["ee"], b.arrays["ee"])


def test_valve_schedules_delivered_late_lose_their_first_rows_to_the_previous_look_ahead(capture, monkeypatch):
    """The real-time loop's delay in lockstep: each schedule reaches the robot 3 steps after its
    commanded wrench, so its first 3 rows are lost and those steps run on the previous schedule's
    look-ahead, exactly; with no delay every row is applied."""
    from gateway.control import ThrusterCompensator

    sent = []
    schedule = ThrusterCompensator.schedule

    def record(self, *a, **kw):
        v = schedule(self, *a, **kw)
        sent.append(v)
        return v

    monkeypatch.setattr(ThrusterCompensator, "schedule", record)
    sc = capture.replace(duration_s=0.6)
    for delay in (0, 3):
        sent.clear()
        tr, info = closed_loop.run_compensated(sc, valve_delay_steps=delay)
        thr = info["thrusters"]
        assert len(sent) == sum(thr["commands"].values()) >= 50
        assert thr["late"] == delay * len(sent)
        applied = thr["applied"]
        bits = 1 << np.arange(applied.shape[1])
        for prev, v in zip(sent, sent[1:]):
            k0 = v.t_ns // 1_000_000
            rows = np.array(v.masks())
            if k0 + 10 > len(applied):
                break
            before = np.array(prev.masks())[10:10 + delay]      # the previous look-ahead
            want = np.concatenate([before, rows[delay:10]])
            got = applied[k0:k0 + 10] @ bits
            assert np.array_equal(got, want), f"schedule at step {k0}"


def test_valve_schedules_older_than_the_robots_deadline_are_dropped_whole(capture):
    """Delays of 3 and 7 steps in turn, a deadline of 5: every second schedule is dropped, and
    its steps run on the previous schedule's look-ahead; without a deadline none is."""
    sc = capture.replace(duration_s=0.5)
    _, kept = closed_loop.run_compensated(sc, valve_delay_steps=[3, 7])
    _, dropped = closed_loop.run_compensated(sc, valve_delay_steps=[3, 7], valve_max_age_steps=5)
    n = sum(kept["thrusters"]["commands"].values())
    assert kept["thrusters"]["too_old"] == 0 and kept["thrusters"]["late"] == 5 * n - (n % 2) * 2
    assert dropped["thrusters"]["too_old"] == n // 2 and dropped["thrusters"]["late"] == 3 * (n - n // 2)


def test_disabled_the_same_path_is_the_open_loop(capture):
    # the drives under the compensator's open-loop commands: the flight software's torque one step
    # later, so the joint torque error is the open loop's (within 5 %), not the compensated one's
    sc = capture.replace(duration_s=0.6)
    tr, info = closed_loop.run_compensated(sc, enabled=False)
    ol = Simulation(sc).run()
    cut = closed_loop.removed(closed_loop.torque_rms(ol)["overall"], closed_loop.torque_rms(tr)["overall"])
    assert abs(cut) < 0.05
    assert all(c["closed"] == 0 for c in info["commands"].values())


def test_a_silent_sensor_opens_the_loops_within_one_step_and_they_resume_when_estimates_return(capture):
    # arm0's F/T sensor goes silent for 100 ms: the gateway's epochs need every sensor, so no
    # estimate of either arm comes (then they come back flagged until the filters settle); both
    # loops open once the last good estimate is stale_s old, and both close again
    sc = capture.replace(duration_s=1.0)
    tr, info = closed_loop.run_compensated(sc, command_limit=0.7, faults=Faults(silent=(("arm0", 0.6, 0.1),)))
    ev = [(e["arm"], e["state"], e["t_s"]) for e in info["transitions"]]
    stale = 0.010                                 # JointLoopSettings.stale_s
    assert [(a, s) for a, s, _ in ev] == [("arm0", "closed"), ("arm1", "closed"), ("arm0", "open"), ("arm1", "open"),
                                          ("arm0", "closed"), ("arm1", "closed")]
    # open at the first command after the last good estimate (0.599 s) became stale: one step
    assert all(0.599 + stale < t <= 0.599 + stale + 0.002 for _, s, t in ev[2:4])
    assert info["transitions"][2]["reason"] == "stale:efforts"
    assert info["flags"]["estimate:not-good"] > 0           # the flagged estimates after the gap
    closed = info["closed"]
    t = tr.arrays["t_s"]
    during = (t > 0.612) & (t < 0.7)
    assert not closed[during].any()
    # open loop is the desired torque as the arm bus carried it: the drives applied the flight
    # software's command of the step before, nothing added (within the wire's 0.05 N m resolution)
    k = np.flatnonzero(during)
    np.testing.assert_allclose(info["applied"][k], tr.arrays["tau_cmd"][k - 1], rtol=0, atol=0.025 + 1e-9)
    assert closed[t > 0.85].all()


def test_a_silent_imu_puts_the_thrusters_on_the_nominal_allocation_within_one_step_and_back(capture):
    # the IMU goes silent for 100 ms: the thruster efforts go stale, the thruster loop takes the
    # nominal wrenches from the first valves after the last good estimate is stale_s old (20 ms),
    # and closes again once estimates are good
    sc = capture.replace(duration_s=1.0)
    tr, info = closed_loop.run_compensated(sc, faults=Faults(silent=(("imu", 0.5, 0.1),)))
    thr = info["thrusters"]
    ev = [(e["state"], e["t_s"]) for e in thr["transitions"]]
    assert [s for s, _ in ev] == ["closed", "open", "closed"]
    assert 0.5 < ev[1][1] <= 0.5 + 0.020 + 0.003                 # the last good estimate is at most 2 ms before
    assert thr["transitions"][1]["reason"] == "stale:efforts" or thr["transitions"][1]["reason"].startswith(
        "estimate:not-good")
    t = tr.arrays["t_s"]
    assert not thr["closed"][(t > ev[1][1] + 0.0015) & (t < 0.6)].any()
    assert thr["closed"][t > ev[2][1] + 0.0015].all()


def test_a_thruster_the_fault_detector_names_is_never_fired_again():
    # thruster 2 (the busiest) stuck closed from 2.0 s (after the detector's warm-up): the gateway
    # names it (0.22 s later on 2026-11-26) and the valve is not commanded again
    from simulator import scenario as scenarios

    sc = scenarios.load("capture", {"duration_s": 2.6})
    data = dict(sc.data)
    data["degrade"] = [{"kind": "thruster_stuck", "thruster": 2, "onset_s": 2.0, "state": "closed"}]
    tr, info = closed_loop.run_compensated(scenarios._build(sc.name, sc.text, data))
    thr = info["thrusters"]
    named = [e for e in thr["transitions"] if e["state"] == "fault"]
    assert named and "thruster2" in named[0]["reason"] and 2.0 < named[0]["t_s"] < 2.5
    after = tr.arrays["t_s"] > named[0]["t_s"] + 0.0015
    assert thr["applied"][~after, 2].any() and not thr["applied"][after, 2].any()
    assert thr["flags"]["fault:thruster2"] > 0


def test_the_robots_drives_apply_fresh_commands_from_zenoh_and_never_late_ones(capture):
    import zenoh

    from gateway import codec
    from gateway.control.messages import DriveCommand, encode_drive_command
    from gateway.keys import drive_command
    from gateway.zenoh_config import make_config
    from support import free_port, subscribed, wait_until

    sim = Simulation(capture.replace(duration_s=0.1), external_drives=True)
    ep = f"tcp/127.0.0.1:{free_port()}"
    t = 1_000_000_000
    with zenoh.open(make_config(mode="router", listen=[ep])) as a, \
            zenoh.open(make_config(mode="client", connect=[ep])) as b:
        inbox = closed_loop.DriveInbox(b, sim, max_age_s=0.005)
        pub = codec.declare_publisher(a, drive_command("paper_robot", "arm0"))
        try:
            subscribed(a, drive_command("paper_robot", "arm0"))
            codec.put(pub, encode_drive_command(DriveCommand("arm0", t, ("arm0/j1", "arm0/j2"), (111.0, -22.0),
                                                             (100.0, -20.0), (11.0, -2.0), True)))
            wait_until(lambda: inbox.received == 1, "the drive command")
            sim.step()
            inbox.apply(now_ns=t + 4_000_000)                  # 4 ms old: applied to arm0, arm1 on its own
            sim.step()
            np.testing.assert_array_equal(sim.drive_applied[1, :2], [111.0, -22.0])
            np.testing.assert_array_equal(sim.drive_applied[1, 2:], sim.trace.arrays["tau_cmd"][1, 2:])
            inbox.apply(now_ns=t + 6_000_000)                  # 6 ms old: too late, the flight software's
            sim.step()
            np.testing.assert_array_equal(sim.drive_applied[2], sim.trace.arrays["tau_cmd"][2])
            # an older command arriving after it is ignored; a payload that is no command is counted
            codec.put(pub, encode_drive_command(DriveCommand("arm0", t - 1, ("arm0/j1", "arm0/j2"), (0.0, 0.0),
                                                             (0.0, 0.0), (0.0, 0.0), False)))
            codec.put(pub, b"{}")
            wait_until(lambda: inbox.received + inbox.rejected >= 3, "the late and the bad payloads")
            assert inbox.latest["arm0"].t_ns == t and inbox.rejected == 1
            s = inbox.summary()
            assert s["arm_steps_applied"] == {"closed": 1, "open": 0, "late_or_none": 3}
        finally:
            pub.undeclare()
            inbox.close()


def test_the_robots_valves_follow_fresh_schedules_from_zenoh_within_its_keep_out(capture):
    import time

    import zenoh

    from gateway import codec
    from gateway.control.messages import ThrusterValves, encode_thruster_valves
    from gateway.keys import thruster_valves
    from gateway.zenoh_config import make_config
    from support import free_port, subscribed, wait_until

    sim = Simulation(capture.replace(duration_s=0.1), external_thrusters=True)
    n = sim.layout.n
    ep = f"tcp/127.0.0.1:{free_port()}"
    ms = 1_000_000
    masks = (0b11, 0b110, 0, 0b1100, (1 << n) - 1, 0b1, 0b10, 0b100, 0b1000, 0b10000)
    with zenoh.open(make_config(mode="router", listen=[ep])) as a, \
            zenoh.open(make_config(mode="client", connect=[ep])) as b:
        # the deadline is judged on the host clock at arrival: set for the too-old case below only
        # (a loaded host can take more than 5 ms from t0 to this schedule's arrival)
        inbox = closed_loop.ValveInbox(b, sim, max_age_s=10.0)
        pub = codec.declare_publisher(a, thruster_valves("paper_robot"))
        try:
            subscribed(a, thruster_valves("paper_robot"))
            t0 = time.time_ns()                     # the host time step 0 went out

            def step():
                r = sim.step()
                inbox.apply(r, now_ns=t0 + r.t_ns + 80_000)   # each step out 80 us after it was due
                return r

            for _ in range(3):
                step()
            assert abs(inbox.t0_ns - (t0 + 80_000)) == 0
            # the valves of steps 4..13 (their first step's host time 4.03 ms after t0: rounded to step 4)
            v = ThrusterValves(t0 + 4 * ms + 30_000, masks[0], (0.0,) * n, True, (), masks[1:], ms)
            codec.put(pub, encode_thruster_valves(v))
            wait_until(lambda: inbox.received == 1, "the valve schedule")
            # the keep-out of this period excludes thruster 1: closed by the robot, counted
            sim.allowed = np.ones(n, dtype=bool)
            sim.allowed[1] = False
            keep = sim.allowed.copy()
            step()                                  # step 3 out: the schedule goes to the simulation
            while sim.k < 16:
                step()
            got = sim.valves_applied[4:14]
            want = (np.array(masks)[:, None] >> np.arange(n)) & 1 != 0
            np.testing.assert_array_equal(got, want & keep)
            assert sim.valves_external[4:14].all() and not sim.valves_external[:4].any()
            assert not sim.valves_external[14:16].any()      # beyond the schedule: the flight software's
            assert inbox.keep_out_closed == int((want & ~keep).sum()) == 4
            # too old on arrival (10 ms or more after its first step), and a step already run: not applied
            inbox.max_age_ns = 5 * ms
            codec.put(pub, encode_thruster_valves(ThrusterValves(time.time_ns() - 10 * ms, 1, (0.0,) * n, True)))
            wait_until(lambda: inbox.too_old == 1, "the old schedule")
            inbox.max_age_ns = 10 ** 10                 # (this test's steps are not paced: only late rows)
            codec.put(pub, encode_thruster_valves(ThrusterValves(t0 + 2 * ms, 1, (0.0,) * n, True, (), (1,), ms)))
            codec.put(pub, b"{}")
            wait_until(lambda: inbox.received + inbox.rejected == 4, "the late and the bad schedules")
            step()
            s = inbox.summary()
            assert (s["applied"], s["too_old"], s["rejected"], s["rows_late"]) == (2, 1, 1, 2)
            assert s["steps_external"] == 10 and s["first_step_to_arrival_us"]["n"] == 3
        finally:
            pub.undeclare()
            inbox.close()


def test_bsc_demo_closed_loop_writes_the_report_keys_and_figures(tmp_path, capsys):
    import json

    from gateway.cli import main

    out = tmp_path / "d"
    run = ["demo", "--duration", "0.3", "--no-sweep", "--no-record", "--quiet", "--out", str(out)]
    assert main(run + ["--closed-loop", "--report-only"]) == 0
    printed = capsys.readouterr().out
    assert "closed loop, the scenario as it is:" in printed and "outer loop limited to 70 %" in printed
    report = json.loads((out / "report.json").read_text())
    for block in (report["closed_loop"], report["closed_loop"]["headroom"]):
        for case in ("no_friction", "open_loop", "compensated"):
            assert set(block["ee_rms_error_m"][case]) == {"arm0", "arm1", "overall"}
        for key in ("joint_torque_rms_error_nm", "thruster_wrench_rms_error"):
            assert set(block[key]) >= {"open_loop", "compensated"}
    for name in ("closed_loop_ee_error.png", "closed_loop_joint_torques.png", "closed_loop_thruster_wrench.png",
                 "closed_loop_headroom_ee_error.png", "closed_loop_headroom_joint_torques.png",
                 "closed_loop_headroom_thruster_wrench.png"):
        assert (out / name).stat().st_size > 10_000, name
    assert main(run + ["--realtime"]) == 2
    assert "give --closed-loop too" in capsys.readouterr().err
    assert main(run + ["--closed-loop", "--realtime-thrusters"]) == 2
    assert "give --realtime too" in capsys.readouterr().err


@pytest.mark.parametrize("args, says", [
    (["--drives-from", "tcp/127.0.0.1:9"], "--drives-from needs --realtime"),
    (["--command-limit", "0"], "--command-limit must be a fraction in (0, 1]"),
    (["--command-limit", "1.5"], "--command-limit must be a fraction in (0, 1]"),
    (["--drive-max-age", "0"], "--drive-max-age must be positive"),
    (["--valves-from", "tcp/127.0.0.1:9"], "--valves-from needs --realtime"),
    (["--thrust-limit", "0"], "--thrust-limit must be a fraction in (0, 1]"),
    (["--valve-max-age", "-1"], "--valve-max-age must be positive"),
])
def test_bsc_sim_closed_loop_options_are_checked_in_one_line(args, says, tmp_path, capsys):
    from gateway.cli import main

    assert main(["sim", "--duration", "0.1", "--no-plots", "--quiet", "--out", str(tmp_path), *args]) == 2
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1
