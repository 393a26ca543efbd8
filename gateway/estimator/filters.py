"""Spacecraft angular acceleration and thruster wrench from a rate gyro: filters and their trade-off.

The gyro gives rates; docs/method.md needs ``dw_s``. Differencing a navigation-class gyro at 1 kHz
amplifies its white rate noise by ``sqrt(2) * rate_hz``: hundreds of mrad/s^2, thousands of N m of
apparent thruster moment on a 5808 kg m^2 spacecraft. Three remedies, from plainest to best:

- :class:`LowPassDifferentiator` (live, causal): ``H(s) = wc^2 s / (s^2 + 2 zeta wc s + wc^2)``,
  a derivative below the cutoff ``fc = wc / 2 pi`` rolling off as 1/f above it; low-frequency
  group delay ``2 zeta / wc`` (45 ms at 5 Hz, zeta = 0.707). :func:`lowpass_derivative` is the
  same filter over a whole array.
- :func:`savgol_derivative` (offline only, non-causal, zero lag): local polynomial fit.
- :class:`RotationalKF` (live): a Kalman filter on the spacecraft's rotational dynamics
  ``I_s dw = tau_thr + tau_arms - w x (I_s w)``, where ``tau_arms`` (the arms' moment on the
  spacecraft about C) is KNOWN from the F/T sensors, and the thruster moment is a random walk
  (pulse-modulated thrusters: mostly constant, with jumps). State ``(w, tau_thr)``, measured by
  the gyro. It returns ``tau_thr`` directly and ``dw = I_s^-1 (tau_thr + tau_arms - w x I_s w)``.
  :class:`TranslationalKF` is the same idea for the force, measured by the accelerometer.

:func:`measure_tradeoff` measures noise against lag for all of them on a synthetic signal.
Everything is in the body frame; units in the docstrings. No I/O.
"""
from __future__ import annotations

import math
from typing import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import integrate, signal

SQRT_HALF = math.sqrt(0.5)


def gyro_rate_sigma(arw_deg_per_sqrt_h: float, rate_hz: float) -> float:
    """Per-sample standard deviation (rad/s) of a gyro's white rate noise from its angle random walk.

    ARW N (deg/sqrt(h)) is the rate noise density: N * pi/180 / 60 rad/sqrt(s). Sampled at
    ``rate_hz`` (noise bandwidth rate_hz / 2, two-sided), sigma = density * sqrt(rate_hz).
    0.07 deg/sqrt(h) at 1 kHz gives 6.44e-4 rad/s.
    """
    density = arw_deg_per_sqrt_h * math.pi / 180.0 / 60.0
    return density * math.sqrt(rate_hz)


# --- filtered derivative -----------------------------------------------------------------------

def lowpass_differentiator_coefficients(cutoff_hz: float, rate_hz: float,
                                        zeta: float = SQRT_HALF) -> tuple[np.ndarray, np.ndarray]:
    """``(b, a)`` of the discrete second-order low-pass differentiator (Tustin, prewarped at fc)."""
    if not 0.0 < cutoff_hz < rate_hz / 2.0:
        raise ValueError(f"cutoff {cutoff_hz} Hz must be in (0, {rate_hz / 2}) Hz")
    wa = 2.0 * rate_hz * math.tan(math.pi * cutoff_hz / rate_hz)
    ba: tuple[np.ndarray, np.ndarray] = signal.bilinear([wa * wa, 0.0], [1.0, 2.0 * zeta * wa, wa * wa], fs=rate_hz)
    return ba


class LowPassDifferentiator:
    """Causal filtered derivative of a vector signal, one sample at a time (DF-II transposed).

    ``H(s) = wc^2 s / (s^2 + 2 zeta wc s + wc^2)``: a true derivative well below ``cutoff_hz``,
    -3 dB relative to it at the cutoff (zeta = 0.707), -40 dB/decade relative to it above.
    Low-frequency group delay ``2 zeta / (2 pi cutoff_hz)`` s. Output in (input unit)/s.
    """

    def __init__(self, cutoff_hz: float, rate_hz: float, zeta: float = SQRT_HALF,
                 shape: tuple[int, ...] = (3,)) -> None:
        self.cutoff_hz, self.rate_hz, self.zeta = cutoff_hz, rate_hz, zeta
        self.b, self.a = lowpass_differentiator_coefficients(cutoff_hz, rate_hz, zeta)
        self._zi = signal.lfilter_zi(self.b, self.a)
        self._z = np.zeros((2, *shape))
        self._primed = False

    @property
    def group_delay_s(self) -> float:
        return 2.0 * self.zeta / (2.0 * math.pi * self.cutoff_hz)

    def reset(self, x0: np.ndarray | None = None) -> None:
        """Forget the past; start at rest at ``x0`` (or at the next sample when None)."""
        if x0 is None:
            self._primed = False
        else:
            self._z = self._zi.reshape(2, *([1] * np.ndim(x0))) * np.asarray(x0, dtype=float)
            self._primed = True

    def update(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        if not self._primed:
            self.reset(x)
        b, a, z = self.b, self.a, self._z
        y: np.ndarray = b[0] * x + z[0]
        z[0] = b[1] * x - a[1] * y + z[1]
        z[1] = b[2] * x - a[2] * y
        return y


def lowpass_derivative(x: np.ndarray, rate_hz: float, cutoff_hz: float,
                       zeta: float = SQRT_HALF) -> np.ndarray:
    """:class:`LowPassDifferentiator` over a whole array ``(N, ...)``, starting at rest at ``x[0]``."""
    x = np.asarray(x, dtype=float)
    b, a = lowpass_differentiator_coefficients(cutoff_hz, rate_hz, zeta)
    zi = signal.lfilter_zi(b, a).reshape(2, *([1] * (x.ndim - 1))) * x[0]
    y: np.ndarray
    y, _ = signal.lfilter(b, a, x, axis=0, zi=zi)
    return y


def savgol_derivative(x: np.ndarray, rate_hz: float, window_s: float, polyorder: int = 2) -> np.ndarray:
    """Savitzky-Golay derivative along axis 0, (input unit)/s. OFFLINE: centred, uses the future."""
    n = max(polyorder + 2, int(round(window_s * rate_hz)) | 1)
    dx: np.ndarray = signal.savgol_filter(np.asarray(x, dtype=float), n, polyorder, deriv=1,
                                          delta=1.0 / rate_hz, axis=0, mode="interp")
    return dx


# --- Kalman filters ----------------------------------------------------------------------------

def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), axis=-1)


def _skew(r: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])


class RotationalKF:
    """Extended Kalman filter for the spacecraft's rate and thruster moment, body frame.

    Model, sampled at ``rate_hz`` (Euler, input held over the sample interval)::

        I_s dw/dt = tau_thr + tau_arms - w x (I_s w)      tau_arms known (F/T sensors)
        d tau_thr/dt = white noise, intensity torque_walk^2 ((N m)^2/s)
        gyro = w + white noise (gyro_sigma rad/s per sample)

    ``torque_walk`` (N m/sqrt(s)) sets the trade-off: larger follows thruster jumps faster and
    lets more gyro noise through (:func:`measure_tradeoff`). For jumps of size J every T seconds,
    ``J / sqrt(T)`` is the matched value. ``arm_torque_sigma`` (N m per sample) is the noise of
    ``tau_arms`` (from the F/T noise), entering as process noise on w.

    :meth:`step` is the live form; :meth:`run` applies it to arrays.
    """

    def __init__(self, inertia: np.ndarray, rate_hz: float, gyro_sigma: float, torque_walk: float,
                 arm_torque_sigma: float = 0.0, w0: np.ndarray | None = None,
                 tau0: np.ndarray | None = None, tau0_sigma: float = 1e3) -> None:
        self.I = np.array(inertia, dtype=float)
        self.I_inv = np.linalg.inv(self.I)
        self.dt = 1.0 / rate_hz
        self.R = gyro_sigma ** 2 * np.eye(3)
        self.Q = np.zeros((6, 6))
        self.Q[:3, :3] = self.dt ** 2 * arm_torque_sigma ** 2 * self.I_inv @ self.I_inv.T
        self.Q[3:, 3:] = torque_walk ** 2 * self.dt * np.eye(3)
        self.x = np.zeros(6)
        self.P = np.diag([gyro_sigma ** 2] * 3 + [tau0_sigma ** 2] * 3)
        self._w0_given = w0 is not None
        if w0 is not None:
            self.x[:3] = w0
        if tau0 is not None:
            self.x[3:] = tau0

    def step(self, gyro: np.ndarray, tau_arms: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One sample: gyro rate (rad/s, body frame), arms' moment on the spacecraft about C (N m).

        Returns ``(w, tau_thr, dw)``: filtered rate (rad/s), thruster moment about C (N m),
        angular acceleration (rad/s^2), all body frame, at this sample's time.
        """
        gyro = np.asarray(gyro, dtype=float)
        u = np.asarray(tau_arms, dtype=float)
        if not self._w0_given:
            self.x[:3] = gyro
            self._w0_given = True
        x, P = self.x, self.P
        # update: H = [I 0]
        S = P[:3, :3] + self.R
        K = np.linalg.solve(S, P[:3, :]).T
        x += K @ (gyro - x[:3])
        P -= K @ P[:3, :]
        P += P.T
        P *= 0.5
        w, tau = x[:3].copy(), x[3:].copy()
        Iw = self.I @ w
        dw = self.I_inv @ (tau + u - _cross(w, Iw))
        # predict over one interval with u held
        J = -self.I_inv @ (_skew(w) @ self.I - _skew(Iw))
        F = np.eye(6)
        F[:3, :3] += self.dt * J
        F[:3, 3:] = self.dt * self.I_inv
        x[:3] += self.dt * dw
        self.P = F @ P @ F.T + self.Q
        return w, tau, dw

    def run(self, gyro: np.ndarray, tau_arms: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`step` over ``(N, 3)`` arrays; returns ``(w, tau_thr, dw)``, each ``(N, 3)``."""
        gyro, tau_arms = np.asarray(gyro, dtype=float), np.asarray(tau_arms, dtype=float)
        out = np.empty((3, len(gyro), 3))
        for k in range(len(gyro)):
            out[0, k], out[1, k], out[2, k] = self.step(gyro[k], tau_arms[k])
        return out[0], out[1], out[2]


class TranslationalKF:
    """Kalman filter for the thruster force, body frame: ``m_s a_s = f_thr + f_arms``.

    ``f_arms`` (the arms' force on the spacecraft, known from the F/T sensors) and the
    accelerometer ``a_s`` (at C, body frame, m/s^2, noise ``accel_sigma`` per sample) measure
    ``f_thr``; ``f_thr`` is a random walk of intensity ``force_walk`` (N/sqrt(s)). The three axes
    are independent and identical, so the covariance is one scalar.
    """

    def __init__(self, mass: float, rate_hz: float, accel_sigma: float, force_walk: float,
                 f0: np.ndarray | None = None, f0_sigma: float = 1e3) -> None:
        self.m = float(mass)
        self.dt = 1.0 / rate_hz
        self.r = accel_sigma ** 2
        self.q = force_walk ** 2 * self.dt
        self.f = np.zeros(3) if f0 is None else np.array(f0, dtype=float)
        self.P = f0_sigma ** 2

    def step(self, a_s: np.ndarray, f_arms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Returns ``(f_thr, a_hat)``: thruster force (N) and filtered acceleration of C (m/s^2)."""
        u = np.asarray(f_arms, dtype=float)
        h = 1.0 / self.m
        K = self.P * h / (h * h * self.P + self.r)
        self.f = self.f + K * (np.asarray(a_s, dtype=float) - h * (self.f + u))
        self.P = (1.0 - K * h) * self.P + self.q
        return self.f.copy(), h * (self.f + u)

    def run(self, a_s: np.ndarray, f_arms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a_s, f_arms = np.asarray(a_s, dtype=float), np.asarray(f_arms, dtype=float)
        f, a = np.empty_like(a_s), np.empty_like(a_s)
        for k in range(len(a_s)):
            f[k], a[k] = self.step(a_s[k], f_arms[k])
        return f, a


# --- the noise-versus-lag trade-off ------------------------------------------------------------

PAPER_INERTIA = np.diag([3446.0, 3446.0, 5808.0])   # paper_robot spacecraft, kg m^2


@dataclass(frozen=True, slots=True)
class RotationScenario:
    """A synthetic rotational run sampled at ``rate_hz``: all arrays ``(N, 3)``, body frame."""

    rate_hz: float
    t_s: np.ndarray          # (N,)
    w: np.ndarray            # true rate, rad/s
    dw: np.ndarray           # true angular acceleration, rad/s^2
    tau_thr: np.ndarray      # true thruster moment, N m (piecewise constant)
    tau_arms: np.ndarray     # arms' moment on the spacecraft, N m (known)
    gyro: np.ndarray         # w + white noise
    step_times_s: np.ndarray
    inertia: np.ndarray


def rotation_scenario(inertia: np.ndarray = PAPER_INERTIA, rate_hz: float = 1000.0,
                      duration_s: float = 20.0, gyro_sigma: float | None = None,
                      step_period_s: float = 2.0, step_nm: float = 100.0,
                      arm_nm: float = 200.0, seed: int = 0) -> RotationScenario:
    """Thruster moment jumping every ``step_period_s`` (uniform in +-step_nm per axis), smooth arm
    moments (0.1-0.3 Hz sines of amplitude ``arm_nm``), exact rigid-body rates integrated piece by
    piece, plus white gyro noise (default: 0.07 deg/sqrt(h) ARW, :func:`gyro_rate_sigma`)."""
    rng = np.random.default_rng(seed)
    if gyro_sigma is None:
        gyro_sigma = gyro_rate_sigma(0.07, rate_hz)
    inertia = np.asarray(inertia, dtype=float)
    I_inv = np.linalg.inv(inertia)
    N = int(round(duration_s * rate_hz))
    t = np.arange(N) / rate_hz
    n_steps = int(math.ceil(duration_s / step_period_s))
    levels = rng.uniform(-step_nm, step_nm, size=(n_steps, 3))
    step_times = np.arange(1, n_steps) * step_period_s
    f_arm = rng.uniform(0.1, 0.3, size=3)
    ph_arm = rng.uniform(0, 2 * np.pi, size=3)

    def arms(tt: float | np.ndarray) -> np.ndarray:
        moment: np.ndarray = arm_nm * np.sin(2 * np.pi * f_arm * np.asarray(tt)[..., None] + ph_arm)
        return moment

    tau_thr = levels[np.minimum((t // step_period_s).astype(int), n_steps - 1)]
    w = np.empty((N, 3))
    w_now = rng.uniform(-0.02, 0.02, size=3)
    for k in range(n_steps):
        lo, hi = k * step_period_s, min((k + 1) * step_period_s, duration_s)
        idx = np.nonzero((t >= lo) & (t < hi))[0]
        if len(idx) == 0:
            continue
        lev = levels[k]

        def rhs(tt: float, ww: np.ndarray, lev: np.ndarray = lev) -> np.ndarray:
            dww: np.ndarray = I_inv @ (lev + arms(tt) - _cross(ww, inertia @ ww))
            return dww

        sol = integrate.solve_ivp(rhs, (lo, hi), w_now, method="DOP853", rtol=1e-11, atol=1e-14,
                                  dense_output=True)
        w[idx] = sol.sol(t[idx]).T
        w_now = sol.y[:, -1]
    tau_arms = arms(t)
    dw = (tau_thr + tau_arms - _cross(w, w @ inertia.T)) @ I_inv.T
    gyro = w + gyro_sigma * rng.standard_normal((N, 3))
    return RotationScenario(rate_hz, t, w, dw, tau_thr, tau_arms, gyro, step_times, inertia)


@dataclass(frozen=True, slots=True)
class TradeoffRow:
    """One estimator's thruster-moment error on a :class:`RotationScenario` (after a warm-up).

    ``noise_rms_nm``: RMS of (estimate on noisy gyro - estimate on noise-free gyro), the part due
    to gyro noise. ``rise90_s``: mean time, on noise-free data, from a thruster jump until the
    estimate has covered 90 % of it (on the axis with the largest jump). ``rms_error_nm``: RMS of
    (estimate - truth) with noise: both effects together. All over the three axes, N m.
    """

    method: str
    setting: str
    noise_rms_nm: float
    rise90_s: float
    rms_error_nm: float
    causal: bool = True


def _moment_from_dw(sc: RotationScenario, w: np.ndarray, dw: np.ndarray) -> np.ndarray:
    # METHOD section 1, arms' part moved to the left: tau_thr = I dw + w x I w - tau_arms
    tau_thr: np.ndarray = dw @ sc.inertia.T + _cross(w, w @ sc.inertia.T) - sc.tau_arms
    return tau_thr


def _rise90(sc: RotationScenario, est: np.ndarray) -> float:
    times = []
    for ts in sc.step_times_s:
        k = int(round(ts * sc.rate_hz))
        jump = sc.tau_thr[k] - sc.tau_thr[k - 1]
        ax = int(np.argmax(np.abs(jump)))
        before = sc.tau_thr[k - 1, ax]
        frac = (est[k - 1:, ax] - before) / jump[ax]     # from the last sample before the jump
        reached = np.nonzero(frac >= 0.9)[0]
        if len(reached):
            times.append(reached[0] / sc.rate_hz)
    return float(np.mean(times)) if times else math.inf


def measure_tradeoff(sc: RotationScenario | None = None,
                     cutoffs_hz: Sequence[float] = (0.5, 1.0, 2.0, 5.0, 20.0),
                     savgol_windows_s: Sequence[float] = (0.1, 0.5),
                     torque_walks: Sequence[float] = (10.0, 30.0, 100.0, 300.0),
                     gyro_sigma: float | None = None, warmup_s: float = 1.0) -> list[TradeoffRow]:
    """Noise against lag of every thruster-moment estimator here on one synthetic scenario.

    Estimators: raw backward difference of the gyro; :func:`lowpass_derivative` at each cutoff;
    :func:`savgol_derivative` (offline) at each window; :class:`RotationalKF` at each torque walk.
    The difference-based ones turn ``dw`` into a moment with METHOD section 1.
    """
    if gyro_sigma is None:
        gyro_sigma = gyro_rate_sigma(0.07, sc.rate_hz if sc is not None else 1000.0)
    if sc is None:
        sc = rotation_scenario(gyro_sigma=gyro_sigma)
    fs = sc.rate_hz
    k0 = int(warmup_s * fs)
    rows: list[TradeoffRow] = []

    def row(method: str, setting: str, estimate: Callable[[np.ndarray], np.ndarray], causal: bool = True) -> None:
        noisy, clean = estimate(sc.gyro), estimate(sc.w)
        rows.append(TradeoffRow(
            method, setting,
            noise_rms_nm=float(np.sqrt(np.mean((noisy[k0:] - clean[k0:]) ** 2))),
            rise90_s=_rise90(sc, clean),
            rms_error_nm=float(np.sqrt(np.mean((noisy[k0:] - sc.tau_thr[k0:]) ** 2))),
            causal=causal))

    def raw(g: np.ndarray) -> np.ndarray:
        dw = np.vstack([np.zeros((1, 3)), np.diff(g, axis=0) * fs])
        return _moment_from_dw(sc, g, dw)

    row("raw difference", "1 sample", raw)
    for fc in cutoffs_hz:
        def lowpass(g: np.ndarray, fc: float = fc) -> np.ndarray:
            return _moment_from_dw(sc, g, lowpass_derivative(g, fs, fc))
        row("low-pass differentiator", f"fc = {fc:g} Hz", lowpass)
    for win in savgol_windows_s:
        def savgol(g: np.ndarray, win: float = win) -> np.ndarray:
            return _moment_from_dw(sc, g, savgol_derivative(g, fs, win))
        row("Savitzky-Golay (offline)", f"window {win:g} s, order 2", savgol, causal=False)
    for q in torque_walks:
        def kf(g: np.ndarray, q: float = q) -> np.ndarray:
            f = RotationalKF(sc.inertia, fs, gyro_sigma=gyro_sigma, torque_walk=q)
            return f.run(g, sc.tau_arms)[1]
        row("rotational KF", f"walk {q:g} N m/sqrt(s)", kf)
    return rows


def format_tradeoff(rows: list[TradeoffRow]) -> str:
    """A Markdown table of :func:`measure_tradeoff` rows."""
    lines = ["| estimator | setting | noise RMS (N m) | 90 % rise (ms) | total RMS error (N m) |",
             "|---|---|---:|---:|---:|"]
    def num(x: float) -> str:
        return f"{x:,.0f}" if abs(x) >= 100 else f"{x:.3g}"

    for r in rows:
        lines.append(f"| {r.method} | {r.setting} | {num(r.noise_rms_nm)} | {1e3 * r.rise90_s:.0f} | "
                     f"{num(r.rms_error_nm)} |")
    return "\n".join(lines)
