"""Thruster fault detection and isolation: which thruster, which fault, from the filter's innovation.

The valve-aided filter (:mod:`.thruster_kernel`) explains the thruster wrench through the valve
commands, ``sum_i v_i W_i``; the IMU and the F/T sensors see the wrench the thrusters really
exert (the momentum balance, docs/method.md section 1). At every IMU update the difference of
the two is the filter's innovation ``e = y - H x`` with covariance ``S = H P H^T + R``
(:func:`.thruster_kernel.imu_tap`). A faulty thruster j leaves a known signature in it, the
valve's wrench ``W_j`` seen through the accelerometer rows (``Ha W_j``) and the gyro-difference
rows (``W_j`` moment), times a known time profile:

- ``open`` (stuck open, a leak): thrust with the valve closed, ``g = (1 - vbar_j) Ha W_j`` and
  ``(1 - vt_j) W_j^tau``; ``theta`` = the leak's fraction of the thrust (1: stuck open);
- ``loss`` (stuck closed, partial loss): no or less thrust with the valve open,
  ``g = -vbar_j Ha W_j``, ``-vt_j W_j^tau``; ``theta`` = the fraction lost (1: stuck closed).

- ``tilt`` (a misalignment change: the thrust turned off its direction), two angles ``phi``
  across the nominal direction ``d``: ``g = vbar_j Ha T_j phi`` and ``vt_j T_j^tau phi``, ``T_j``
  the wrench of a tilt by one radian, ``F [u; p x u]`` for ``u`` across ``d`` (:func:`signatures`).

``vbar_j`` is valve j's open fraction over the IMU interval and ``vt_j`` its weight in the gyro
difference (the rows of H). For each of these ``2 n`` hypotheses a generalised likelihood ratio
over an exponentially forgetting window, with whitened ``g`` and ``e`` (``L^-1``, ``S = L L^T``)::

    A = sum lambda^(k-u) g_u^T S_u^-1 g_u,   B = sum lambda^(k-u) g_u^T S_u^-1 e_u
    theta = B / A,   T = B^2 / A  (theta > 0, else 0)

``T`` is chi-squared with one degree of freedom while healthy (a tilt: ``A`` 2 x 2, ``B`` 2-vector,
``phi = A^-1 B``, ``T = B^T A^-1 B`` with two). Two windows: a short one for the
gross faults (a stuck valve, 0.1 s) and a long one for partial losses and leaks (4 s). The
hypothesis with the largest ``T`` above its window's threshold for ``hold`` updates in a row is
raised: it names the thruster (the direction and moment arm of ``W_j`` and the valve's time
profile tell the thrusters apart) and the type, from the family and ``theta`` (a loss of
:data:`CLOSED_THETA` or more is "stuck closed", a leak of :data:`OPEN_THETA` or more "stuck
open"). The signatures use the NOMINAL valve wrenches (the filter's prior): the learned ones
follow a fault once it is there, and ``theta`` is then relative to nominal thrust (a healthy
thruster delivers 0.9-1.0 of it).

The filter learns from an IMU sample only when its normalised innovation squared is at most
:data:`GATE` (the sample that first shows a gross fault comes before the detector
has seen it), and not at all while a fault is suspected. A confirmed stuck valve is modelled
through the valve mask; if it comes back (its own signature with the opposite sign, the valve
taken as commanded), the fault is cleared: an alarm of type ``cleared``, the mask back to the
command. A partial loss in the filter whose thrust comes back (its own signature with the opposite
sign, a CUSUM for its own size) is cleared too, the lost part put back on the valve's wrench.

The filter keeps learning while a fault is too small to be suspected, so a loss that began when
its CUSUM last left zero is partly learnt into the valve's wrench before it is raised: the
innovation it leaves is not ``g`` but ``rho_j g``, where ``rho_j`` (1 at the onset) is the part the
filter has not learnt yet (:func:`follow`: after every update it learns from, ``rho_j`` loses the
part of the remaining loss that update's gain ``K = P+ H^T R^-1`` took into the valve's force,
along its nominal thrust). The loss CUSUMs, a long loss candidate's own sums and the partial loss
put into the filter use ``rho_j g``, so the size is the whole loss, not what is left of it
(Willsky and Jones' likelihood ratio for a jump in a Kalman filter's state, restricted to the
valve's force along its nominal thrust).

Everything here is compiled (numba, explicit loops, no fastmath, nogil, cache): :func:`observe`
takes one IMU update's tap, the live estimator and the offline run (:func:`run_events`) call the
same function, so a replay gives the same alarms as the live run. No I/O.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from robot_description.thrusters import ThrusterLayout

from . import thruster_kernel as tk
from .thruster_kernel import F64, I64

from .jitopts import jit as _jit, jit_alloc as _jit_alloc   # numba's njit, with the kernels' options

RULE = "thruster-fault"                # the rule name of its alerts (live and bsc analyze)
OPEN, LOSS = 0, 1                      # hypothesis families (then the tilts, hypotheses 2 n + j)
FAMILIES = ("open", "loss", "tilt")
STUCK_OPEN, LEAK, STUCK_CLOSED, PARTIAL_LOSS, CLEARED, MISALIGNMENT = range(6)
TYPES = ("stuck open", "leak", "stuck closed", "partial loss", "cleared", "misalignment")
TYPE_KEYS = ("stuck_open", "leak", "stuck_closed", "partial_loss", "cleared", "misalignment")
OPEN_THETA = 0.5                       # a leak of at least this fraction of nominal thrust: stuck open
CLOSED_THETA = 0.75                    # a loss of at least this fraction: stuck closed
SHORT, LONG = 0, 1

# the detector's constants (float64 array, :meth:`FdiSettings.config`)
(_C_LAM, _C_THETA1, _C_H, _C_THETA_MIN, _C_HOLD, _C_SUSPECT, _C_CONFIRM, _C_WARMUP,
 _C_N, _C_GATE, _C_NOISE_ALPHA, _C_LAM_TILT, _C_TILT_MIN,
 _C_HOLD_VALVE) = 0, 1, 2, 4, 6, 8, 10, 12, 13, 14, 15, 16, 17, 18
_NCFG = 19
# its state (float64 array): a header; per hypothesis of the open and loss families (h = 2 n) the
# short window's A and B, the CUSUM, its A and B since it last left zero, and whether it was
# raised; per thruster (tilt hypothesis h + j) whether its tilt was raised (right after the open and
# loss families' flags: one flag per hypothesis, h + n in a row) and its window's 2 x 2 A (a11, a12,
# a22) and B (b1, b2); while a long candidate is confirmed, every tilt's sums (5 n) and every open and
# loss hypothesis' A and B (2 h) since it was raised; per thruster the loss CUSUM's rho (n,
# :func:`follow`); per hypothesis of the open and loss families the gross CUSUM, its A and B since it
# last left zero (:data:`GROSS_THETA`); the faults (:data:`_NF` numbers each); the alarm rows
# (:data:`EVENT_FIELDS`)
_S_UPDATES, _S_EVENTS, _S_BEST, _S_RUN, _S_LEARN, _S_NFAULTS, _S_OPEN, _S_CLOSED, _S_CLEARED, _S_NOISE, _S_HDR = (
    0, 1, 2, 4, 6, 7, 8, 9, 10, 11, 12)
_A, _B, _CU, _CA, _CB, _RAISED = range(6)        # blocks of h = 2 n numbers after the header
MAX_FAULTS = 4
# a fault: its hypothesis, A and B since it was raised, the size that raised it, updates since,
# when it was detected (ns), the detector (SHORT, LONG), its statistic, its stage, its type once
# confirmed; for a fault in the filter the recovery test's A and B (a stuck valve: short window; a
# partial loss: since its CUSUM last left zero), its run, when the run began (ns), and the CUSUM;
# a tilt's 2 x 2 A and B since it was raised, and the second angle of the size that raised it; a long
# loss candidate's rho when raised (the part of its loss the filter had not learnt: 1 for the others);
# an open or loss candidate of the long window: its CUSUM's A and B when raised (since the CUSUM last
# left zero, about the onset), pooled into its size when it is confirmed
(_F_HYP, _F_A, _F_B, _F_THETA0, _F_COUNT, _F_T, _F_WIN, _F_STAT, _F_STAGE, _F_TYPE, _F_RA, _F_RB, _F_RRUN,
 _F_RT, _F_RC, _F_T11, _F_T12, _F_T22, _F_T1, _F_T2, _F_THETA0B, _F_RHO, _F_PA, _F_PB) = range(24)
_NF = 24
_F_BIAS0 = _F_T11      # a leak in the filter: the bias states' part along its wrench when confirmed (a tilt's place)
CONFIRMING, IN_FILTER, IN_DETECTOR, TO_FILTER, CLEARED_STAGE, TO_CLEAR, DISMISSED = 0, 1, 2, 3, 4, 5, 6
GROSS_THETA = 1.0
"""The size (of nominal thrust) the short detector's CUSUM is tuned for: a stuck valve. Its
increments ``b - a/2`` are about ``-a/2`` while healthy, so its sums ``A``, ``B`` since it last left
zero begin at about the onset. The short window's forgetting mixes the healthy updates before the
onset into its ``A`` and ``B``: a valve stuck closed at a 9 ms pulse, then idle (the checkout's
thruster 7), carried a statistic ``B^2/A`` of about 370 and a size of 1, which the 0.1 s window
diluted to 95 and 0.27, below both its threshold and its smallest size. It speaks for the short
detector only where :func:`_gross` says so (:data:`GROSS_FLOOR`, :data:`GROSS_MIN_SIZE`, the window's
best hypothesis): then the short detector's statistic and size are this CUSUM's ``B^2/A`` and
``B/A``, and a fault it raises starts its own sums from the CUSUM's (:func:`observe`): a valve idle
after the pulse is sized on the pulse, not on the first updates of its next command."""
GROSS_FLOOR = 80.0
"""The gross CUSUM's ``B^2/A`` counts for the short detector only above this (and above the
window's). Healthy capture, three_arm and checkout sessions (47, 2026-11-27) peak at 24-45 on it,
partly above the window's suspicion level of 40; the checkout's thruster 7, stuck closed, reached
about 370 after a 9 ms pulse."""
GROSS_MIN_SIZE = 0.8
"""... and only at this size or more (of nominal thrust; a stuck valve's is about 1), and only for
the hypothesis the short window fits best. Without these two (``KERNELS`` 12-13) a 30 % leak in
the capture family was raised as another thruster stuck open in 15 of 18 runs: the part of a
persistent leak along a correlated hypothesis (thruster 12's open for thruster 10's leak, size
0.58) grows a CUSUM without bound, where the window's statistic stays bounded; the gross CUSUM was
then off (``KERNELS`` 14)."""
GATE = 80.0
"""The largest normalised innovation squared ``e^T S^-1 e`` (6 degrees of freedom) of an IMU sample
the filter learns from when no fault is suspected. The sample that first shows a gross fault comes
before the detector has seen it: a stuck-closed valve that had fired only four times before lost a
third of its nominal wrench to the filter in that one update, and was then typed a partial loss.
Healthy capture and three_arm sessions peak at 44-62; the first sample of a valve stuck at its
firing gives 110-150. (A constant, not an :class:`FdiSettings` field: those are configuration keys
of the gateway, each documented in gateway/config.py.)"""
NOISE_TAU_S = 2.0
"""Time constant of the innovation's measured noise level (:func:`noise_level`): the mean of
``e^T S^-1 e / m`` over the healthy updates, a running mean over the first ones (the warm-up) and
an exponential one of this time constant after. Healthy capture and three_arm sessions of the
scenarios' sensor classes end at 1.78-1.86 (seeds 500-502; the filter's noise figures are the IMU's
alone, the F/T sensors' noise and the model's errors come on top); ``bsc demo``'s noise sweep: 0.58
(x0.5), 6.5 (x2), 26 (x4). A noisier sensor raised every statistic and normalised innovation by as
much: at x4 the gate held most healthy samples and the suspicion held the filter (the thruster
force went from 3.58 to 7.36 % NRMSE). So above a level of :data:`NOISE_REF` (where the
detectors' thresholds and the gate were set, on those healthy sessions) the filter's IMU noise
variances scale with it (:func:`r_scale`, :func:`imu_update`), and with them its innovation
covariance and every statistic the detectors whiten by it."""
NOISE_REF = 2.0                        # the noise level the thresholds and the gate were set at (healthy: 1.8)
NOISE_CLIP = 4.0                       # an update adds at most this multiple of the current level
RELEARN_SIGMA = 0.05                   # a partial loss put into the filter: its wrench's new sigma, of nominal
TAKEOVER_MARGIN = 4.0                  # another hypothesis takes over a long candidate by this much more
RHO_MIN = 0.25                         # a loss CUSUM whose loss the filter learnt all but this of restarts
EVENT_FIELDS = ("t_ns", "thruster", "type", "theta", "stat", "window", "detected_t_ns")
_NEV = len(EVENT_FIELDS)


@dataclass(frozen=True)
class FdiSettings:
    """The two detectors' settings.

    Short (gross faults): a GLR over an exponentially forgetting window of ``short_s``, alarm at
    ``h_short`` (chi-squared, 1 degree of freedom while healthy; the innovation is not quite
    white, the gyro differences being MA(1); healthy capture sessions peak near 20) for a size
    of at least ``theta_min_short``. Long (partial losses, leaks): per hypothesis a CUSUM of the
    log-likelihood ratio for a fault of size ``theta1`` (fraction of nominal thrust), which
    restarts by itself while healthy, so an onset anywhere in the session is found without
    diluting its evidence with the healthy part; alarm at ``h_long`` for a size (estimated since
    the CUSUM last left zero) of at least ``theta_min_long``. ``hold_*``: updates in a row with
    the same best hypothesis above threshold; ``confirm_*``: updates after that over which the
    fault's size is estimated on its own, which gives the type; ``suspect``: above it (short
    GLR) or above 3/4 of ``h_long`` (CUSUM) the filter stops learning (a fault must not be learnt
    into the healthy model while it is being decided); ``warmup_s``: no alarm while the filter
    converges from its prior. Otherwise the filter learns from an IMU sample only when its
    normalised innovation squared is at most :data:`GATE`.

    Misalignment changes (a thruster's direction tilted): per thruster a GLR of the tilt, two
    angles across its nominal direction, over an exponentially forgetting window of ``tilt_s``;
    its log-likelihood ratio (half the statistic, chi-squared with 2 degrees of freedom while
    healthy) competes with the CUSUMs of the long detector, under its threshold, hold and
    confirmation, for a tilt of at least ``tilt_min_deg``.

    ``hold_valve``: a valve whose loss CUSUM is above it keeps its learned wrench while the rest of
    the filter learns (:func:`holding`, a Schmidt "consider" update in
    :func:`.thruster_kernel.imu_tap`); 0 turns this off. Without it a valve that fires alone, or
    in few combinations, is the filter's only explanation of its missing thrust: the filter learnt
    a 15 % loss before its CUSUM reached the suspicion level, and the loss went unnamed."""

    short_s: float = 0.1
    h_short: float = 200.0
    theta_min_short: float = 0.5
    hold_short: int = 25
    confirm_short: int = 50
    theta1: float = 0.1
    h_long: float = 40.0
    theta_min_long: float = 0.05
    hold_long: int = 50
    confirm_long: int = 250
    suspect: float = 40.0
    warmup_s: float = 0.2
    tilt_s: float = 0.5
    tilt_min_deg: float = 3.0
    hold_valve: float = 10.0

    def config(self, n: int, imu_period_s: float) -> np.ndarray:
        c = np.zeros(_NCFG)
        c[_C_LAM] = math.exp(-imu_period_s / self.short_s)
        c[_C_THETA1] = self.theta1
        c[_C_H], c[_C_H + 1] = self.h_short, self.h_long
        c[_C_THETA_MIN], c[_C_THETA_MIN + 1] = self.theta_min_short, self.theta_min_long
        c[_C_HOLD], c[_C_HOLD + 1] = self.hold_short, self.hold_long
        c[_C_SUSPECT], c[_C_SUSPECT + 1] = self.suspect, 0.75 * self.h_long
        c[_C_CONFIRM], c[_C_CONFIRM + 1] = self.confirm_short, self.confirm_long
        c[_C_WARMUP] = round(self.warmup_s / imu_period_s)
        c[_C_N] = n
        c[_C_GATE] = GATE
        c[_C_NOISE_ALPHA] = imu_period_s / NOISE_TAU_S
        c[_C_LAM_TILT] = math.exp(-imu_period_s / self.tilt_s)
        c[_C_TILT_MIN] = math.radians(self.tilt_min_deg)
        c[_C_HOLD_VALVE] = self.hold_valve if self.hold_valve > 0.0 else math.inf
        return c


@_jit
def _fault_base(n: int) -> int:
    """Where the fault records begin in the state of ``n`` thrusters (:func:`_offsets`)."""
    return _gross_base(n) + 3 * 2 * n


@_jit
def _gross_base(n: int) -> int:
    """Where the gross CUSUMs (``3 h``: the CUSUMs, then their ``A``, then their ``B``) are in the state."""
    return _S_HDR + 6 * 2 * n + 16 * n


@_jit
def _rho_base(n: int) -> int:
    """Where the loss CUSUMs' ``rho`` (one per thruster) are in the state."""
    return _S_HDR + 6 * 2 * n + 15 * n


def _offsets(n: int) -> tuple[int, int, int]:
    faults = int(_fault_base(n))
    return _S_HDR, faults, faults + _NF * MAX_FAULTS


SIG_COLS = 18
"""Columns of the detector's per-thruster signature table (:func:`signatures`)."""


def signatures(layout: ThrusterLayout, W: np.ndarray) -> np.ndarray:
    """The detector's table of what each thruster's faults look like, ``(n, 18)``: its nominal
    wrench ``W[j]`` (the filter's prior, ``[force; moment about C]``), then what tilting its thrust
    by one radian adds, towards ``u1`` (the body axis most perpendicular to its direction, made
    perpendicular) and towards ``u2 = d x u1``: ``F [u_k; p x u_k]`` (``F`` its nominal thrust,
    ``p`` its position). The position along the thrust axis changes the moment of a tilt and
    cannot be read off ``W``: hence the layout."""
    n = layout.n
    out = np.zeros((n, SIG_COLS))
    out[:, :6] = W
    for j in range(n):
        d = np.asarray(layout.dir[j], dtype=float)
        d = d / math.sqrt(float(d @ d))
        e = np.eye(3)[int(np.argmin(np.abs(d)))]
        u1 = e - (e @ d) * d
        u1 /= math.sqrt(float(u1 @ u1))
        u2 = np.cross(d, u1)
        for k, u in enumerate((u1, u2)):
            f = float(layout.max_n[j]) * u
            out[j, 6 + 6 * k:12 + 6 * k] = np.concatenate([f, np.cross(layout.pos_m[j], f)])
    return np.ascontiguousarray(out)


def state_size(n: int, max_events: int) -> int:
    """Length of the detector's state for ``n`` thrusters and room for ``max_events`` alarms."""
    return _offsets(n)[2] + _NEV * max_events


def new_state(n: int, max_events: int = 64) -> np.ndarray:
    st = np.zeros(state_size(n, max_events))
    st[_S_BEST], st[_S_BEST + 1] = -1.0, -1.0
    st[_S_LEARN] = math.inf
    st[_S_NOISE] = 1.0
    rb = int(_rho_base(n))
    st[rb:rb + n] = 1.0
    return st


@_jit
def _whiten(L: F64, m: int, v: F64, out: F64) -> None:
    """``out = L^-1 v``."""
    for r in range(m):
        a = v[r]
        for k in range(r):
            a -= L[r, k] * out[k]
        out[r] = a / L[r, r]


@_jit
def _signature(Wnom: F64, Ha: F64, tap: F64, n: int, m: int, j: int, fam: int, g: F64, cmd: bool = False) -> None:
    """The innovation a fault of family ``fam`` of thruster ``j`` of size 1 would cause (m,), the
    valve as the filter takes it, or as commanded (``cmd``)."""
    off = tk.TAP_VALVES + (2 * n if cmd else 0)
    vbar = tap[off + j]
    vt = tap[off + n + j]
    ca = (1.0 - vbar) if fam == OPEN else -vbar
    cg = (1.0 - vt) if fam == OPEN else -vt
    for r in range(3):
        acc = 0.0
        for q in range(6):
            acc += Ha[6 * r + q] * Wnom[j, q]
        g[r] = ca * acc
    for r in range(3):
        g[3 + r] = cg * Wnom[j, 3 + r] if m == 6 else 0.0


@_jit
def _project(Wnom: F64, Ha: F64, tap: F64, L: F64, n: int, m: int, j: int, fam: int, ew: F64, g: F64, gw: F64,
             cmd: bool = False) -> tuple[float, float]:
    """A hypothesis' whitened signature into ``gw`` (:func:`_signature`, ``L^-1 g``) and its two
    sums with the whitened innovation ``ew``: ``(g^T S^-1 g, g^T S^-1 e)``."""
    _signature(Wnom, Ha, tap, n, m, j, fam, g, cmd)
    _whiten(L, m, g, gw)
    a = 0.0
    b = 0.0
    for r in range(m):
        a += gw[r] * gw[r]
        b += gw[r] * ew[r]
    return a, b


@_jit
def _tilt_project(Wnom: F64, Ha: F64, tap: F64, L: F64, n: int, m: int, j: int, ew: F64, g: F64, gw: F64,
                  gw2: F64) -> tuple[float, float, float, float, float]:
    """Thruster ``j``'s two whitened tilt signatures (:func:`signatures`' columns 6-17, seen while
    the valve is open as the filter takes it) into ``gw`` and ``gw2``, and their sums with each
    other and with the whitened innovation: ``(a11, a12, a22, b1, b2)``."""
    vbar = tap[tk.TAP_VALVES + j]
    vt = tap[tk.TAP_VALVES + n + j]
    for k in range(2):
        c0 = 6 + 6 * k
        for r in range(3):
            acc = 0.0
            for q in range(6):
                acc += Ha[6 * r + q] * Wnom[j, c0 + q]
            g[r] = vbar * acc
        for r in range(3):
            g[3 + r] = vt * Wnom[j, c0 + 3 + r] if m == 6 else 0.0
        _whiten(L, m, g, gw if k == 0 else gw2)
    a11 = 0.0
    a12 = 0.0
    a22 = 0.0
    b1 = 0.0
    b2 = 0.0
    for r in range(m):
        a11 += gw[r] * gw[r]
        a12 += gw[r] * gw2[r]
        a22 += gw2[r] * gw2[r]
        b1 += gw[r] * ew[r]
        b2 += gw2[r] * ew[r]
    return a11, a12, a22, b1, b2


@_jit
def _solve2(a11: float, a12: float, a22: float, b1: float, b2: float) -> tuple[float, float, float]:
    """``phi = A^-1 b`` of a symmetric 2 x 2 ``A`` and the statistic ``b^T A^-1 b`` (zeros when
    ``A`` is singular)."""
    det = a11 * a22 - a12 * a12
    if not det > 1e-12 * (a11 * a22 + 1e-300):
        return 0.0, 0.0, 0.0
    p1 = (a22 * b1 - a12 * b2) / det
    p2 = (a11 * b2 - a12 * b1) / det
    return p1, p2, p1 * b1 + p2 * b2


@_jit
def _tilt_solve(st: F64, base: int, stride: int) -> tuple[float, float, float]:
    """:func:`_solve2` of a tilt's five sums ``(a11, a12, a22, b1, b2)`` kept at ``base`` every ``stride``."""
    return _solve2(st[base], st[base + stride], st[base + 2 * stride], st[base + 3 * stride], st[base + 4 * stride])


@_jit
def _tilt_add(st: F64, base: int, stride: int, lam: float, a11: float, a12: float, a22: float, b1: float,
              b2: float) -> None:
    """A tilt's five sums at ``base`` every ``stride`` times ``lam``, plus the update's."""
    st[base] = lam * st[base] + a11
    st[base + stride] = lam * st[base + stride] + a12
    st[base + 2 * stride] = lam * st[base + 2 * stride] + a22
    st[base + 3 * stride] = lam * st[base + 3 * stride] + b1
    st[base + 4 * stride] = lam * st[base + 4 * stride] + b2


@_jit
def _norm2(Wnom: F64, j: int, c0: int) -> float:
    """The squared norm of thruster ``j``'s nominal force (``c0`` 0) or moment (3)."""
    return float(Wnom[j, c0] * Wnom[j, c0] + Wnom[j, c0 + 1] * Wnom[j, c0 + 1] + Wnom[j, c0 + 2] * Wnom[j, c0 + 2])


@_jit
def _takes_over(llr: float, own: float, last: bool) -> bool:
    """Whether a hypothesis of log-likelihood ratio ``llr`` explains the same updates better than the
    candidate's ``own``: by :data:`TAKEOVER_MARGIN` plus twice the ratio's noise, ``sqrt(2 llr)``
    (``2 llr`` is a non-central chi-squared of variance about ``4 llr``); at the ``last`` decision
    by the margin alone. On the real path, 0.5 s after it was raised, a 10 % leak of thruster 4
    scored 117 against a leak of 8 (126) and a tilt of 1 (128): not yet a decision; a tilt of
    thruster 2 against the leak of 11 it looks like, 1100 against 990: a decision."""
    noise = 0.0 if last else 2.0 * math.sqrt(2.0 * llr)
    return bool(llr - own > TAKEOVER_MARGIN + noise)


@_jit
def _theta(st: F64, o: int) -> float:
    """A fault's size: the window's until it is confirmed, then its own estimate since raised."""
    if st[o + _F_STAGE] == CONFIRMING or st[o + _F_A] <= 0.0:
        theta: float = st[o + _F_THETA0]
    else:
        theta = st[o + _F_B] / st[o + _F_A]
    return theta


@_jit
def _stuck_theta(fam: int) -> float:
    """The smallest size of a stuck valve in family ``fam``: a leak or loss below it is partial."""
    return OPEN_THETA if fam == OPEN else CLOSED_THETA


@_jit
def _fault_type(fam: int, theta: float) -> int:
    if fam == OPEN:
        return STUCK_OPEN if theta >= _stuck_theta(fam) else LEAK
    return STUCK_CLOSED if theta >= _stuck_theta(fam) else PARTIAL_LOSS


@_jit
def _stats(st: F64, h_all: int, w: int, k: int) -> tuple[float, float]:
    """(statistic, size) of hypothesis k in detector w."""
    if w == SHORT:
        A = st[_S_HDR + _A * h_all + k]
        B = st[_S_HDR + _B * h_all + k]
        T = 0.0
        theta = 0.0
        if A > 0.0 and B > 0.0:
            T = B * B / A
            theta = B / A
        return T, theta
    A = st[_S_HDR + _CA * h_all + k]
    B = st[_S_HDR + _CB * h_all + k]
    return st[_S_HDR + _CU * h_all + k], (B / A if A > 0.0 else 0.0)


@_jit
def _gross(st: F64, h_all: int, k: int, T: float) -> bool:
    """Whether the gross CUSUM of hypothesis ``k``, the short window's best at ``T``, speaks for
    the short detector: above :data:`GROSS_FLOOR` and ``T``, at a stuck valve's size
    (:data:`GROSS_MIN_SIZE`)."""
    g = _gross_base(h_all // 2) + k
    if st[g] <= 0.0:                              # else B > A / 2 > 0
        return False
    GA = st[g + h_all]
    GB = st[g + 2 * h_all]
    return bool(GB * GB / GA > max(T, GROSS_FLOOR) and GB / GA >= GROSS_MIN_SIZE)


@_jit
def _best(st: F64, h_all: int, w: int) -> tuple[int, float, float]:
    """The hypothesis with the largest statistic of detector ``w``, that statistic and its size
    (-1, 0.0, 0.0: none above zero). The short detector's is its window's best, whose gross CUSUM
    takes the statistic and size over where :func:`_gross` says so: only the hypothesis the
    window fits best, so a correlated one cannot take a fault that is another's."""
    best = -1
    best_t = 0.0
    theta = 0.0
    for k in range(h_all):
        T, th = _stats(st, h_all, w, k)
        if T > best_t:
            best_t = T
            best = k
            theta = th
    if w == SHORT and best >= 0 and _gross(st, h_all, best, best_t):
        g = _gross_base(h_all // 2) + best
        best_t = st[g + 2 * h_all] * st[g + 2 * h_all] / st[g + h_all]
        theta = st[g + 2 * h_all] / st[g + h_all]
    return best, best_t, theta


@_jit
def _event(st: F64, ev0: int, t_ns: float, j: int, typ: int, theta: float, stat: float, win: float,
           since_ns: float) -> None:
    """Append an alarm row (:data:`EVENT_FIELDS`) when there is room."""
    ne = int(st[_S_EVENTS])
    if ev0 + _NEV * (ne + 1) <= st.shape[0]:
        q = ev0 + _NEV * ne
        st[q] = t_ns
        st[q + 1] = j
        st[q + 2] = typ
        st[q + 3] = theta
        st[q + 4] = stat
        st[q + 5] = win
        st[q + 6] = since_ns
        st[_S_EVENTS] = ne + 1


@_jit
def _restart(st: F64, h_all: int) -> None:
    """Both detectors from zero (the filter's model of the faults changed)."""
    for k in range(5 * h_all):
        st[_S_HDR + k] = 0.0
    n = h_all // 2
    for k in range(n, 6 * n):                     # the tilts' sums (not their flags)
        st[_S_HDR + 6 * h_all + k] = 0.0
    g = _gross_base(n)
    for k in range(3 * h_all):
        st[g + k] = 0.0
    for w in range(2):
        st[_S_BEST + w] = -1.0
        st[_S_RUN + w] = 0.0
    rb = _rho_base(n)
    for j in range(n):
        st[rb + j] = 1.0


@_jit_alloc
def observe(st: F64, cfg: F64, Wnom: F64, Ha: F64, tap: F64, t_ns: int) -> float:
    """One IMU update's innovation ``tap`` (:func:`.thruster_kernel.imu_tap`) at ``t_ns`` into the
    detector state ``st``. Returns what the filter may learn from the next update, its ``learn``
    (:func:`learning`): 0.0 while a fault is suspected or being confirmed, else the innovation
    gate (``math.inf`` during the warm-up). Confirmed alarms are appended to the state's alarm
    rows (:func:`events`); a confirmed fault is then the filter's to model (:func:`valve_mask`,
    :func:`accommodate`). ``Wnom`` (n, 6): nominal valve wrenches ``[force; moment about C]``
    (body frame; N, N m); ``Ha`` (18,): the accelerometer rows' map of a wrench, row-major 3 x 6.

    A raised fault is confirmed ``confirm`` updates later, its type from its size estimated over
    those updates alone. Until the filter models it, its signature times its size is taken out
    of the innovation the other hypotheses see."""
    if tap[tk.TAP_APPLIED] == 0.0:
        return float(st[_S_LEARN])
    n = int(cfg[_C_N])
    h_all = 2 * n
    tb = _S_HDR + 6 * h_all                   # the tilts' block: flags, then their sums
    tr = tb + 6 * n                           # the tilts' sums since a long candidate was raised
    tq = tr + 5 * n                           # ... and the open and loss hypotheses' A and B
    rb = tq + 2 * h_all                       # the loss CUSUMs' rho
    gb = _gross_base(n)                       # the gross CUSUMs
    fbase = _fault_base(n)
    ev0 = fbase + _NF * MAX_FAULTS
    m = int(tap[tk.TAP_ROWS])
    S = tap[tk.TAP_S:tk.TAP_S + 36].reshape((6, 6))      # row-major, stride 6
    L = np.zeros((6, 6))
    if not tk.cholesky(S, m, L):
        return float(st[_S_LEARN])
    # the innovation's measured noise level, when above the thresholds' (NOISE_REF): the filter's
    # IMU noise was k times its configured variance in this update (r_scale, set by imu_update),
    # so S, every statistic whitened by it and the gate's normalised innovation already carry k
    k_noise = r_scale(st)
    e = np.zeros(6)
    for r in range(m):
        e[r] = tap[tk.TAP_E + r]
    ew = np.zeros(6)
    g = np.zeros(6)
    gw = np.zeros(6)
    gw2 = np.zeros(6)
    _whiten(L, m, e, ew)
    # faults the filter does not model: their sizes from the raw innovation, then out of it
    nf = int(st[_S_NFAULTS])
    confirming = False
    for f in range(nf):
        o = fbase + _NF * f
        leak_in_filter = st[o + _F_STAGE] == IN_FILTER and st[o + _F_TYPE] == LEAK
        if st[o + _F_STAGE] != CONFIRMING and st[o + _F_STAGE] != IN_DETECTOR and not leak_in_filter:
            continue
        hyp = int(st[o + _F_HYP])
        if st[o + _F_WIN] == LONG and st[o + _F_STAGE] == CONFIRMING:
            # every hypothesis on the same innovation, since the candidate was raised
            for j in range(n):
                a11, a12, a22, b1, b2 = _tilt_project(Wnom, Ha, tap, L, n, m, j, ew, g, gw, gw2)
                _tilt_add(st, tr + j, n, 1.0, a11, a12, a22, b1, b2)
                for fam in range(2):
                    a, b = _project(Wnom, Ha, tap, L, n, m, j, fam, ew, g, gw)
                    rj = st[rb + j] if fam == LOSS else 1.0
                    st[tq + 2 * j + fam] += rj * rj * a
                    st[tq + h_all + 2 * j + fam] += rj * b
        if hyp >= h_all:                          # a tilt: its 2 x 2 sums
            a11, a12, a22, b1, b2 = _tilt_project(Wnom, Ha, tap, L, n, m, hyp - h_all, ew, g, gw, gw2)
            _tilt_add(st, o + _F_T11, 1, 1.0, a11, a12, a22, b1, b2)
            continue
        a, b = _project(Wnom, Ha, tap, L, n, m, hyp // 2, hyp % 2, ew, g, gw)
        rj = st[o + _F_RHO]
        a *= rj * rj
        b *= rj
        if leak_in_filter:
            # the filter's measurement is corrected for the leak at its current size: its size
            # refined on the innovation with that part added back (least squares since raised)
            b += (st[o + _F_B] / st[o + _F_A]) * a
        st[o + _F_A] += a
        st[o + _F_B] += b
    for f in range(nf):
        o = fbase + _NF * f
        if st[o + _F_STAGE] != CONFIRMING and st[o + _F_STAGE] != IN_DETECTOR:
            continue
        hyp = int(st[o + _F_HYP])
        if hyp >= h_all:
            p1, p2, _ = _tilt_solve(st, o + _F_T11, 1)
            if st[o + _F_STAGE] == CONFIRMING and st[o + _F_T11] <= 0.0:
                p1 = st[o + _F_THETA0]            # the window's estimate until its own has data
                p2 = st[o + _F_THETA0B]
            _tilt_project(Wnom, Ha, tap, L, n, m, hyp - h_all, ew, g, gw, gw2)
            for r in range(m):
                ew[r] -= p1 * gw[r] + p2 * gw2[r]
        else:
            th = _theta(st, o) * st[o + _F_RHO]
            _signature(Wnom, Ha, tap, n, m, hyp // 2, hyp % 2, g)
            _whiten(L, m, g, gw)
            for r in range(m):
                ew[r] -= th * gw[r]
        if st[o + _F_STAGE] != CONFIRMING:
            continue
        st[o + _F_COUNT] += 1.0
        confirm = cfg[_C_CONFIRM + int(st[o + _F_WIN])]
        if (st[o + _F_WIN] == LONG and hyp < h_all and st[o + _F_A] > 0.0
                and st[o + _F_THETA0] >= _stuck_theta(hyp % 2)):
            # a stuck valve the long window raised first (a short pulse at the onset, then idle: the
            # short window's size was diluted below its smallest) is a gross fault: once it has
            # data of its own, the short window's confirmation, not the long one's 0.5 s for a
            # partial loss's size (with none, an alternative would be weighed against nothing)
            confirm = cfg[_C_CONFIRM + SHORT]
        if st[o + _F_COUNT] < confirm:
            confirming = True
            continue
        if st[o + _F_WIN] == LONG:
            # which hypothesis explains the innovation since the candidate was raised best, by
            # log-likelihood ratio? The CUSUM raises the first to cross, and a correlated one can be
            # first (a tilt can look like another thruster's leak while its valve is open, not while
            # it is closed); another takes over by a margin beyond the ratio's noise (its standard
            # deviation is about sqrt(2 llr)), a tilt above the long threshold too
            if hyp < h_all:
                B0 = st[o + _F_B]
                own = 0.5 * B0 * B0 / st[o + _F_A] if st[o + _F_A] > 0.0 and B0 > 0.0 else 0.0
            else:
                own = 0.5 * _tilt_solve(st, o + _F_T11, 1)[2]
            # an alternative better but within the noise: keep measuring (up to 4 confirm periods),
            # then the margin alone decides
            last = st[o + _F_COUNT] >= 4.0 * confirm
            best = -1
            best_llr = own
            close = False
            for k in range(h_all):
                A = st[tq + k]
                B = st[tq + h_all + k]
                llr = 0.5 * B * B / A if A > 0.0 and B > 0.0 else 0.0
                if (k == hyp or llr <= best_llr or st[_S_HDR + _RAISED * h_all + k] != 0.0
                        or B / A < cfg[_C_THETA_MIN + LONG]):
                    continue
                if _takes_over(llr, own, last):
                    best = k
                    best_llr = llr
                else:
                    close = True
            for j in range(n):
                p1, p2, T = _tilt_solve(st, tr + j, n)
                llr = 0.5 * T
                if (h_all + j == hyp or llr <= best_llr or llr <= cfg[_C_H + LONG]
                        or st[_S_HDR + _RAISED * h_all + h_all + j] != 0.0
                        or math.sqrt(p1 * p1 + p2 * p2) < cfg[_C_TILT_MIN]):
                    continue
                if _takes_over(llr, own, last):
                    best = h_all + j
                    best_llr = llr
                else:
                    close = True
            if best < 0 and close:
                confirming = True
                continue
            if best >= 0:
                st[_S_HDR + _RAISED * h_all + hyp] = 0.0
                st[_S_HDR + _RAISED * h_all + best] = 1.0
                hyp = best
                st[o + _F_HYP] = hyp
                st[o + _F_STAT] = best_llr
                st[o + _F_PA] = 0.0               # the CUSUM's sums were the raised hypothesis'
                st[o + _F_PB] = 0.0
                if hyp < h_all:
                    st[o + _F_A] = st[tq + hyp]
                    st[o + _F_B] = st[tq + h_all + hyp]
                    st[o + _F_RHO] = st[rb + hyp // 2] if hyp % 2 == LOSS else 1.0
                else:
                    j = hyp - h_all
                    for k in range(5):
                        st[o + _F_T11 + k] = st[tr + k * n + j]
        if hyp >= h_all:
            # a tilt, measured on its own since raised: below the smallest tilt alarmed it is
            # dismissed (as below), else a misalignment, its angle in degrees, for the filter
            p1, p2, _ = _tilt_solve(st, o + _F_T11, 1)
            ang = math.sqrt(p1 * p1 + p2 * p2)
            st[_S_HDR + _RAISED * h_all + hyp] = 0.0 if ang < cfg[_C_TILT_MIN] else 1.0
            if ang < cfg[_C_TILT_MIN]:
                st[o + _F_STAGE] = DISMISSED
                st[_S_CLEARED] += 1.0
            else:
                st[o + _F_TYPE] = MISALIGNMENT
                _event(st, ev0, float(t_ns), hyp - h_all, MISALIGNMENT, math.degrees(ang), st[o + _F_STAT],
                       st[o + _F_WIN], st[o + _F_T])
                st[o + _F_STAGE] = TO_FILTER
            _restart(st, h_all)
            continue
        if st[o + _F_A] <= 0.0 and st[o + _F_WIN] == SHORT:
            # nothing measured since the short window raised it (A 0: a loss of a valve not
            # commanded since). That window's size is low: it mixes in the healthy updates before
            # the onset (a valve stuck closed at a 20-30 ms pulse, then idle: 0.60-0.73, a partial
            # loss). The long detector's CUSUM of the same hypothesis measures since it last left
            # zero, about the onset: the larger of the two
            ca = st[_S_HDR + _CA * h_all + hyp]
            if st[_S_HDR + _CU * h_all + hyp] > 0.0 and ca > 0.0:
                st[o + _F_THETA0] = max(st[o + _F_THETA0], st[_S_HDR + _CB * h_all + hyp] / ca)
        theta = st[o + _F_B] / st[o + _F_A] if st[o + _F_A] > 0.0 else st[o + _F_THETA0]
        # a long candidate's size: its own sums since raised pooled with its CUSUM's before (about
        # the onset on). A valve idle over most of the confirmation leaves few updates of its own
        # (a 10 % loss raised with A 6228 was typed on 72, one probe burst, and sized 0.33)
        pa = st[o + _F_A] + st[o + _F_PA]
        size = (st[o + _F_B] + st[o + _F_PB]) / pa if pa > 0.0 else theta
        # the type is a size test: while the size is within 3 of its standard errors
        # (1 / sqrt(A)) of the type's threshold, keep measuring (up to 4 confirm periods); with
        # nothing measured since the short window raised it, a size below the threshold waits for
        # the valve's next command (up to the same), one at or above it decides
        edge = _stuck_theta(hyp % 2)
        if (st[o + _F_COUNT] < 4.0 * confirm
                and ((st[o + _F_A] <= 0.0 and st[o + _F_WIN] == SHORT and theta < edge)
                     or (pa > 0.0 and abs(size - edge) * math.sqrt(pa) < 3.0))):
            confirming = True
            continue
        if theta < cfg[_C_THETA_MIN + int(st[o + _F_WIN])]:
            # measured on its own, the fault is below the smallest size its detector raises for
            # (at or below zero, it is none): a transient, not a fault; no alarm, it may be raised again
            st[o + _F_STAGE] = DISMISSED
            st[_S_CLEARED] += 1.0                # no longer unresolved (its slot is reused)
            st[_S_HDR + _RAISED * h_all + hyp] = 0.0
            _restart(st, h_all)
            continue
        st[o + _F_A] = pa                         # from now on the fault's size is the pooled one
        st[o + _F_B] += st[o + _F_PB]
        typ = _fault_type(hyp % 2, size)
        st[o + _F_TYPE] = typ
        _event(st, ev0, float(t_ns), hyp // 2, typ, size, st[o + _F_STAT], st[o + _F_WIN], st[o + _F_T])
        if typ == STUCK_OPEN:
            st[_S_OPEN] = float(int(st[_S_OPEN]) | (1 << (hyp // 2)))
            st[o + _F_STAGE] = TO_FILTER
        elif typ == STUCK_CLOSED:
            st[_S_CLOSED] = float(int(st[_S_CLOSED]) | (1 << (hyp // 2)))
            st[o + _F_STAGE] = IN_FILTER
        elif typ == PARTIAL_LOSS:
            st[o + _F_STAGE] = TO_FILTER
        else:
            st[o + _F_STAGE] = TO_FILTER       # a leak: the filter's measurement corrected for it (leaks())
        _restart(st, h_all)                   # the detectors restart on the accommodated innovation
    # the noise level from this update, the unmodelled faults taken out: in the warm-up a running
    # mean, then an exponential one over healthy updates (not while a fault is suspected: the
    # last verdict held the filter), each update clipped to NOISE_CLIP times the level
    nis = 0.0
    for r in range(m):
        nis += ew[r] * ew[r]
    nis = nis * k_noise / m
    lvl = st[_S_NOISE]
    if nis > NOISE_CLIP * lvl:
        nis = NOISE_CLIP * lvl
    if st[_S_UPDATES] < cfg[_C_WARMUP]:
        st[_S_NOISE] = lvl + (nis - lvl) / (st[_S_UPDATES] + 1.0)
    elif st[_S_LEARN] > 0.0:
        st[_S_NOISE] = lvl + cfg[_C_NOISE_ALPHA] * (nis - lvl)
    lam = cfg[_C_LAM]
    # stuck valves in the filter: has the valve come back? Its own signature with the opposite
    # sign (a valve modelled open that gives no thrust while commanded closed; one modelled
    # closed that thrusts while commanded open), the short detector's window, alarm and hold
    recovering = False
    for f in range(nf):
        o = fbase + _NF * f
        if st[o + _F_STAGE] != IN_FILTER or (st[o + _F_TYPE] != STUCK_OPEN and st[o + _F_TYPE] != STUCK_CLOSED):
            continue
        hyp = int(st[o + _F_HYP])
        j = hyp // 2
        a, b = _project(Wnom, Ha, tap, L, n, m, j, hyp % 2, ew, g, gw, True)
        st[o + _F_RA] = lam * st[o + _F_RA] + a
        st[o + _F_RB] = lam * st[o + _F_RB] + b
        A = st[o + _F_RA]
        B = st[o + _F_RB]
        T = B * B / A if A > 0.0 and B < 0.0 else 0.0
        back = -B / A if T > 0.0 else 0.0
        if T > cfg[_C_SUSPECT]:
            recovering = True
        if T <= cfg[_C_H] or back < cfg[_C_THETA_MIN]:
            st[o + _F_RRUN] = 0.0
            continue
        if st[o + _F_RRUN] == 0.0:
            st[o + _F_RT] = float(t_ns)
        st[o + _F_RRUN] += 1.0
        if st[o + _F_RRUN] < cfg[_C_HOLD]:
            continue
        _event(st, ev0, float(t_ns), j, CLEARED, back, T, SHORT, st[o + _F_RT])
        bit = 1 << j
        st[_S_OPEN] = float(int(st[_S_OPEN]) & ~bit)
        st[_S_CLOSED] = float(int(st[_S_CLOSED]) & ~bit)
        st[o + _F_STAGE] = TO_CLEAR
        st[_S_CLEARED] += 1.0
        st[_S_HDR + _RAISED * h_all + hyp] = 0.0       # it may fail again
        _restart(st, h_all)                             # the detectors restart on the valve as commanded
        recovering = True
    # partial losses and leaks in the filter: has the thrust come back (stopped)? Their own
    # signature with the opposite sign (more thrust than modelled while the valve is open; less
    # while it is closed), a CUSUM for the fault's own size: no other hypothesis explains it, and
    # leaks of other thrusters took a returned thrust
    for f in range(nf):
        o = fbase + _NF * f
        typ = st[o + _F_TYPE]
        if st[o + _F_STAGE] != IN_FILTER or (typ != PARTIAL_LOSS and typ != LEAK):
            continue
        hyp = int(st[o + _F_HYP])
        theta = st[o + _F_B] / st[o + _F_A] if st[o + _F_A] > 0.0 else st[o + _F_THETA0]
        a, b = _project(Wnom, Ha, tap, L, n, m, hyp // 2, hyp % 2, ew, g, gw)
        rc = st[o + _F_RC] - theta * b - 0.5 * theta * theta * a
        if rc <= 0.0:
            st[o + _F_RC] = 0.0
            st[o + _F_RA] = 0.0
            st[o + _F_RB] = 0.0
        else:
            st[o + _F_RC] = rc
            st[o + _F_RA] += a
            st[o + _F_RB] += b
        back = -st[o + _F_RB] / st[o + _F_RA] if st[o + _F_RA] > 0.0 else 0.0
        if st[o + _F_RC] > cfg[_C_SUSPECT + LONG]:
            recovering = True
        if st[o + _F_RC] <= cfg[_C_H + LONG] or back < 0.5 * theta:
            st[o + _F_RRUN] = 0.0
            continue
        if st[o + _F_RRUN] == 0.0:
            st[o + _F_RT] = float(t_ns)
        st[o + _F_RRUN] += 1.0
        if st[o + _F_RRUN] < cfg[_C_HOLD + LONG]:
            continue
        _event(st, ev0, float(t_ns), hyp // 2, CLEARED, back, st[o + _F_RC], LONG, st[o + _F_RT])
        # a partial loss: its lost part goes back on the valve's wrench (accommodate); a leak was
        # never in the filter's state, only in its measurement (leaks()): it is simply gone
        st[o + _F_STAGE] = TO_CLEAR if typ == PARTIAL_LOSS else CLEARED_STAGE
        st[_S_CLEARED] += 1.0
        st[_S_HDR + _RAISED * h_all + hyp] = 0.0        # it may be lost again
        _restart(st, h_all)                             # the detectors restart on the thrust restored
        recovering = True
    st[_S_UPDATES] += 1.0
    upd = st[_S_UPDATES]
    th1 = cfg[_C_THETA1]
    for j in range(n):
        for fam in range(2):
            a, b = _project(Wnom, Ha, tap, L, n, m, j, fam, ew, g, gw)
            k = 2 * j + fam
            st[_S_HDR + _A * h_all + k] = lam * st[_S_HDR + _A * h_all + k] + a
            st[_S_HDR + _B * h_all + k] = lam * st[_S_HDR + _B * h_all + k] + b
            gu = st[gb + k] + GROSS_THETA * b - 0.5 * GROSS_THETA * GROSS_THETA * a
            if gu <= 0.0:
                st[gb + k] = 0.0
                st[gb + h_all + k] = 0.0
                st[gb + 2 * h_all + k] = 0.0
            else:
                st[gb + k] = gu
                st[gb + h_all + k] += a
                st[gb + 2 * h_all + k] += b
            if fam == LOSS:                   # what the filter has not learnt of a loss since the onset
                rj = st[rb + j]
                a *= rj * rj
                b *= rj
            cu = st[_S_HDR + _CU * h_all + k] + th1 * b - 0.5 * th1 * th1 * a
            if cu <= 0.0:
                st[_S_HDR + _CU * h_all + k] = 0.0
                st[_S_HDR + _CA * h_all + k] = 0.0
                st[_S_HDR + _CB * h_all + k] = 0.0
                if fam == LOSS:
                    st[rb + j] = 1.0          # the onset is from the next update on
            else:
                st[_S_HDR + _CU * h_all + k] = cu
                st[_S_HDR + _CA * h_all + k] += a
                st[_S_HDR + _CB * h_all + k] += b
    lt = cfg[_C_LAM_TILT]
    for j in range(n):
        a11, a12, a22, b1, b2 = _tilt_project(Wnom, Ha, tap, L, n, m, j, ew, g, gw, gw2)
        _tilt_add(st, tb + n + j, n, lt, a11, a12, a22, b1, b2)
    if upd <= cfg[_C_WARMUP]:
        st[_S_LEARN] = math.inf
        return math.inf
    suspect = confirming or recovering
    gross = False
    for w in range(2):
        best, best_t, theta = _best(st, h_all, w)
        theta_min = cfg[_C_THETA_MIN + w]
        phi2 = 0.0
        if w == LONG:
            # the tilts compete with the CUSUMs by their log-likelihood ratio, half the GLR
            for j in range(n):
                p1, p2, T = _tilt_solve(st, tb + n + j, n)
                if 0.5 * T > best_t:
                    best, best_t, theta, phi2 = h_all + j, 0.5 * T, p1, p2
            if best >= h_all:
                theta_min = cfg[_C_TILT_MIN]
        if best_t > cfg[_C_SUSPECT + w]:
            suspect = True
            if w == SHORT and theta >= cfg[_C_THETA_MIN]:
                gross = True              # a gross fault is the short detector's to name: its GLR fits
        if w == LONG and gross:
            continue
        size = math.sqrt(theta * theta + phi2 * phi2) if best >= h_all else theta
        if best < 0 or best_t <= cfg[_C_H + w] or size < theta_min:
            st[_S_BEST + w] = -1.0
            st[_S_RUN + w] = 0.0
            continue
        if st[_S_BEST + w] == best:
            st[_S_RUN + w] += 1.0
        else:
            st[_S_BEST + w] = best
            st[_S_RUN + w] = 1.0
        slot = nf                                 # a dismissed fault's slot first
        for f in range(nf):
            if st[fbase + _NF * f + _F_STAGE] == DISMISSED:
                slot = f
                break
        if (st[_S_RUN + w] < cfg[_C_HOLD + w] or st[_S_HDR + _RAISED * h_all + best] != 0.0 or confirming
                or recovering or slot >= MAX_FAULTS):    # one decision at a time: a recovery looks like a new fault
            continue
        st[_S_HDR + _RAISED * h_all + best] = 1.0
        o = fbase + _NF * slot
        st[o + _F_HYP] = best
        st[o + _F_A] = 0.0
        st[o + _F_B] = 0.0
        if w == SHORT and _gross(st, h_all, best, _stats(st, h_all, w, best)[0]):
            # the gross CUSUM's sums since about the onset are the fault's first evidence: its size
            # is estimated on them and on what comes after (a valve idle after a short pulse has
            # nothing after)
            st[o + _F_A] = st[gb + h_all + best]
            st[o + _F_B] = st[gb + 2 * h_all + best]
        st[o + _F_THETA0] = theta
        st[o + _F_COUNT] = 0.0
        st[o + _F_T] = float(t_ns)
        st[o + _F_WIN] = w
        st[o + _F_STAT] = best_t
        st[o + _F_STAGE] = CONFIRMING
        st[o + _F_TYPE] = -1.0
        st[o + _F_RA] = 0.0
        st[o + _F_RB] = 0.0
        st[o + _F_RRUN] = 0.0
        st[o + _F_RT] = 0.0
        st[o + _F_RC] = 0.0
        for k in range(5):
            st[o + _F_T11 + k] = 0.0
        st[o + _F_THETA0B] = phi2
        st[o + _F_RHO] = st[rb + best // 2] if w == LONG and best < h_all and best % 2 == LOSS else 1.0
        st[o + _F_PA] = 0.0
        st[o + _F_PB] = 0.0
        if w == LONG and best < h_all:
            st[o + _F_PA] = st[_S_HDR + _CA * h_all + best]
            st[o + _F_PB] = st[_S_HDR + _CB * h_all + best]
        for k in range(5 * n + 2 * h_all):
            st[tr + k] = 0.0
        if slot == nf:
            nf += 1
            st[_S_NFAULTS] = nf
        else:
            st[_S_CLEARED] -= 1.0                 # the dismissed one's count given back
        confirming = True
        suspect = True
    learn = 0.0 if suspect else cfg[_C_GATE]
    st[_S_LEARN] = learn
    return learn


@_jit
def holding(st: F64, cfg: F64) -> int:
    """The valves whose wrench the next update leaves as it is (a mask, bit j: valve j): those
    whose loss CUSUM is above ``hold_valve``, so that a loss being decided is not learnt into the
    valve's healthy wrench (the rest of the filter still learns)."""
    n = int(cfg[_C_N])
    h_all = 2 * n
    hold = 0
    for j in range(n):
        if st[_S_HDR + _CU * h_all + 2 * j + LOSS] > cfg[_C_HOLD_VALVE]:
            hold |= 1 << j
    return hold


@_jit_alloc
def follow(st: F64, cfg: F64, Wnom: F64, Ha: F64, tap: F64, P: F64, cst: F64, hold: int = 0) -> None:
    """After an IMU update the filter learnt from (``P`` its posterior covariance, ``tap`` the
    update's rows): for each valve open in it whose loss CUSUM is above zero, the part ``rho_j``
    of a loss since the CUSUM's onset that the filter has still not learnt. A loss of size one
    left the filter's valve block off by ``rho_j w`` (``w`` the valve's nominal wrench); the update
    took ``K H (rho_j w)`` of it, ``K = P+ H^T R^-1`` (the Kalman gain from the posterior covariance,
    R the IMU rows' variances as the update used them); ``rho_j`` keeps what remains of the force
    along the nominal thrust.
    The other blocks' share (the bias states, valves correlated through the shared gain) is left
    out."""
    n = int(cfg[_C_N])
    h_all = 2 * n
    m = int(tap[tk.TAP_ROWS])
    ns = 6 * n + 6
    rb = _rho_base(n)
    rinv = np.empty(6)
    for r in range(3):
        rinv[r] = 1.0 / (cst[tk._R_ACC] * cst[tk._RSCALE])
    for r in range(3):
        rinv[3 + r] = 1.0 / (cst[tk._R_MOM + r] * cst[tk._RSCALE])
    s = np.empty(6)
    z = np.empty(ns)
    for j in range(n):
        if st[_S_HDR + _CU * h_all + 2 * j + LOSS] <= 0.0 or (hold >> j) & 1:
            continue
        vbar = tap[tk.TAP_VALVES + j]
        vt = tap[tk.TAP_VALVES + n + j]
        if vbar == 0.0 and vt == 0.0:
            continue
        # s = R^-1 H w, the valve's nominal wrench seen through this update's rows
        for r in range(3):
            acc = 0.0
            for q in range(6):
                acc += Ha[6 * r + q] * Wnom[j, q]
            s[r] = vbar * acc * rinv[r]
        for r in range(3):
            s[3 + r] = vt * Wnom[j, 3 + r] * rinv[3 + r] if m == 6 else 0.0
        # z = H^T s: every open valve's block and the bias states (the rows of imu_tap)
        for c in range(ns):
            z[c] = 0.0
        for i in range(n + 1):
            fa = 1.0 if i == n else tap[tk.TAP_VALVES + i]
            fg = 1.0 if i == n else tap[tk.TAP_VALVES + n + i]
            if fa != 0.0:
                for q in range(6):
                    acc = 0.0
                    for r in range(3):
                        acc += Ha[6 * r + q] * s[r]
                    z[6 * i + q] = fa * acc
            if m == 6 and fg != 0.0:
                for r in range(3):
                    z[6 * i + 3 + r] += fg * s[3 + r]
        # the part of w the update took into valve j's force, along its nominal thrust (the force
        # alone: a tilt's columns are across it there, while their moments are not across w's, so
        # a tilt in the filter would read as thrust learnt; a 20 degree tilt of thruster 2 was then
        # named a partial loss too)
        num = 0.0
        den = 0.0
        for q in range(3):
            acc = 0.0
            Pr = P[6 * j + q]
            for c in range(ns):
                acc += Pr[c] * z[c]
            num += Wnom[j, q] * acc
            den += Wnom[j, q] * Wnom[j, q]
        rho = st[rb + j] * max(0.0, 1.0 - num / den)
        if rho < RHO_MIN:
            # the filter has learnt most of a loss that began when this CUSUM left zero: a loss
            # that old is in the valve's wrench, and a CUSUM that has hovered above zero that long
            # holds no onset to follow. It starts again (a healthy one would otherwise stop moving)
            k = 2 * j + LOSS
            st[_S_HDR + _CU * h_all + k] = 0.0
            st[_S_HDR + _CA * h_all + k] = 0.0
            st[_S_HDR + _CB * h_all + k] = 0.0
            rho = 1.0
        st[rb + j] = rho


@_jit
def _inflate_along(P: F64, Wnom: F64, j: int, c0: int) -> None:
    """Room for valve ``j``'s learned wrench to refine along one direction of the signature table
    (``Wnom[j, c0:c0 + 6]``: its nominal wrench, a change of its thrust; a tilt's column): ``P``'s
    valve block gains ``RELEARN_SIGMA^2 w w^T``, rank one, so the filter refines the fault's size
    and not the valve's direction or moment arm, which the fault leaves as they were. Bitwise
    symmetric: ``w_q w_r`` and ``w_r w_q`` are the same product."""
    s2 = RELEARN_SIGMA * RELEARN_SIGMA
    for q in range(6):
        for r in range(6):
            P[6 * j + q, 6 * j + r] += s2 * (Wnom[j, c0 + q] * Wnom[j, c0 + r])


@_jit
def accommodate(st: F64, cfg: F64, Wnom: F64, x: F64, P: F64) -> None:
    """Put confirmed faults into the filter. A partial loss: the valve's learned wrench less the
    lost part, and room to refine the loss's size (:func:`_inflate_along`: along the valve's nominal
    wrench only; P stays bitwise symmetric). Until 2026-11-26 its whole diagonal grew, and the filter
    then traded the valve's force for its moments through the accelerometer's lever arm (thruster 2,
    10 % loss: mx 4 N m off for 1.5 s after the alarm, 7.4 % against 4.6 %). A
    stuck-open valve (modelled open through :func:`valve_mask`): its learned wrench scaled to the
    size measured while it was confirmed (always open, its wrench can no longer be told from the
    bias states, and a valve that had never fired still holds the nominal prior). A stuck-closed
    valve needs only the mask. A stuck valve just cleared (:func:`observe`): its wrench and the bias
    states relearn (their variances grow by :data:`RELEARN_SIGMA` of its nominal wrench), as the
    two were one sum while it was stuck open, and it was not learnt while stuck closed. A partial
    loss just cleared: the lost part back on the valve's wrench, and room to refine it. A leak (in the
    filter's measurement, :func:`leaks`): what the bias states learn along its wrench after its
    confirmation goes onto its size (a valve that never fires leaks a constant wrench, which they
    learn as well as its size does; they are not published). Moving their whole part along it
    moved their healthy value too (thrusters 10 and 11 leaking 10 %: 5.4 -> 7.4 %, 3.4 -> 5.7 %)."""
    n = int(cfg[_C_N])
    fbase = _fault_base(n)
    for f in range(int(st[_S_NFAULTS])):
        o = fbase + _NF * f
        if st[o + _F_TYPE] == LEAK and (st[o + _F_STAGE] == TO_FILTER or st[o + _F_STAGE] == IN_FILTER):
            # a leak is a wrench along the valve's nominal one whenever it is closed (always, for a
            # valve that never fires), which the bias states (not published) learn as well as its
            # size does. What they learn along it from its confirmation on is the leak's: moved onto
            # its size (its least squares' B), so the published wrench carries it. Their part along
            # it when it was confirmed stays theirs (their healthy value)
            j = int(st[o + _F_HYP]) // 2
            dot = 0.0
            for q in range(6):
                dot += x[6 * n + q] * Wnom[j, q]
            d = dot / (_norm2(Wnom, j, 0) + _norm2(Wnom, j, 3))
            if st[o + _F_STAGE] == TO_FILTER:
                st[o + _F_BIAS0] = d
                st[o + _F_STAGE] = IN_FILTER
            elif st[o + _F_A] > 0.0:
                d -= st[o + _F_BIAS0]
                for q in range(6):
                    x[6 * n + q] -= d * Wnom[j, q]
                st[o + _F_B] += d * st[o + _F_A]
            continue
        if st[o + _F_STAGE] == TO_CLEAR and st[o + _F_TYPE] == PARTIAL_LOSS:
            # the lost part back on the valve's learned wrench, and room to refine it
            j = int(st[o + _F_HYP]) // 2
            theta = st[o + _F_B] / st[o + _F_A] if st[o + _F_A] > 0.0 else st[o + _F_THETA0]
            for q in range(6):
                x[6 * j + q] += theta * Wnom[j, q]
            _inflate_along(P, Wnom, j, 0)
            st[o + _F_STAGE] = CLEARED_STAGE
            continue
        if st[o + _F_STAGE] == TO_CLEAR:
            # while stuck, the valve's wrench and the bias states were one sum (always open) or the
            # valve was not learnt (never open): both relearn
            j = int(st[o + _F_HYP]) // 2
            f2 = _norm2(Wnom, j, 0)
            t2 = _norm2(Wnom, j, 3)
            for q in range(6):
                v = RELEARN_SIGMA * RELEARN_SIGMA * (f2 if q < 3 else t2)
                P[6 * j + q, 6 * j + q] += v
                P[6 * n + q, 6 * n + q] += v
            st[o + _F_STAGE] = CLEARED_STAGE
            continue
        if st[o + _F_STAGE] != TO_FILTER:
            continue
        if int(st[o + _F_HYP]) >= 2 * n:
            # a misalignment: the tilt measured while it was confirmed onto the valve's learned
            # wrench, and room to refine its two angles (rank two, along the tilt's columns)
            j = int(st[o + _F_HYP]) - 2 * n
            p1, p2, _ = _tilt_solve(st, o + _F_T11, 1)
            f2 = _norm2(Wnom, j, 0)
            # the signatures are of nominal thrust: the angle is the thrust turned across over the
            # thrust the valve really gives (its learned wrench along nominal), on its alarm row
            along = 0.0
            for q in range(3):
                along += x[6 * j + q] * Wnom[j, q]
            along /= f2
            ne = int(st[_S_EVENTS])
            q0 = _fault_base(n) + _NF * MAX_FAULTS + _NEV * (ne - 1)
            sn = min(1.0, math.sqrt(p1 * p1 + p2 * p2) / along) if along > 0.0 else 0.0
            if ne > 0 and along > 0.0 and st[q0 + 1] == j and st[q0 + 2] == MISALIGNMENT:
                st[q0 + 3] = math.degrees(math.asin(sn))
            # the thrust turned by phi keeps cos(phi) of itself along its old direction: the
            # signatures are first order (across only), so the part 1 - cos(phi) along it (6 % at
            # 20 degrees, force and moment) is taken off here, or the loss CUSUMs see it as a loss
            drop = along * (1.0 - math.sqrt(1.0 - sn * sn))
            for q in range(6):
                x[6 * j + q] += p1 * Wnom[j, 6 + q] + p2 * Wnom[j, 12 + q] - drop * Wnom[j, q]
            _inflate_along(P, Wnom, j, 6)          # room to refine the two angles (radians), no more
            _inflate_along(P, Wnom, j, 12)
            st[o + _F_STAGE] = IN_FILTER
            continue
        j = int(st[o + _F_HYP]) // 2
        theta = st[o + _F_B] / st[o + _F_A] if st[o + _F_A] > 0.0 else st[o + _F_THETA0]
        f2 = _norm2(Wnom, j, 0)
        st[o + _F_STAGE] = IN_FILTER
        if int(st[o + _F_HYP]) % 2 == OPEN:
            along = 0.0                       # the learned wrench's thrust along nominal, of nominal
            for q in range(3):
                along += x[6 * j + q] * Wnom[j, q]
            along /= f2
            if along > 0.0:
                for q in range(6):
                    x[6 * j + q] *= theta / along
            continue
        # what the filter had not learnt of the loss when it was raised (the rest it already holds)
        r = st[o + _F_RHO]
        for q in range(6):
            x[6 * j + q] -= theta * r * Wnom[j, q]
        _inflate_along(P, Wnom, j, 0)


@_jit
def learning(st: F64) -> float:
    """What the filter may learn from the next IMU update, the ``learn`` of
    :func:`.thruster_kernel.imu_tap` (:func:`observe`'s last verdict): 0.0 nothing, else the
    largest normalised innovation squared it learns from."""
    return float(st[_S_LEARN])


@_jit
def r_scale(st: F64) -> float:
    """What the thruster filter's IMU noise variances are multiplied by in the next update: the
    innovation's measured noise level over :data:`NOISE_REF` when above it, else 1 (the sensors
    as configured). A noisier IMU than configured (the noise sweep's x2, x4) would otherwise be
    learnt from as if it were exact: the filter's wrenches chase its noise."""
    lvl = st[_S_NOISE]
    return float(lvl / NOISE_REF) if lvl > NOISE_REF else 1.0


@_jit
def noise_level(st: F64) -> float:
    """The innovation's measured noise level, the mean of ``e^T S^-1 e / m`` (:data:`NOISE_TAU_S`):
    1 when the innovation is as large as the filter predicts, 1.8 in healthy sessions of the
    scenarios' sensor classes."""
    return float(st[_S_NOISE])


@_jit
def unresolved(st: F64) -> bool:
    """A thruster fault has been raised (being confirmed, or confirmed) and not cleared: the
    thruster wrench is not to be trusted as healthy."""
    return bool(st[_S_NFAULTS] > st[_S_CLEARED])


@_jit
def leaks(st: F64, n: int, out: F64) -> None:
    """The confirmed leaks the filter models, ``out`` (n,): valve j delivers ``out[j]`` of its
    nominal wrench while closed (0: no leak). Their size is refined at every IMU update (and takes
    what the bias states learn along the leak's wrench, :func:`accommodate`)."""
    fbase = _fault_base(n)
    for j in range(n):
        out[j] = 0.0
    for f in range(int(st[_S_NFAULTS])):
        o = fbase + _NF * f
        if st[o + _F_STAGE] == IN_FILTER and st[o + _F_TYPE] == LEAK and st[o + _F_A] > 0.0:
            out[int(st[o + _F_HYP]) // 2] = max(0.0, st[o + _F_B] / st[o + _F_A])


@_jit
def add_leaks(st: F64, Wnom: F64, mask: int | np.int64, out: F64) -> None:
    """Add to a step's thruster wrench ``out`` (6,) what the confirmed leaks deliver: each leaking
    valve closed in ``mask`` (as the filter takes it, :func:`valve_mask`) its size times its
    nominal wrench (nothing when there is no leak: ``out`` bit for bit). A thruster has one leak
    in the filter at most (raised again only once the earlier one is cleared)."""
    n = Wnom.shape[0]
    fbase = _fault_base(n)
    for f in range(int(st[_S_NFAULTS])):
        o = fbase + _NF * f
        if st[o + _F_STAGE] == IN_FILTER and st[o + _F_TYPE] == LEAK and st[o + _F_A] > 0.0:
            j = int(st[o + _F_HYP]) // 2
            th = max(0.0, st[o + _F_B] / st[o + _F_A])
            if th != 0.0 and not (mask >> j) & 1:
                for q in range(6):
                    out[q] += th * Wnom[j, q]


@_jit
def valve_mask(st: F64, mask: int | np.int64) -> np.int64:
    """The valves the filter should take as open in a step commanded ``mask``, bits 0..n-1: the
    confirmed stuck-open ones added, the stuck-closed ones removed; and ``mask`` itself from bit
    :data:`.thruster_kernel.COMMANDED` up, which the filter ignores and its innovation tap reports
    (the recovery test of a stuck valve needs the command)."""
    cmd = np.int64(mask) & ((np.int64(1) << tk.COMMANDED) - 1)
    return ((cmd | np.int64(st[_S_OPEN])) & ~np.int64(st[_S_CLOSED])) | (cmd << tk.COMMANDED)


def size_text(fault: str, theta: float) -> str:
    """A fault's size as its alerts and reports say it: a leak or a partial loss as a percentage
    of nominal thrust, a stuck valve as the fraction it delivers (or lost), a misalignment as the
    tilt's angle."""
    if fault == "misalignment":
        return f"tilted {theta:.1f} deg"
    if fault in ("leak", "partial loss"):
        return f"{theta:.0%} of nominal thrust"
    return f"size {theta:.2f} of nominal thrust"


def events(st: np.ndarray, n: int) -> np.ndarray:
    """The alarms raised so far, ``(k, 7)`` rows of :data:`EVENT_FIELDS` (a copy)."""
    ev0 = _offsets(n)[2]
    k = int(st[_S_EVENTS])
    return st[ev0:ev0 + _NEV * k].reshape(k, _NEV).copy()


def faults(st: np.ndarray, n: int) -> list[tuple[int, str, float]]:
    """The faults raised and not cleared: ``(thruster, family, size)`` (size: fraction of nominal
    thrust; a tilt's: its angle, degrees)."""
    o = _offsets(n)[1]
    out = []
    for f in range(int(st[_S_NFAULTS])):
        r = st[o + _NF * f:o + _NF * (f + 1)]
        if r[_F_STAGE] == CLEARED_STAGE or r[_F_STAGE] == TO_CLEAR or r[_F_STAGE] == DISMISSED:
            continue
        hyp, A, B = int(r[_F_HYP]), r[_F_A], r[_F_B]
        if hyp >= 2 * n:                          # a tilt: its angle, degrees
            p1, p2, _ = _tilt_solve(r, _F_T11, 1)
            if r[_F_T11] <= 0.0:
                p1, p2 = r[_F_THETA0], r[_F_THETA0B]
            out.append((hyp - 2 * n, "tilt", math.degrees(math.hypot(p1, p2))))
            continue
        out.append((hyp // 2, FAMILIES[hyp % 2], float(B / A) if A > 0 else float(r[_F_THETA0])))
    return out


# -- one IMU sample through the filter and the detector (live: core.py; offline: run_events) --------------

@_jit_alloc
def imu_update(x: F64, P: F64, Q: F64, cst: F64, c: F64, hist_t: I64, hist_arm: F64, hist_mask: I64, ist: I64,
               fst: F64, t_ns: int, accel: F64, rate: F64, tap: F64, st: F64, cfg: F64, Wnom: F64, Ha: F64) -> bool:
    """The thruster filter's update of one IMU sample (:func:`.thruster_kernel.imu_tap`) with the
    IMU's noise as measured (:func:`r_scale`) and what the detector let it learn (:func:`learning`),
    then the detector's verdict (:func:`observe`), what the filter learnt of a loss the detector is
    gathering evidence of (:func:`follow`) and the confirmed faults put into the filter
    (:func:`accommodate`). True if the sample was applied."""
    cst[tk._RSCALE] = r_scale(st)
    lk = np.zeros(Wnom.shape[0])
    leaks(st, Wnom.shape[0], lk)
    learnt = ist[tk._UPDATES]
    hold = holding(st, cfg)
    if not tk.imu_tap(x, P, Q, cst, c, hist_t, hist_arm, hist_mask, ist, fst, t_ns, accel, rate, tap, st[_S_LEARN],
                      lk, Wnom, hold):
        return False
    observe(st, cfg, Wnom, Ha, tap, t_ns)
    if ist[tk._UPDATES] != learnt:
        follow(st, cfg, Wnom, Ha, tap, P, cst, hold)
    accommodate(st, cfg, Wnom, x, P)
    return True


# -- offline: a recorded event stream through the filter and the detector --------------------------------

@_jit
def run_events(x: F64, P: F64, Q: F64, cst: F64, c: F64, hist_t: I64, hist_arm: F64, hist_mask: I64, ist: I64,
               fst: F64, kind: I64, t_ns: I64, arm: F64, masks: I64, accel: F64, rate: F64, st: F64, cfg: F64,
               Wnom: F64, Ha: F64, tap: F64, out_stat: F64, out_wrench: F64) -> None:
    """:func:`.thruster_kernel.run_events` with the detector after every applied IMU update, the
    confirmed stuck valves modelled (:func:`valve_mask`) and partial losses put into the filter
    (:func:`accommodate`). ``out_stat[k]`` (IMU events) = the largest statistic of the short and
    the long detector, and their hypotheses (``2 j + family``), -1 where none; other events get
    zeros. ``out_wrench[k]`` (STEP, WRENCH_ONLY): the thruster wrench of the step (body frame, N,
    N m) with the faults found so far modelled; zero for IMU events."""
    n = Wnom.shape[0]
    h_all = 2 * n
    for k in range(kind.shape[0]):
        kd = kind[k]
        for q in range(4):
            out_stat[k, q] = 0.0
        for q in range(6):
            out_wrench[k, q] = 0.0
        if kd == tk.IMU:
            if imu_update(x, P, Q, cst, c, hist_t, hist_arm, hist_mask, ist, fst, t_ns[k], accel[k], rate[k],
                          tap, st, cfg, Wnom, Ha):
                for w in range(2):
                    best, bt, _ = _best(st, h_all, w)
                    out_stat[k, 2 * w] = bt
                    out_stat[k, 2 * w + 1] = best
        else:
            mk = valve_mask(st, masks[k])
            tk.wrench(x, mk, out_wrench[k])
            add_leaks(st, Wnom, mk, out_wrench[k])
            if kd == tk.STEP:
                tk.push_epoch(hist_t, hist_arm, hist_mask, ist, t_ns[k], arm[k], mk)
