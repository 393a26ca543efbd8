"""The numpy thruster filter (``ThrusterFilter``: the compiled filter's prior and its reference
form in the tests) is written for speed; these hold it to the plain forms, same bits:
``ThrusterFilter.imu`` against the straightforward numpy form of its update (kept here), and the
LAPACK shortcut it calls (``model.solve``) against ``np.linalg.solve``."""
from __future__ import annotations

import numpy as np
import pytest

from gateway.estimator.model import cross, solve
from gateway.estimator.thrusters import ThrusterFilter
from robot_description.thrusters import ThrusterLayout


def _same(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.tobytes() == b.tobytes()


def test_solve_shortcut_equals_numpy():
    rng = np.random.default_rng(5)
    for _ in range(500):
        m = rng.integers(1, 8)
        S = rng.normal(size=(m, m))
        S = S @ S.T + np.eye(m)
        B = rng.normal(size=(m, int(rng.integers(1, 120))))
        assert _same(solve(S, B), np.linalg.solve(S, B))
        assert _same(solve(S, B.T.T[:, 0].copy()), np.linalg.solve(S, B[:, 0]))
        assert _same(solve(S, np.asfortranarray(B)), np.linalg.solve(S, np.asfortranarray(B)))
    with pytest.raises(np.linalg.LinAlgError, match="Singular"):
        solve(np.zeros((3, 3)), np.ones(3))


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
