"""Joint accelerations and F/T bias per arm: one Kalman filter over every sensor of the arm.

Why: the full joint torque of a distal joint is a small difference of large F/T-side terms. Taken
from the sensor side (the measured wrench carried down the chain), each joint's estimate carries
the F/T noise and bias through its lever arm; taken from the distal side (the inertial wrench of
the links beyond it) it needs the joint accelerations, and the F/T wrench alone barely sees those
of the light distal links. The encoder rates see them well, the F/T sensor sees the proximal ones
well: this filter uses both. The published torque is then, per joint, the distal side of the
filtered state and the sensor side fused by their predicted variances (:func:`fuse`, called by
``chain_kernel._epoch``, step 4). docs/estimator.md, section 2b, has the study behind it.

State of arm j with n joints (N = 2 n + 6):

    x = [dq (n), ddq (n), b (6)]          rad/s, rad/s^2, the F/T bias (sensor frame, N and N m)

- process: ``dq += dt ddq``; ``ddq`` a random walk (white jerk of spectral density
  ``jerk_psd``, rad^2/s^5), ``b`` a slow random walk (``bias_walk_n``, ``bias_walk_nm`` per
  sqrt(s)): the residual after taring, which drifts with temperature, and with it whatever slow
  wrench the model does not explain (its mass and inertia errors), which would otherwise go into
  the accelerations (measured: a 5 % wrong model cost the second joints of capture 5.5 % with a
  walk of 0.01 N/sqrt(s), 2.4 % with 1 N/sqrt(s), the nominal model 0.80 % and 0.70 %);
- F/T, 6 scalars: ``ft_r - w0_r = sum_k J_rk ddq_k + b_r + noise`` (``w0``: the sensor wrench
  the model predicts with ``ddq = 0``; ``J``: its response to each joint's acceleration; both
  from the chain pass of the same epoch), noise ``force_sigma_n`` / ``torque_sigma_nm``;
- encoder rates, n scalars: ``rate_i = dq_i + noise`` (``rate_sigma_rad_s``).

A sample that is missing, saturated or faulty is not applied, and neither are an arm's F/T rows
while one of its joints is, or while the base motion is not trusted (an F/T sample, the valve
command or a sound IMU sample missing: its rows are the model at this epoch's angles and base
motion); the prediction carries the state through.

The F/T rows are linear in the state given q, dq and the base motion, so this is a linear
Kalman filter with time-varying ``H``. Measurements are applied one scalar at a time (their noise
is independent): no matrix inverse, ``P -= k k^T s`` keeps P exactly symmetric (each product is
computed once for both triangles). Every operation is an explicit loop in a fixed order (no
BLAS, no reductions, no fastmath): live and replay give the same bits.

The filter starts at the first epoch of an arm whose F/T rows may be applied: ``dq`` from the
rates, ``ddq`` from the least-squares solution of the F/T rows (what the chain pass already
computes), ``b = 0`` with the priors' variances.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from numba import njit

from .model import EstimatorSettingsError

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

MAX_STATE = 2 * 6 + 6           # an arm of at most chain_kernel.MAX_ARM_JOINTS joints

_jit = njit(cache=True, fastmath=False, error_model="numpy", nogil=True)

# the constants array (JointFilterSettings.constants)
C_ON, C_JERK, C_WALK_F, C_WALK_T, C_RATE_VAR, C_FORCE_VAR, C_TORQUE_VAR, C_ACC0_VAR, C_BIAS0_F, C_BIAS0_T, \
    C_MAX_DT, C_MODEL = range(12)
N_CONST = 12
SCRATCH_ROWS = 3 + 2 * 6         # h, P h; the arm's D (n, n) and A_tau (n, 6) for the fusion; E_i
# per arm bookkeeping (the state row after the MAX_STATE values)
S_STARTED = MAX_STATE
ROW = MAX_STATE + 1


@dataclass(frozen=True)
class JointFilterSettings:
    """Noise figures of the joint filter. Defaults: the sensor classes of the default scenario
    as they arrive on the wire (docs/estimator.md, section 2b): an F/T sensor of 0.25 N /
    0.025 N m per sample plus the frames' 0.05 N / 0.05 N m resolution, encoder rates of
    2e-5 rad/s plus the frames' 2.5e-4 rad/s resolution (its uniform error, 7.2e-5 rad/s,
    dominates), an F/T bias of up to a newton after taring."""

    enabled: bool = True               # False: joint accelerations by least squares from the F/T wrench alone
    jerk_psd: float = 100.0            # white jerk of each joint, rad^2/s^5 (the random walk of ddq)
    rate_sigma_rad_s: float = 7.5e-5   # encoder rate noise with the wire's resolution, 1 sigma per sample
    force_sigma_n: float = 0.25        # F/T force noise with the wire's resolution, 1 sigma per sample
    torque_sigma_nm: float = 0.029     # F/T moment noise with the wire's resolution, 1 sigma per sample
    accel_prior: float = 10.0          # initial ddq uncertainty beyond the least-squares start, rad/s^2
    bias_prior_n: float = 1.0          # F/T force bias after taring, 1 sigma
    bias_prior_nm: float = 0.1         # F/T moment bias after taring, 1 sigma
    bias_walk_n: float = 1.0           # random walk of the unexplained wrench (F/T bias, model error), N per sqrt(s)
    bias_walk_nm: float = 0.3          # the same, moment, N m per sqrt(s)
    max_gap_s: float = 0.1             # a longer silence restarts the arm's filter
    model_uncertainty: float = 0.02    # relative error of the model's masses and inertias, 1 sigma (fusion)

    def __post_init__(self) -> None:
        if not isinstance(self.enabled, bool):
            raise EstimatorSettingsError(f"enabled must be true or false, got {self.enabled!r}")
        for name, value in vars(self).items():
            if name == "enabled":
                continue
            low = 0.0 if name == "model_uncertainty" else None
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value)
                                               and (value >= low if low is not None else value > 0)):
                raise EstimatorSettingsError(f"{name} must be a number {'>= 0' if low is not None else '> 0'}, "
                                             f"got {value!r}")

    def constants(self) -> np.ndarray:
        c = np.zeros(N_CONST)
        c[C_ON] = 1.0 if self.enabled else 0.0
        c[C_JERK] = self.jerk_psd
        c[C_WALK_F] = self.bias_walk_n ** 2
        c[C_WALK_T] = self.bias_walk_nm ** 2
        c[C_RATE_VAR] = self.rate_sigma_rad_s ** 2
        c[C_FORCE_VAR] = self.force_sigma_n ** 2
        c[C_TORQUE_VAR] = self.torque_sigma_nm ** 2
        c[C_ACC0_VAR] = self.accel_prior ** 2
        c[C_BIAS0_F] = self.bias_prior_n ** 2
        c[C_BIAS0_T] = self.bias_prior_nm ** 2
        c[C_MAX_DT] = self.max_gap_s
        c[C_MODEL] = self.model_uncertainty ** 2
        return c


def new_state(n_arms: int) -> tuple[np.ndarray, np.ndarray]:
    """``(x, P)``: per arm the state row (``ROW``: the state, then 1 once started) and its
    covariance ``(MAX_STATE, MAX_STATE)``; zero: not started."""
    return np.zeros((max(n_arms, 1), ROW)), np.zeros((max(n_arms, 1), MAX_STATE, MAX_STATE))


@_jit
def _scalar_update(x: F64, P: F64, N: int, h: F64, z: float, var: float, ph: F64) -> None:
    """x, P after the scalar measurement ``z = h . x + noise(var)``; ``ph``: N scratch."""
    s = var
    for a in range(N):
        acc = 0.0
        for b in range(N):
            acc += P[a, b] * h[b]
        ph[a] = acc
    for a in range(N):
        s += h[a] * ph[a]
    e = z
    for a in range(N):
        e -= h[a] * x[a]
    g = e / s
    for a in range(N):
        x[a] += ph[a] * g
    for a in range(N):
        pa = ph[a] / s
        for b in range(a, N):
            d = pa * ph[b]
            P[a, b] -= d
            if b != a:
                P[b, a] -= d


@_jit
def start(st: F64, P: F64, n: int, rate: F64, ddq_ls: F64, c: F64) -> None:
    """The arm's first epoch: dq from the rates, ddq from least squares, b = 0."""
    for a in range(MAX_STATE):
        st[a] = 0.0
        for b in range(MAX_STATE):
            P[a, b] = 0.0
    for i in range(n):
        st[i] = rate[i]
        st[n + i] = ddq_ls[i]
        P[i, i] = c[C_RATE_VAR]
        P[n + i, n + i] = c[C_ACC0_VAR]
    for r in range(3):
        P[2 * n + r, 2 * n + r] = c[C_BIAS0_F]
        P[2 * n + 3 + r, 2 * n + 3 + r] = c[C_BIAS0_T]
    st[S_STARTED] = 1.0


@_jit
def predict(st: F64, P: F64, n: int, dt: float, c: F64) -> None:
    """The state and covariance ``dt`` seconds on: ``x = F x``, ``P = F P F^T + Q``."""
    N = 2 * n + 6
    for i in range(n):
        st[i] += dt * st[n + i]
    # P F^T then F (P F^T): F adds dt * row (n + i) to row i
    for a in range(N):
        for i in range(n):
            P[a, i] += dt * P[a, n + i]
    for i in range(n):
        for b in range(N):
            P[i, b] += dt * P[n + i, b]
    q = c[C_JERK]
    for i in range(n):
        P[i, i] += q * dt * dt * dt / 3.0
        P[i, n + i] += q * dt * dt / 2.0
        P[n + i, i] += q * dt * dt / 2.0
        P[n + i, n + i] += q * dt
    for r in range(3):
        P[2 * n + r, 2 * n + r] += c[C_WALK_F] * dt
        P[2 * n + 3 + r, 2 * n + 3 + r] += c[C_WALK_T] * dt


@_jit
def update(st: F64, P: F64, n: int, W: F64, ft: F64, ft_ok: bool, rate: F64, rate_ok: I64, c: F64,
           h: F64, ph: F64) -> None:
    """Apply this epoch's F/T rows (if ``ft_ok``) and encoder rates (where ``rate_ok[i]``).

    ``W`` (n + 1, 6): the chain pass's ``J`` columns (``W[k]``) and ``w0`` (``W[n]``), sensor
    frame; ``ft`` (6,) the measured wrench; ``h``, ``ph``: MAX_STATE scratch each."""
    N = 2 * n + 6
    if ft_ok:
        for r in range(6):
            for a in range(N):
                h[a] = 0.0
            for k in range(n):
                h[n + k] = W[k, r]
            h[2 * n + r] = 1.0
            var = c[C_FORCE_VAR] if r < 3 else c[C_TORQUE_VAR]
            _scalar_update(st, P, N, h, ft[r] - W[n, r], var, ph)
    for i in range(n):
        if rate_ok[i] == 0:
            continue
        for a in range(N):
            h[a] = 0.0
        h[i] = 1.0
        _scalar_update(st, P, N, h, rate[i], c[C_RATE_VAR], ph)


@_jit
def fuse(st: F64, P: F64, n: int, c: F64, D: F64, A: F64, W: F64, ftb: F64, tau_d: F64, tau_s: F64,
         out: F64, E: F64) -> None:
    """Per joint, the distal side ``tau_d`` and the sensor side ``tau_s`` weighted by their
    predicted variances into ``out`` (n,); ``ftb`` the measured wrench less the bias (sensor frame).

    - distal: ``(eps tau_d)^2 + D_i P_dd D_i^T``; ``D`` (n, n): the distal torque's response to
      each joint's acceleration, ``eps`` the model's relative error;
    - sensor: the F/T noise through the joint's lever arm ``sum_r sigma_r^2 A_ir^2``, the bias's
      uncertainty ``A_i P_bb A_i^T``, the proximal links' inertial torque ``h_i = A_i ftb - tau_s``
      with its model error ``(eps h_i)^2`` and its acceleration error ``E_i P_dd E_i^T``,
      ``E_ik = A_i J_k - D_ik``; ``A`` (n, 6) the rows of ``A_tau``, ``W[k]`` ``J``'s columns;
    ``E``: n scratch (joint i's row).

    The weight of the sensor side is ``var_d / (var_d + var_s)``. Correlations between the two
    (both see the same acceleration estimate) are left out: a documented simplification.
    """
    eps2 = c[C_MODEL]
    for i in range(n):
        vd = eps2 * tau_d[i] * tau_d[i]
        vs = 0.0
        hi = -tau_s[i]
        for r in range(6):
            a = A[i, r]
            hi += a * ftb[r]
            vs += a * a * (c[C_FORCE_VAR] if r < 3 else c[C_TORQUE_VAR])
        vs += eps2 * hi * hi
        for a in range(n):
            e = -D[i, a]
            for r in range(6):
                e += A[i, r] * W[a, r]
            E[a] = e
        for a in range(n):
            da = D[i, a]
            ea = E[a]
            for b in range(n):
                db = D[i, b]
                eb = E[b]
                pab = P[n + a, n + b]
                vd += da * pab * db
                vs += ea * pab * eb
        for r in range(6):
            vs += A[i, r] * A[i, r] * (c[C_BIAS0_F] if r < 3 else c[C_BIAS0_T])
        tot = vd + vs
        w = vd / tot if tot > 0.0 else 0.0
        out[i] = tau_d[i] + w * (tau_s[i] - tau_d[i])
