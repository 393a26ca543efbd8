"""What each thruster valve really delivers, learned live: the valve-aided thruster filter.

The thruster wrench is a sum of pulses: PWPFM switches valves every millisecond, and an IMU
cannot resolve 1 ms pulses through its noise (a navigation accelerometer of 20 ug/sqrt(Hz) on a
2400 kg spacecraft is ~10 N of apparent force per 2 ms sample). But the valve commands are on the
spacecraft bus at 1 kHz (``THRUSTER_VALVE_CMD``), and while a valve is open its thruster exerts
an almost constant wrench ``W_i`` (its thrust, direction and moment arm; slowly changing with
temperature and tank pressure, or abruptly when it degrades). So::

    thruster wrench(t) = sum_i valve_i(t) W_i                    (body frame, about C)

and the filter estimates the ``W_i`` (6 numbers per thruster) from every IMU sample, whose
accelerometer and gyro see the same pulses averaged over their interval, after the arms'
reaction (F/T sensors) is removed. The nominal layout (robot_description.thrusters) is the prior:
thrust along the nominal direction with ``gain_sigma`` uncertainty of its own plus
``common_gain_sigma`` shared by every thruster (one propellant feed: the tank pressure moves every
thrust together, so the thrusters that fire teach the gain of those that rarely do),
``lateral_sigma`` across it (misalignment), moment = position x force. A 6-vector of constant
"bias" states absorbs what the IMU and the F/T sensors see that no valve explains (sensor biases);
it is reported, never added to the thrust.

Measurement model, IMU sample k averaging the steps (epochs) of its interval I_k (n = steps per
IMU sample, dt = step):

    accel:  R_imu a_imu - mean_{s in I_k} known_a(s) = mean_{s in I_k} sum_i v_i(s) Ha W_i + Ha b
            known_a(s) = f_arm(s)/m + (I^-1 (tau_arm(s) - w x I w)) x r + w x (w x r)
            Ha = [I/m, -[r]x I^-1]
    gyro:   I (w_k - w_{k-1}) / (n dt) - sum_u c_u (tau_arm(u) - w x I w) = sum_u c_u sum_i v_i(u) W_i^tau + b^tau
            c_u: the exact weights of step u's angular acceleration in the difference of two
            interval averages (triangular, sum 1)

``f_arm, tau_arm`` is the arms' wrench on the spacecraft (``arm_reaction``). The noise of
consecutive gyro differences is correlated (MA(1)); the filter treats it as white (documented
simplification; modelled exactly, the moments come 2-10 times closer: benchmarks/bench_gyro_noise.py
and docs/estimator.md). Everything here is per-sample Python + numpy, called as the estimator would:
:meth:`ThrusterFilter.push_epoch` at 1 kHz, :meth:`ThrusterFilter.imu` at the IMU rate. The
product runs the compiled form, :mod:`.thruster_kernel`, which takes its prior from this class;
this one is its reference form in the tests.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from robot_description.thrusters import ThrusterLayout

from .model import EstimatorModel, EstimatorSettingsError, skew
from .model import solve as _solve


@dataclass(frozen=True)
class ThrusterFilterSettings:
    """Noise figures and priors. Defaults: the navigation-grade IMU class of the default scenario
    (docs/estimator.md) as it arrives on the wire (quantization of the CAN frames included)."""

    accel_sigma: float = 3.1e-3        # m/s^2 per IMU sample (20 ug/sqrt(Hz) at 500 Hz, + wire quantization)
    gyro_sigma: float = 2.9e-5         # rad/s per IMU sample (ARW + 2^-14 rad/s wire quantization)
    gain_sigma: float = 0.04           # prior: each thruster's own gain (thrust along its direction), fraction of max
    common_gain_sigma: float = 0.08    # prior: the gain all thrusters share (one propellant feed), fraction of max
    lateral_sigma: float = 0.02        # prior: thrust across it (misalignment ~1.15 deg), fraction of max
    moment_sigma_nm: float = 2.0       # prior: moment not explained by position x force
    walk_force: float = 0.003          # random walk of each thruster's force, fraction of max per sqrt(s)
    walk_moment_nm: float = 0.6        # random walk of each thruster's moment, N m per sqrt(s)
    bias_force_sigma_n: float = 5.0    # prior of the bias states (sensor biases seen as force / moment)
    bias_moment_sigma_nm: float = 10.0

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            zero_ok = name == "common_gain_sigma"                    # 0: every thruster's gain its own
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value)
                                               and (value >= 0 if zero_ok else value > 0)):
                raise EstimatorSettingsError(f"{name} must be a number {'>= 0' if zero_ok else '> 0'}, got {value!r}")


_Step = tuple[int, np.ndarray, np.ndarray]
"""One recorded step: ``(t_ns, arm wrench (6,), valves (n,))``."""


class ThrusterFilter:
    """Kalman filter on the per-valve wrenches ``W`` ``(n, 6)`` plus 6 bias states."""

    def __init__(self, model: EstimatorModel, layout: ThrusterLayout, *, dt: float = 1e-3, imu_steps: int = 2,
                 settings: ThrusterFilterSettings | None = None):
        s = settings or ThrusterFilterSettings()
        if imu_steps < 1:
            raise EstimatorSettingsError(f"imu_steps must be at least 1 (steps per IMU sample), got {imu_steps}")
        self.model, self.layout, self.settings = model, layout, s
        self.n = n = layout.n
        self.dt, self.imu_steps = dt, imu_steps
        self.ns = 6 * n + 6
        I = model.inertia_s
        self.I, self.I_inv, self.m = I, np.linalg.inv(I), model.mass_s
        self.r, self.R_imu = model.r_imu, model.R_imu
        self.Ha = np.hstack([np.eye(3) / self.m, -skew(self.r) @ self.I_inv])      # (3, 6)
        x = np.zeros(self.ns)
        P = np.zeros((self.ns, self.ns))
        walk = np.zeros(self.ns)
        for i in range(n):
            d, fmax = layout.dir[i], layout.max_n[i]
            G = np.vstack([np.eye(3), skew(layout.pos_m[i])])
            dd = np.outer(d, d)
            Sf = (s.gain_sigma * fmax) ** 2 * dd + (s.lateral_sigma * fmax) ** 2 * (np.eye(3) - dd)
            x[6 * i:6 * i + 6] = G @ (d * fmax)
            P[6 * i:6 * i + 6, 6 * i:6 * i + 6] = G @ Sf @ G.T + np.diag([0, 0, 0] + [s.moment_sigma_nm ** 2] * 3)
            walk[6 * i:6 * i + 3] = (s.walk_force * fmax) ** 2
            walk[6 * i + 3:6 * i + 6] = s.walk_moment_nm ** 2
        # the shared gain: every pair of thrusters correlated along their nominal wrenches (x's prior)
        P[:6 * n, :6 * n] += s.common_gain_sigma ** 2 * np.outer(x[:6 * n], x[:6 * n])
        P[6 * n:6 * n + 3, 6 * n:6 * n + 3] = np.eye(3) * s.bias_force_sigma_n ** 2
        P[6 * n + 3:, 6 * n + 3:] = np.eye(3) * s.bias_moment_sigma_nm ** 2
        self.x, self.P = x, P
        self.Q_per_s = walk
        T = imu_steps * dt
        self.r_acc = s.accel_sigma ** 2
        self.r_mom = (np.sqrt(2.0) * s.gyro_sigma / T * np.diag(I)) ** 2
        # gyro-difference weights c_u over the 2n-1 steps before the end of interval k (oldest first)
        nn = imu_steps
        c: list[float] = []
        for u in range(-2 * nn + 1, 0):            # u relative to the last step of I_k (0)
            now = sum(1 for s_ in range(-nn + 1, 1) if s_ > u)
            prev = sum(1 for s_ in range(-2 * nn + 1, -nn + 1) if s_ > u)
            c.append((now - prev) / nn ** 2)
        self.c = np.array(c)                        # length 2n - 1, sum 1
        self._hist: deque[_Step] = deque(maxlen=2 * nn + 2)
        self._prev_gyro: tuple[int, np.ndarray] | None = None
        self._last_update_ns: int | None = None
        self.updates = 0
        self.w = np.zeros(3)                        # latest gyro rate, body frame
        # Scratch for imu(): H is written in place (rows 0-2 accelerometer, 3-5 gyro difference;
        # H[:3] is itself a C-contiguous (3, ns) array, used when there is no gyro row), the
        # constant bias columns once. The valve columns are the products np.kron would form.
        ns = self.ns
        self._H = np.zeros((6, ns))
        self._H[:3, 6 * n:] = self.Ha
        self._H[3:, 6 * n + 3:] = np.eye(3)
        self._Ha_valves = self._H[:3, :6 * n].reshape(3, n, 6)
        self._Hw_valves = self._H[3:, :6 * n].reshape(3, n, 6)
        if not (np.shares_memory(self._Ha_valves, self._H) and np.shares_memory(self._Hw_valves, self._H)):
            raise RuntimeError("numpy copied instead of viewing the valve columns of H")
        self._Ha_b = self.Ha[:, None, :]
        self._E_b = np.hstack([np.zeros((3, 3)), np.eye(3)])[:, None, :]
        self._R3 = np.diag(np.full(3, self.r_acc))
        self._R6 = np.diag(np.concatenate([np.full(3, self.r_acc), self.r_mom]))
        self._y = np.empty(6)
        self._sym = np.empty((ns, ns))              # the other buffer of the symmetrised P
        self._rl = self.r.tolist()
        self._Iinv_T = self.I_inv.T
        self._step_ns = self.dt * 1e9
        self._W = self.W

    # -- the estimate ----------------------------------------------------------------------------
    @property
    def W(self) -> np.ndarray:
        """(n, 6) current estimate of each valve's wrench ``[force; moment about C]``."""
        return self.x[:6 * self.n].reshape(self.n, 6)

    @property
    def bias(self) -> np.ndarray:
        """The bias states ``[force (N); moment (N m)]`` as seen by the IMU and F/T sensors."""
        return self.x[6 * self.n:]

    def wrench(self, valves: np.ndarray) -> np.ndarray:
        """Thruster wrench ``[f; tau]`` for the open valves ``valves`` (n,) of one step."""
        W = self._W
        if W.base is not self.x:                    # x replaced from outside: a fresh view
            W = self._W = self.W
        wrench: np.ndarray = valves @ W
        return wrench

    def efficiency(self) -> np.ndarray:
        """Per thruster: estimated thrust along the nominal direction / nominal thrust."""
        eff: np.ndarray = np.einsum("ij,ij->i", self.W[:, :3], self.layout.dir) / self.layout.max_n
        return eff

    # -- inputs ----------------------------------------------------------------------------------
    def push_epoch(self, t_ns: int, arm_wrench: np.ndarray, valves: np.ndarray) -> None:
        """Record one step: the arms' wrench on the spacecraft and the valves open during it."""
        self._hist.append((t_ns, arm_wrench, valves))

    def _steps(self, t_end_ns: float, count: int) -> list[_Step] | None:
        """The last ``count`` recorded steps ending at ``t_end_ns`` (oldest first), or None if any is missing."""
        step = self.dt * 1e9
        half = 0.5 * step
        out: list[_Step] = []
        hist = self._hist
        for j in range(count - 1, -1, -1):
            t = t_end_ns - j * step
            for h in hist:                      # the first (oldest) step within half a step
                if abs(h[0] - t) < half:
                    out.append(h)
                    break
            else:
                return None
        return out

    def imu(self, t_ns: int, accel_imu: np.ndarray, rate_imu: np.ndarray) -> bool:
        """Apply one IMU sample (IMU frame) covering the ``imu_steps`` steps that end at ``t_ns``.

        Returns False (nothing applied) when a step of its interval is missing.

        Written for speed with the arithmetic of the plain numpy form kept operation for
        operation (same bits): matrix products stay numpy calls on operands of the same shape
        and layout; element-wise 3-vector work is done on Python floats (the same IEEE double
        operations in the same order); means of ``k`` rows are the sequential sum / ``k`` that
        ``ndarray.mean(0)`` computes.
        """
        w = self.R_imu @ np.asarray(rate_imu, dtype=float)
        a = self.R_imu @ np.asarray(accel_imu, dtype=float)
        prev, self._prev_gyro = self._prev_gyro, (t_ns, w)
        self.w = w
        nn = self.imu_steps
        cur = self._steps(t_ns, nn)
        if cur is None:
            return False
        I = self.I
        w0, w1, w2 = w.tolist()
        i0, i1, i2 = (I @ w).tolist()
        g0, g1, g2 = w1 * i2 - w2 * i1, w2 * i0 - w0 * i2, w0 * i1 - w1 * i0     # cross(w, I w)
        r0, r1, r2 = self._rl
        H, y = self._H, self._y
        # accelerometer: known = f_arm / m + (I^-1 (tau_arm - w x I w)) x r + w x (w x r)
        rows = [e[1].tolist() for e in cur]
        X = (np.array([[u[3] - g0, u[4] - g1, u[5] - g2] for u in rows]) @ self._Iinv_T).tolist()
        c0, c1, c2 = w1 * r2 - w2 * r1, w2 * r0 - w0 * r2, w0 * r1 - w1 * r0           # w x r
        d0, d1, d2 = w1 * c2 - w2 * c1, w2 * c0 - w0 * c2, w0 * c1 - w1 * c0           # w x (w x r)
        m = self.m
        s0 = s1 = s2 = None
        for u, (x0, x1, x2) in zip(rows, X):
            k0 = u[0] / m + (x1 * r2 - x2 * r1) + d0
            k1 = u[1] / m + (x2 * r0 - x0 * r2) + d1
            k2 = u[2] / m + (x0 * r1 - x1 * r0) + d2
            if s0 is None:
                s0, s1, s2 = k0, k1, k2
            else:
                s0, s1, s2 = s0 + k0, s1 + k1, s2 + k2
        if s0 is None or s1 is None or s2 is None:          # no step: cannot be, imu_steps >= 1 (__init__)
            raise EstimatorSettingsError(f"imu_steps must be at least 1, got {nn}")
        a0, a1, a2 = a.tolist()
        y[:3] = (a0 - s0 / nn, a1 - s1 / nn, a2 - s2 / nn)
        V = np.array([e[2] for e in cur])
        np.multiply((np.add.reduce(V, 0) / nn)[None, :, None], self._Ha_b, out=self._Ha_valves)
        nrows = 3
        # gyro difference: I (w_k - w_{k-1}) / (n dt) - sum_u c_u (tau_arm(u) - w x I w)
        step_ns = self._step_ns
        if prev is not None and abs((t_ns - prev[0]) - nn * step_ns) < 0.5 * step_ns:
            span = self._steps(t_ns - step_ns, 2 * nn - 1)
            if span is not None:
                p0, p1, p2 = prev[1].tolist()
                e0, e1, e2 = (I @ np.array([w0 - p0, w1 - p1, w2 - p2])).tolist()
                armu = np.array([[u[3] - g0, u[4] - g1, u[5] - g2] for u in (e[1].tolist() for e in span)])
                b0, b1, b2 = (self.c @ armu).tolist()
                T = nn * self.dt
                y[3:] = (e0 / T - b0, e1 / T - b1, e2 / T - b2)
                Vu = np.array([e[2] for e in span])
                np.multiply((self.c @ Vu)[None, :, None], self._E_b, out=self._Hw_valves)
                nrows = 6
        # random walk since the last update, then the update
        P = self.P
        if self._last_update_ns is not None:
            dt = max(0.0, (t_ns - self._last_update_ns) * 1e-9)
            if P.flags.c_contiguous:
                P.reshape(-1)[::self.ns + 1] += self.Q_per_s * dt      # the diagonal, in place
            else:
                P[np.diag_indices(self.ns)] += self.Q_per_s * dt
        self._last_update_ns = t_ns
        if nrows == 6:
            R = self._R6
        else:
            H, y, R = H[:3], y[:3].copy(), self._R3
        PHt = P @ H.T
        S = H @ PHt + R
        K = _solve(S, PHt.T).T
        self.x += K @ (y - H @ self.x)
        P -= K @ PHt.T
        # P = 0.5 * (P + P.T), into the other buffer (P and _sym take turns; nothing else holds P)
        sym = self._sym
        np.add(P, P.T, out=sym)
        np.multiply(0.5, sym, out=sym)
        self.P, self._sym = sym, P
        self.updates += 1
        return True
