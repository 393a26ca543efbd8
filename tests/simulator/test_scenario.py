"""Scenario files: defaults, validation, degradations."""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

from simulator import scenario
from simulator.engine import Simulation
from simulator.scenario import ScenarioError


def test_defaults_are_the_capture_task():
    sc = scenario.load()
    assert sc.name == "capture" and sc.robot == "paper_robot"
    assert sc.cfg.target.spin_rpm == 3.0 and sc.cfg.target.radius_m == 3.0


@pytest.mark.parametrize("text, match", [
    ("durtion_s = 3\n", "unknown scenario key 'durtion_s'"),
    ("[noise.ft]\nforce_noise_n = 'big'\n", "noise.ft.force_noise_n"),
    ("[[degrade]]\nkind = 'gremlins'\n", "kind must be one of"),
    ("[[degrade]]\nkind = 'thruster_loss'\nthruster = 1\n", "missing key 'onset_s'"),
    ("duration_s = [\n", "not valid TOML"),
    ("[faults]\ndrop_rat = 0.1\n", "unknown key.*drop_rat"),
    ("[friction]\nper_joint = 3\n", "friction.per_joint' must be a table"),
    ("[controller]\ntask = 'dance'\n", "controller.task must be one of capture, checkout"),
    ("[controller]\nprobe_force_n = -5\n", "controller.probe_force_n must be a size >= 0"),
    ("[controller]\nprobe_dwell_s = 0\n", "controller.probe_dwell_s must be positive"),
])
def test_bad_files_name_the_problem(tmp_path, text, match):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(ScenarioError, match=match):
        scenario.load(f)


def test_partial_file_merges_over_defaults(tmp_path):
    f = tmp_path / "short.toml"
    f.write_text("duration_s = 0.5\n[friction]\ncoulomb_fraction = 0.45\n")
    sc = scenario.load(f)
    assert sc.duration_s == 0.5 and sc.cfg.friction.coulomb_fraction == 0.45
    assert sc.cfg.noise.imu.rate_hz == 500           # untouched default


def test_free_tables_pass_through(tmp_path):
    """friction.per_joint and [faults] are absent from the default file, yet valid."""
    f = tmp_path / "worn.toml"
    f.write_text('duration_s = 0.01\n[friction]\nper_joint = { "arm0/j2" = 0.55 }\n'
                 '[faults]\ndrop_rate = 0.01\nsilent = [["imu", 0.1, 0.2]]\n')
    sc = scenario.load(f)
    assert sc.data["faults"]["drop_rate"] == 0.01
    sim = Simulation(sc)
    j2 = sim.robot.joint_names.index("arm0/j2")
    assert sim.dyn.friction.coulomb_nm[j2] == pytest.approx(0.55 * sim.robot.effort_limit[j2])
    assert sim.dyn.friction.coulomb_nm[0] == pytest.approx(0.30 * sim.robot.effort_limit[0])


def test_checkout_fires_every_thruster_and_holds_the_pose():
    """The checkout: over one probe cycle (12 directions x 0.25 s) every thruster fires, the
    demand leans each way along and about every axis in its turn, the arms hold the positions they
    started in and the spacecraft its pose (within 1 cm and 0.5 degree)."""
    sc = scenario.load("checkout", {"duration_s": 3.1})
    assert sc.cfg.controller.task == "checkout" and scenario.load().cfg.controller.probe_force_n == 0.0
    sim = Simulation(sc)
    tr = sim.run()
    assert tr["valves"].any(axis=0).all()                      # every thruster fired
    dwell = round(sc.cfg.controller.probe_dwell_s * 1000)       # steps of 1 ms
    for k in range(12):
        axis, sign = k // 2, 1 - 2 * (k % 2)
        demand = tr["thr_demand"][k * dwell:(k + 1) * dwell, axis]
        size = sc.cfg.controller.probe_force_n if axis < 3 else sc.cfg.controller.probe_moment_nm
        assert sign * demand.mean() > 0.5 * size, (k, demand.mean())
    xd, xdd = sim.ctrl.desired(np.array([0.0, 1.5, 3.0]))
    assert np.array_equal(xd, np.broadcast_to(sim.ctrl.x0, xd.shape)) and not xdd.any()
    q = tr["q"]
    assert np.abs(q[:, :3] - q[0, :3]).max() < 0.01
    turned = [np.linalg.norm(pin.log3(pin.Quaternion(x[6], x[3], x[4], x[5]).toRotationMatrix())) for x in q[::50]]
    assert math.degrees(max(turned)) < 0.5


def test_degradations_act_at_their_onset():
    sc = scenario.load("capture", {"duration_s": 0.6})
    data = dict(sc.data)
    data["degrade"] = [
        {"kind": "friction_growth", "joint": "arm0/j2", "onset_s": 0.2, "to_fraction": 0.6, "ramp_s": 0.2},
        {"kind": "thruster_stuck", "thruster": 3, "onset_s": 0.3, "state": "open"},
        {"kind": "ft_bias_drift", "arm": "arm1", "onset_s": 0.1, "force_n_per_s": [10.0, 0, 0],
         "torque_nm_per_s": [0, 0, 0]},
    ]
    sim = Simulation(scenario._build(sc.name, sc.text, data))
    tr = sim.run()
    assert sim.dyn.friction.coulomb_nm[1] == pytest.approx(0.6 * sim.robot.effort_limit[1])
    assert tr["valves"][350:, 3].all() and not tr["valves"][:100, 3].all()
    bias = tr["ft_meas"][:, 1, 0] - tr["ft_true"][:, 1, 0]
    assert bias[550:].mean() - bias[:90].mean() == pytest.approx(10.0 * 0.5, abs=0.3)


def test_a_stuck_valve_is_not_in_the_valve_commands():
    """The bus carries the flight software's valve commands (PWPFM); a stuck valve changes what
    the thruster does (the trace's actual valve state), not what it was told."""
    sc = scenario.load("capture", {"duration_s": 0.8})
    data = dict(sc.data)
    data["degrade"] = [{"kind": "thruster_stuck", "thruster": 2, "onset_s": 0.4, "state": "closed"}]
    sim = Simulation(scenario._build(sc.name, sc.text, data))
    commanded = np.array([sim.step().valves for _ in range(sim.n_steps)])
    actual = sim.trace["valves"]
    assert np.array_equal(commanded[:400], actual[:400])
    assert not actual[400:, 2].any() and commanded[400:, 2].any()
    assert np.array_equal(np.delete(commanded, 2, axis=1), np.delete(actual, 2, axis=1))


def _degraded_runs(degrade: dict):
    """0.6 s of capture healthy and with ``degrade`` from 0.3 s: (scenario, degraded scenario,
    healthy trace, degraded trace, the degraded run stepped with external valves)."""
    sc = scenario.load("capture", {"duration_s": 0.6})
    data = dict(sc.data)
    data["degrade"] = [degrade]
    bad = scenario._build(sc.name, sc.text, data)
    ref, tr = Simulation(sc).run(), Simulation(bad).run()
    stepped = Simulation(bad, external_thrusters=True)
    while stepped.k < stepped.n_steps:
        stepped.step()
    return sc, bad, ref, tr, stepped


def test_a_leaking_valve_thrusts_while_closed_and_nothing_else_changes():
    """thruster_leak: from its onset a closed valve delivers that fraction of the thrust it gives
    open (gain, pressure, heating); before it, bit for bit the healthy run (after it the flight
    software answers the leak); the stepped path (external valves) gives the same thrust."""
    sc, leaky, ref, tr, stepped = _degraded_runs({"kind": "thruster_leak", "thruster": 5, "onset_s": 0.3,
                                                  "factor": 0.25})
    k0 = 300
    assert np.array_equal(tr["thrust"][:k0], ref["thrust"][:k0])
    closed = ~tr["valves"][k0:, 5]
    assert closed.sum() > 100
    # while closed: a quarter of what the valve gives open, its gain (scatter, pressure; heating
    # moves it by under 2 %) times its maximum
    err = Simulation(leaky).thr_err
    full = err.layout.max_n[5] * err.scatter[5] * err.pressure
    assert np.allclose(tr["thrust"][k0:, 5][closed], 0.25 * full, rtol=0.02)
    with pytest.raises(ValueError, match="thruster_leak factor"):
        bad = dict(sc.data)
        bad["degrade"] = [{"kind": "thruster_leak", "thruster": 5, "onset_s": 0.3, "factor": 1.5}]
        Simulation(scenario._build(sc.name, sc.text, bad))
    np.testing.assert_allclose(stepped.trace["thrust"], tr["thrust"], rtol=0, atol=1e-9)


def test_a_tilted_thruster_turns_its_thrust_and_nothing_else_changes():
    """thruster_misalign: from its onset a thruster's thrust acts along its actual direction tilted
    by angle_deg towards the body axis most perpendicular to it; its thrust magnitude, the valves
    and every other thruster unchanged; before the onset bit for bit the healthy run; the stepped
    path (external valves) gives the same wrench."""
    from simulator.thrusters import tilted

    sc, bent, ref, tr, stepped = _degraded_runs({"kind": "thruster_misalign", "thruster": 2, "onset_s": 0.3,
                                                 "angle_deg": 20.0})
    k0 = 300
    assert np.array_equal(tr["thr_act"][:k0], ref["thr_act"][:k0])
    err = Simulation(bent).thr_err
    d = err.dir_actual[2]
    new = tilted(d, 20.0)
    assert math.degrees(math.acos(float(new @ d))) == pytest.approx(20.0, abs=1e-9)
    assert abs(float(new[2])) > 0.3                     # thruster 2 (in the x-y plane) tilts towards z
    col = np.concatenate([new, np.cross(err.layout.pos_m[2], new)])
    others = np.delete(np.arange(err.layout.n), 2)
    want = tr["thrust"][k0:, others] @ err.B_actual[:, others].T + tr["thrust"][k0:, 2:3] * col
    assert tr["valves"][k0:, 2].sum() > 20
    np.testing.assert_allclose(tr["thr_act"][k0:], want, rtol=0, atol=1e-9)
    np.testing.assert_allclose(stepped.trace["thr_act"], tr["thr_act"], rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="thruster_misalign angle_deg"):
        bad = dict(sc.data)
        bad["degrade"] = [{"kind": "thruster_misalign", "thruster": 2, "onset_s": 0.3, "angle_deg": 120.0}]
        Simulation(scenario._build(sc.name, sc.text, bad))
