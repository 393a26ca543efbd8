"""The joint filter and the fused torques written independently of the kernel, on numpy and
Pinocchio: the oracle of tests/gateway/estimator/test_joint_filter.py and of reference_live.py."""
from __future__ import annotations

import numpy as np

from gateway.estimator import joint_filter as jf
from gateway.estimator.torques import (_model_sensor_wrenches, _rnea, joint_torque_matrix, joint_torques,
                                       sensor_jacobians)

DT = 1e-3


def _J_w0(model, data, q, dq, a_s, w_s, dw_s):
    """Per arm J (6, n) and w0 (6,) from Pinocchio's rnea, as joint_accelerations_from_ft builds them."""
    _rnea(model, data, q, dq, np.zeros(model.n_joints), a_s, w_s, dw_s)
    w0 = _model_sensor_wrenches(model, data)
    return sensor_jacobians(model, data), w0


class DenseFilter:
    """The same model, written the textbook way: dense F, Q, H; one joint update per epoch with
    S^-1 (numpy); state [dq, ddq, b] per arm."""

    def __init__(self, n: int, s: jf.JointFilterSettings):
        self.n, self.s = n, s
        N = 2 * n + 6
        self.x, self.P = np.zeros(N), np.zeros((N, N))
        self.started = False

    def start(self, rate, ddq_ls):
        n, s = self.n, self.s
        self.x[:] = 0.0
        self.x[:n], self.x[n:2 * n] = rate, ddq_ls
        self.P = np.diag(np.r_[np.full(n, s.rate_sigma_rad_s ** 2), np.full(n, s.accel_prior ** 2),
                               np.full(3, s.bias_prior_n ** 2), np.full(3, s.bias_prior_nm ** 2)])
        self.started = True

    def step(self, J, y, ft_ok, rate, rate_ok):
        n, s = self.n, self.s
        N = 2 * n + 6
        F = np.eye(N)
        F[:n, n:2 * n] = DT * np.eye(n)
        Q = np.zeros((N, N))
        qj = s.jerk_psd
        Q[:n, :n] = qj * DT ** 3 / 3 * np.eye(n)
        Q[:n, n:2 * n] = Q[n:2 * n, :n] = qj * DT ** 2 / 2 * np.eye(n)
        Q[n:2 * n, n:2 * n] = qj * DT * np.eye(n)
        Q[2 * n:, 2 * n:] = np.diag(np.r_[np.full(3, s.bias_walk_n ** 2), np.full(3, s.bias_walk_nm ** 2)]) * DT
        self.x = F @ self.x
        self.P = F @ self.P @ F.T + Q
        rows, z, var = [], [], []
        if ft_ok:
            H = np.zeros((6, N))
            H[:, n:2 * n] = J
            H[:, 2 * n:] = np.eye(6)
            rows.append(H)
            z.append(y)
            var += [s.force_sigma_n ** 2] * 3 + [s.torque_sigma_nm ** 2] * 3
        for i in range(n):
            if rate_ok[i]:
                h = np.zeros((1, N))
                h[0, i] = 1.0
                rows.append(h)
                z.append([rate[i]])
                var.append(s.rate_sigma_rad_s ** 2)
        if not rows:
            return
        H, zz, R = np.vstack(rows), np.concatenate(z), np.diag(var)
        S = H @ self.P @ H.T + R
        K = np.linalg.solve(S, H @ self.P).T
        self.x = self.x + K @ (zz - H @ self.x)
        self.P = self.P - K @ H @ self.P


class SequentialFilter(DenseFilter):
    """The kernel's order (F/T rows, then rates, one scalar at a time) in numpy, in ``dtype``
    (np.longdouble: extended precision, what the kernel's bits should be near, rounding aside)."""

    def __init__(self, n: int, s: jf.JointFilterSettings, dtype=np.longdouble):
        super().__init__(n, s)
        self.dtype = dtype

    def start(self, rate, ddq_ls):
        super().start(rate, ddq_ls)
        self.x, self.P = self.x.astype(self.dtype), self.P.astype(self.dtype)

    def step(self, J, y, ft_ok, rate, rate_ok, dt=DT):
        n, s, L = self.n, self.s, self.dtype
        N = 2 * n + 6
        d, qj = L(dt), L(s.jerk_psd)
        self.x[:n] += d * self.x[n:2 * n]
        F = np.eye(N, dtype=L)
        F[:n, n:2 * n] = d * np.eye(n, dtype=L)
        Q = np.zeros((N, N), dtype=L)
        Q[:n, :n] = qj * d ** 3 / 3 * np.eye(n)
        Q[:n, n:2 * n] = Q[n:2 * n, :n] = qj * d ** 2 / 2 * np.eye(n)
        Q[n:2 * n, n:2 * n] = qj * d * np.eye(n)
        walk = np.r_[np.full(3, s.bias_walk_n ** 2), np.full(3, s.bias_walk_nm ** 2)]
        Q[2 * n:, 2 * n:] = np.diag(walk).astype(L) * d
        self.P = F @ self.P @ F.T + Q
        rows = []
        if ft_ok:
            for r in range(6):
                h = np.zeros(N, dtype=L)
                h[n:2 * n], h[2 * n + r] = J[r], 1
                rows.append((h, L(y[r]), L(s.force_sigma_n ** 2 if r < 3 else s.torque_sigma_nm ** 2)))
        for i in range(n):
            if rate_ok[i]:
                h = np.zeros(N, dtype=L)
                h[i] = 1
                rows.append((h, L(rate[i]), L(s.rate_sigma_rad_s ** 2)))
        for h, z, var in rows:
            ph = self.P @ h
            sv = h @ ph + var
            self.x = self.x + ph * ((z - h @ self.x) / sv)
            self.P = self.P - np.outer(ph, ph) / sv


def _fused(model, data, s, fP, q, dq, ddq, ft, a_s, w_s, dw_s, Js, bias):
    """The published torques from the filtered ddq, on Pinocchio: the distal side (the model's
    inverse dynamics of the links beyond each joint) and the sensor side (the measured wrench less
    the filter's bias ``bias`` (p, 6) down the chain, joint_torques), weighted by the variances
    joint_filter.fuse documents."""
    ft = ft - np.asarray(bias, dtype=float)
    tau_d = _rnea(model, data, q, dq, ddq, a_s, w_s, dw_s)[6:]
    tau_s = joint_torques(model, data, q, dq, ddq, ft, a_s, w_s, dw_s)
    A = joint_torque_matrix(model, data, q)
    nj = model.n_joints
    M = np.empty((nj, nj))                       # torques of unit joint accelerations, nothing else moving
    for k in range(nj):
        e = np.zeros(nj)
        e[k] = 1.0
        M[:, k] = _rnea(model, data, q, np.zeros(nj), e, np.zeros(3), np.zeros(3), np.zeros(3))[6:]
    eps2 = s.model_uncertainty ** 2
    sig2 = np.r_[np.full(3, s.force_sigma_n ** 2), np.full(3, s.torque_sigma_nm ** 2)]
    out = np.empty(nj)
    for a in model.arms:
        cols = list(a.columns)
        n = len(cols)
        Pdd = fP[a.index][n:2 * n, n:2 * n]
        Pbb = fP[a.index][2 * n:2 * n + 6, 2 * n:2 * n + 6]
        for i, col in enumerate(cols):
            D = M[col, cols]
            E = A[col] @ Js[a.index] - D
            h = A[col] @ ft[a.index] - tau_s[col]
            vd = eps2 * tau_d[col] ** 2 + D @ Pdd @ D
            vs = (A[col] ** 2) @ sig2 + A[col] @ Pbb @ A[col] + eps2 * h ** 2 + E @ Pdd @ E
            out[col] = tau_d[col] + vd / (vd + vs) * (tau_s[col] - tau_d[col])
    return out
