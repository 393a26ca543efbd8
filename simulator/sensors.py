"""Sensor models: six-axis F/T per arm, spacecraft IMU, joint encoders.

Each model turns a true quantity into what the device reports: bias (constant per session,
plus scenario drifts), white noise, quantization at the device resolution, and saturation at
its range (clamped and flagged, never wrapped). Noise is drawn in blocks from the model's own
random stream, so a scenario and seed give bit-identical readings.

The models are evaluated over blocks of samples (arrays with a leading sample axis): the
simulator records the truth every step and runs the sensor models over many steps at once,
which costs a few numpy calls per block instead of per sample. Sample ``i`` of a device always
uses row ``i`` of its noise stream, however the samples are grouped into blocks.

Noise densities are converted to per-sample standard deviations at the output rate:
``sigma = density * sqrt(rate)`` (white noise, one-sided density).
"""
from __future__ import annotations

import math

import numpy as np

BLOCK = 1024
UG = 9.80665e-6          # one micro-g in m/s^2


class _Noise:
    """Standard normal draws of a fixed width; row ``i`` is the device's ``i``-th sample.

    Rows are generated a block of ``BLOCK`` at a time, in order, from the device's own stream,
    so the values do not depend on how the rows are asked for.
    """

    def __init__(self, rng: np.random.Generator, width: int):
        self.rng, self.width = rng, width
        self.blocks: list[np.ndarray] = []

    def _block(self, b: int) -> np.ndarray:
        while len(self.blocks) <= b:
            self.blocks.append(self.rng.standard_normal((BLOCK, self.width)))
        return self.blocks[b]

    def row(self, i: int) -> np.ndarray:
        b, j = divmod(i, BLOCK)
        return (self.blocks[b] if b < len(self.blocks) else self._block(b))[j]

    def rows(self, i0: int, i1: int) -> np.ndarray:
        """(i1 - i0, width) rows i0..i1-1."""
        b0, b1 = i0 // BLOCK, (i1 - 1) // BLOCK
        if b0 == b1:
            return self._block(b0)[i0 - b0 * BLOCK: i1 - b0 * BLOCK]
        parts = [self._block(b) for b in range(b0, b1 + 1)]
        return np.concatenate(parts)[i0 - b0 * BLOCK: i1 - b0 * BLOCK]


def quantize(x: np.ndarray, res: float | np.ndarray) -> np.ndarray:
    return (x / res).round() * res       # ndarray.round: the same rounding as np.round, 3x cheaper


def clamp(x: np.ndarray, lo, hi) -> np.ndarray:
    """np.clip(x, lo, hi) for lo <= hi, without its per-call overhead."""
    return np.minimum(np.maximum(x, lo), hi)


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for 3-vectors; np.cross costs ~10 us a call, this under 1 us."""
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return np.array((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0))


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a x b for (..., 3) arrays, component formulas as :func:`cross3`."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), axis=-1)


class ForceTorqueSensors:
    """The six-axis F/T sensors of all ``p`` arms, read together, one sample per step.

    A reading is ``(p, 6)`` rows [fx fy fz tx ty tz] (N, N m): moment about each sensor origin,
    each sensor's own frame. Each sensor has its own constant bias; an ft_bias_drift
    degradation adds a drift (the ``drift`` argument of :meth:`read_block`).
    """

    def __init__(self, cfg, scale: float, p: int, rng: np.random.Generator):
        self.res = np.array([cfg.force_resolution_n] * 3 + [cfg.torque_resolution_nm] * 3)
        self.sigma = scale * np.array([cfg.force_noise_n] * 3 + [cfg.torque_noise_nm] * 3)
        self.range = np.array([cfg.force_range_n] * 3 + [cfg.torque_range_nm] * 3)
        bias_sigma = scale * np.array([cfg.force_bias_n] * 3 + [cfg.torque_bias_nm] * 3)
        self.bias = bias_sigma * rng.standard_normal((p, 6))
        self.p = p
        self.noise = _Noise(rng, 6 * p)

    def read_block(self, wrench: np.ndarray, i0: int,
                   drift: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(readings (K, p, 6), saturated (K, p) bool) for the true wrenches (K, p, 6) of
        samples i0..i0+K-1; ``drift`` (K, p, 6) or None."""
        K = len(wrench)
        x = wrench + self.bias
        if drift is not None:
            x += drift
        x += self.sigma * self.noise.rows(i0, i0 + K).reshape(K, self.p, 6)
        sat = (np.abs(x) > self.range).any(axis=-1)
        return quantize(clamp(x, -self.range, self.range), self.res), sat


class Imu:
    """Navigation IMU on the spacecraft: specific force, angular rate (IMU frame), attitude.

    Like real strapdown units, the accelerometer and gyro outputs are averages over the output
    interval (velocity and angle increments divided by the interval), not point samples, so
    thruster pulses shorter than the interval are not aliased away.
    """

    def __init__(self, cfg, scale: float, rng: np.random.Generator, R_imu: np.ndarray, r_imu: np.ndarray):
        self.rate_hz = cfg.rate_hz
        self.R_imu, self.r_imu = R_imu, r_imu
        arw = math.radians(cfg.gyro_arw_deg_rt_h) / 60.0          # rad/s/sqrt(Hz)
        self.gyro_sigma = scale * arw * math.sqrt(cfg.rate_hz)
        self.acc_sigma = scale * cfg.accel_noise_ug_rt_hz * UG * math.sqrt(cfg.rate_hz)
        self.att_sigma = scale * math.radians(cfg.attitude_noise_deg)
        self.gyro_bias = scale * math.radians(cfg.gyro_bias_deg_h) / 3600.0 * rng.standard_normal(3)
        self.acc_bias = scale * cfg.accel_bias_ug * UG * rng.standard_normal(3)
        self.gyro_res, self.acc_res = cfg.gyro_resolution_rad_s, cfg.accel_resolution_m_s2
        self.gyro_range, self.acc_range = cfg.gyro_range_rad_s, cfg.accel_range_m_s2
        self.noise = _Noise(rng, 9)

    def specific_force_body(self, a_c: np.ndarray, w: np.ndarray, dw: np.ndarray) -> np.ndarray:
        """Specific force at the IMU point, body frame: a_C + dw x r + w x (w x r) (zero g).

        Rows (..., 3) of the classical acceleration of C, angular rate and angular acceleration."""
        r = self.r_imu
        r0, r1, r2 = r.tolist()
        w0, w1, w2 = w[..., 0], w[..., 1], w[..., 2]
        wr = (w0 * r0 + w1 * r1 + w2 * r2)[..., None]
        ww = (w0 * w0 + w1 * w1 + w2 * w2)[..., None]
        return a_c + cross_rows(dw, r) + w * wr - r * ww

    def read_block(self, a_c: np.ndarray, w: np.ndarray, dw: np.ndarray, R_world_body: np.ndarray, i0: int):
        """Samples i0..i0+M-1 from the truth over their averaging intervals.

        ``a_c, w, dw``: (M, e, 3) classical acceleration of C, angular rate and angular
        acceleration (body frame) at the e steps of each interval; ``R_world_body`` (M, 3, 3):
        attitude at the end of each interval. Returns (quat_wxyz, rate, accel, true_rate,
        true_accel, saturated) with a leading axis M.
        """
        M, e = a_c.shape[:2]
        f = self.specific_force_body(a_c, w, dw)
        acc_sum, gyro_sum = f[:, 0].copy(), w[:, 0].copy()
        for j in range(1, e):                     # in time order, as the increments accumulate
            acc_sum += f[:, j]
            gyro_sum += w[:, j]
        acc_true = (acc_sum / e) @ self.R_imu       # R_imu^T x, row-wise
        rate_true = (gyro_sum / e) @ self.R_imu
        n = self.noise.rows(i0, i0 + M)
        acc = acc_true + self.acc_bias + self.acc_sigma * n[:, :3]
        rate = rate_true + self.gyro_bias + self.gyro_sigma * n[:, 3:6]
        sat = (np.abs(acc) > self.acc_range).any(axis=1) | (np.abs(rate) > self.gyro_range).any(axis=1)
        acc = quantize(clamp(acc, -self.acc_range, self.acc_range), self.acc_res)
        rate = quantize(clamp(rate, -self.gyro_range, self.gyro_range), self.gyro_res)
        R = (R_world_body @ self.R_imu) @ _small_rotations(self.att_sigma * n[:, 6:9])
        return rotations_to_quat_wxyz(R), rate, acc, rate_true, acc_true, sat


class Encoders:
    """Absolute joint encoders (angle, quantized) with the drive's velocity estimate."""

    def __init__(self, cfg, scale: float, n: int, rng: np.random.Generator):
        self.res = 2.0 * math.pi / (1 << int(cfg.bits_per_rev))
        self.rate_sigma = scale * cfg.rate_noise_rad_s
        self.noise = _Noise(rng, n)
        self._rate_block, self._rate_rows = -1, []

    def read(self, q: np.ndarray, dq: np.ndarray, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Sample ``i``: (angles, rates) for the true joint angles and rates (n,)."""
        return quantize(q, self.res), dq + self.rate_sigma * self.noise.row(i)

    def measured_state(self, q: np.ndarray, v: np.ndarray, i: int, nq_base: int = 7,
                       nv_base: int = 6) -> tuple[np.ndarray, np.ndarray]:
        """``q`` and ``v`` with the joint entries (after the first ``nq_base`` / ``nv_base``)
        replaced by encoder sample ``i``: the same numbers as :meth:`read`, in Python floats
        (cheaper than numpy for a few joints; ``round`` rounds half to even like numpy, and
        ``or x * 0.0`` keeps numpy's sign of a zero)."""
        res = self.res
        ql, vl = q.tolist(), v.tolist()
        ql[nq_base:] = [round(x / res) * res or x * 0.0 for x in ql[nq_base:]]
        b, j = divmod(i, BLOCK)
        if b != self._rate_block:              # sigma * noise of a block of samples, as floats
            self._rate_rows = (self.rate_sigma * self.noise._block(b)).tolist()
            self._rate_block = b
        vl[nv_base:] = [d + e for d, e in zip(vl[nv_base:], self._rate_rows[j])]
        return np.array(ql), np.array(vl)

    def read_block(self, q: np.ndarray, dq: np.ndarray, i0: int) -> tuple[np.ndarray, np.ndarray]:
        """Samples i0..i0+K-1 for (K, n) true angles and rates; the same values as :meth:`read`."""
        return quantize(q, self.res), dq + self.rate_sigma * self.noise.rows(i0, i0 + len(q))


def _small_rotation(a: np.ndarray) -> np.ndarray:
    x, y, z = a
    return np.array([[1.0, -z, y], [z, 1.0, -x], [-y, x, 1.0]])


def _small_rotations(a: np.ndarray) -> np.ndarray:
    """(M, 3, 3) first-order rotations I + [a]x for rows a (M, 3)."""
    x, y, z = a[:, 0], a[:, 1], a[:, 2]
    R = np.empty((len(a), 3, 3))
    R[:, 0, 0] = R[:, 1, 1] = R[:, 2, 2] = 1.0
    R[:, 0, 1], R[:, 0, 2] = -z, y
    R[:, 1, 0], R[:, 1, 2] = z, -x
    R[:, 2, 0], R[:, 2, 1] = -y, x
    return R


def rotation_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (re-normalised)."""
    return rotations_to_quat_wxyz(R[None])[0]


def rotations_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """(M, 4) unit quaternions (w, x, y, z), w >= 0, of rotation matrices (M, 3, 3), re-normalised.

    Shepperd's method: from the trace when it is positive, else from the largest diagonal term.
    """
    q = np.empty((len(R), 4))
    t = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
    pos = t > 0
    if pos.any():
        Rp = R[pos]
        s = np.sqrt(t[pos] + 1.0) * 2
        q[pos] = np.stack([0.25 * s, (Rp[:, 2, 1] - Rp[:, 1, 2]) / s, (Rp[:, 0, 2] - Rp[:, 2, 0]) / s,
                           (Rp[:, 1, 0] - Rp[:, 0, 1]) / s], axis=1)
    if not pos.all():
        big = np.argmax(np.diagonal(R, axis1=1, axis2=2), axis=1)
        for i in range(3):
            sel = ~pos & (big == i)
            if not sel.any():
                continue
            j, k = (i + 1) % 3, (i + 2) % 3
            Rs = R[sel]
            s = np.sqrt(1.0 + Rs[:, i, i] - Rs[:, j, j] - Rs[:, k, k]) * 2
            qs = np.empty((len(Rs), 4))
            qs[:, 0] = (Rs[:, k, j] - Rs[:, j, k]) / s
            qs[:, 1 + i] = 0.25 * s
            qs[:, 1 + j] = (Rs[:, j, i] + Rs[:, i, j]) / s
            qs[:, 1 + k] = (Rs[:, k, i] + Rs[:, i, k]) / s
            q[sel] = qs
    q /= np.sqrt((q * q).sum(axis=1))[:, None]
    q[q[:, 0] < 0] *= -1.0
    return q
