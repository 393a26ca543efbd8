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

Contact (:func:`contact_test`, on with ``contact``). A force on the arm that the model does not
know (a grasp, a push, a collision) enters the F/T sensor but not the model: the filter above
would take it into the accelerations and, within some 10 ms, into the bias, and the distal side
of every joint would miss it. The test compares the sensor with the encoders, independently of
the filter: the residual ``ft - w0 - b_ref - J (rate - rate_prev) / dt`` (the accelerations from
the encoders' rate differences, the bias ``b_ref`` a slow average of the filter's over quiet
time), averaged over ``contact_window_s``, against its noise (the encoders' through ``J``, the
F/T sensor's, a floor, and the model's relative error times the model wrench) and against its own
usual size over the last seconds out of contact (sensors noisier than the settings say raise it
everywhere; a contact raises it above its past). The model's relative error is learned out of
contact (:func:`_learn_model_error`): ``contact_model_error`` until the arm's motion teaches it,
never below ``contact_model_error_min``. A residual that stands out
(``contact_significance``) for a window, and means more than ``contact_force_n`` or
``contact_moment_nm`` at the end effector, starts a contact: the state gains

    e (6)       the contact wrench on the end effector: force (N), moment about it (N m), body axes

a random walk (``contact_walk_n``, ``contact_walk_nm``) in the F/T rows through ``G`` (the sensor
wrench of each unit component, from the chain pass), started at the averaged residual's wrench;
the bias goes back to its value a few quiet windows before (it follows a new wrench within some
10 ms) and holds (a contact is not drift); the sensor side takes off that bias; the distal side carries
``G e`` down the chain. Quiet for a window (the residual below a quarter of the significance, or
below half of both sizes), the contact ends and ``e`` leaves the state. A contact is taken to
act on the last link: one on a proximal link is published as the wrench at the end effector that
the sensor cannot tell from it, and the torques of the joints beyond it are off by its share.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .jitopts import jit as _jit   # numba's njit, with the kernels' options
from .model import EstimatorSettingsError

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

MAX_STATE = 2 * 6 + 12          # [dq, ddq, b, e] of an arm of at most chain_kernel.MAX_ARM_JOINTS joints

# the constants array (JointFilterSettings.constants)
C_ON, C_JERK, C_WALK_F, C_WALK_T, C_RATE_VAR, C_FORCE_VAR, C_TORQUE_VAR, C_ACC0_VAR, C_BIAS0_F, C_BIAS0_T, \
    C_MAX_DT, C_MODEL, C_CONTACT, C_ON_F, C_ON_T, C_WINDOW, C_EWALK_F, C_EWALK_T, C_CHI, C_FLOOR_F, C_FLOOR_T, \
    C_CMODEL, C_CMODEL_MIN = range(23)
N_CONST = 23
# h, P h; the arm's D (n, n) and A_tau (n, 6) for the fusion; E_i; G (6, 6): the sensor wrench of a
# unit contact wrench; three unit forces carried from the end effector to C; the end effector from C
SCRATCH_ROWS = 3 + 2 * 6 + 6 + 3 + 1 + 6
R_G = 15                         # first row of G
R_UNIT = 21                      # first row of the unit forces
R_EE = 24                        # the end effector from C, body frame (m)
R_S = 25                         # (6, 7) the contact test's covariance and solve
# per arm bookkeeping, the state row after the MAX_STATE values
S_STARTED = MAX_STATE
S_MODE = MAX_STATE + 1           # 1: in contact, the state has the contact wrench e
S_AVG_T = MAX_STATE + 2          # seconds of residual in the average (the test waits for a window)
S_TIMER = MAX_STATE + 3          # seconds the test has held its verdict (leaky): standing out, or in contact quiet
S_HAVE_PREV = MAX_STATE + 4      # 1: S_PREV holds the last epoch's rates
S_RES = MAX_STATE + 5            # (6) the averaged residual wrench, sensor frame
S_PREV = MAX_STATE + 11          # (6) the last epoch's rates
S_WRENCH = MAX_STATE + 17        # (6) the averaged residual as a contact wrench (body axes, about the end effector)
S_PREV_Y = MAX_STATE + 23        # (6) the last epoch's ft - w0 - b
S_PREV_J = MAX_STATE + 29        # (6 x 6) the last epoch's J, row r at S_PREV_J + 6 r
S_CHI = MAX_STATE + 65           # the averaged residual's squared Mahalanobis length (its noise: 6 on average)
S_B_QUIET = MAX_STATE + 66       # (6) the bias averaged over B_MEMORY windows of quiet epochs
S_PBB = MAX_STATE + 72           # (6) in contact: the bias's variances when it began (restored at its end)
S_CHI_AVG = MAX_STATE + 78       # the usual S_CHI out of contact, averaged over CHI_MEMORY windows
S_PREV_M = MAX_STATE + 79        # (6) the last epoch's model wrench w0 + J ddq (its uncertainty)
S_RING_T = MAX_STATE + 85        # seconds into the current window of the bias checkpoints
S_RING_OK = MAX_STATE + 86       # 1: every epoch of the current window has been quiet
S_RING = MAX_STATE + 87          # (RING x 6) the bias at the end of the last RING quiet windows, newest first
RING = 4
S_EPS = MAX_STATE + 87 + 6 * RING  # (4) the model error's averages: force excess, force model^2, moment the same
S_HOLD = S_EPS + 4               # 1: the base motion is in doubt this epoch (the caller's: a thruster fault suspected)
S_DOUBT = S_EPS + 5              # seconds the test still holds after the doubt (until the residual is back)
ROW = S_EPS + 6
CHI_MEMORY = 40.0
TIMER_GAIN = 5.0
B_MEMORY = 10.0
DOUBT_WINDOWS = 4.0              # the longest hold after the base motion was in doubt, windows
EPS_MEMORY = 40.0                # windows of memory of the learned model error
EPS_PRIOR_N = 20.0               # the prior model error weighs as much as a model force of this length, N,
EPS_PRIOR_NM = 20.0              # and a model moment of this length, N m


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
    contact: bool = True               # detect contact (an unknown wrench at the end effector); False: never
    contact_significance: float = 60.0 # a contact: the averaged residual's squared length in its noise above this
    contact_force_n: float = 2.0       # and the force it means at the end effector above this, N,
    contact_moment_nm: float = 1.0     # or the moment about it above this, N m (it ends below half of each)
    contact_window_s: float = 0.05     # time constant of the averaged residual, s
    contact_floor_n: float = 0.3       # what the model misses in the averaged residual, force, 1 sigma, N
    contact_floor_nm: float = 0.3      # the same, moment, N m
    contact_model_error: float = 0.03  # and the model's relative error in its wrench, until learned (a contact must
    #                                    stand out of it)
    contact_model_error_min: float = 0.01  # the least relative error it learns (from the arm's motion out of contact)
    contact_walk_n: float = 5.0        # how fast a contact force changes, random walk, N per sqrt(s)
    contact_walk_nm: float = 1.0       # the same, moment, N m per sqrt(s)

    def __post_init__(self) -> None:
        for flag in ("enabled", "contact"):
            if not isinstance(getattr(self, flag), bool):
                raise EstimatorSettingsError(f"{flag} must be true or false, got {getattr(self, flag)!r}")
        for name, value in vars(self).items():
            if name in ("enabled", "contact"):
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
        c[C_CONTACT] = 1.0 if self.contact else 0.0
        c[C_CHI] = self.contact_significance
        c[C_FLOOR_F] = self.contact_floor_n ** 2
        c[C_FLOOR_T] = self.contact_floor_nm ** 2
        c[C_CMODEL] = self.contact_model_error ** 2
        c[C_CMODEL_MIN] = self.contact_model_error_min ** 2
        c[C_ON_F] = self.contact_force_n
        c[C_ON_T] = self.contact_moment_nm
        c[C_WINDOW] = self.contact_window_s
        c[C_EWALK_F] = self.contact_walk_n ** 2
        c[C_EWALK_T] = self.contact_walk_nm ** 2
        return c


def new_state(n_arms: int) -> tuple[np.ndarray, np.ndarray]:
    """``(x, P)``: per arm the state row (``ROW``: the state, then the bookkeeping ``S_*``) and
    its covariance ``(MAX_STATE, MAX_STATE)``; zero: not started."""
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
    """The arm's first epoch: dq from the rates, ddq from least squares, b = 0; no contact."""
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
    for a in range(S_STARTED, ROW):
        st[a] = 0.0
    st[S_STARTED] = 1.0
    st[S_CHI_AVG] = 6.0


@_jit
def predict(st: F64, P: F64, n: int, N: int, dt: float, c: F64) -> None:
    """The state and covariance ``dt`` seconds on: ``x = F x``, ``P = F P F^T + Q``; ``N`` the
    hypothesis's size (``2 n + 6``, or ``2 n + 12`` with a contact wrench)."""
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
    if N == 2 * n + 6:                 # with a contact wrench, the bias holds: a contact is not drift
        for r in range(3):
            P[2 * n + r, 2 * n + r] += c[C_WALK_F] * dt
            P[2 * n + 3 + r, 2 * n + 3 + r] += c[C_WALK_T] * dt
    else:
        for r in range(3):
            P[2 * n + 6 + r, 2 * n + 6 + r] += c[C_EWALK_F] * dt
            P[2 * n + 9 + r, 2 * n + 9 + r] += c[C_EWALK_T] * dt


@_jit
def update(st: F64, P: F64, n: int, N: int, W: F64, G: F64, ft: F64, ft_ok: bool, rate: F64, rate_ok: I64,
           c: F64, h: F64, ph: F64) -> None:
    """Apply this epoch's F/T rows (if ``ft_ok``) and encoder rates (where ``rate_ok[i]``).

    ``W`` (n + 1, 6): the chain pass's ``J`` columns (``W[k]``) and ``w0`` (``W[n]``), sensor
    frame; ``G`` (6, 6): the sensor wrench of each unit component of the contact wrench
    (``G[k]``; used when ``N = 2 n + 12``); ``ft`` (6,) the measured wrench; ``h``, ``ph``:
    MAX_STATE scratch each."""
    if ft_ok:
        for r in range(6):
            for a in range(N):
                h[a] = 0.0
            for k in range(n):
                h[n + k] = W[k, r]
            h[2 * n + r] = 1.0
            if N > 2 * n + 6:
                for k in range(6):
                    h[2 * n + 6 + k] = G[k, r]
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
def contact_test(st: F64, P: F64, n: int, dt: float, W: F64, ft: F64, ft_ok: bool, rate: F64, rate_ok: I64,
                 sr: F64, pe: F64, c: F64, tmp: F64, S: F64) -> None:
    """The contact test of one epoch, before the filter's update; enters or leaves contact
    (``tmp``: 6, ``S``: (6, 7) scratch).

    The residual ``ft - w0 - b_ref - J (rate - rate_prev) / dt``: what the sensor measures beyond
    the model, the bias and the accelerations the encoders see (their rate differences: independent
    of the F/T sensor, and averaged their noise does not pile up); in contact the held bias. The
    F/T side is the previous epoch's: the rate difference over a period is the acceleration of the
    period's start, the drives and valves holding their commands over it (taken with this epoch's
    F/T sample, every change of a command would leave ``J`` times its acceleration step in the
    average). Averaged over ``C_WINDOW`` seconds (first-order), weighed against its noise
    (:func:`_significance`, ``S_CHI``) and carried to the end effector as a wrench on it
    (``S_WRENCH``: body axes, moment about the end effector ``pe``, m from C; ``sr`` the sensor's
    placement). Out of contact, significant (``C_CHI``) and big (above ``C_ON_F`` or ``C_ON_T``)
    for a window in all (a leaky count): a contact begins (:func:`_enter`); not while ``S_HOLD``
    (the caller's: the base motion in doubt) nor after it until the residual is back below
    ``C_CHI`` (at most ``DOUBT_WINDOWS`` windows): the count runs down and nothing is learned. In contact, below a
    quarter of ``C_CHI`` or half of both sizes for a window in all (a leaky count): it ends
    (:func:`_leave`). The bias
    reference ``S_B_QUIET`` follows the filter's bias over quiet epochs only. An epoch with a
    sample missing, here or in the last epoch, adds nothing."""
    ok = st[S_HAVE_PREV] != 0.0
    for i in range(n):
        if rate_ok[i] == 0:
            ok = False
    if ok:
        a = dt / c[C_WINDOW]
        if a > 1.0:
            a = 1.0
        for r in range(6):
            x = st[S_PREV_Y + r]
            for k in range(n):
                x -= st[S_PREV_J + 6 * r + k] * (rate[k] - st[S_PREV + k]) / dt
            st[S_RES + r] += a * (x - st[S_RES + r])
        st[S_AVG_T] += dt
        w = st[S_WRENCH:S_WRENCH + 6]         # the contact wrench that explains it
        _contact_wrench(sr, pe, st[S_RES:S_RES + 6], w)
        f = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
        m = math.sqrt(w[3] * w[3] + w[4] * w[4] + w[5] * w[5])
        # against the residual's own usual size: sensors noisier than the settings say, or a model
        # less exact, raise it everywhere, a contact raises it above its past
        chi = _significance(st, n, a, dt, c, S)
        scale = st[S_CHI_AVG] / 6.0
        if scale > 1.0:
            chi /= scale
        st[S_CHI] = chi
        # the base motion in doubt (an unexplained wrench on the spacecraft: the model's inertial
        # wrench of the arm is off on every arm at once): no contact begins, nothing is learned;
        # after it, until the averaged residual is back below the significance (at most
        # DOUBT_WINDOWS windows: what still stands out then is the arm's)
        if st[S_HOLD] != 0.0:
            st[S_DOUBT] = DOUBT_WINDOWS * c[C_WINDOW]
        elif chi < c[C_CHI] or st[S_DOUBT] <= dt:
            st[S_DOUBT] = 0.0
        else:
            st[S_DOUBT] -= dt
        held = st[S_HOLD] != 0.0 or st[S_DOUBT] > 0.0
        if st[S_MODE] == 0.0 and chi < c[C_CHI] and not held:
            st[S_CHI_AVG] += a / CHI_MEMORY * (chi * (scale if scale > 1.0 else 1.0) - st[S_CHI_AVG])
        big = f > c[C_ON_F] or m > c[C_ON_T]
        if st[S_AVG_T] >= 3.0 * c[C_WINDOW]:
            if st[S_MODE] == 0.0:
                if not (big and chi > c[C_CHI]) and not held:
                    _learn_model_error(st, n, a, dt, c)
                if big and chi > c[C_CHI] and not held:
                    # out of contact: how long the residual has stood out, the faster the further
                    # (up to TIMER_GAIN times: a knock far out of the noise is flagged sooner)
                    g = chi / c[C_CHI]
                    st[S_TIMER] += dt * (g if g < TIMER_GAIN else TIMER_GAIN)
                    if st[S_TIMER] >= c[C_WINDOW]:
                        _enter(st, P, n, sr, pe, c, tmp)
                elif st[S_TIMER] > dt:
                    st[S_TIMER] -= dt
                else:
                    st[S_TIMER] = 0.0
                if chi < 0.25 * c[C_CHI]:
                    for r in range(6):
                        st[S_B_QUIET + r] += a / B_MEMORY * (st[2 * n + r] - st[S_B_QUIET + r])
                else:
                    st[S_RING_OK] = 0.0
                _checkpoint(st, n, dt, c)
            elif (f < 0.5 * c[C_ON_F] and m < 0.5 * c[C_ON_T]) or chi < 0.25 * c[C_CHI]:
                st[S_TIMER] += dt
                if st[S_TIMER] >= c[C_WINDOW]:
                    _leave(st, P, n)
            elif st[S_TIMER] > dt:             # a leaky count, as for a contact's beginning
                st[S_TIMER] -= dt
            else:
                st[S_TIMER] = 0.0
        else:
            for r in range(6):
                st[S_B_QUIET + r] = st[2 * n + r]
                for k in range(RING):
                    st[S_RING + 6 * k + r] = st[2 * n + r]
    have = ft_ok
    for i in range(n):
        st[S_PREV + i] = rate[i]
        if rate_ok[i] == 0:
            have = False
    for r in range(6):
        st[S_PREV_Y + r] = ft[r] - W[n, r] - (st[2 * n + r] if st[S_MODE] != 0.0 else st[S_B_QUIET + r])
        m_r = W[n, r]
        for k in range(n):
            st[S_PREV_J + 6 * r + k] = W[k, r]
            m_r += W[k, r] * st[n + k]
        st[S_PREV_M + r] = m_r
    st[S_HAVE_PREV] = 1.0 if have else 0.0


@_jit
def _enter(st: F64, P: F64, n: int, sr: F64, pe: F64, c: F64, tmp: F64) -> None:
    """A contact begins: the bias goes back to its oldest checkpoint (RING quiet windows ago:
    before the contact, which the filter's bias follows within some 10 ms) and holds (its
    variances kept for the end, its covariance zero: no update moves it); the state gains the
    contact wrench, started at the averaged residual's, with an uncertainty of its size."""
    K = 2 * n + 6
    st[S_MODE] = 1.0
    st[S_TIMER] = 0.0
    old = S_RING + 6 * (RING - 1)
    for r in range(6):
        tmp[r] = st[S_RES + r]
        st[2 * n + r] = st[old + r]
        st[S_PBB + r] = P[2 * n + r, 2 * n + r]
    w = st[S_WRENCH:S_WRENCH + 6]
    _contact_wrench(sr, pe, tmp, w)
    for u in range(2 * n, K + 6):
        for v in range(K + 6):
            P[u, v] = 0.0
            P[v, u] = 0.0
    # its uncertainty: the size of the wrench and the thresholds (the average lags a rising contact)
    sf = c[C_ON_F] + math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    sm = c[C_ON_T] + math.sqrt(w[3] * w[3] + w[4] * w[4] + w[5] * w[5])
    for r in range(6):
        st[K + r] = w[r]
    for r in range(3):
        P[K + r, K + r] = sf * sf
        P[K + 3 + r, K + 3 + r] = sm * sm


@_jit
def _checkpoint(st: F64, n: int, dt: float, c: F64) -> None:
    """At the end of each window out of contact: if every epoch of it was quiet, the filter's
    bias becomes the newest checkpoint and the oldest is dropped."""
    st[S_RING_T] += dt
    if st[S_RING_T] < c[C_WINDOW]:
        return
    if st[S_RING_OK] != 0.0:
        for k in range(RING - 1, 0, -1):
            for r in range(6):
                st[S_RING + 6 * k + r] = st[S_RING + 6 * (k - 1) + r]
        for r in range(6):
            st[S_RING + r] = st[2 * n + r]
    st[S_RING_T] = 0.0
    st[S_RING_OK] = 1.0


@_jit
def _leave(st: F64, P: F64, n: int) -> None:
    """A contact ends: the state loses the contact wrench, the bias learns again from the
    variances it had when the contact began."""
    K = 2 * n + 6
    st[S_MODE] = 0.0
    for u in range(K, K + 6):
        st[u] = 0.0
        for v in range(K + 6):
            P[u, v] = 0.0
            P[v, u] = 0.0
    for r in range(6):
        P[2 * n + r, 2 * n + r] = st[S_PBB + r]


@_jit
def _contact_wrench(sr: F64, pe: F64, res: F64, w: F64) -> None:
    """``w``: the wrench on the end effector (body axes; force, then moment about the end
    effector ``pe``) whose sensor wrench is the residual ``res`` (sensor frame, measured sign)."""
    sensor_to_c(sr, res, w)
    f0, f1, f2 = w[0], w[1], w[2]
    w[0] = -f0
    w[1] = -f1
    w[2] = -f2
    w[3] = -(w[3] - (pe[1] * f2 - pe[2] * f1))
    w[4] = -(w[4] - (pe[2] * f0 - pe[0] * f2))
    w[5] = -(w[5] - (pe[0] * f1 - pe[1] * f0))


@_jit
def _model_error(st: F64, c: F64, k: int) -> float:
    """The model's squared relative error, force (``k`` 0) or moment (``k`` 2): what the arm's
    motion has taught (:func:`_learn_model_error`), with the prior ``C_CMODEL`` worth a model
    wrench of ``EPS_PRIOR_*``, never below ``C_CMODEL_MIN``."""
    w = EPS_PRIOR_N * EPS_PRIOR_N if k == 0 else EPS_PRIOR_NM * EPS_PRIOR_NM
    e: float = (st[S_EPS + k] + w * c[C_CMODEL]) / (st[S_EPS + k + 1] + w)
    floor: float = c[C_CMODEL_MIN]
    return e if e > floor else floor


@_jit
def _learn_model_error(st: F64, n: int, a: float, dt: float, c: F64) -> None:
    """Out of contact, unless the residual stands out: the averaged residual's squared length per
    axis beyond what the sensors explain, and the model wrench's squared length, each averaged over
    ``EPS_MEMORY`` windows, force and moment apart. Their ratio is the model's squared relative
    error (:func:`_model_error`): a model a few percent off leaves a residual in proportion to the
    model wrench, an exact one only the sensors' noise. Learned rather than assumed, the error of
    an exact model lets a contact on a fast-moving arm stand out of a residual of its true size."""
    vr = c[C_RATE_VAR] * (a / dt) * (a / dt)
    nf = 3.0 * (a / (2.0 - a) * c[C_FORCE_VAR] + c[C_FLOOR_F])
    nt = 3.0 * (a / (2.0 - a) * c[C_TORQUE_VAR] + c[C_FLOOR_T])
    rf = 0.0
    rt = 0.0
    mf = 0.0
    mt = 0.0
    for r in range(6):
        acc = 0.0
        for k in range(n):
            acc += st[S_PREV_J + 6 * r + k] * st[S_PREV_J + 6 * r + k]
        x = st[S_RES + r]
        y = st[S_PREV_M + r]
        if r < 3:
            nf += vr * acc
            rf += x * x
            mf += y * y
        else:
            nt += vr * acc
            rt += x * x
            mt += y * y
    g = a / EPS_MEMORY
    st[S_EPS] += g * ((rf - nf) / 3.0 - st[S_EPS])
    st[S_EPS + 1] += g * (mf - st[S_EPS + 1])
    st[S_EPS + 2] += g * ((rt - nt) / 3.0 - st[S_EPS + 2])
    st[S_EPS + 3] += g * (mt - st[S_EPS + 3])


@_jit
def _significance(st: F64, n: int, a: float, dt: float, c: F64, S: F64) -> float:
    """``r^T S^-1 r`` of the averaged residual ``r`` (``st[S_RES:]``) and its covariance ``S``
    under no contact: the encoder rates' noise through the last epoch's ``J``, ``(sigma_rate
    a / dt)^2 J J^T`` (the average of rate differences keeps a fraction ``a`` of one sample's
    noise); the F/T noise, ``a / (2 - a) sigma^2``; a floor; and the model's error, a fraction
    (:func:`_model_error`) of the model wrench's force and moment lengths on every force and moment axis
    (a few percent off on each body moves a wrench between axes: the sensor wrench is a small sum
    of large terms). Cholesky in place (``S``: (6, 7) scratch, the last column the solve's)."""
    vr = c[C_RATE_VAR] * (a / dt) * (a / dt)
    mf = 0.0
    mt = 0.0
    for r in range(3):
        mf += st[S_PREV_M + r] * st[S_PREV_M + r]
        mt += st[S_PREV_M + 3 + r] * st[S_PREV_M + 3 + r]
    mf *= _model_error(st, c, 0)
    mt *= _model_error(st, c, 2)
    for r in range(6):
        for q in range(r + 1):
            acc = 0.0
            for k in range(n):
                acc += st[S_PREV_J + 6 * r + k] * st[S_PREV_J + 6 * q + k]
            S[r, q] = vr * acc
        if r < 3:
            S[r, r] += a / (2.0 - a) * c[C_FORCE_VAR] + c[C_FLOOR_F] + mf
        else:
            S[r, r] += a / (2.0 - a) * c[C_TORQUE_VAR] + c[C_FLOOR_T] + mt
    for r in range(6):                       # lower Cholesky factor
        for q in range(r + 1):
            acc = S[r, q]
            for k in range(q):
                acc -= S[r, k] * S[q, k]
            if q == r:
                S[r, r] = math.sqrt(acc) if acc > 0.0 else 1e-300
            else:
                S[r, q] = acc / S[q, q]
    chi = 0.0
    for r in range(6):                       # forward substitution: |L^-1 r|^2
        acc = st[S_RES + r]
        for k in range(r):
            acc -= S[r, k] * S[k, 6]
        S[r, 6] = acc / S[r, r]
        chi += S[r, 6] * S[r, 6]
    return chi


@_jit
def sensor_to_c(sr: F64, x: F64, y: F64) -> None:
    """y: the sensor wrench ``x`` (sensor frame, about S_j) about C, body frame (``sr``: R_j
    row-major, then S_j - C)."""
    f0 = sr[0] * x[0] + sr[1] * x[1] + sr[2] * x[2]
    f1 = sr[3] * x[0] + sr[4] * x[1] + sr[5] * x[2]
    f2 = sr[6] * x[0] + sr[7] * x[1] + sr[8] * x[2]
    n0 = sr[0] * x[3] + sr[1] * x[4] + sr[2] * x[5]
    n1 = sr[3] * x[3] + sr[4] * x[4] + sr[5] * x[5]
    n2 = sr[6] * x[3] + sr[7] * x[4] + sr[8] * x[5]
    r0, r1, r2 = sr[9], sr[10], sr[11]
    y[0] = f0
    y[1] = f1
    y[2] = f2
    y[3] = n0 + (r1 * f2 - r2 * f1)
    y[4] = n1 + (r2 * f0 - r0 * f2)
    y[5] = n2 + (r0 * f1 - r1 * f0)


@_jit
def fuse(st: F64, P: F64, n: int, c: F64, D: F64, A: F64, W: F64, G: F64, ftb: F64, tau_d: F64, tau_s: F64,
         out: F64, E: F64) -> None:
    """Per joint, the distal side ``tau_d`` and the sensor side ``tau_s`` weighted by their
    predicted variances into ``out`` (n,); ``ftb`` the measured wrench less the bias (sensor frame).

    - distal: ``(eps tau_d)^2 + D_i P_dd D_i^T``; ``D`` (n, n): the distal torque's response to
      each joint's acceleration, ``eps`` the model's relative error; in contact (``st[S_MODE]``)
      also the contact wrench's uncertainty ``(A_i G) P_ee (A_i G)^T``, ``G`` (6, 6) as in
      :func:`update`;
    - sensor: the F/T noise through the joint's lever arm ``sum_r sigma_r^2 A_ir^2``, the bias's
      uncertainty ``A_i P_bb A_i^T`` (in contact, where the bias holds, its variances when the
      contact began), the proximal links' inertial torque ``h_i = A_i ftb - tau_s``
      with its model error ``(eps h_i)^2`` and its acceleration error ``E_i P_dd E_i^T``,
      ``E_ik = A_i J_k - D_ik``; ``A`` (n, 6) the rows of ``A_tau``, ``W[k]`` ``J``'s columns;
    ``E``: MAX_STATE scratch (joint i's row E_i, then A_i G).

    The weight of the sensor side is ``var_d / (var_d + var_s)``. Correlations between the two
    (both see the same acceleration estimate) are left out: a documented simplification.
    """
    eps2 = c[C_MODEL]
    contact = st[S_MODE] != 0.0
    ke = 2 * n + 6
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
        if contact:
            for k in range(6):
                g = 0.0
                for r in range(6):
                    g += A[i, r] * G[k, r]
                E[6 + k] = g
            for k in range(6):
                for m in range(6):
                    vd += E[6 + k] * P[ke + k, ke + m] * E[6 + m]
        if contact:                          # the bias holds, at the variances it had
            for r in range(6):
                vs += A[i, r] * A[i, r] * st[S_PBB + r]
        else:
            for r in range(6):
                ar = A[i, r]
                for q in range(6):
                    vs += ar * P[2 * n + r, 2 * n + q] * A[i, q]
        tot = vd + vs
        w = vd / tot if tot > 0.0 else 0.0
        out[i] = tau_d[i] + w * (tau_s[i] - tau_d[i])
