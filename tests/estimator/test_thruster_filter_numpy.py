"""The live estimator's fast paths give the same bits as the plain forms they replace:
``LiveTorques`` against the three public per-sample functions, the LAPACK shortcuts against
``np.linalg``, and ``ThrusterFilter.imu`` against the straightforward numpy form of its update
(kept here as the reference)."""
from __future__ import annotations

import numpy as np
import pytest

from gateway.estimator.model import EstimatorModel, cross, lstsq1, solve
from gateway.estimator.thrusters import ThrusterFilter
from gateway.estimator.torques import (LiveTorques, joint_accelerations_from_ft, joint_torques,
                                       joint_torques_simplified)
from robot_description.thrusters import ThrusterLayout


def _same(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("stacked", [True, False])
def test_live_torques_equal_the_public_functions(emodel, stacked):
    rng = np.random.default_rng(3)
    fast = LiveTorques(emodel, emodel.data())
    assert fast._stacked                       # both test robots have arms of equal length
    fast._stacked = stacked                    # the per-arm path (arms of different lengths)
    ref = emodel.data()
    n, p = emodel.n_joints, emodel.n_arms
    for _ in range(200):
        q, dq = rng.uniform(-3, 3, n), rng.uniform(-1, 1, n)
        ft = rng.normal(0, 50, (p, 6))
        a_s, w_s, dw_s = rng.normal(0, 0.1, 3), rng.normal(0, 0.05, 3), rng.normal(0, 0.01, 3)
        simp, ddq, full = fast.epoch(q, dq, ft, list(a_s), w_s, dw_s)
        r_simp = joint_torques_simplified(emodel, ref, q, ft)
        r_ddq = joint_accelerations_from_ft(emodel, ref, q, dq, ft, a_s, w_s, dw_s)
        r_full = joint_torques(emodel, ref, q, dq, r_ddq, ft, a_s, w_s, dw_s)
        assert _same(simp, r_simp) and _same(ddq, r_ddq) and _same(full, r_full)


def test_lapack_shortcuts_equal_numpy():
    rng = np.random.default_rng(5)
    for _ in range(500):
        m = rng.integers(1, 8)
        S = rng.normal(size=(m, m))
        S = S @ S.T + np.eye(m)
        B = rng.normal(size=(m, int(rng.integers(1, 120))))
        assert _same(solve(S, B), np.linalg.solve(S, B))
        assert _same(solve(S, B.T.T[:, 0].copy()), np.linalg.solve(S, B[:, 0]))
        assert _same(solve(S, np.asfortranarray(B)), np.linalg.solve(S, np.asfortranarray(B)))
        A = rng.normal(size=(6, int(rng.integers(1, 6)))) * 10.0 ** rng.integers(-3, 4)
        b = rng.normal(size=6)
        assert _same(lstsq1(A, b), np.linalg.lstsq(A, b, rcond=None)[0])
    with pytest.raises(np.linalg.LinAlgError, match="Singular"):
        solve(np.zeros((3, 3)), np.ones(3))
    with pytest.raises(np.linalg.LinAlgError):
        lstsq1(np.full((6, 2), np.nan), np.ones(6))


def _reference_imu(kf: ThrusterFilter, t_ns: int, accel_imu, rate_imu) -> bool:
    """``ThrusterFilter.imu`` as first written: plain numpy, new arrays everywhere."""
    w = kf.R_imu @ np.asarray(rate_imu, dtype=float)
    a = kf.R_imu @ np.asarray(accel_imu, dtype=float)
    prev, kf._prev_gyro = kf._prev_gyro, (t_ns, w)
    kf.w = w
    nn = kf.imu_steps

    def steps(t_end_ns, count):
        step = kf.dt * 1e9
        out, hist = [], list(kf._hist)
        for j in range(count - 1, -1, -1):
            t = t_end_ns - j * step
            e = next((h for h in hist if abs(h[0] - t) < 0.5 * step), None)
            if e is None:
                return None
            out.append(e)
        return out

    cur = steps(t_ns, nn)
    if cur is None:
        return False
    n, ns = kf.n, kf.ns
    I, Iinv, r = kf.I, kf.I_inv, kf.r
    gyro_term = cross(w, I @ w)
    ys, Hs, Rs = [], [], []
    arm = np.array([e[1] for e in cur])
    V = np.array([e[2] for e in cur])
    known = arm[:, :3] / kf.m + cross((arm[:, 3:] - gyro_term) @ Iinv.T, r) + cross(w, cross(w, r))
    ys.append(a - known.mean(0))
    Ha = np.zeros((3, ns))
    vbar = V.mean(0)
    Ha[:, :6 * n] = np.kron(vbar[None, :], kf.Ha)
    Ha[:, 6 * n:] = kf.Ha
    Hs.append(Ha)
    Rs.append(np.full(3, kf.r_acc))
    step_ns = kf.dt * 1e9
    if prev is not None and abs((t_ns - prev[0]) - nn * step_ns) < 0.5 * step_ns:
        span = steps(t_ns - step_ns, 2 * nn - 1)
        if span is not None:
            armu = np.array([e[1] for e in span])
            Vu = np.array([e[2] for e in span])
            ys.append(I @ (w - prev[1]) / (nn * kf.dt) - kf.c @ (armu[:, 3:] - gyro_term))
            Hw = np.zeros((3, ns))
            vt = kf.c @ Vu
            Hw[:, :6 * n] = np.kron(vt[None, :], np.hstack([np.zeros((3, 3)), np.eye(3)]))
            Hw[:, 6 * n + 3:] = np.eye(3)
            Hs.append(Hw)
            Rs.append(kf.r_mom)
    if kf._last_update_ns is not None:
        dt = max(0.0, (t_ns - kf._last_update_ns) * 1e-9)
        kf.P[np.diag_indices(ns)] += kf.Q_per_s * dt
    kf._last_update_ns = t_ns
    H = np.vstack(Hs)
    y = np.concatenate(ys)
    PHt = kf.P @ H.T
    S = H @ PHt + np.diag(np.concatenate(Rs))
    K = np.linalg.solve(S, PHt.T).T
    kf.x += K @ (y - H @ kf.x)
    kf.P -= K @ PHt.T
    kf.P = 0.5 * (kf.P + kf.P.T)
    kf.updates += 1
    return True


@pytest.mark.parametrize("imu_steps", [2, 3, 1])
def test_thruster_filter_update_equals_the_plain_numpy_form(emodel, imu_steps):
    layout = ThrusterLayout.named()
    fast, ref = (ThrusterFilter(emodel, layout, dt=1e-3, imu_steps=imu_steps) for _ in range(2))
    rng = np.random.default_rng(imu_steps)
    applied = 0
    for k in range(1, 600):
        t = 1_000_000_000 + k * 1_000_000
        if rng.random() < 0.02:
            continue                                  # a missing epoch: its IMU sample is not applied
        arm = rng.normal(0, 20, 6)
        valves = (rng.random(layout.n) < 0.3).astype(float)
        fast.push_epoch(t, arm, valves)
        ref.push_epoch(t, arm, valves)
        assert _same(fast.wrench(valves), valves @ ref.W)
        if k % imu_steps == 0 and rng.random() > 0.03:  # IMU samples, a few lost
            acc, rate = rng.normal(0, 0.05, 3), rng.normal(0, 0.01, 3)
            assert fast.imu(t, acc, rate) == _reference_imu(ref, t, acc, rate)
            applied += fast.updates == ref.updates
            assert _same(fast.x, ref.x) and _same(fast.P, ref.P) and _same(fast.w, ref.w)
    assert applied > 100
