"""The valve-aided thruster filter (:mod:`.thrusters`) as compiled (numba) kernels.

Same model, prior, random walk, measurement rows and gating as :class:`.thrusters.ThrusterFilter`
(its docstring has the equations); the state is a handful of numpy arrays, so a live caller calls
:func:`push_epoch` / :func:`imu` once per event and an offline caller hands a whole ordered event
stream to :func:`run_events`, both through the same inner functions.

The update, reformulated (exact in exact arithmetic, no approximation):

- ``H`` is sparse with a Kronecker structure: the valve columns of the accelerometer rows are
  ``vbar_i Ha`` (``vbar_i`` the mean open fraction of valve i over the IMU interval, ``Ha`` the
  fixed 3x6 block), those of the gyro rows ``vt_i [0 I]`` (``vt_i`` the c-weighted fractions);
  a valve closed over the whole interval has zero columns. Only the non-zero entries are kept
  (per row: column index, value), so ``P H^T`` costs ``O(ns nnz)``, not ``O(ns^2 m)``. Left out
  terms are products with an exact zero: they add nothing.
- ``S = H P H^T + R`` (m x m, m = 3 or 6) is SPD: ``S = L L^T`` (Cholesky). With
  ``B = P H^T L^-T`` the gain is ``K = P H^T S^-1 = B L^-1``, so ``x += B (L^-1 (y - H x))`` and
  ``P -= K H P = B B^T``. ``P[i, j]`` and ``P[j, i]`` receive the same products in the same order
  (``B[i, r] B[j, r] == B[j, r] B[i, r]`` in IEEE arithmetic), so a bitwise-symmetric P stays
  bitwise symmetric: the symmetrisation pass of the numpy form is not needed (the prior is
  symmetrised once, at construction).
- With a prior whose valve blocks are uncorrelated (``common_gain_sigma`` = 0: the shared gain
  correlates them all, and then every valve is active from the start), a valve that has never
  been open in any update ("inactive") has zero cross-covariance with every other state: its
  rows of ``P H^T`` are sums of products with exact zeros, so its rows of ``B`` are zero and
  the update leaves its rows of ``x`` and ``P`` as they are. The kernels skip those rows (bit
  for bit the dense result, up to the sign of a zero). The random walk still adds ``Q_per_s dt``
  to the whole diagonal.
- ``P H^T`` is formed from rows of ``P`` (``P[c, :]`` for the columns ``c`` of ``H``): the same
  numbers as ``P[:, c]`` since P is bitwise symmetric, and contiguous.

Bits: explicit loops in a fixed order (ascending indices; sums start from the first term or from
0.0 as written), no BLAS/LAPACK, no numpy reductions, ``fastmath=False`` (no reassociation, no
fused multiply-add), and nothing but the state arrays carries from one event to the next. So one
:func:`run_events` call, any split of the stream and one call per event give the same bits. Against
the numpy form (LU solve, BLAS sums, symmetrisation) they differ by rounding only. Measured after
4000 updates (paper_robot, 18 valves, 500 Hz IMU; the 8 s capture session of ``bsc demo`` and a
simulated stream): x within 4e-14 of max|x| (3e-12 of each state's sigma), P within 8e-14 of the
correlation scale sqrt(P_ii P_jj) (tests/gateway/estimator/test_thruster_kernel.py checks 1e-9). The prior
is the numpy form's, computed once by it.

History matching is the numpy form's: a ring of the last ``2 imu_steps + 2`` pushed steps, in push
order (no de-duplication); an IMU sample at ``t_ns`` takes, for each wanted step time
``t_ns - j dt``, the oldest pushed step within half a step of it; a missing one and the sample is
not applied (its gyro rate is still kept for the next gyro difference).

Usage::

    kf = CompiledThrusterFilter(EstimatorModel.from_robot(robot), ThrusterLayout.named())
    thr = kf.wrench(mask)                                  # every 1 kHz step: [f; tau] (6,)
    kf.push_epoch(t_ns, arm_wrench, mask)                  # trusted steps only
    applied = kf.imu(t_ns, accel_imu, rate_imu)            # each IMU sample
    wrench, applied = kf.run(kind, t_ns, arm, mask, accel, rate)       # a recorded stream
"""
from __future__ import annotations

import math
from typing import Iterable

import numpy as np
import numpy.typing as npt

from robot_description.thrusters import ThrusterLayout

from .model import EstimatorModel
from .thrusters import ThrusterFilter, ThrusterFilterSettings

# IEEE semantics, no fast-math: the bits are fixed whatever the batch
from .jitopts import jit as _jit, jit_alloc as _jit_alloc   # numba's njit, with the kernels' options

F64 = npt.NDArray[np.float64]     # any shape: each function's docstring gives it
I64 = npt.NDArray[np.int64]
State = tuple[F64, F64, F64, F64, F64, I64, F64, I64, I64, F64]
"""``(x, P, Q_per_s, cst, c, hist_t, hist_arm, hist_mask, ist, fst)``: :attr:`CompiledThrusterFilter.state`."""

MAX_VALVES = 32             # the wire's valve mask (bit i = valve i open)

# event kinds of run_events
STEP = 0                    # a trusted step: thruster wrench out, then pushed into the history
IMU = 1                     # an IMU sample
WRENCH_ONLY = 2             # a step the filter must not learn from: thruster wrench out only

# cst (float64): constants
_M, _DT, _STEP_NS, _R_ACC, _R_MOM, _I, _IINV, _RIMU, _RV, _HA, _T, _RSCALE = 0, 1, 2, 3, 4, 7, 16, 25, 34, 37, 55, 56
_NCST = 57
# ist (int64): counters and small state
_H_START, _H_COUNT, _HAVE_PREV, _PREV_NS, _HAVE_LAST, _LAST_NS, _UPDATES, _ACTIVE, _NRUNS, _RUNS = range(10)
# fst (float64): previous gyro rate (body), latest gyro rate (body)
_PREV_W, _W = 0, 3


# -- history -------------------------------------------------------------------------------------
@_jit
def cholesky(S: F64, m: int, L: F64) -> bool:
    """``S[:m, :m] = L L^T`` from the lower triangle of ``S`` (the upper is not read), into
    ``L``'s lower triangle; False if not positive definite. Explicit loops: the same bits
    whatever the caller (the filter's update, the fault detector's whitening)."""
    for j in range(m):
        d = S[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not d > 0.0:
            return False
        L[j, j] = math.sqrt(d)
        for i in range(j + 1, m):
            v = S[i, j]
            for k in range(j):
                v -= L[i, k] * L[j, k]
            L[i, j] = v / L[j, j]
    return True


@_jit
def push_epoch(hist_t: I64, hist_arm: F64, hist_mask: I64, ist: I64, t_ns: int, arm_wrench: F64,
               valves_mask: int | np.int64) -> None:
    """Record one step at ``t_ns`` (int ns): the arms' wrench on the spacecraft ``arm_wrench`` (6,)
    (body frame, force through C, moment about C; N, N m) and the valves open during it (bit i of
    ``valves_mask`` = valve i). The oldest entry goes when the ring is full (a deque's maxlen)."""
    K = hist_t.shape[0]
    start, count = ist[_H_START], ist[_H_COUNT]
    if count < K:
        slot = (start + count) % K
        ist[_H_COUNT] = count + 1
    else:
        slot = start
        ist[_H_START] = (start + 1) % K
    hist_t[slot] = t_ns
    for q in range(6):
        hist_arm[slot, q] = arm_wrench[q]
    hist_mask[slot] = valves_mask


@_jit
def _steps(hist_t: I64, ist: I64, step_ns: float, t_end: float, count: int, out: I64) -> bool:
    """Slots of the ``count`` steps ending at ``t_end`` (float ns), oldest first, into ``out``:
    for each wanted time the oldest entry within half a step. False if one is missing."""
    K = hist_t.shape[0]
    start, n_hist = ist[_H_START], ist[_H_COUNT]
    half = 0.5 * step_ns
    for j in range(count - 1, -1, -1):
        t = t_end - j * step_ns
        found = -1
        for e in range(n_hist):
            slot = (start + e) % K
            if abs(float(hist_t[slot]) - t) < half:
                found = slot
                break
        if found < 0:
            return False
        out[count - 1 - j] = found
    return True


@_jit
def _mv3(M: F64, v0: float, v1: float, v2: float) -> tuple[float, float, float]:
    """``M v`` for a row-major 3x3 ``M`` (9,), sums left to right."""
    return (M[0] * v0 + M[1] * v1 + M[2] * v2, M[3] * v0 + M[4] * v1 + M[5] * v2,
            M[6] * v0 + M[7] * v1 + M[8] * v2)


# -- the estimate --------------------------------------------------------------------------------
@_jit
def wrench(x: F64, valves_mask: int | np.int64, out: F64) -> None:
    """Thruster wrench ``[f; tau]`` into ``out`` (6,) (body frame, force through C, moment about C;
    N, N m): the sum of ``W_i`` over the open valves, ascending valve index."""
    n = (x.shape[0] - 6) // 6
    for q in range(6):
        out[q] = 0.0
    for i in range(n):
        if (valves_mask >> i) & 1:
            for q in range(6):
                out[q] += x[6 * i + q]


@_jit
def _set_runs(ist: I64, n: int, active: int | np.int64) -> None:
    """Contiguous column ranges of the active valves' blocks and the bias block, from the
    valve bitmask ``active`` (ascending)."""
    nr = 0
    i = 0
    while i < n:
        if (active >> i) & 1:
            j = i
            while j < n and (active >> j) & 1:
                j += 1
            ist[_RUNS + 2 * nr] = 6 * i
            ist[_RUNS + 2 * nr + 1] = 6 * j
            nr += 1
            i = j
        else:
            i += 1
    # the bias block (always active), joined to a run ending at it
    if nr > 0 and ist[_RUNS + 2 * nr - 1] == 6 * n:
        ist[_RUNS + 2 * nr - 1] = 6 * n + 6
    else:
        ist[_RUNS + 2 * nr] = 6 * n
        ist[_RUNS + 2 * nr + 1] = 6 * n + 6
        nr += 1
    ist[_NRUNS] = nr
    ist[_ACTIVE] = active


@_jit
def _downdate(P: F64, Bt: F64, m: int, ilo: int, ihi: int, jlo: int, jhi: int) -> None:
    """``P[i, j] -= sum_r Bt[r, i] Bt[r, j]`` (r ascending) for i in [ilo, ihi), j in [jlo, jhi).
    The inner loops run over slices from 0 (no negative-index handling), so they vectorise; the
    operations of each element stay the same and in the same order."""
    nj = jhi - jlo
    B0, B1, B2 = Bt[0, jlo:jhi], Bt[1, jlo:jhi], Bt[2, jlo:jhi]
    if m == 6:
        B3, B4, B5 = Bt[3, jlo:jhi], Bt[4, jlo:jhi], Bt[5, jlo:jhi]
        for i in range(ilo, ihi):
            b0, b1, b2, b3, b4, b5 = Bt[0, i], Bt[1, i], Bt[2, i], Bt[3, i], Bt[4, i], Bt[5, i]
            Pi = P[i, jlo:jhi]
            for j in range(nj):
                Pi[j] = (((((Pi[j] - b0 * B0[j]) - b1 * B1[j]) - b2 * B2[j]) - b3 * B3[j]) - b4 * B4[j]) - b5 * B5[j]
    else:
        for i in range(ilo, ihi):
            b0, b1, b2 = Bt[0, i], Bt[1, i], Bt[2, i]
            Pi = P[i, jlo:jhi]
            for j in range(nj):
                Pi[j] = ((Pi[j] - b0 * B0[j]) - b1 * B1[j]) - b2 * B2[j]


_APPLIED, _NOT_PD, _GATED = 0, 1, 2     # what _update did


@_jit_alloc
def _update(x: F64, P: F64, ist: I64, m: int, y: F64, hc: I64, hv: F64, hn: I64, R: F64, gate: float) -> int:
    """Kalman update with the m (3 or 6) sparse rows ``hc``/``hv``/``hn`` of H (column indices,
    values, count per row), measurement ``y`` and noise variances ``R``, on the active rows and
    columns (``ist`` runs), when the normalised innovation squared ``e^T S^-1 e`` is at most
    ``gate``. Returns :data:`_APPLIED`, :data:`_NOT_PD` (nothing changed: S is not positive
    definite, a NaN or inf in P) or :data:`_GATED` (nothing changed)."""
    ns = x.shape[0]
    nr = ist[_NRUNS]
    # Bt = (P H^T)^T on the active columns; P[c, :] is P[:, c] (P bitwise symmetric)
    Bt = np.empty((m, ns))
    for r in range(m):
        for a in range(nr):
            lo, hi = ist[_RUNS + 2 * a], ist[_RUNS + 2 * a + 1]
            Br = Bt[r, lo:hi]
            for i in range(hi - lo):
                Br[i] = 0.0
            for k in range(hn[r]):
                h = hv[r, k]
                Pc = P[hc[r, k], lo:hi]
                for i in range(hi - lo):
                    Br[i] += Pc[i] * h
    # S = H P H^T + R, lower triangle; its Cholesky factor L
    S = np.empty((m, m))
    for r in range(m):
        for s in range(r + 1):
            acc = 0.0
            for k in range(hn[r]):
                acc += hv[r, k] * Bt[s, hc[r, k]]
            S[r, s] = acc
        S[r, r] += R[r]
    L = np.zeros((m, m))
    if not cholesky(S, m, L):
        return _NOT_PD
    # z = L^-1 (y - H x)
    z = np.empty(m)
    nis = 0.0
    for r in range(m):
        acc = 0.0
        for k in range(hn[r]):
            acc += hv[r, k] * x[hc[r, k]]
        v = y[r] - acc
        for k in range(r):
            v -= L[r, k] * z[k]
        z[r] = v / L[r, r]
        nis += z[r] * z[r]
    if not nis <= gate:
        return _GATED
    # B = P H^T L^-T in place: row r of Bt from rows 0..r-1
    for a in range(nr):
        lo, hi = ist[_RUNS + 2 * a], ist[_RUNS + 2 * a + 1]
        for r in range(m):
            Br = Bt[r, lo:hi]
            for k in range(r):
                lrk = L[r, k]
                Bk = Bt[k, lo:hi]
                for i in range(hi - lo):
                    Br[i] -= lrk * Bk[i]
            lrr = L[r, r]
            for i in range(hi - lo):
                Br[i] /= lrr
    # x += B z; P -= B B^T (the same products in the same order for P[i, j] and P[j, i])
    for a in range(nr):
        for i in range(ist[_RUNS + 2 * a], ist[_RUNS + 2 * a + 1]):
            acc = 0.0
            for r in range(m):
                acc += Bt[r, i] * z[r]
            x[i] += acc
    for a in range(nr):
        for a2 in range(nr):
            _downdate(P, Bt, m, ist[_RUNS + 2 * a], ist[_RUNS + 2 * a + 1],
                      ist[_RUNS + 2 * a2], ist[_RUNS + 2 * a2 + 1])
    return _APPLIED


@_jit_alloc
def imu(x: F64, P: F64, Q: F64, cst: F64, c: F64, hist_t: I64, hist_arm: F64, hist_mask: I64, ist: I64, fst: F64,
        t_ns: int, accel_imu: F64, rate_imu: F64) -> bool:
    """Apply one IMU sample at ``t_ns`` (int ns, the end of its interval): ``accel_imu`` (m/s^2)
    and ``rate_imu`` (rad/s), (3,) each, IMU frame. True when applied; False (nothing applied but
    the gyro rate kept) when a step of its interval is missing. Raises ``ValueError`` when the
    innovation covariance is not positive definite (a NaN or inf in P); the random walk is then
    already applied and nothing else."""
    return imu_tap(x, P, Q, cst, c, hist_t, hist_arm, hist_mask, ist, fst, t_ns, accel_imu, rate_imu,
                   np.empty(0), math.inf)


# the innovation tap of imu_tap (float64 row): applied, rows, e = y - H x (6), S = H P H^T + R
# (6 x 6, row-major, the first ``rows`` rows and columns), then per valve its open fraction in the
# accelerometer rows (vbar, n) and its weight in the gyro-difference rows (vt, n), then the same
# two of the valves as commanded (the bits from COMMANDED up of the pushed masks; n each)
TAP_APPLIED, TAP_ROWS, TAP_E, TAP_S, TAP_VALVES = 0, 1, 2, 8, 44
COMMANDED = 32
"""Bits ``COMMANDED + i`` of a pushed valve mask: valve i as commanded, when the caller models
some valves otherwise in bits 0..n-1 (the fault detector's stuck valves, :func:`.fdi.valve_mask`).
The filter reads only bits 0..n-1; the tap reports both."""


def tap_size(n: int) -> int:
    """Length of the innovation tap of :func:`imu_tap` for ``n`` valves."""
    return TAP_VALVES + 4 * n


@_jit
def _tap(x: F64, P: F64, m: int, y: F64, hc: I64, hv: F64, hn: I64, R: F64, cnt: F64, nn: float, vt: F64,
         ccnt: F64, cvt: F64, tap: F64) -> None:
    """The innovation of an update before it is applied: ``e = y - H x`` and its covariance
    ``S = H P H^T + R`` (P after the random walk), with the valve fractions that make H and the
    same of the valves as commanded (``ccnt``, ``cvt``)."""
    n = (x.shape[0] - 6) // 6
    tap[TAP_APPLIED] = 1.0
    tap[TAP_ROWS] = m
    for k in range(TAP_S, TAP_VALVES):
        tap[k] = 0.0
    for r in range(6):
        tap[TAP_E + r] = 0.0
    for r in range(m):
        acc = 0.0
        for k in range(hn[r]):
            acc += hv[r, k] * x[hc[r, k]]
        tap[TAP_E + r] = y[r] - acc
        for s in range(m):
            acc = 0.0
            for k in range(hn[r]):
                ck_ = hc[r, k]
                for q in range(hn[s]):
                    acc += hv[r, k] * hv[s, q] * P[ck_, hc[s, q]]
            if r == s:
                acc += R[r]
            tap[TAP_S + 6 * r + s] = acc
    for i in range(n):
        tap[TAP_VALVES + i] = cnt[i] / nn
        tap[TAP_VALVES + n + i] = vt[i] if m == 6 else 0.0
        tap[TAP_VALVES + 2 * n + i] = ccnt[i] / nn
        tap[TAP_VALVES + 3 * n + i] = cvt[i] if m == 6 else 0.0


@_jit_alloc
def _held_update(x: F64, P: F64, ist: I64, m: int, y: F64, hc: I64, hv: F64, hn: I64, R: F64, gate: float,
                 hold: int, n: int) -> int:
    """:func:`_update` with the valves of the mask ``hold`` considered, not estimated (a Schmidt
    update, :func:`imu_tap`): their blocks of ``x`` and ``P`` keep their prior values."""
    nh = 0
    for i in range(n):
        if (hold >> i) & 1:
            nh += 6
    held = np.empty(nh, dtype=np.int64)
    k = 0
    for i in range(n):
        if (hold >> i) & 1:
            for q in range(6):
                held[k] = 6 * i + q
                k += 1
    xh = np.empty(nh)
    Ph = np.empty((nh, nh))
    for a in range(nh):
        xh[a] = x[held[a]]
        for b in range(nh):
            Ph[a, b] = P[held[a], held[b]]
    done = _update(x, P, ist, m, y, hc, hv, hn, R, gate)
    if done == _APPLIED:
        for a in range(nh):
            x[held[a]] = xh[a]
            for b in range(nh):
                P[held[a], held[b]] = Ph[a, b]
    return done


@_jit_alloc
def imu_tap(x: F64, P: F64, Q: F64, cst: F64, c: F64, hist_t: I64, hist_arm: F64, hist_mask: I64, ist: I64,
            fst: F64, t_ns: int, accel_imu: F64, rate_imu: F64, tap: F64, learn: float, leak: F64 | None = None,
            Wleak: F64 | None = None, hold: int = 0) -> bool:
    """:func:`imu`, and when ``tap`` is not empty (length :func:`tap_size`) the update's
    innovation written into it before the update (``tap[TAP_APPLIED]`` 0 when nothing was
    applied). The tap only reads the state. ``learn``: the largest normalised innovation squared
    ``e^T S^-1 e`` the filter learns from. ``math.inf``: every sample, the filter's bits are
    :func:`imu`'s; ``0.0``: none, the sample is measured (the tap, the random walk) but ``x`` and
    ``P`` are not updated (the fault detector's hold while it suspects a fault, :mod:`.fdi`); in
    between, an innovation gate (the detector's: the sample that first shows a gross fault is not
    learnt into the healthy model before the detector has seen it). True when the sample was
    measured, learnt or not.

    ``leak`` (n,), ``Wleak`` (n, 6): valves that leak, known (the fault detector's confirmed
    leaks, :mod:`.fdi`): valve i delivers ``leak[i] Wleak[i]`` while closed, an input the
    measurement is corrected for before the innovation (``y -= leak_i (1 - vbar_i) Ha Wleak_i``,
    the gyro rows ``leak_i (1 - vt_i) Wleak_i`` moment), so the filter does not learn it into the
    valves' wrenches and the bias states. Zero (or None): the measurement as it is, bit for bit.

    ``hold``: a mask of valves whose wrench the update leaves as it is (bit i: valve i; the fault
    detector's valves under suspicion of a loss, :mod:`.fdi`): a Schmidt "consider" update. Their
    blocks of ``x`` and ``P`` (among themselves) keep their values, their cross-covariance with
    the other states takes the update's downdate, which is the covariance of the update whose gain
    is zero on them and the Kalman gain elsewhere. 0: every state learns, bit for bit as before."""
    want = tap.shape[0] > 0
    if want:
        tap[TAP_APPLIED] = 0.0
    ns = x.shape[0]
    n = (ns - 6) // 6
    nn = (c.shape[0] + 1) // 2
    step_ns = cst[_STEP_NS]
    # gyro and accelerometer in the body frame
    ra0, ra1, ra2 = rate_imu[0], rate_imu[1], rate_imu[2]
    ac0, ac1, ac2 = accel_imu[0], accel_imu[1], accel_imu[2]
    Rm = cst[_RIMU:_RIMU + 9]
    w0, w1, w2 = _mv3(Rm, ra0, ra1, ra2)
    a0, a1, a2 = _mv3(Rm, ac0, ac1, ac2)
    have_prev, prev_ns = ist[_HAVE_PREV], ist[_PREV_NS]
    p0, p1, p2 = fst[_PREV_W], fst[_PREV_W + 1], fst[_PREV_W + 2]
    ist[_HAVE_PREV] = 1
    ist[_PREV_NS] = t_ns
    fst[_PREV_W], fst[_PREV_W + 1], fst[_PREV_W + 2] = w0, w1, w2
    fst[_W], fst[_W + 1], fst[_W + 2] = w0, w1, w2
    cur = np.empty(nn, dtype=np.int64)
    if not _steps(hist_t, ist, step_ns, float(t_ns), nn, cur):
        return False
    Is = cst[_I:_I + 9]             # inertia of the spacecraft, body frame, about C
    Iinv = cst[_IINV:_IINV + 9]
    i0, i1, i2 = _mv3(Is, w0, w1, w2)
    g0, g1, g2 = w1 * i2 - w2 * i1, w2 * i0 - w0 * i2, w0 * i1 - w1 * i0       # w x I w
    r0, r1, r2 = cst[_RV], cst[_RV + 1], cst[_RV + 2]
    cr0, cr1, cr2 = w1 * r2 - w2 * r1, w2 * r0 - w0 * r2, w0 * r1 - w1 * r0     # w x r
    d0, d1, d2 = w1 * cr2 - w2 * cr1, w2 * cr0 - w0 * cr2, w0 * cr1 - w1 * cr0  # w x (w x r)
    m_s = cst[_M]
    y = np.empty(6)
    R = np.empty(6)
    hc = np.empty((6, 6 * n + 6), dtype=np.int64)
    hv = np.empty((6, 6 * n + 6))
    hn = np.zeros(6, dtype=np.int64)
    # accelerometer: known = f_arm / m + (I^-1 (tau_arm - w x I w)) x r + w x (w x r), mean over I_k
    s0 = s1 = s2 = 0.0
    cnt = np.zeros(n)
    ccnt = np.zeros(n)                 # as commanded (the tap only)
    cvt = np.zeros(n)
    support = 0
    for u in range(nn):
        e = cur[u]
        t0 = hist_arm[e, 3] - g0
        t1 = hist_arm[e, 4] - g1
        t2 = hist_arm[e, 5] - g2
        x0, x1, x2 = _mv3(Iinv, t0, t1, t2)
        k0 = hist_arm[e, 0] / m_s + (x1 * r2 - x2 * r1) + d0
        k1 = hist_arm[e, 1] / m_s + (x2 * r0 - x0 * r2) + d1
        k2 = hist_arm[e, 2] / m_s + (x0 * r1 - x1 * r0) + d2
        if u == 0:
            s0, s1, s2 = k0, k1, k2
        else:
            s0, s1, s2 = s0 + k0, s1 + k1, s2 + k2
        mask = hist_mask[e]
        support |= mask
        for i in range(n):
            if (mask >> i) & 1:
                cnt[i] += 1.0
            if want and (mask >> (COMMANDED + i)) & 1:
                ccnt[i] += 1.0
    y[0], y[1], y[2] = a0 - s0 / nn, a1 - s1 / nn, a2 - s2 / nn
    Ha = cst[_HA:_HA + 18]
    for r in range(3):
        k = 0
        for i in range(n):
            if cnt[i] != 0.0:
                f = cnt[i] / nn
                for q in range(6):
                    h = f * Ha[6 * r + q]
                    if h != 0.0:
                        hc[r, k] = 6 * i + q
                        hv[r, k] = h
                        k += 1
        for q in range(6):
            if Ha[6 * r + q] != 0.0:
                hc[r, k] = 6 * n + q
                hv[r, k] = Ha[6 * r + q]
                k += 1
        hn[r] = k
        R[r] = cst[_R_ACC] * cst[_RSCALE]
    m = 3
    vt = np.zeros(n)
    # gyro difference: I (w_k - w_{k-1}) / (n dt) - sum_u c_u (tau_arm(u) - w x I w)
    if have_prev != 0 and abs(float(t_ns - prev_ns) - nn * step_ns) < 0.5 * step_ns:
        span = np.empty(2 * nn - 1, dtype=np.int64)
        if _steps(hist_t, ist, step_ns, float(t_ns) - step_ns, 2 * nn - 1, span):
            e0 = w0 - p0
            e1 = w1 - p1
            e2 = w2 - p2
            T = cst[_T]
            b0 = b1 = b2 = 0.0
            for u in range(2 * nn - 1):
                e = span[u]
                cu = c[u]
                b0 += cu * (hist_arm[e, 3] - g0)
                b1 += cu * (hist_arm[e, 4] - g1)
                b2 += cu * (hist_arm[e, 5] - g2)
                mask = hist_mask[e]
                support |= mask
                for i in range(n):
                    if (mask >> i) & 1:
                        vt[i] += cu
                    if want and (mask >> (COMMANDED + i)) & 1:
                        cvt[i] += cu
            j0, j1, j2 = _mv3(Is, e0, e1, e2)
            y[3], y[4], y[5] = j0 / T - b0, j1 / T - b1, j2 / T - b2
            for r in range(3):
                k = 0
                for i in range(n):
                    if vt[i] != 0.0:
                        hc[3 + r, k] = 6 * i + 3 + r
                        hv[3 + r, k] = vt[i]
                        k += 1
                hc[3 + r, k] = 6 * n + 3 + r
                hv[3 + r, k] = 1.0
                hn[3 + r] = k + 1
                R[3 + r] = cst[_R_MOM + r] * cst[_RSCALE]
            m = 6
    if leak is not None and Wleak is not None:
        for i in range(n):
            li = leak[i]
            if li == 0.0:
                continue
            ca = li * (1.0 - cnt[i] / nn)
            for r in range(3):
                acc = 0.0
                for q in range(6):
                    acc += Ha[6 * r + q] * Wleak[i, q]
                y[r] -= ca * acc
            if m == 6:
                for r in range(3):
                    y[3 + r] -= li * (1.0 - vt[i]) * Wleak[i, 3 + r]
    # random walk since the last update (the whole diagonal)
    if ist[_HAVE_LAST] != 0:
        dt = max(0.0, float(t_ns - ist[_LAST_NS]) * 1e-9)
        for i in range(ns):
            P[i, i] += Q[i] * dt
    ist[_HAVE_LAST] = 1
    ist[_LAST_NS] = t_ns
    if want:
        _tap(x, P, m, y, hc, hv, hn, R, cnt, float(nn), vt, ccnt, cvt, tap)
    if not learn > 0.0:
        return True
    support &= (np.int64(1) << n) - 1
    if support & ~ist[_ACTIVE]:
        _set_runs(ist, n, ist[_ACTIVE] | support)
    if hold == 0:
        done = _update(x, P, ist, m, y, hc, hv, hn, R, learn)
    else:
        done = _held_update(x, P, ist, m, y, hc, hv, hn, R, learn, hold, n)
    if done == _NOT_PD:
        raise ValueError("innovation covariance not positive definite")
    if done == _APPLIED:
        ist[_UPDATES] += 1
    return True


@_jit
def run_events(x: F64, P: F64, Q: F64, cst: F64, c: F64, hist_t: I64, hist_arm: F64, hist_mask: I64, ist: I64,
               fst: F64, kind: I64, t_ns: I64, arm: F64, masks: I64, accel: F64, rate: F64, out_wrench: F64,
               out_applied: npt.NDArray[np.int8]) -> None:
    """Apply an ordered event stream: event k of kind ``kind[k]`` (STEP, IMU, WRENCH_ONLY) at
    ``t_ns[k]`` with ``arm[k]`` (6,), ``masks[k]`` (STEP, WRENCH_ONLY) or ``accel[k]``, ``rate[k]``
    (3,) each, IMU frame (IMU). Writes ``out_wrench[k]`` (STEP and WRENCH_ONLY: the thruster
    wrench of the step with the estimate before it, body frame, N, N m; zero for IMU) and
    ``out_applied[k]`` (IMU: 1 if applied; 0 otherwise). Any other kind is a WRENCH_ONLY. An
    innovation covariance that is not positive definite raises ``ValueError`` (:func:`imu`), the
    events before it applied."""
    for k in range(kind.shape[0]):
        kd = kind[k]
        out_applied[k] = 0
        if kd == IMU:
            for q in range(6):
                out_wrench[k, q] = 0.0
            out_applied[k] = imu(x, P, Q, cst, c, hist_t, hist_arm, hist_mask, ist, fst, t_ns[k], accel[k], rate[k])
        else:
            wrench(x, masks[k], out_wrench[k])
            if kd == STEP:
                push_epoch(hist_t, hist_arm, hist_mask, ist, t_ns[k], arm[k], masks[k])


# -- the wrapper ---------------------------------------------------------------------------------
class CompiledThrusterFilter:
    """:class:`.thrusters.ThrusterFilter` on compiled kernels: per-valve wrenches ``W`` (n, 6) plus
    6 bias states, valves given as bitmasks (bit i = valve i open, n <= 32).

    ``x`` and ``P`` are the live state arrays. Writing into them is allowed with two rules the
    update relies on: P stays bitwise symmetric, and a valve that has never been open in an
    update keeps zero cross-covariance (its rows are skipped until it is; with a shared gain in
    the prior every valve is active from the start)."""

    def __init__(self, model: EstimatorModel, layout: ThrusterLayout, *, dt: float = 1e-3, imu_steps: int = 2,
                 settings: ThrusterFilterSettings | None = None):
        # the prior and constants are the numpy form's, computed by it
        ref = ThrusterFilter(model, layout, dt=dt, imu_steps=imu_steps, settings=settings)
        if ref.n > MAX_VALVES:
            raise ValueError(f"{ref.n} thrusters; valve masks carry at most {MAX_VALVES}")
        self.model, self.layout, self.settings = model, layout, ref.settings
        self.n, self.ns, self.dt, self.imu_steps = ref.n, ref.ns, dt, imu_steps
        # P symmetrised once: the update keeps it bitwise symmetric from then on
        self._x = ref.x.copy()
        self._P = np.ascontiguousarray(0.5 * (ref.P + ref.P.T))
        self._Q = np.ascontiguousarray(ref.Q_per_s, dtype=np.float64)
        cst = np.zeros(_NCST)
        cst[_M], cst[_DT], cst[_STEP_NS], cst[_R_ACC] = ref.m, dt, ref.dt * 1e9, ref.r_acc
        cst[_R_MOM:_R_MOM + 3] = ref.r_mom
        cst[_I:_I + 9] = np.asarray(ref.I, dtype=float).reshape(9)
        cst[_IINV:_IINV + 9] = np.asarray(ref.I_inv, dtype=float).reshape(9)
        cst[_RIMU:_RIMU + 9] = np.asarray(ref.R_imu, dtype=float).reshape(9)
        cst[_RV:_RV + 3] = ref.r
        cst[_HA:_HA + 18] = ref.Ha.reshape(18)
        cst[_T] = imu_steps * dt
        cst[_RSCALE] = 1.0                 # the IMU noise as configured (set_noise_scale)
        self._cst = cst
        self._c = np.ascontiguousarray(ref.c, dtype=np.float64)
        K = 2 * imu_steps + 2
        self._hist_t = np.zeros(K, dtype=np.int64)
        self._hist_arm = np.zeros((K, 6))
        self._hist_mask = np.zeros(K, dtype=np.int64)
        self._ist = np.zeros(_RUNS + 2 * (self.n + 1), dtype=np.int64)
        self._fst = np.zeros(6)
        # a prior with a shared gain correlates every valve with every other: all active from the start
        shared = self.settings.common_gain_sigma > 0.0
        _set_runs(self._ist, self.n, np.int64((1 << self.n) - 1) if shared else np.int64(0))
        self._state: State = (self._x, self._P, self._Q, self._cst, self._c, self._hist_t, self._hist_arm,
                              self._hist_mask, self._ist, self._fst)

    @property
    def state(self) -> State:
        """The arrays the kernels take first, ``(x, P, Q_per_s, cst, c, hist_t, hist_arm, hist_mask,
        ist, fst)``: ``imu(*kf.state, t_ns, accel, rate)``, ``run_events(*kf.state, ...)``;
        ``push_epoch`` takes ``hist_t, hist_arm, hist_mask, ist``. The live arrays, updated in place."""
        return self._state

    def share(self, arrays: Iterable[np.ndarray]) -> None:
        """Work on ``arrays`` from now on: the same shapes, dtypes and order as :attr:`state`,
        e.g. views of a caller's state buffer (the compiled estimator keeps all its state in two
        buffers). The current values are copied into them first."""
        given = tuple(arrays)
        if len(given) != len(self._state) or any(a.shape != b.shape or a.dtype != b.dtype
                                                 for a, b in zip(given, self._state)):
            raise ValueError("share() needs arrays shaped like CompiledThrusterFilter.state")
        for a, b in zip(given, self._state):
            a[...] = b
        (self._x, self._P, self._Q, self._cst, self._c, self._hist_t, self._hist_arm, self._hist_mask,
         self._ist, self._fst) = given
        self._state = (self._x, self._P, self._Q, self._cst, self._c, self._hist_t, self._hist_arm,
                       self._hist_mask, self._ist, self._fst)

    # -- the estimate ----------------------------------------------------------------------------
    @property
    def x(self) -> np.ndarray:
        """(6 n + 6,) the state: ``W`` row by row, then the bias. The live array."""
        return self._x

    @property
    def P(self) -> np.ndarray:
        """(ns, ns) the state covariance. The live array."""
        return self._P

    @property
    def W(self) -> np.ndarray:
        """(n, 6) current estimate of each valve's wrench ``[force (N); moment about C (N m)]``,
        body frame (a view of ``x``)."""
        return self._x[:6 * self.n].reshape(self.n, 6)

    @property
    def bias(self) -> np.ndarray:
        """The bias states ``[force (N); moment (N m)]`` as seen by the IMU and F/T sensors."""
        return self._x[6 * self.n:]

    @property
    def w(self) -> np.ndarray:
        """(3,) latest gyro rate, body frame, rad/s (zero before the first IMU sample)."""
        return self._fst[_W:_W + 3].copy()

    @property
    def updates(self) -> int:
        """IMU samples applied so far."""
        return int(self._ist[_UPDATES])

    def wrench(self, valves_mask: int) -> np.ndarray:
        """Thruster wrench ``[f; tau]`` (6,) of a step with the valves ``valves_mask`` open (body
        frame, force through C, moment about C; N, N m). A new array."""
        out = np.empty(6)
        wrench(self._x, valves_mask, out)
        return out

    def efficiency(self) -> np.ndarray:
        """Per thruster: estimated thrust along the nominal direction / nominal thrust."""
        eff: np.ndarray = np.einsum("ij,ij->i", self.W[:, :3], self.layout.dir) / self.layout.max_n
        return eff

    # -- inputs ----------------------------------------------------------------------------------
    def push_epoch(self, t_ns: int, arm_wrench: np.ndarray, valves_mask: int) -> None:
        """Record one trusted step at ``t_ns``: the arms' wrench on the spacecraft ``arm_wrench``
        (6,) (body frame, about C; N, N m) and the valves open during it (bitmask)."""
        push_epoch(self._hist_t, self._hist_arm, self._hist_mask, self._ist, t_ns,
                   np.ascontiguousarray(arm_wrench, dtype=np.float64), valves_mask)

    def imu(self, t_ns: int, accel_imu: np.ndarray, rate_imu: np.ndarray) -> bool:
        """Apply one IMU sample (IMU frame; m/s^2, rad/s) covering the ``imu_steps`` steps that end
        at ``t_ns``. False (nothing applied) when a step of its interval is missing."""
        try:
            return imu(*self._state, t_ns, np.ascontiguousarray(accel_imu, dtype=np.float64),
                       np.ascontiguousarray(rate_imu, dtype=np.float64))
        except ValueError as exc:
            raise np.linalg.LinAlgError(str(exc)) from None

    def run(self, kind: np.ndarray, t_ns: np.ndarray, arm: np.ndarray | None = None,
            masks: np.ndarray | None = None, accel: np.ndarray | None = None,
            rate: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Apply an ordered event stream (see :func:`run_events`): ``kind`` (N,) (STEP, IMU,
        WRENCH_ONLY), ``t_ns`` (N,) int ns, ``arm`` (N, 6), ``masks`` (N,) int, ``accel`` and ``rate``
        (N, 3), IMU frame; rows a kind does not use are ignored (None: zeros). Returns the thruster
        wrench of each step ``(N, 6)`` (zero rows for IMU events) and whether each IMU sample was
        applied ``(N,)`` bool. Raises ``np.linalg.LinAlgError`` as :meth:`imu` does, the events
        before the failing one applied."""
        kind = np.ascontiguousarray(kind, dtype=np.int64)
        N = kind.shape[0]
        if N and not np.isin(kind, (STEP, IMU, WRENCH_ONLY)).all():
            raise ValueError(f"event kinds are {STEP} (step), {IMU} (IMU sample) or {WRENCH_ONLY} (wrench only)")

        def rows(a: np.ndarray | None, width: int, dtype: npt.DTypeLike = np.float64) -> np.ndarray:
            if a is None:
                return np.zeros((N, width) if width else N, dtype=dtype)
            a = np.ascontiguousarray(a, dtype=dtype)
            if a.shape != ((N, width) if width else (N,)):
                raise ValueError(f"expected {N} rows, got shape {a.shape}")
            return a

        t = rows(t_ns, 0, np.int64)
        out_w = np.zeros((N, 6))
        out_a = np.zeros(N, dtype=np.int8)
        try:
            run_events(*self._state, kind, t, rows(arm, 6), rows(masks, 0, np.int64), rows(accel, 3),
                       rows(rate, 3), out_w, out_a)
        except ValueError as exc:
            raise np.linalg.LinAlgError(str(exc)) from None
        return out_w, out_a.astype(bool)
