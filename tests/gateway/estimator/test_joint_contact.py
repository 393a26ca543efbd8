"""Contact at an end effector (gateway/estimator/joint_filter.py, contact_test): the contact
wrench's columns against Pinocchio, and whole sessions of the simulator (firmware frames through
the gateway's session) with a contact, without one, with noisier sensors and a wrong model."""
from __future__ import annotations

import dataclasses

import numpy as np
import pinocchio as pin
import pytest

import robot_description as rd
from gateway.estimator import EstimatorModel
from gateway.estimator import chain_kernel as ck
from gateway.estimator import joint_filter as jf
from gateway.estimator.core import CoreSettings
from harness import demo
from robot_description.generate import random_spec, urdf_text
from simulator import scenario


def _kernel_scratch(model: EstimatorModel, q: np.ndarray) -> np.ndarray:
    """The joint filter's scratch rows after one epoch of the last arm at angles ``q``."""
    arrs = ck.pack(model)
    p, nj = model.n_arms, model.n_joints
    rng = np.random.default_rng(1)
    outs = [np.empty(nj), np.empty(nj), np.empty(nj), np.empty(3), np.empty(3), np.empty(6)]
    fst, fP = jf.new_state(p)
    fh = np.zeros((jf.SCRATCH_ROWS, jf.MAX_STATE))
    ck._epoch(arrs.arm_n, arrs.arm_col, arrs.sensor, arrs.link, arrs.base, np.array(ck.WEIGHTS), -1.0, q,
              rng.uniform(-0.3, 0.3, nj), rng.normal(0, 5, (p, 6)), np.zeros(6), np.zeros(3), *outs,
              *ck._scratch(p, arrs.link.shape[1]), 1e-3, np.ones(p, np.int64), np.ones(nj, np.int64), fst, fP,
              jf.JointFilterSettings().constants(), fh)
    return fh


@pytest.mark.parametrize("name", ["paper_robot", "three_arm", "random"])
def test_contact_columns_are_pinocchios(name, tmp_path):
    """G[k]: the F/T wrench of a unit wrench on the end effector (force along body axis k, then
    moment about axis k - 3, about the end effector), from the kernel's chain pass; Pinocchio: RNEA
    at rest with that external force, the first joint's transmitted force in the sensor frame."""
    if name == "random":
        path = tmp_path / "r.urdf"
        path.write_text(urdf_text(random_spec(5)))
        robot = rd.load(str(path))
    else:
        robot = rd.load(name)
    model = EstimatorModel.from_robot(robot)
    rng = np.random.default_rng(2)
    for _ in range(3):
        q = rng.uniform(-1.5, 1.5, model.n_joints)
        fh = _kernel_scratch(model, q)
        arm = robot.arms[-1]                       # the scratch holds the last arm's pass
        m, d = robot.model, robot.model.createData()
        qf = pin.neutral(m)
        qf[7:] = q
        pin.framesForwardKinematics(m, d, qf)      # the base at the origin: world = body axes
        p_ee = d.oMf[arm.ee_frame].translation
        assert np.abs(fh[jf.R_EE, :3] - p_ee).max() < 1e-12
        ee_joint = m.frames[arm.ee_frame].parentJoint
        z = np.zeros(m.nv)
        for k in range(6):
            u = np.zeros(3)
            u[k % 3] = 1.0
            f, mo = (u, np.zeros(3)) if k < 3 else (np.zeros(3), u)
            world = pin.Force(f, mo + np.cross(p_ee, f))           # about the world origin
            fext = [pin.Force.Zero() for _ in range(m.njoints)]
            fext[ee_joint] = d.oMi[ee_joint].actInv(world)
            pin.rnea(m, d, qf, z, z, fext)
            j1 = arm.joints[0]
            want = d.oMf[arm.sensor_frame].actInv(d.oMi[j1].act(d.f[j1])).vector
            assert np.abs(fh[jf.R_G + k, :6] - want).max() < 1e-10, (k, fh[jf.R_G + k, :6], want)


def _session(name: str, contact: list[dict], duration: float = 3.0, contact_on: bool = True, **over):
    sc = scenario.load(name, {"duration_s": duration, **over.pop("scenario", {})})
    sc.data["contact"] = contact
    robot = rd.load(sc.robot)
    settings = CoreSettings(joints=jf.JointFilterSettings(contact=contact_on))
    trace, est, _ = demo.run_offline(sc, settings=settings, **over)
    return trace, est, robot, demo.contacts(trace, est, robot, contact)


def _nrmse(trace, est, lo: float, hi: float) -> np.ndarray:
    t, tau = trace.arrays["t_s"], trace.arrays["tau_act"]
    m = (t >= lo) & (t < hi)
    return np.sqrt(np.nanmean((est.full[m] - tau[m]) ** 2, axis=0)) / np.abs(tau).max(axis=0)


def test_a_contact_is_found_measured_and_released():
    """three_arm, 20 N on the centre arm's end effector (inertial axes) for 1.2 s: flagged within
    0.2 s, dropped within 0.3 s of its end, its wrench within 3 N / 4 N m RMS of the truth (the
    ramp in included), no contact on the other arms; the touched arm's torques during it within
    6 % (measured 0.02 / 1.2 / 4.6 %: the contact wrench also takes the base motion's error, from
    the thruster filter's wrench, and carries it to the distal joint), where the same session
    without the contact test is off by more than four times as much (the third joint 38 %)."""
    touch = [{"arm": "center", "onset_s": 1.2, "duration_s": 1.2, "force_n": [0.0, 20.0, 0.0]}]
    trace, est, robot, rep = _session("three_arm", touch)
    (c,) = rep["contacts"]
    assert c["flagged_after_s"] is not None and c["flagged_after_s"] < 0.2, c
    assert c["released_after_s"] is not None and c["released_after_s"] < 0.3, c
    assert c["force_rms_error_n"] < 3.0 and c["moment_rms_error_nm"] < 4.0, c
    assert all(v == 0.0 for v in rep["false_contact_s"].values()), rep
    with_test = _nrmse(trace, est, 1.4, 2.4)[:3]
    _, est_off, _, rep_off = _session("three_arm", touch, contact_on=False)
    without = _nrmse(trace, est_off, 1.4, 2.4)[:3]
    assert rep_off["contacts"][0]["flagged_after_s"] is None
    assert with_test.max() < 0.06, with_test
    assert without.max() > 4 * with_test.max(), (with_test, without)


def test_a_knock_on_a_fast_arm_stands_out_of_the_model_error_the_test_learned():
    """The contact demo's knock: 40 N on capture's arm1 at 6 s for 0.3 s, while the arm moves fast
    (a model wrench of 150-200 N). With the model's error learned from the motion before (about
    0.4 % for this exact model, so the floor of 1 %) it is flagged within 0.1 s (measured 45-49 ms);
    assumed at 3 % (what the test learns at least, raised to the prior) it is flagged only after
    0.15 s (measured 178 ms), and the second joint pays for it."""
    knock = [{"arm": "arm1", "onset_s": 6.0, "duration_s": 0.3, "force_n": [40.0, 0.0, 0.0], "ramp_s": 0.01}]
    learned = _session("capture", knock, duration=6.6, scenario={"seed": 7})[3]["contacts"][0]
    sc = scenario.load("capture", {"duration_s": 6.6, "seed": 7})
    sc.data["contact"] = knock
    assumed = CoreSettings(joints=jf.JointFilterSettings(contact_model_error_min=0.03))
    trace, est, _ = demo.run_offline(sc, settings=assumed)
    fixed = demo.contacts(trace, est, rd.load(sc.robot), knock)["contacts"][0]
    assert learned["flagged_after_s"] is not None and learned["flagged_after_s"] < 0.1, learned
    assert fixed["flagged_after_s"] is None or fixed["flagged_after_s"] > 0.15, fixed


def test_a_thruster_stuck_open_is_not_a_contact(tmp_path):
    """A thruster stuck open pushes the spacecraft with a wrench the model does not know, so every
    arm's model wrench is off at once (measured: the residual's significance in the thousands on
    both of capture's arms). While the thruster fault detector suspects a fault, and after it until
    the residual is back, no contact begins; without the detector (nothing to say the base motion
    is in doubt) the same session flags contacts."""
    from harness.fdi import FaultCase

    case = FaultCase(thruster=0, fault="stuck_open", onset_s=3.0, duration_s=3.6)
    path = tmp_path / "stuck.toml"
    path.write_text(case.toml())
    sc = scenario.load(str(path))
    _, est, _ = demo.run_offline(sc)
    assert np.isnan(est.contact).all()
    _, blind, _ = demo.run_offline(scenario.load(str(path)), settings=CoreSettings(fdi=None))
    assert not np.isnan(blind.contact).all()


@pytest.mark.parametrize("case", ["capture", "three_arm", "capture noise x4", "capture 5 % wrong model"])
def test_no_contact_where_there_is_none(case):
    """Healthy sessions: no arm is ever in contact, with the nominal sensors, four times their
    noise, or a model whose masses and inertias are 5 % off."""
    name = case.split()[0]
    over: dict = {}
    if "x4" in case:
        over["scenario"] = {"noise.scale": 4.0}
    if "wrong" in case:
        over["model_robot"] = rd.perturbed(rd.load(scenario.load(name).robot), 0.05, seed=1)
    _, est, _, rep = _session(name, [], duration=4.0, **over)
    assert np.isnan(est.contact).all(), rep


def test_settings_are_checked():
    with pytest.raises(jf.EstimatorSettingsError, match="contact must be true or false"):
        jf.JointFilterSettings(contact=1)
    with pytest.raises(jf.EstimatorSettingsError, match="contact_window_s must be a number > 0"):
        jf.JointFilterSettings(contact_window_s=0.0)
    assert dataclasses.replace(jf.JointFilterSettings(), contact=False).constants()[jf.C_CONTACT] == 0.0
    with pytest.raises(jf.EstimatorSettingsError, match="contact_model_error_min must be a number > 0"):
        jf.JointFilterSettings(contact_model_error_min=-0.01)
    assert jf.JointFilterSettings(contact_model_error_min=0.02).constants()[jf.C_CMODEL_MIN] == pytest.approx(4e-4)
