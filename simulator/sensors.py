"""Sensor models: six-axis F/T per arm, spacecraft IMU, joint encoders.

Each model turns a true quantity into what the device reports: bias (constant per session,
plus scenario drifts), white noise, quantization at the device resolution, and saturation at
its range (clamped and flagged, never wrapped). Noise is drawn in blocks from the model's own
random stream, so a scenario and seed give bit-identical readings.

Noise densities are converted to per-sample standard deviations at the output rate:
``sigma = density * sqrt(rate)`` (white noise, one-sided density).
"""
from __future__ import annotations

import math

import numpy as np

BLOCK = 1024
UG = 9.80665e-6          # one micro-g in m/s^2


class _Noise:
    """Standard normal draws of a fixed width, generated a block at a time."""

    def __init__(self, rng: np.random.Generator, width: int):
        self.rng, self.width = rng, width
        self.buf = np.empty((0, width))
        self.i = 0

    def next(self) -> np.ndarray:
        if self.i >= len(self.buf):
            self.buf = self.rng.standard_normal((BLOCK, self.width))
            self.i = 0
        row = self.buf[self.i]
        self.i += 1
        return row


def quantize(x: np.ndarray, res: float | np.ndarray) -> np.ndarray:
    return np.round(x / res) * res


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for 3-vectors; np.cross costs ~10 us a call, this under 1 us."""
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return np.array((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0))


class ForceTorqueSensors:
    """The six-axis F/T sensors of all ``p`` arms, read together.

    A reading is ``(p, 6)`` rows [fx fy fz tx ty tz] (N, N m): moment about each sensor origin,
    each sensor's own frame. Each sensor has its own constant bias; ``drift`` (p, 6) is added by
    an ft_bias_drift degradation.
    """

    def __init__(self, cfg, scale: float, p: int, rng: np.random.Generator):
        self.res = np.array([cfg.force_resolution_n] * 3 + [cfg.torque_resolution_nm] * 3)
        self.sigma = scale * np.array([cfg.force_noise_n] * 3 + [cfg.torque_noise_nm] * 3)
        self.range = np.array([cfg.force_range_n] * 3 + [cfg.torque_range_nm] * 3)
        bias_sigma = scale * np.array([cfg.force_bias_n] * 3 + [cfg.torque_bias_nm] * 3)
        self.bias = bias_sigma * rng.standard_normal((p, 6))
        self.drift = np.zeros((p, 6))
        self.p = p
        self.noise = _Noise(rng, 6 * p)

    def read(self, wrench: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(readings (p, 6), saturated (p,) bool) for the true wrenches (p, 6)."""
        x = wrench + self.bias + self.drift + self.sigma * self.noise.next().reshape(self.p, 6)
        sat = (np.abs(x) > self.range).any(axis=1)
        return quantize(np.clip(x, -self.range, self.range), self.res), sat


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
        self._acc_sum = np.zeros(3)
        self._gyro_sum = np.zeros(3)
        self._n = 0

    def specific_force_body(self, a_c: np.ndarray, w: np.ndarray, dw: np.ndarray) -> np.ndarray:
        """Specific force at the IMU point, body frame: a_C + dw x r + w x (w x r) (zero g)."""
        r = self.r_imu
        return a_c + cross3(dw, r) + w * float(w @ r) - r * float(w @ w)

    def accumulate(self, a_c: np.ndarray, w: np.ndarray, dw: np.ndarray) -> None:
        self._acc_sum += self.specific_force_body(a_c, w, dw)
        self._gyro_sum += w
        self._n += 1

    def read(self, R_world_body: np.ndarray):
        """(quat_wxyz, rate, accel, true_rate, true_accel, saturated) over the interval since the last read."""
        n = max(self._n, 1)
        acc_true = self.R_imu.T @ (self._acc_sum / n)
        rate_true = self.R_imu.T @ (self._gyro_sum / n)
        self._acc_sum[:] = 0.0
        self._gyro_sum[:] = 0.0
        self._n = 0
        e = self.noise.next()
        acc = acc_true + self.acc_bias + self.acc_sigma * e[:3]
        rate = rate_true + self.gyro_bias + self.gyro_sigma * e[3:6]
        sat = bool(np.any(np.abs(acc) > self.acc_range) or np.any(np.abs(rate) > self.gyro_range))
        acc = quantize(np.clip(acc, -self.acc_range, self.acc_range), self.acc_res)
        rate = quantize(np.clip(rate, -self.gyro_range, self.gyro_range), self.gyro_res)
        R = R_world_body @ self.R_imu @ _small_rotation(self.att_sigma * e[6:9])
        return rotation_to_quat_wxyz(R), rate, acc, rate_true, acc_true, sat


class Encoders:
    """Absolute joint encoders (angle, quantized) with the drive's velocity estimate."""

    def __init__(self, cfg, scale: float, n: int, rng: np.random.Generator):
        self.res = 2.0 * math.pi / (1 << int(cfg.bits_per_rev))
        self.rate_sigma = scale * cfg.rate_noise_rad_s
        self.noise = _Noise(rng, n)

    def read(self, q: np.ndarray, dq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return quantize(q, self.res), dq + self.rate_sigma * self.noise.next()


def _small_rotation(a: np.ndarray) -> np.ndarray:
    x, y, z = a
    return np.array([[1.0, -z, y], [z, 1.0, -x], [-y, x, 1.0]])


def rotation_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (re-normalised)."""
    t = R[0, 0] + R[1, 1] + R[2, 2]
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = math.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k]) * 2
        q = np.empty(4)
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q
