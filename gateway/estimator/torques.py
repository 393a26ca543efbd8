"""Joint torques from the base F/T sensors (docs/method.md section 2), one sample at a time.

The reference forms, computed with Pinocchio into an :class:`EstimatorData` (scratch, one per
thread): the test oracle of the compiled :mod:`.chain_kernel`, which the product runs. The tests
hold these against Pinocchio's inverse dynamics of the whole free-flying robot, and the kernel
against these.

Inputs, for every function here (one sample):

- ``q``, ``dq``, ``ddq``: arm joint angles (rad), rates (rad/s), accelerations (rad/s^2), shape
  ``(n_joints,)`` in ``Robot.joint_names`` order;
- ``ft``: ``(p, 6)``, per arm ``[f_j, t_j]``: the wrench the spacecraft exerts on arm j, sensor
  frame, moment about S_j (N, N m);
- ``a_s``, ``w_s``, ``dw_s``: classical acceleration of C (m/s^2), angular rate (rad/s) and
  angular acceleration (rad/s^2) of the spacecraft, body frame (see :func:`.wrench.imu_to_body`).

Output torques are the net torque the actuator delivers to the chain (motor minus friction),
N m, about the joint axis, same order as ``q``.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from .model import EstimatorData, EstimatorModel


def joint_torque_matrix(model: EstimatorModel, data: EstimatorData, q: np.ndarray) -> np.ndarray:
    """A_tau(q): ``(n_joints, 6)``; row i applies to the wrench of the arm owning joint i.

    Row i is ``[z_i^T S(S - o_i), z_i^T]`` with the axis ``z_i`` and origin ``o_i`` of joint i in
    the sensor frame of its arm (so ``S = 0``): ``[(o_i x z_i)^T, z_i^T]``, the joint's unit
    twist seen from the sensor. Also left in ``data.A_tau``.
    """
    pm, pd = model.robot.model, data.pin_data
    data.q[7:] = q
    pin.forwardKinematics(pm, pd, data.q)
    _fill_A_tau(model, data)
    return data.A_tau.copy()


def _fill_A_tau(model: EstimatorModel, data: EstimatorData) -> None:
    pd = data.pin_data
    for arm in model.arms:
        for col, jid, twist in zip(arm.columns, arm.joints, arm.unit_twists):
            # joint frame -> sensor frame (base at identity): the unit twist seen from the sensor
            data.A_tau[col] = (arm.sensor_inv * pd.oMi[jid]).act(twist).vector


def _apply(model: EstimatorModel, A_tau: np.ndarray, ft: np.ndarray) -> np.ndarray:
    tau: np.ndarray = (A_tau * np.asarray(ft, dtype=float)[model.joint_arm]).sum(axis=1)
    return tau


def joint_torques_simplified(model: EstimatorModel, data: EstimatorData, q: np.ndarray,
                             ft: np.ndarray) -> np.ndarray:
    """The paper's simplified estimate ``tau_hat = A_tau(q) w``: no model, no joint rates.

    Exact for the first joint of each arm (nothing between it and the sensor), whatever the
    motion; the links between the sensor and joint i add an error for i > 1 when they accelerate.
    """
    return _apply(model, joint_torque_matrix(model, data, q), ft)


def _rnea(model: EstimatorModel, data: EstimatorData, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray,
          a_s: np.ndarray, w_s: np.ndarray, dw_s: np.ndarray) -> np.ndarray:
    # Forces do not depend on the base's linear velocity (zero gravity, Galilean invariance) nor on
    # its pose: put the base at the origin, at rest in translation. Then Pinocchio's spatial base
    # acceleration equals the classical a_s.
    pm, pd = model.robot.model, data.pin_data
    data.q[7:] = q
    data.v[3:6] = w_s
    data.v[6:] = dq
    data.a[:3] = a_s
    data.a[3:6] = dw_s
    data.a[6:] = ddq
    tau: np.ndarray = pin.rnea(pm, pd, data.q, data.v, data.a)
    pin.forwardKinematics(pm, pd, data.q)          # oMi for A_tau; does not touch data.f
    _fill_A_tau(model, data)
    return tau


def _model_sensor_wrenches(model: EstimatorModel, data: EstimatorData) -> np.ndarray:
    pd = data.pin_data
    w = np.empty((model.n_arms, 6))
    for arm in model.arms:
        j1 = arm.joints[0]
        w[arm.index] = arm.sensor_inv.act(pd.oMi[j1].act(pd.f[j1])).vector
    return w


def bias_torques(model: EstimatorModel, data: EstimatorData, q: np.ndarray, dq: np.ndarray,
                 ddq: np.ndarray, a_s: np.ndarray, w_s: np.ndarray, dw_s: np.ndarray) -> np.ndarray:
    """h: the part of ``A_tau w`` spent on the links between the sensor and each joint, N m.

    ``h_i = z_i . sum_{k<i} (N_k + (c_k - o_i) x F_k)`` from the model's masses and inertias,
    the base motion and the joint motion; zero for the first joint of each arm. Computed as
    ``A_tau w_model - tau_model`` from Pinocchio's inverse dynamics of the whole robot, where
    ``w_model`` is the sensor wrench the model predicts: the distal links cancel.
    """
    tau_m = _rnea(model, data, q, dq, ddq, a_s, w_s, dw_s)
    h: np.ndarray = _apply(model, data.A_tau, _model_sensor_wrenches(model, data)) - tau_m[6:]
    return h


def joint_torques(model: EstimatorModel, data: EstimatorData, q: np.ndarray, dq: np.ndarray,
                  ddq: np.ndarray, ft: np.ndarray, a_s: np.ndarray, w_s: np.ndarray,
                  dw_s: np.ndarray) -> np.ndarray:
    """The full estimate ``tau = A_tau(q) w - h(q, dq, ddq, a_s, w_s, dw_s)`` (paper eq. 11), N m.

    Equivalently ``tau_model + A_tau (w - w_model)``: the model's inverse dynamics corrected by
    what the sensors see that the model did not predict (friction, payload, unmodelled contact
    beyond the joint). Only the proximal links' model enters the result.
    """
    tau_m = _rnea(model, data, q, dq, ddq, a_s, w_s, dw_s)
    w_model = _model_sensor_wrenches(model, data)
    tau: np.ndarray = tau_m[6:] + _apply(model, data.A_tau, np.asarray(ft, dtype=float) - w_model)
    return tau


def joint_accelerations_from_ft(model: EstimatorModel, data: EstimatorData, q: np.ndarray, dq: np.ndarray,
                                ft: np.ndarray, a_s: np.ndarray, w_s: np.ndarray, dw_s: np.ndarray,
                                weights: np.ndarray | None = None) -> np.ndarray:
    """Joint accelerations (rad/s^2) that make the model's sensor wrenches match the measured ones.

    In zero gravity an arm's sensor wrench is the rate of change of the arm's momentum: affine in
    its joint accelerations given ``q``, ``dq`` and the base motion, ``w = w0 + J ddq``. Each arm's
    ``ddq`` is the weighted least-squares solution (``weights`` (6,): 1/sigma of the F/T channels;
    default force 1/0.25 N, moment 1/0.025 N m). Needs as many independent wrench components as
    the arm has joints (planar two-link arm: fx, fy, tz for two joints). This is the high-bandwidth
    acceleration the full estimate needs: no numerical differentiation, no lag.
    """
    _rnea(model, data, q, dq, np.zeros(model.n_joints), a_s, w_s, dw_s)
    w0 = _model_sensor_wrenches(model, data)
    wt = np.array([4.0, 4.0, 4.0, 40.0, 40.0, 40.0]) if weights is None else np.asarray(weights, dtype=float)
    ddq = np.zeros(model.n_joints)
    for arm, J in zip(model.arms, sensor_jacobians(model, data)):
        rhs = (np.asarray(ft[arm.index], dtype=float) - w0[arm.index]) * wt
        ddq[list(arm.columns)] = np.linalg.lstsq(J * wt[:, None], rhs, rcond=None)[0]
    return ddq


def sensor_jacobians(model: EstimatorModel, data: EstimatorData) -> list[np.ndarray]:
    """Per arm ``J`` (6, n): the sensor wrench (sensor frame) per unit acceleration of each of its
    joints, nothing else moving, at the configuration in ``data.q`` (one Pinocchio RNEA per joint)."""
    pm, pd = model.robot.model, data.pin_data
    v0 = np.zeros(pm.nv)
    out = []
    for arm in model.arms:
        J = np.empty((6, len(arm.columns)))
        j1 = arm.joints[0]
        for k, col in enumerate(arm.columns):
            a = np.zeros(pm.nv)
            a[6 + col] = 1.0
            pin.rnea(pm, pd, data.q, v0, a)
            J[:, k] = arm.sensor_inv.act(pd.oMi[j1].act(pd.f[j1])).vector
        out.append(J)
    return out
