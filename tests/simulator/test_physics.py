"""Physics of the simulated robot, each checked against an independent computation."""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

import robot_description
from simulator import scenario
from simulator.dynamics import Dynamics, Friction
from simulator.engine import Simulation


def _moving_state(robot, rng):
    q = robot.neutral()
    q[7:] = rng.uniform(-1.5, 1.5, robot.n_joints)
    v = np.zeros(robot.nv)
    v[:6] = rng.normal(0, [0.1, 0.1, 0.1, 0.02, 0.02, 0.05])
    v[6:] = rng.uniform(-0.5, 0.5, robot.n_joints)
    return q, v


@pytest.mark.parametrize("name", ["paper_robot", "three_arm"])
def test_momentum_conserved_without_thrusters_or_friction(name):
    robot = robot_description.load(name)
    rng = np.random.default_rng(1)
    dyn = Dynamics(robot.model, Friction.none(robot.n_joints), 1e-3)
    dyn.q, dyn.v = _moving_state(robot, rng)
    h0 = dyn.momentum_world()
    freq = rng.uniform(0.5, 3.0, robot.n_joints)
    for k in range(10_000):   # 10 s at 1 kHz, internal motor torques at 30 % of each rating
        dyn.step(np.zeros(6), 0.3 * robot.effort_limit * np.sin(freq * k * 1e-3))
    drift = np.abs(dyn.momentum_world() - h0).max() / np.abs(h0).max()
    assert drift < 1e-9, drift


def test_friction_never_adds_energy_and_keeps_momentum():
    robot = robot_description.load()
    rng = np.random.default_rng(2)
    n = robot.n_joints
    fr = Friction(0.3 * robot.effort_limit, 0.35 * robot.effort_limit, np.full(n, 5.0))
    dyn = Dynamics(robot.model, fr, 1e-3)
    dyn.q, dyn.v = _moving_state(robot, rng)
    h0 = dyn.momentum_world()
    energy = [dyn.kinetic_energy()]
    for _ in range(3000):
        dyn.step(np.zeros(6), np.zeros(n))
        energy.append(dyn.kinetic_energy())
    energy = np.array(energy)
    assert np.all(np.diff(energy) <= 1e-9 * energy[0])
    assert energy[-1] < 0.9 * energy[0]           # it really dissipated
    assert dyn.stuck.all()                         # and every joint came to rest relative to its parent
    assert np.abs(dyn.momentum_world() - h0).max() / np.abs(h0).max() < 1e-9


def test_friction_sticks_below_breakaway_and_slips_above():
    robot = robot_description.load()
    n = robot.n_joints
    static = 0.3 * robot.effort_limit
    fr = Friction(0.25 * robot.effort_limit, static, np.zeros(n))

    def run(frac):
        dyn = Dynamics(robot.model, fr, 1e-3)
        q = robot.neutral()
        q[7:] = [0.3, 1.2, -0.3, -1.2]
        dyn.q = q
        tau = np.zeros(n)
        tau[0] = frac * static[0]                  # push joint 1 of arm 0 only
        for _ in range(500):
            dyn.step(np.zeros(6), tau)
        return dyn

    held = run(0.9)
    assert abs(held.v[6]) < 1e-12 and held.stuck[0]
    assert abs(held.q[7] - 0.3) < 1e-9
    assert abs(held.tau_friction[0]) <= static[0]
    moved = run(1.3)
    assert not moved.stuck[0] and moved.v[6] > 1e-3


def test_no_stick_slip_chatter_in_smooth_tanh_sense():
    # A smooth tanh model would creep under a constant sub-breakaway torque; ours must not.
    robot = robot_description.load()
    n = robot.n_joints
    fr = Friction(0.3 * robot.effort_limit, 0.3 * robot.effort_limit, np.zeros(n))
    dyn = Dynamics(robot.model, fr, 1e-3)
    dyn.q[7:] = [0.0, 1.0, 0.0, -1.0]
    tau = 0.5 * fr.static_nm
    q0 = dyn.q.copy()
    for _ in range(2000):
        dyn.step(np.zeros(6), tau)
    assert np.abs(dyn.q[7:] - q0[7:]).max() < 1e-9


@pytest.fixture(scope="module")
def capture_run():
    sc = scenario.load("capture", {"duration_s": 1.5})
    sim = Simulation(sc)
    return sim, sim.run()


def test_ft_truth_is_rate_of_change_of_arm_momentum(capture_run):
    """Newton-Euler on each arm: d/dt of its momentum = the sensor wrench (inertial frame)."""
    sim, tr = capture_run
    robot = sim.robot
    model, data = robot.model, robot.model.createData()
    q, v, a = tr["q"], tr["v"], tr["a"]
    k = 900                                                 # an interior step
    for i, arm in enumerate(robot.arms):
        bodies = list(arm.joints)

        def momentum(qk, vk):
            pin.forwardKinematics(model, data, qk, vk)
            lin, ang = np.zeros(3), np.zeros(3)
            for j in bodies:
                Y = model.inertias[j]
                oM = data.oMi[j]
                c = oM.act(Y.lever)
                vc = oM.rotation @ (data.v[j].linear + np.cross(data.v[j].angular, Y.lever))
                w = oM.rotation @ data.v[j].angular
                lin += Y.mass * vc
                ang += np.cross(c, Y.mass * vc) + oM.rotation @ Y.inertia @ oM.rotation.T @ w
            return lin, ang

        # exact time derivative via Pinocchio's velocity-level identities: central difference of
        # the integrated state along (v, a) over +-h (independent of the simulator's integrator)
        h = 1e-5
        qp = pin.integrate(model, q[k], v[k] * h + 0.5 * a[k] * h * h)
        qm = pin.integrate(model, q[k], -v[k] * h + 0.5 * a[k] * h * h)
        lp, ap = momentum(qp, v[k] + a[k] * h)
        lm, am = momentum(qm, v[k] - a[k] * h)
        dl, da = (lp - lm) / (2 * h), (ap - am) / (2 * h)
        pin.framesForwardKinematics(model, data, q[k])
        oS = data.oMf[arm.sensor_frame]
        f_w = oS.rotation @ tr["ft_true"][k, i, :3]
        t_w = oS.rotation @ tr["ft_true"][k, i, 3:] + np.cross(oS.translation, f_w)
        assert np.allclose(dl, f_w, atol=1e-3 * max(1.0, np.abs(f_w).max()), rtol=0), (dl, f_w)
        assert np.allclose(da, t_w, atol=1e-3 * max(1.0, np.abs(t_w).max()), rtol=0), (da, t_w)


def test_ft_projection_on_joint1_is_joint1_actual_torque(capture_run):
    sim, tr = capture_run
    robot = sim.robot
    model = robot.model
    for i, arm in enumerate(robot.arms):
        j1 = arm.joints[0]
        col = arm.iv[0] - 6
        S_M_j1 = model.frames[arm.sensor_frame].placement.actInv(model.jointPlacements[j1])
        for k in range(100, tr.n, 97):
            w = tr["ft_true"][k, i]
            # moment about joint 1's origin, in joint 1's (pre-rotation) frame, projected on its axis
            f = pin.Force(w[:3], w[3:])
            fj = S_M_j1.actInv(f)
            z = _axis(model, j1)
            assert abs(float(z @ fj.angular) - tr["tau_act"][k, col]) < 1e-6 * max(1.0, abs(tr["tau_act"][k, col]))


def _axis(model, j):
    S = model.joints[j].shortname()
    return {"JointModelRZ": np.array([0, 0, 1.0]), "JointModelRY": np.array([0, 1.0, 0]),
            "JointModelRX": np.array([1.0, 0, 0])}[S]


def test_thruster_truth_equals_inverse_dynamics_base_wrench(capture_run):
    sim, tr = capture_run
    model = sim.robot.model
    data = model.createData()
    for k in range(50, tr.n, 101):
        tau = pin.rnea(model, data, tr["q"][k], tr["v"][k], tr["a"][k])
        assert np.allclose(tau[:6], tr["thr_act"][k], atol=1e-6)
        assert np.allclose(tau[6:], tr["tau_act"][k], atol=1e-6)


def test_deterministic_bit_identical():
    sc = scenario.load("capture", {"duration_s": 0.3})
    a, b = Simulation(sc).run(), Simulation(sc).run()
    for key in a.arrays:
        assert np.array_equal(a[key], b[key]), key
    c = Simulation(sc.replace(seed=sc.seed + 1)).run()
    assert not np.array_equal(a["ft_meas"], c["ft_meas"])


def test_three_arm_robot_runs():
    sc = scenario.load("three_arm", {"duration_s": 0.5})
    sim = Simulation(sc)
    tr = sim.run()
    assert tr["ft_true"].shape[1:] == (3, 6)
    assert tr["tau_act"].shape[1] == 9
    assert np.isfinite(tr["q"]).all()


def test_step_and_run_give_the_same_trace_and_readings_match_it():
    """run() evaluates the sensors over blocks, step() one step at a time: same numbers."""
    sc = scenario.load("capture", {"duration_s": 0.25})
    ran = Simulation(sc).run()
    sim = Simulation(sc)
    readings = [sim.step() for _ in range(sim.n_steps)]
    stepped = sim.trace
    for key in ran.arrays:
        assert np.array_equal(ran[key], stepped[key]), key
    imu = [r for r in readings if r.imu is not None]
    assert len(imu) == stepped.n_imu
    for k, r in enumerate(readings):
        assert r.t_ns == k * 1_000_000
        assert np.array_equal(r.ft, ran["ft_meas"][k]) and not r.ft_saturated.any()
        assert np.array_equal(r.joint_angle, ran["enc_angle"][k])
        assert np.array_equal(r.joint_rate, ran["enc_rate"][k])
        assert np.array_equal(r.valves, ran["valves"][k])
        assert (r.torque_cmd is not None) == (k % sim.ctrl_every == 0)
        assert (r.thruster_cmd is not None) == (k % sim.base_every == 0)
        if r.torque_cmd is not None:
            assert np.array_equal(r.torque_cmd, ran["tau_cmd"][k])
    for s, r in enumerate(imu):
        assert np.array_equal(r.imu[0], ran["imu_quat"][s]) and np.array_equal(r.imu[2], ran["imu_acc"][s])


def test_ft_truth_equals_rnea_transmitted_wrench(capture_run):
    """The F/T truth (from the physics step's ABA forces, transformed in blocks) is Pinocchio's
    RNEA joint force of (q, v, a), moved to the sensor frame."""
    sim, tr = capture_run
    model = sim.robot.model
    data = model.createData()
    for k in range(0, tr.n, 137):
        pin.rnea(model, data, tr["q"][k], tr["v"][k], tr["a"][k])
        for i, arm in enumerate(sim.robot.arms):
            j = arm.joints[0]
            f = model.frames[arm.sensor_frame].placement.actInv(data.liMi[j].act(data.f[j]))
            assert np.allclose(tr["ft_true"][k, i], f.vector, rtol=0, atol=1e-9 * max(1.0, np.abs(f.vector).max()))


def test_imu_block_matches_a_per_sample_reference(capture_run):
    """IMU outputs against a direct per-sample evaluation of the documented model."""
    sim, tr = capture_run
    imu, e = sim.imu, sim.imu_every
    q, v, acc = tr["q"], tr["v"], tr["base_acc"]
    r = imu.r_imu
    for s in range(0, tr.n_imu - 1, 53):
        rows = range(s * e, (s + 1) * e)
        sf = [acc[k, :3] + np.cross(acc[k, 3:], r) + np.cross(v[k, 3:6], np.cross(v[k, 3:6], r)) for k in rows]
        acc_true = imu.R_imu.T @ np.mean(sf, axis=0)
        rate_true = imu.R_imu.T @ np.mean([v[k, 3:6] for k in rows], axis=0)
        assert np.allclose(tr["imu_acc_true"][s], acc_true, rtol=0, atol=1e-12)
        assert np.allclose(tr["imu_rate_true"][s], rate_true, rtol=0, atol=1e-14)
        R = pin.XYZQUATToSE3(q[(s + 1) * e, :7]).rotation @ imu.R_imu
        qw = tr["imu_quat"][s]
        Rm = pin.Quaternion(qw[0], qw[1], qw[2], qw[3]).toRotationMatrix()
        assert np.abs(Rm - R).max() < 10 * imu.att_sigma + 1e-9     # attitude noise only
        assert abs(tr["imu_t_s"][s] - (s + 1) * e * 1e-3) < 1e-12


@pytest.mark.parametrize("name", ["paper_robot", "three_arm"])
def test_inverse_mass_diagonal_stays_under_its_bound(name):
    """The friction model skips computing M^-1 when a joint is too fast to stick, using a bound on
    diag(M^-1) valid in every configuration (simulator.dynamics.minv_diagonal_bound): check it
    against Pinocchio's M^-1 over random configurations."""
    from simulator.dynamics import minv_diagonal_bound

    robot = robot_description.load(name)
    model, data = robot.model, robot.data()
    bound = np.array(minv_diagonal_bound(model))
    rng = np.random.default_rng(7)
    worst = 0.0
    for _ in range(2000):
        q = pin.randomConfiguration(model, -np.pi * np.ones(model.nq), np.pi * np.ones(model.nq))
        q[:3] = rng.normal(size=3)
        q[3:7] = pin.Quaternion(*rng.normal(size=4)).normalized().coeffs()
        minv = pin.computeMinverse(model, data, q)
        diag = np.diag(np.triu(minv) + np.triu(minv, 1).T)[6:]
        assert (diag <= bound).all(), (diag, bound)
        worst = max(worst, float((diag / bound).max()))
    assert 0.2 < worst < 1.0            # a bound, and not a vacuous one
