"""Vectorised forms over N samples, for offline replay and analysis.

Same inputs as :mod:`.torques` with a leading sample axis: ``q``, ``dq``, ``ddq`` ``(N, n_joints)``,
``ft`` ``(N, p, 6)``, ``a_s``, ``w_s``, ``dw_s`` ``(N, 3)``; torques out ``(N, n_joints)``.

Pinocchio is not called per sample: a recursive Newton-Euler pass runs over each serial chain,
vectorised over samples. Quantities are laid out ``(6, n)`` (components first, samples
contiguous) in each joint's internal frame (joint axis = +z, see :mod:`.model`), so the constant
parts of each transform are one small matrix product and the joint rotation touches two rows.
Samples go in chunks that stay in cache.
"""
from __future__ import annotations

import numpy as np

from .model import EstimatorModel
from .wrench import thruster_wrench

DEFAULT_CHUNK = 4096


def _rotz_T(x: np.ndarray, c: np.ndarray, s: np.ndarray) -> None:
    """In place: both 3-blocks of ``x`` (6, n) -> Rz(q)^T x (into the rotated joint frame)."""
    x0 = x[0::3].copy()                  # rows 0 and 3
    x1 = x[1::3]                         # rows 1 and 4 (view)
    x[0::3] = c * x0 + s * x1
    x[1::3] = c * x1 - s * x0


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (3, n) arrays."""
    return np.stack((a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]))


def _check(model: EstimatorModel, q: np.ndarray, ft: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    q = np.asarray(q, dtype=float)
    ft = np.asarray(ft, dtype=float)
    if q.ndim != 2 or q.shape[1] != model.n_joints:
        raise ValueError(f"q must be (N, {model.n_joints}), got {q.shape}")
    if ft.shape != (q.shape[0], model.n_arms, 6):
        raise ValueError(f"ft must be ({q.shape[0]}, {model.n_arms}, 6), got {ft.shape}")
    return q, ft


def joint_torques_simplified_batch(model: EstimatorModel, q: np.ndarray, ft: np.ndarray,
                                   chunk: int = DEFAULT_CHUNK) -> np.ndarray:
    """``tau_hat = A_tau(q) w`` for N samples, ``(N, n_joints)`` N m."""
    q, ft = _check(model, q, ft)
    N = q.shape[0]
    out = np.empty((N, model.n_joints))
    for lo in range(0, N, chunk):
        hi = min(lo + chunk, N)
        qT = q[lo:hi].T
        c_all, s_all = np.cos(qT), np.sin(qT)
        for arm in model.arms:
            G = arm.A_s @ ft[lo:hi, arm.index].T       # wrench on the arm about C, body frame
            for link, col in zip(arm.chain, arm.columns):
                G = link.X_force @ G
                _rotz_T(G, c_all[col], s_all[col])
                out[lo:hi, col] = G[5]
    return out


def joint_torques_batch(model: EstimatorModel, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray,
                        ft: np.ndarray, a_s: np.ndarray, w_s: np.ndarray, dw_s: np.ndarray,
                        chunk: int = DEFAULT_CHUNK, return_bias: bool = False):
    """The full estimate ``tau = A_tau w - h`` for N samples, ``(N, n_joints)`` N m.

    With ``return_bias`` also returns ``h`` (same shape). The recursion, per arm, starts from the
    body frame at C with the base twist ``(0, w_s)`` (forces do not depend on the base's linear
    velocity in zero gravity) and spatial acceleration ``(a_s, dw_s)``, and from the sensor
    wrench moved to C. At joint i: the transmitted wrench's axis component is tau_i; then the
    inertial wrench of link i (``I a + v x* I v``) is taken off before moving to joint i+1.
    """
    q, ft = _check(model, q, ft)
    dq, ddq = np.asarray(dq, dtype=float), np.asarray(ddq, dtype=float)
    a_s, w_s, dw_s = (np.asarray(x, dtype=float) for x in (a_s, w_s, dw_s))
    N = q.shape[0]
    for name, x, n in (("dq", dq, model.n_joints), ("ddq", ddq, model.n_joints),
                       ("a_s", a_s, 3), ("w_s", w_s, 3), ("dw_s", dw_s, 3)):
        if x.shape != (N, n):
            raise ValueError(f"{name} must be ({N}, {n}), got {x.shape}")
    out = np.empty((N, model.n_joints))
    bias = np.empty((N, model.n_joints)) if return_bias else None
    for lo in range(0, N, chunk):
        hi = min(lo + chunk, N)
        n = hi - lo
        qT = q[lo:hi].T
        c_all, s_all = np.cos(qT), np.sin(qT)
        dqT, ddqT = dq[lo:hi].T, ddq[lo:hi].T
        V0 = np.zeros((6, n))
        V0[3:] = w_s[lo:hi].T
        A0 = np.concatenate((a_s[lo:hi].T, dw_s[lo:hi].T))
        for arm in model.arms:
            V, A = V0, A0
            G = arm.A_s @ ft[lo:hi, arm.index].T
            if return_bias:
                H = np.zeros((6, n))               # accumulated inertial wrench of proximal links
            for link, col in zip(arm.chain, arm.columns):
                c, s, qd, qdd = c_all[col], s_all[col], dqT[col], ddqT[col]
                V = link.X_motion @ V
                A = link.X_motion @ A
                G = link.X_force @ G
                _rotz_T(V, c, s)
                _rotz_T(A, c, s)
                _rotz_T(G, c, s)
                V[5] += qd
                # a_i = X a_p + S ddq + v_i x S dq, S = (0, e_z)
                A[0] += V[1] * qd
                A[1] -= V[0] * qd
                A[3] += V[4] * qd
                A[4] -= V[3] * qd
                A[5] += qdd
                out[lo:hi, col] = G[5]
                if return_bias:
                    H = link.X_force @ H
                    _rotz_T(H, c, s)
                    bias[lo:hi, col] = H[5]
                # inertial wrench of link i about its joint origin: I a + v x* (I v)
                Iv = link.inertia @ V
                F = link.inertia @ A
                v, w = V[:3], V[3:]
                F[:3] += _cross(w, Iv[:3])
                F[3:] += _cross(w, Iv[3:]) + _cross(v, Iv[:3])
                G = G - F
                if return_bias:
                    H = H + F
    return (out, bias) if return_bias else out


def thruster_wrench_batch(model: EstimatorModel, ft: np.ndarray, a_s: np.ndarray, w_s: np.ndarray,
                          dw_s: np.ndarray) -> np.ndarray:
    """:func:`.wrench.thruster_wrench` over N samples, ``(N, 6)`` (the same broadcasting code)."""
    return thruster_wrench(model, ft, a_s, w_s, dw_s)
