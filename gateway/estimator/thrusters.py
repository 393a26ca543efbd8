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
thrust along the nominal direction with ``gain_sigma`` uncertainty, ``lateral_sigma`` across it
(misalignment), moment = position x force. A 6-vector of constant "bias" states absorbs what the
IMU and the F/T sensors see that no valve explains (sensor biases); it is reported, never added
to the thrust.

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
simplification). Everything here is per-sample Python + numpy; the live pipeline calls
:meth:`ThrusterFilter.push_epoch` at 1 kHz and :meth:`ThrusterFilter.imu` at the IMU rate.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from robot_description.thrusters import ThrusterLayout

from .model import EstimatorModel, cross, skew


@dataclass(frozen=True)
class ThrusterFilterSettings:
    """Noise figures and priors. Defaults: the navigation-grade IMU class of the default scenario
    (docs/estimator.md) as it arrives on the wire (quantization of the CAN frames included)."""

    accel_sigma: float = 3.1e-3        # m/s^2 per IMU sample (20 ug/sqrt(Hz) at 500 Hz, + wire quantization)
    gyro_sigma: float = 2.9e-5         # rad/s per IMU sample (ARW + 2^-14 rad/s wire quantization)
    gain_sigma: float = 0.08           # prior: thrust along the nominal direction, fraction of max thrust
    lateral_sigma: float = 0.02        # prior: thrust across it (misalignment ~1.15 deg), fraction of max
    moment_sigma_nm: float = 2.0       # prior: moment not explained by position x force
    walk_force: float = 0.003          # random walk of each thruster's force, fraction of max per sqrt(s)
    walk_moment_nm: float = 0.6        # random walk of each thruster's moment, N m per sqrt(s)
    bias_force_sigma_n: float = 5.0    # prior of the bias states (sensor biases seen as force / moment)
    bias_moment_sigma_nm: float = 10.0


class ThrusterFilter:
    """Kalman filter on the per-valve wrenches ``W`` ``(n, 6)`` plus 6 bias states."""

    def __init__(self, model: EstimatorModel, layout: ThrusterLayout, *, dt: float = 1e-3, imu_steps: int = 2,
                 settings: ThrusterFilterSettings | None = None):
        s = settings or ThrusterFilterSettings()
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
        P[6 * n:6 * n + 3, 6 * n:6 * n + 3] = np.eye(3) * s.bias_force_sigma_n ** 2
        P[6 * n + 3:, 6 * n + 3:] = np.eye(3) * s.bias_moment_sigma_nm ** 2
        self.x, self.P = x, P
        self.Q_per_s = walk
        T = imu_steps * dt
        self.r_acc = s.accel_sigma ** 2
        self.r_mom = (np.sqrt(2.0) * s.gyro_sigma / T * np.diag(I)) ** 2
        # gyro-difference weights c_u over the 2n-1 steps before the end of interval k (oldest first)
        nn = imu_steps
        c = []
        for u in range(-2 * nn + 1, 0):            # u relative to the last step of I_k (0)
            now = sum(1 for s_ in range(-nn + 1, 1) if s_ > u)
            prev = sum(1 for s_ in range(-2 * nn + 1, -nn + 1) if s_ > u)
            c.append((now - prev) / nn ** 2)
        self.c = np.array(c)                        # length 2n - 1, sum 1
        self._hist: deque = deque(maxlen=2 * nn + 2)   # (t_ns, arm wrench (6,), valves (n,))
        self._prev_gyro: tuple[int, np.ndarray] | None = None
        self._last_update_ns: int | None = None
        self.updates = 0
        self.w = np.zeros(3)                        # latest gyro rate, body frame

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
        return valves @ self.W

    def efficiency(self) -> np.ndarray:
        """Per thruster: estimated thrust along the nominal direction / nominal thrust."""
        return np.einsum("ij,ij->i", self.W[:, :3], self.layout.dir) / self.layout.max_n

    # -- inputs ----------------------------------------------------------------------------------
    def push_epoch(self, t_ns: int, arm_wrench: np.ndarray, valves: np.ndarray) -> None:
        """Record one step: the arms' wrench on the spacecraft and the valves open during it."""
        self._hist.append((t_ns, arm_wrench, valves))

    def _steps(self, t_end_ns: int, count: int) -> list | None:
        """The last ``count`` recorded steps ending at ``t_end_ns`` (oldest first), or None if any is missing."""
        step = self.dt * 1e9
        out = []
        hist = list(self._hist)
        for j in range(count - 1, -1, -1):
            t = t_end_ns - j * step
            e = next((h for h in hist if abs(h[0] - t) < 0.5 * step), None)
            if e is None:
                return None
            out.append(e)
        return out

    def imu(self, t_ns: int, accel_imu: np.ndarray, rate_imu: np.ndarray) -> bool:
        """Apply one IMU sample (IMU frame) covering the ``imu_steps`` steps that end at ``t_ns``.

        Returns False (nothing applied) when a step of its interval is missing.
        """
        w = self.R_imu @ np.asarray(rate_imu, dtype=float)
        a = self.R_imu @ np.asarray(accel_imu, dtype=float)
        prev, self._prev_gyro = self._prev_gyro, (t_ns, w)
        self.w = w
        nn = self.imu_steps
        cur = self._steps(t_ns, nn)
        if cur is None:
            return False
        n, ns = self.n, self.ns
        I, Iinv, r = self.I, self.I_inv, self.r
        gyro_term = cross(w, I @ w)
        ys, Hs, Rs = [], [], []
        # accelerometer
        arm = np.array([e[1] for e in cur])
        V = np.array([e[2] for e in cur])
        known = arm[:, :3] / self.m + cross((arm[:, 3:] - gyro_term) @ Iinv.T, r) + cross(w, cross(w, r))
        ys.append(a - known.mean(0))
        Ha = np.zeros((3, ns))
        vbar = V.mean(0)
        Ha[:, :6 * n] = np.kron(vbar[None, :], self.Ha)
        Ha[:, 6 * n:] = self.Ha
        Hs.append(Ha)
        Rs.append(np.full(3, self.r_acc))
        # gyro difference
        step_ns = self.dt * 1e9
        if prev is not None and abs((t_ns - prev[0]) - nn * step_ns) < 0.5 * step_ns:
            span = self._steps(t_ns - step_ns, 2 * nn - 1)
            if span is not None:
                armu = np.array([e[1] for e in span])
                Vu = np.array([e[2] for e in span])
                ys.append(I @ (w - prev[1]) / (nn * self.dt) - self.c @ (armu[:, 3:] - gyro_term))
                Hw = np.zeros((3, ns))
                vt = self.c @ Vu
                Hw[:, :6 * n] = np.kron(vt[None, :], np.hstack([np.zeros((3, 3)), np.eye(3)]))
                Hw[:, 6 * n + 3:] = np.eye(3)
                Hs.append(Hw)
                Rs.append(self.r_mom)
        # random walk since the last update, then the update
        if self._last_update_ns is not None:
            dt = max(0.0, (t_ns - self._last_update_ns) * 1e-9)
            self.P[np.diag_indices(ns)] += self.Q_per_s * dt
        self._last_update_ns = t_ns
        H = np.vstack(Hs)
        y = np.concatenate(ys)
        PHt = self.P @ H.T
        S = H @ PHt + np.diag(np.concatenate(Rs))
        K = np.linalg.solve(S, PHt.T).T
        self.x += K @ (y - H @ self.x)
        self.P -= K @ PHt.T
        self.P = 0.5 * (self.P + self.P.T)
        self.updates += 1
        return True
