"""Thruster wrench from the base F/T sensors and the spacecraft motion (docs/method.md section 1).

All functions broadcast over leading sample dimensions: pass ``ft`` of shape ``(p, 6)`` and
vectors ``(3,)`` for one sample, or ``(N, p, 6)`` and ``(N, 3)`` for a batch. No I/O, no state.
"""
from __future__ import annotations

import numpy as np

from .model import EstimatorModel, cross


def thruster_wrench(model: EstimatorModel, ft: np.ndarray, a_s: np.ndarray, w_s: np.ndarray,
                    dw_s: np.ndarray) -> np.ndarray:
    """The thruster wrench ``[f_s, tau_s]``: body frame, force through C (N), moment about C (N m).

    ``ft`` ``(..., p, 6)``: per arm ``[f_j, t_j]``, the wrench the spacecraft exerts on arm j,
    sensor frame, moment about S_j. ``a_s``: classical acceleration of C, body frame, m/s^2 (what
    an accelerometer at C reads). ``w_s``, ``dw_s``: body angular rate (rad/s) and its time
    derivative (rad/s^2), body frame.

        f_s   = sum_j R_j f_j                        + m_s a_s
        tau_s = sum_j (R_j t_j + r_j x R_j f_j)      + I_s dw_s + w_s x (I_s w_s)
    """
    ft = np.asarray(ft, dtype=float)
    lead = ft.shape[:-2]
    out: np.ndarray = ft.reshape(*lead, -1) @ model.A_s_all.T
    out[..., :3] += model.mass_s * np.asarray(a_s)
    out[..., 3:] += spacecraft_inertial_moment(model, w_s, dw_s)
    return out


def spacecraft_inertial_moment(model: EstimatorModel, w_s: np.ndarray, dw_s: np.ndarray) -> np.ndarray:
    """``I_s dw_s + w_s x (I_s w_s)``, N m about C, body frame (the spacecraft alone)."""
    w_s = np.asarray(w_s, dtype=float)
    moment: np.ndarray = np.asarray(dw_s) @ model.inertia_s.T + cross(w_s, w_s @ model.inertia_s.T)
    return moment


def arm_reaction(model: EstimatorModel, ft: np.ndarray) -> np.ndarray:
    """The wrench ALL arms exert on the spacecraft, ``[f, tau]`` about C, body frame (N, N m).

    It is ``-sum_j A_s(j) w_j``: the input the rotational/translational Kalman filters need
    (``filters.RotationalKF``, ``filters.TranslationalKF``).
    """
    ft = np.asarray(ft, dtype=float)
    reaction: np.ndarray = -(ft.reshape(*ft.shape[:-2], -1) @ model.A_s_all.T)
    return reaction


def imu_to_body(model: EstimatorModel, accel_imu: np.ndarray, rate_imu: np.ndarray,
                dw_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """IMU readings -> ``(a_s, w_s)`` for :func:`thruster_wrench`.

    ``accel_imu``: specific force at the IMU point, IMU frame, m/s^2. ``rate_imu``: angular rate,
    IMU frame, rad/s. ``dw_s``: angular acceleration, body frame, rad/s^2 (from a filter: the
    gyro gives rates only). Returns the classical acceleration of C and the angular rate, both in
    the body frame, removing the lever arm r = IMU - C:

        a_imu = a_C + dw x r + w x (w x r)
    """
    R, r = model.R_imu, model.r_imu
    w_s = np.asarray(rate_imu, dtype=float) @ R.T
    a_imu = np.asarray(accel_imu, dtype=float) @ R.T
    a_s = a_imu - cross(np.asarray(dw_s, dtype=float), r) - cross(w_s, cross(w_s, r))
    return a_s, w_s


def body_to_inertial(model: EstimatorModel, quat_wxyz: np.ndarray) -> np.ndarray:
    """Rotation body -> inertial from the IMU attitude (quaternion IMU -> inertial, scalar first).

    Returns ``(3, 3)`` or ``(N, 3, 3)``; apply to a body vector ``x`` as ``R @ x``.
    """
    q = np.asarray(quat_wxyz, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    R_ii = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)
    R_bi: np.ndarray = R_ii @ model.R_imu.T
    return R_bi
