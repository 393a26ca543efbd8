"""The joint filter (gateway/estimator/joint_filter.py) inside the chain kernel: against a dense
Kalman filter written independently on Pinocchio, and against the simulator's truth."""
from __future__ import annotations

import numpy as np
import pytest

import robot_description as rd
from gateway.estimator import EstimatorModel, arm_reaction
from gateway.estimator import chain_kernel as ck
from gateway.estimator import joint_filter as jf
from gateway.estimator.model import EstimatorSettingsError
from gateway.estimator.torques import joint_accelerations_from_ft

from reference_joint_filter import DT, DenseFilter, SequentialFilter, _fused, _J_w0

EPOCHS = 1000


def _trajectory(model: EstimatorModel, rng: np.random.Generator, B: int):
    """Smooth joint motion, F/T readings of tens of N, gaps: every input of ck.epoch_kernel per epoch."""
    n, p = model.n_joints, model.n_arms
    t = np.arange(B) * DT
    f = rng.uniform(0.2, 1.5, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    q = np.sin(2 * np.pi * f * t[:, None] + ph)
    dq = 2 * np.pi * f * np.cos(2 * np.pi * f * t[:, None] + ph) + rng.normal(0, 2e-5, (B, n))
    ft = rng.normal(0.0, 20.0, (p, 6)) + rng.normal(0.0, 0.3, (B, p, 6))
    thr = rng.normal(0.0, 30.0, (B, 6))
    w_s = rng.normal(0.0, 0.05, (B, 3))
    ft_ok = (rng.random((B, p)) > 0.1).astype(np.int64)
    ft_ok[0] = 1
    rate_ok = (rng.random((B, n)) > 0.1).astype(np.int64)
    return q, dq, ft, thr, w_s, ft_ok, rate_ok


@pytest.mark.parametrize("robot", ["paper_robot", "three_arm"])
def test_agrees_with_a_dense_filter_on_pinocchio(robot):
    model = EstimatorModel.from_robot(rd.load(robot))
    data = model.data()
    s = jf.JointFilterSettings(contact=False)   # the filter alone: the contact test has tests of its own
    kernel = ck.EpochKernel(model, joint_filter=s)
    args = kernel._args
    fst, fP = jf.new_state(model.n_arms)
    fc = s.constants()
    refs = {"dense": [DenseFilter(len(a.columns), s) for a in model.arms],
            "extended": [SequentialFilter(len(a.columns), s) for a in model.arms]}
    q, dq, ft, thr, w_s, ft_ok, rate_ok = _trajectory(model, np.random.default_rng(21), EPOCHS)
    worst = {"dense": np.zeros(3), "extended": np.zeros(3)}
    for k in range(len(q)):
        out = kernel.outputs()
        ck.epoch_kernel(*args, q[k], dq[k], ft[k], thr[k], w_s[k], *out, DT if k else 1e9, ft_ok[k], rate_ok[k],
                        fst, fP, fc)
        simp, ddq, full, a_s, dw_s, arm_w = out
        # the arms' reaction is the measured one (the thruster filter has bias states of its own)
        want_w = arm_reaction(model, ft[k])
        assert np.abs(arm_w - want_w).max() <= 1e-12 * max(1.0, np.abs(want_w).max())
        Js, w0 = _J_w0(model, data, q[k], dq[k], a_s, w_s[k], dw_s)
        ls = joint_accelerations_from_ft(model, data, q[k], dq[k], ft[k], a_s, w_s[k], dw_s)
        tau = _fused(model, data, s, fP, q[k], dq[k], ddq, ft[k], a_s, w_s[k], dw_s, Js,
                     [fst[a.index, 2 * len(a.columns):2 * len(a.columns) + 6] for a in model.arms])
        for kind, ref in refs.items():
            want = np.empty(model.n_joints)
            for a in model.arms:
                cols = list(a.columns)
                n = len(cols)
                f = ref[a.index]
                if not f.started:
                    assert ft_ok[k, a.index]
                    f.start(dq[k, cols], ls[cols])
                else:
                    f.step(Js[a.index], ft[k, a.index] - w0[a.index], ft_ok[k, a.index], dq[k, cols],
                           rate_ok[k, cols])
                want[cols] = f.x[n:2 * n].astype(float)
                fb = f.x[2 * n:].astype(float)
                b = fst[a.index, 2 * n:2 * n + 6]
                worst[kind][2] = max(worst[kind][2], np.abs(b - fb).max() / max(1.0, np.abs(fb).max()))
            worst[kind][0] = max(worst[kind][0], np.abs(ddq - want).max() / max(1.0, np.abs(want).max()))
            # the torques: the distal and sensor sides of the filtered state, fused
            worst[kind][1] = max(worst[kind][1], np.abs(full - tau).max() / max(1.0, np.abs(tau).max()))
    # The covariance spans eight orders of magnitude (rates known to 2e-5 rad/s, biases to a
    # newton), so rounding anywhere (the inputs: the kernel's J and w0 differ from Pinocchio's at
    # ~1e-15) is amplified. Observed over these 1000 epochs: the kernel within 3e-10 (three_arm)
    # to 3e-8 (paper_robot) of its own order in extended precision, and 3e-7 to 7e-5 of the
    # textbook joint update (P - K H P, not symmetric: the least accurate of the three, here to
    # show that one joint update and the kernel's scalar updates are the same filter); the
    # torques, given ddq, to ~1e-14.
    assert worst["extended"][1] <= 1e-9 and (worst["extended"] <= 1e-7).all(), f"ddq, full, bias: {worst}"
    assert (worst["dense"] <= 1e-3).all(), f"relative errors ddq, full, bias: {worst}"


def test_a_long_silence_restarts_the_filter():
    model = EstimatorModel.from_robot(rd.load("paper_robot"))
    s = jf.JointFilterSettings(max_gap_s=0.05)
    kernel = ck.EpochKernel(model, joint_filter=s)
    q, dq, ft, thr, w_s, _, _ = _trajectory(model, np.random.default_rng(22), 40)
    kernel.batch(q, dq, ft, thr, w_s)
    assert (kernel.filter_state[:, jf.S_STARTED] == 1.0).all()
    fresh = ck.EpochKernel(model, joint_filter=s)
    ref = fresh.epoch(q[-1], dq[-1], ft[-1], thr[-1], w_s[-1])
    kernel.dt = 0.06                              # longer than max_gap_s: started again, as a fresh one
    got = kernel.epoch(q[-1], dq[-1], ft[-1], thr[-1], w_s[-1])
    assert np.array_equal(got[1], ref[1]) and np.array_equal(got[2], ref[2])


def test_settings_are_checked():
    for bad in ({"jerk_psd": 0.0}, {"rate_sigma_rad_s": -1.0}, {"bias_walk_n": float("nan")}, {"enabled": 1},
                {"max_gap_s": True}):
        with pytest.raises(EstimatorSettingsError):
            jf.JointFilterSettings(**bad)


def _nrmse(est, act):
    return np.sqrt(np.mean((est - act) ** 2, axis=0)) / np.abs(act).max(axis=0)


@pytest.fixture(scope="module")
def three_arm_session():
    from simulator import scenario
    from simulator.engine import Simulation

    sim = Simulation(scenario.load("three_arm", {"seed": 1, "duration_s": 4.0}))
    return sim.robot, sim.run().arrays


def _errors(robot, a, model_robot=None):
    """NRMSE per joint of the joint filter's and the least squares' full torques: the kernel alone
    on a simulated session (realistic sensors, the thruster wrench as it really was, so the base
    motion is the kernel's own from the F/T sensors)."""
    model = EstimatorModel.from_robot(model_robot or robot)
    inputs = (a["enc_angle"], a["enc_rate"], a["ft_meas"], a["thr_act"], a["v"][:, 3:6])
    fused = ck.EpochKernel(model).batch(*inputs)[2]
    ls = ck.EpochKernel(model, joint_filter=jf.JointFilterSettings(enabled=False)).batch(*inputs)[2]
    tau = a["tau_act"]
    return _nrmse(fused[50:], tau[50:]), _nrmse(ls[50:], tau[50:])


def test_every_joint_of_three_arm_against_the_simulators_truth(three_arm_session):
    """Every joint within 2.5 % (NRMSE against its peak), where the least squares leave the third
    joints at several times that (observed 1.3-1.7 % against 10-21 %)."""
    robot, a = three_arm_session
    err_f, err_ls = _errors(robot, a)
    names = robot.joint_names
    assert (err_f <= 0.025).all(), dict(zip(names, err_f.round(4)))
    third = [i for i, n in enumerate(names) if n.endswith("j3")]
    assert (err_ls[third] >= 3 * err_f[third]).all(), (err_ls[third], err_f[third])


def test_a_wrong_model_costs_the_distal_joints_not_the_first(three_arm_session):
    """Masses and inertias 5 % off: the first joints keep the sensor side (fused by variance,
    model_uncertainty), the third joints stay well ahead of the least squares (observed 3.4-9.3 %
    against 10.7-21.5 %)."""
    robot, a = three_arm_session
    err_f, err_ls = _errors(robot, a, rd.perturbed(robot, 0.05, seed=1))
    names = robot.joint_names
    first = [i for i, n in enumerate(names) if n.endswith("j1")]
    third = [i for i, n in enumerate(names) if n.endswith("j3")]
    assert (err_f[first] <= 0.005).all(), dict(zip(names, err_f.round(4)))
    assert (err_ls[third] >= 1.5 * err_f[third]).all(), (err_ls[third], err_f[third])


def test_robots_the_tests_have_never_seen(tmp_path):
    """Random robots (robot_description.generate.random_spec: 2-3 arms of 2-4 joints, masses and
    lengths drawn within plausible ranges), three_arm's capture task, the kernel with realistic
    sensors and the true thruster wrench (benchmarks/bench_accuracy.py --random). Issue 17's target
    is every joint within 2 %; measured 2026-11-26 on seeds 0-11: 90 of 98 joints, the others
    distal joints of 8-21 N m peak at 2.1-12 %. Held here: the first joints (the sensor side needs
    no model) within 0.2 %, and at least 80 % of every robot's joints within 2 %."""
    from benchmarks.bench_accuracy import random_scenario, session

    for seed in (1, 3, 4, 5):
        res = session(str(random_scenario(seed, tmp_path)), 1, 3.0)
        filt = {name: r["filter"] for name, r in res.items()}
        first = {n: e for n, e in filt.items() if n.endswith("/j1")}
        assert max(first.values()) <= 0.002, (seed, first)
        assert sum(e <= 0.02 for e in filt.values()) >= 0.8 * len(filt), (seed, filt)
