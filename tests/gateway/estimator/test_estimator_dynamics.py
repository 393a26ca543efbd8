"""The estimator's reference functions (the test oracles of the compiled kernels) against
Pinocchio's inverse dynamics of the whole free-flying robot, and sign conventions done by hand."""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings, strategies as st

import robot_description
from gateway.estimator import (
    EstimatorModel, bias_torques, body_to_inertial, imu_to_body, joint_torque_matrix, joint_torques,
    joint_torques_simplified, thruster_wrench,
)

from estimator_truth import random_state

SEEDS = range(5)
REL = 1e-9
_THREE_ARM = EstimatorModel.from_robot(robot_description.load("three_arm"))


def _close(got, want, rel=REL):
    scale = max(1.0, float(np.abs(want).max()))
    np.testing.assert_allclose(got, want, rtol=0, atol=rel * scale)


@pytest.mark.parametrize("seed", SEEDS)
def test_thruster_wrench_equals_rnea_base_wrench(robot, emodel, seed):
    s = random_state(robot, np.random.default_rng(seed))
    _close(thruster_wrench(emodel, s.ft, s.a_s, s.w_s, s.dw_s), s.tau[:6])


@pytest.mark.parametrize("seed", SEEDS)
def test_full_joint_torques_equal_rnea(robot, emodel, seed):
    s = random_state(robot, np.random.default_rng(seed))
    data = emodel.data()
    _close(joint_torques(emodel, data, s.qj, s.dq, s.ddq, s.ft, s.a_s, s.w_s, s.dw_s), s.tau[6:])


@pytest.mark.parametrize("seed", SEEDS)
def test_simplified_exact_for_first_joint_only(robot, emodel, seed):
    s = random_state(robot, np.random.default_rng(seed))
    data = emodel.data()
    tau_hat = joint_torques_simplified(emodel, data, s.qj, s.ft)
    first = [arm.columns[0] for arm in emodel.arms]
    others = [c for c in range(emodel.n_joints) if c not in first]
    _close(tau_hat[first], s.tau[6:][first])
    err = np.abs(tau_hat[others] - s.tau[6:][others])
    assert np.all(err > 1e-3 * np.abs(s.tau[6:]).max())      # the proximal links' h is missing
    h = bias_torques(emodel, data, s.qj, s.dq, s.ddq, s.a_s, s.w_s, s.dw_s)
    _close(h[first], np.zeros(len(first)))
    _close(tau_hat - h, s.tau[6:])                             # tau = A_tau w - h


def test_simplified_first_joint_needs_no_model(robot):
    """A deliberately wrong model spoils joints 2..n of the full form, never joint 1."""
    truth = EstimatorModel.from_robot(robot)
    wrong = EstimatorModel.from_robot(robot_description.perturbed(robot, 0.05))
    s = random_state(robot, np.random.default_rng(42))
    first = [arm.columns[0] for arm in truth.arms]
    for em in (truth, wrong):
        _close(joint_torques_simplified(em, em.data(), s.qj, s.ft)[first], s.tau[6:][first])
    full = joint_torques(wrong, wrong.data(), s.qj, s.dq, s.ddq, s.ft, s.a_s, s.w_s, s.dw_s)
    _close(full[first], s.tau[6:][first])
    assert np.abs(full - s.tau[6:]).max() > 1e-3


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-3.1, 3.1), min_size=9, max_size=9))
def test_A_tau_rows_are_unit_joint_twists(angles):
    """Row i = [o_i x z_i, z_i] in the sensor frame: a unit axis, linear part normal to it."""
    em = _THREE_ARM
    A = joint_torque_matrix(em, em.data(), np.array(angles[: em.n_joints]))
    np.testing.assert_allclose(np.linalg.norm(A[:, 3:], axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("ik,ik->i", A[:, :3], A[:, 3:]), 0.0, atol=1e-12)
    for arm in em.arms:                                   # first joint: fixed to the sensor, q-independent
        at_zero = joint_torque_matrix(em, em.data(), np.zeros(em.n_joints))
        np.testing.assert_allclose(A[arm.columns[0]], at_zero[arm.columns[0]], atol=1e-12)


@pytest.mark.parametrize("seed", SEEDS)
def test_imu_lever_arm_against_pinocchio(robot, emodel, seed):
    """Specific force and rate at the IMU point (Pinocchio) -> a_s, w_s at C."""
    s = random_state(robot, np.random.default_rng(seed))
    m, d = robot.model, robot.model.createData()
    pin.forwardKinematics(m, d, s.q, s.v, s.a)
    pin.updateFramePlacements(m, d)
    acc_imu = pin.getFrameClassicalAcceleration(m, d, robot.imu_frame, pin.LOCAL).linear
    rate_imu = pin.getFrameVelocity(m, d, robot.imu_frame, pin.LOCAL).angular
    a_s, w_s = imu_to_body(emodel, acc_imu, rate_imu, s.dw_s)
    _close(w_s, s.w_s, 1e-12)
    _close(a_s, s.a_s, 1e-12)
    # batch broadcasting gives the same
    a_b, w_b = imu_to_body(emodel, np.tile(acc_imu, (4, 1)), np.tile(rate_imu, (4, 1)), np.tile(s.dw_s, (4, 1)))
    _close(a_b, np.tile(a_s, (4, 1)), 1e-12)


def test_body_to_inertial(robot, emodel):
    rng = np.random.default_rng(3)
    R_body = pin.rpy.rpyToMatrix(*rng.uniform(-3, 3, 3))        # body -> inertial
    R_imu_inertial = R_body @ robot.R_imu                        # IMU -> inertial
    qt = pin.Quaternion(R_imu_inertial)
    wxyz = np.array([qt.w, qt.x, qt.y, qt.z])
    np.testing.assert_allclose(body_to_inertial(emodel, wxyz), R_body, atol=1e-12)
    np.testing.assert_allclose(body_to_inertial(emodel, np.tile(-wxyz, (2, 1))), [R_body, R_body], atol=1e-12)


def test_sign_conventions_static_hand_case():
    """docs/method.md signs on a case done by hand.

    paper_robot at rest, q = 0: arm0 is straight along its sensor x axis (sensor at
    r = (1.4849, 1.4849, 0) m, turned +45 deg about z; joint 1 at x = 0.15 m, joint 2 at 4.15 m,
    tip at 7.15 m). A contact pushes the tip with F = 100 N along the sensor's +y, and the robot
    is held still (zero acceleration). By hand:

    - the sensor reads the spacecraft's wrench ON the arm, balancing the contact:
      f = (0, -100, 0) N, t = (0, 0, -715) N m (about S);
    - joint torques hold the arm: tau1 = -(7.15 - 0.15) F = -700 N m, tau2 = -(7.15 - 4.15) F = -300 N m;
    - thrusters hold the spacecraft: f_s = -F R y = (70.71, -70.71, 0) N and
      tau_s = -(tip - C) x (F R y) = (0, 0, -925.0) N m (tip at (6.5407, 6.5407, 0) m).
    """
    robot = robot_description.load("paper_robot")
    em = EstimatorModel.from_robot(robot)
    m, d = robot.model, robot.model.createData()
    F = 100.0
    arm = robot.arms[0]
    assert arm.name == "arm0"
    j2 = arm.joints[1]
    fext = [pin.Force.Zero() for _ in range(m.njoints)]
    fext[j2] = pin.Force(np.array([0.0, F, 0.0]), np.array([0.0, 0.0, 3.0 * F]))   # at the tip, joint-2 frame
    q = pin.neutral(m)
    z = np.zeros(m.nv)
    tau = pin.rnea(m, d, q, z, z, fext)
    pin.forwardKinematics(m, d, q)
    pin.updateFramePlacements(m, d)
    w0 = d.oMf[arm.sensor_frame].actInv(d.oMi[arm.joints[0]].act(d.f[arm.joints[0]])).vector
    hand_w0 = np.array([0.0, -F, 0.0, 0.0, 0.0, -7.15 * F])
    hand_tau = np.array([-700.0, -300.0])
    hand_thr = np.array([F * np.sqrt(0.5), -F * np.sqrt(0.5), 0.0, 0.0, 0.0, -925.0])
    np.testing.assert_allclose(w0, hand_w0, atol=1e-9)
    np.testing.assert_allclose(tau[6:8], hand_tau, atol=1e-9)
    np.testing.assert_allclose(tau[:6], hand_thr, atol=0.01)        # 1.48492424 in the URDF: 4 digits
    ft = np.array([hand_w0, np.zeros(6)])
    data = em.data()
    zero3 = np.zeros(3)
    zj = np.zeros(em.n_joints)
    np.testing.assert_allclose(joint_torques_simplified(em, data, zj, ft)[:2], hand_tau, atol=1e-9)
    np.testing.assert_allclose(joint_torques(em, data, zj, zj, zj, ft, zero3, zero3, zero3)[:2], hand_tau, atol=1e-9)
    np.testing.assert_allclose(thruster_wrench(em, ft, zero3, zero3, zero3), hand_thr, atol=0.01)


def test_thruster_wrench_inertial_terms_by_hand():
    """No arm load: f_s = m_s a_s and tau_s = I dw + w x I w (paper_robot: 2400 kg, diag(3446, 3446, 5808))."""
    em = EstimatorModel.from_robot(robot_description.load("paper_robot"))
    ft = np.zeros((2, 6))
    out = thruster_wrench(em, ft, np.array([0.01, 0.0, 0.0]), np.array([0.1, 0.0, 0.2]), np.array([0.0, 0.0, 0.001]))
    # w x I w = (0.1, 0, 0.2) x (344.6, 0, 1161.6) = (0, 0.2*344.6 - 0.1*1161.6, 0) = (0, -47.24, 0)
    np.testing.assert_allclose(out, [24.0, 0.0, 0.0, 0.0, -47.24, 5.808], atol=1e-9)
