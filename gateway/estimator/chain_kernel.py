"""One compiled (numba) kernel for a whole estimator epoch: base motion, joint torques, joint
accelerations, no Pinocchio, no BLAS/LAPACK.

Per epoch, from the F/T readings ``ft`` (p, 6), the thruster wrench ``thr`` (6,), the spacecraft
rate ``w_s`` (3,) and the joint state ``q``, ``dq`` (n_joints,):

- ``arm_w`` (6,): the arms' wrench on the spacecraft, ``-sum_j A_s(j) w_j``; body frame, force
  through C, moment about C; N, N m (``wrench.arm_reaction``);
- ``a_s = (thr_f + arm_f) / m_s`` (m/s^2, classical acceleration of C) and
  ``dw_s = I_s^-1 ((thr_t + arm_t) - w_s x I_s w_s)`` (rad/s^2); body frame;
- ``simp`` (n_joints,): the paper's simplified torques ``A_tau(q) w``, N m;
- ``ddq`` (n_joints,): joint accelerations (rad/s^2): the joint filter's (:mod:`.joint_filter`,
  F/T rows and encoder rates); with the filter off, or at its start, per arm the weighted
  minimum-norm least-squares solution of ``J ddq = w - w0`` (``torques.joint_accelerations_from_ft``);
- ``full`` (n_joints,): the joint torques, N m. With the joint filter: the distal side, the
  model's wrench for the filtered ``ddq`` (``w0 + J ddq``) carried down the chain, i.e. the model's
  inverse dynamics of the links beyond each joint (``torques._rnea``); with it off, the sensor
  side ``tau = A_tau w - h(q, dq, ddq, a_s, w_s, dw_s)`` (paper eq. 11).

A recursive Newton-Euler pass over each serial chain, one sample at a time in explicit loops, in
each joint's internal frame (joint axis +z, :class:`.model.ChainLink`); its test oracle is the
Pinocchio form in :mod:`.torques`. Per arm:

1. forward: twist and acceleration (``ddq = 0``) of each link from the base's, the measured
   wrench carried from C down the chain (its axis component is the simplified torque), each
   link's inertial wrench ``I a + v x* I v`` and the wrenches ``I a_k`` of unit accelerations of
   every proximal joint k (zero velocity: the columns of ``J``);
2. backward: those wrenches summed from the tip back to C, then to the sensor frame: ``w0`` (the
   sensor wrench the model predicts with ``ddq = 0``) and ``J``;
3. ``ddq``: Householder QR of the weighted ``J``, a one-sided Jacobi SVD when it is near rank
   deficiency (:func:`_lstsq`: lstsq's minimum-norm answer either way); then the joint filter's
   predict and update with ``J``, ``w0`` and the rates (it starts from the least-squares ``ddq``);
4. forward again with ``ddq``: the wrench (the model's with the filter, else the measured one)
   carried down the chain, each proximal link's inertial wrench taken off; the axis component at
   joint i is ``full_i``.

Bits: every epoch runs the same scalar operations in a fixed order (explicit loops, no
reductions, no BLAS, ``fastmath=False`` so no reassociation or fused multiply-add), and only the
joint filter's state carries from one epoch to the next, in epoch order, so a batch of N, any
split of it and N calls of one give the same bits. They differ from Pinocchio's and LAPACK's at
~1e-12 relative.

Usage::

    kernel = EpochKernel(EstimatorModel.from_robot(robot_description.load("three_arm")))
    simp, ddq, full, a_s, dw_s, arm_w = kernel.epoch(q, dq, ft, thr, w_s)        # live
    simp, ddq, full, a_s, dw_s, arm_w = kernel.batch(Q, DQ, FT, THR, W_S)        # (B, ...) replay
"""
from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import numpy as np
import numpy.typing as npt

from . import joint_filter as jf
from .jitopts import jit as _jit, jit_alloc as _jit_alloc   # numba's njit: IEEE, no fast-math (the bits are fixed)
from .model import ChainLink, EstimatorModel, EstimatorModelError, skew

WEIGHTS = (4.0, 4.0, 4.0, 40.0, 40.0, 40.0)
"""Default least-squares weights of the F/T channels ``[f, t]``: 1/sigma, force 1/0.25 N, moment
1/0.025 N m (the same as ``torques.joint_accelerations_from_ft``'s default)."""

MAX_ARM_JOINTS = 6
QR_SAFETY = 1e-4          # QR's solution is lstsq's when rcond * kappa_F stays below this
_EPS = float(np.finfo(np.float64).eps)
_MAX_SWEEPS = 60          # one-sided Jacobi converges quadratically: 4-7 sweeps for 6 columns

F64 = npt.NDArray[np.float64]     # any shape: each function's docstring gives it
I64 = npt.NDArray[np.int64]
Outputs = tuple[F64, F64, F64, F64, F64, F64]
"""``(simp, ddq, full, a_s, dw_s, arm_w)`` of :meth:`EpochKernel.epoch` and :meth:`EpochKernel.batch`."""

# layout of ChainArrays.link[j, i]: one link of arm j, internal frames (axis +z)
_LINK = 25                # C (9, row-major) | t (3) | m | h = m c (3) | Io (9, row-major)
_T, _M, _H, _IO = 9, 12, 13, 16
_BASE = 19                # m_s | I_s (9) | I_s^-1 (9)


class ChainArrays(NamedTuple):
    """An :class:`EstimatorModel` as flat float64/int64 arrays for the kernel, arms padded to the
    longest chain ``L`` (padding is zero and never read).

    - ``arm_n`` (p,) int64: joints of each arm; ``arm_col`` (p,) int64: the arm's first column in
      the joint vectors (an arm's columns are contiguous);
    - ``sensor`` (p, 15): ``R_j`` (sensor -> body, row-major, 9), ``r_j = S_j - C`` (body, m),
      and the end effector in the last link's internal frame (m: where a contact acts);
    - ``link`` (p, L, 25): per link, from :class:`.model.ChainLink`: ``C`` (parent internal frame
      -> this internal frame at q = 0, row-major), ``t`` (this joint's origin in the parent's
      internal frame, m; the body frame at C for the first joint), mass ``m`` (kg), first moment
      ``h = m c`` (kg m, CoM ``c`` from the joint origin) and ``Io`` (kg m^2, about the joint
      origin), all in this link's internal frame;
    - ``base`` (19,): ``m_s`` (kg), ``I_s`` and ``I_s^-1`` (row-major; body frame, about C).
    """

    arm_n: I64
    arm_col: I64
    sensor: F64
    link: F64
    base: F64


def pack(model: EstimatorModel) -> ChainArrays:
    """The kernel's arrays, built once. Raises :class:`EstimatorModelError` for an arm of more than
    ``MAX_ARM_JOINTS`` joints or columns that are not contiguous per arm."""
    p = model.n_arms
    L = max((len(a.chain) for a in model.arms), default=0)
    arm_n = np.zeros(p, dtype=np.int64)
    arm_col = np.zeros(p, dtype=np.int64)
    sensor = np.zeros((p, 15))
    link = np.zeros((p, max(L, 1), _LINK))
    for j, arm in enumerate(model.arms):
        n = len(arm.chain)
        if n > MAX_ARM_JOINTS:
            raise EstimatorModelError(f"arm {arm.name!r}: {n} joints; the kernel takes at most {MAX_ARM_JOINTS}")
        if arm.index != j or tuple(arm.columns) != tuple(range(arm.columns[0], arm.columns[0] + n)):
            raise EstimatorModelError(f"arm {arm.name!r}: columns {arm.columns} are not contiguous")
        arm_n[j], arm_col[j] = n, arm.columns[0]
        rb = model.robot.arms[j]
        sensor[j, :9] = np.asarray(rb.R_sc, dtype=float).reshape(9)
        sensor[j, 9:12] = rb.r_sc
        sensor[j, 12:15] = arm.ee_point
        for i, lk in enumerate(arm.chain):
            C = lk.X_motion[:3, :3]
            St = -C.T @ lk.X_motion[:3, 3:]            # X_motion[:3, 3:] = -C S(t)
            I6 = lk.inertia
            Sh = I6[3:, :3]                            # m S(c)
            row = link[j, i]
            row[:9] = C.reshape(9)
            row[_T:_T + 3] = (St[2, 1], St[0, 2], St[1, 0])
            row[_M] = I6[0, 0]
            row[_H:_H + 3] = (Sh[2, 1], Sh[0, 2], Sh[1, 0])
            row[_IO:_IO + 9] = I6[3:, 3:].reshape(9)
            _check_link(arm.name, i, lk, row)
    base = np.zeros(_BASE)
    base[0] = model.mass_s
    base[1:10] = model.inertia_s.reshape(9)
    base[10:19] = model.inertia_s_inv.reshape(9)
    arrays = ChainArrays(arm_n, arm_col, sensor, link, base)
    for a in arrays:
        a.setflags(write=False)
    return arrays


def _check_link(arm: str, i: int, lk: ChainLink, row: np.ndarray) -> None:
    # The kernel applies X_motion, X_force and the inertia in structured form: fail here, not
    # with wrong torques, if ChainLink's conventions ever change.
    C, t, m, h, Io = row[:9].reshape(3, 3), row[_T:_T + 3], row[_M], row[_H:_H + 3], row[_IO:].reshape(3, 3)
    Xm = np.block([[C, -C @ skew(t)], [np.zeros((3, 3)), C]])
    Xf = np.block([[C, np.zeros((3, 3))], [-C @ skew(t), C]])
    I6 = np.block([[m * np.eye(3), -skew(h)], [skew(h), Io]])
    for name, got, want in (("X_motion", Xm, lk.X_motion), ("X_force", Xf, lk.X_force), ("inertia", I6, lk.inertia)):
        if not np.allclose(got, want, rtol=0.0, atol=1e-12 * max(1.0, float(np.abs(want).max()))):
            raise EstimatorModelError(f"arm {arm!r} link {i}: {name} is not in the form the kernel assumes")


# --- 6-vector transforms, in place allowed (every input is read before an output is written) ----

@_jit
def _to_child(lk: F64, c: float, s: float, x: F64, y: F64, tr: int, pu: int) -> None:
    """y = Rz(q)^T [C (x_tr - t x x_pu); C x_pu]: a spatial vector from the parent's internal frame
    to this joint's (``c, s = cos q, sin q``). ``x_tr`` is the triple at offset ``tr``, the one that
    changes with the reference point (a twist's linear velocity, a wrench's moment), ``x_pu`` the
    one at ``pu`` that does not."""
    t0, t1, t2 = lk[9], lk[10], lk[11]
    w0, w1, w2 = x[pu], x[pu + 1], x[pu + 2]
    u0 = x[tr] - (t1 * w2 - t2 * w1)
    u1 = x[tr + 1] - (t2 * w0 - t0 * w2)
    u2 = x[tr + 2] - (t0 * w1 - t1 * w0)
    a0 = lk[0] * u0 + lk[1] * u1 + lk[2] * u2
    a1 = lk[3] * u0 + lk[4] * u1 + lk[5] * u2
    a2 = lk[6] * u0 + lk[7] * u1 + lk[8] * u2
    b0 = lk[0] * w0 + lk[1] * w1 + lk[2] * w2
    b1 = lk[3] * w0 + lk[4] * w1 + lk[5] * w2
    b2 = lk[6] * w0 + lk[7] * w1 + lk[8] * w2
    y[tr] = c * a0 + s * a1
    y[tr + 1] = c * a1 - s * a0
    y[tr + 2] = a2
    y[pu] = c * b0 + s * b1
    y[pu + 1] = c * b1 - s * b0
    y[pu + 2] = b2


@_jit
def _motion_to_child(lk: F64, c: float, s: float, x: F64, y: F64) -> None:
    """y = Rz(q)^T X_motion x, a twist (linear, angular)."""
    _to_child(lk, c, s, x, y, 0, 3)


@_jit
def _force_to_child(lk: F64, c: float, s: float, x: F64, y: F64) -> None:
    """y = Rz(q)^T X_force x, a wrench (force, moment; the moment moves to the joint origin)."""
    _to_child(lk, c, s, x, y, 3, 0)


@_jit
def _force_to_parent(lk: F64, c: float, s: float, x: F64, y: F64) -> None:
    """The inverse of :func:`_force_to_child`: a wrench from this joint's internal frame to the
    parent's (moment about the parent's origin)."""
    a0 = c * x[0] - s * x[1]
    a1 = s * x[0] + c * x[1]
    a2 = x[2]
    b0 = c * x[3] - s * x[4]
    b1 = s * x[3] + c * x[4]
    b2 = x[5]
    f0 = lk[0] * a0 + lk[3] * a1 + lk[6] * a2
    f1 = lk[1] * a0 + lk[4] * a1 + lk[7] * a2
    f2 = lk[2] * a0 + lk[5] * a1 + lk[8] * a2
    t0, t1, t2 = lk[9], lk[10], lk[11]
    y[0] = f0
    y[1] = f1
    y[2] = f2
    y[3] = (lk[0] * b0 + lk[3] * b1 + lk[6] * b2) + (t1 * f2 - t2 * f1)
    y[4] = (lk[1] * b0 + lk[4] * b1 + lk[7] * b2) + (t2 * f0 - t0 * f2)
    y[5] = (lk[2] * b0 + lk[5] * b1 + lk[8] * b2) + (t0 * f1 - t1 * f0)


@_jit
def _inertia(lk: F64, x: F64, y: F64) -> None:
    """y = I x, the link's spatial inertia about its joint origin: ``f = m v - h x w``,
    ``n = h x v + Io w`` (x = (v, w))."""
    m = lk[12]
    h0, h1, h2 = lk[13], lk[14], lk[15]
    v0, v1, v2, w0, w1, w2 = x[0], x[1], x[2], x[3], x[4], x[5]
    y[0] = m * v0 - (h1 * w2 - h2 * w1)
    y[1] = m * v1 - (h2 * w0 - h0 * w2)
    y[2] = m * v2 - (h0 * w1 - h1 * w0)
    y[3] = (h1 * v2 - h2 * v1) + (lk[16] * w0 + lk[17] * w1 + lk[18] * w2)
    y[4] = (h2 * v0 - h0 * v2) + (lk[19] * w0 + lk[20] * w1 + lk[21] * w2)
    y[5] = (h0 * v1 - h1 * v0) + (lk[22] * w0 + lk[23] * w1 + lk[24] * w2)


@_jit
def _velocity_product(lk: F64, V: F64, tmp: F64, y: F64) -> None:
    """y = v x* (I v), the gyroscopic part of the link's inertial wrench (V = (v, w)); tmp: 6 scratch."""
    _inertia(lk, V, tmp)
    v0, v1, v2, w0, w1, w2 = V[0], V[1], V[2], V[3], V[4], V[5]
    p0, p1, p2, l0, l1, l2 = tmp[0], tmp[1], tmp[2], tmp[3], tmp[4], tmp[5]
    y[0] = w1 * p2 - w2 * p1
    y[1] = w2 * p0 - w0 * p2
    y[2] = w0 * p1 - w1 * p0
    y[3] = (w1 * l2 - w2 * l1) + (v1 * p2 - v2 * p1)
    y[4] = (w2 * l0 - w0 * l2) + (v2 * p0 - v0 * p2)
    y[5] = (w0 * l1 - w1 * l0) + (v0 * p1 - v1 * p0)


@_jit
def _joint_motion(V: F64, qd: float, A: F64) -> None:
    """A += v_i x S dq_i (S = +z angular): the velocity-product acceleration of joint i."""
    A[0] += V[1] * qd
    A[1] -= V[0] * qd
    A[3] += V[4] * qd
    A[4] -= V[3] * qd


_sensor_to_c = jf.sensor_to_c   # y = A_s(j) x: a sensor wrench (sensor frame, about S_j) about C, body frame


@_jit
def _c_to_sensor(sr: F64, x: F64, y: F64) -> None:
    """The inverse of :func:`_sensor_to_c`: a wrench about C (body frame) in the sensor frame about S_j."""
    f0, f1, f2 = x[0], x[1], x[2]
    r0, r1, r2 = sr[9], sr[10], sr[11]
    u0 = x[3] - (r1 * f2 - r2 * f1)
    u1 = x[4] - (r2 * f0 - r0 * f2)
    u2 = x[5] - (r0 * f1 - r1 * f0)
    y[0] = sr[0] * f0 + sr[3] * f1 + sr[6] * f2
    y[1] = sr[1] * f0 + sr[4] * f1 + sr[7] * f2
    y[2] = sr[2] * f0 + sr[5] * f1 + sr[8] * f2
    y[3] = sr[0] * u0 + sr[3] * u1 + sr[6] * u2
    y[4] = sr[1] * u0 + sr[4] * u1 + sr[7] * u2
    y[5] = sr[2] * u0 + sr[5] * u1 + sr[8] * u2


# --- least squares ---------------------------------------------------------------------------------

@_jit
def _lstsq(Bt: F64, m: int, n: int, b: F64, Vm: F64, h: F64, rcond: float, x: F64, off: int) -> None:
    """x[off:off + n] = the minimum-norm least-squares solution of ``B x = b`` (what
    ``np.linalg.lstsq(B, b, rcond)`` computes), B (m, n).

    ``Bt`` (>= n, >= m): the n columns of B as rows; ``b`` (>= m,); both overwritten. Scratch:
    ``Vm`` (>= n, >= n), ``h`` (>= m,). ``rcond < 0``: ``eps * max(m, n)``, lstsq's default.

    Householder QR (``B = Q R``, ``Q^T b`` on the fly), then:

    - if ``kappa_F = |R|_F |R^-1|_F`` (>= the 2-norm condition number) is below
      ``QR_SAFETY / rcond``, no singular value can be under ``rcond * s_max``: the solution is
      unique and lstsq's, back substitution gives it (the usual case);
    - otherwise (a zero pivot, dependent columns, near rank deficiency) the one-sided Jacobi SVD of
      R (:func:`_jacobi_min_norm`) gives lstsq's minimum-norm answer, singular values below
      ``rcond * s_max`` counted as zero: dependent columns share the solution, nothing blows up.

    Wide B (n > m) goes to the Jacobi SVD directly.
    """
    if rcond < 0.0:
        rcond = _EPS * max(m, n)
    if n > m:
        _jacobi_min_norm(Bt, m, n, b, Vm, rcond, x, off)
        return
    for k in range(n):
        ss = 0.0
        for r in range(k, m):
            ss += Bt[k, r] * Bt[k, r]
        if ss == 0.0:
            continue                        # nothing left in this column: R_kk = 0
        x0 = Bt[k, k]
        alpha = -math.sqrt(ss) if x0 >= 0.0 else math.sqrt(ss)    # no cancellation in x0 - alpha
        h[k] = x0 - alpha
        vtv = h[k] * h[k]
        for r in range(k + 1, m):
            h[r] = Bt[k, r]
            vtv += h[r] * h[r]
        beta = 2.0 / vtv
        for l in range(k + 1, n):
            s = 0.0
            for r in range(k, m):
                s += h[r] * Bt[l, r]
            s *= beta
            for r in range(k, m):
                Bt[l, r] -= s * h[r]
        s = 0.0
        for r in range(k, m):
            s += h[r] * b[r]
        s *= beta
        for r in range(k, m):
            b[r] -= s * h[r]
        Bt[k, k] = alpha
        for r in range(k + 1, m):
            Bt[k, r] = 0.0
    # R[i, k] = Bt[k, i] (i <= k); R^-1 into Vm for the condition number
    full_rank = True
    for k in range(n):
        if Bt[k, k] == 0.0:
            full_rank = False
    if full_rank:
        rf = 0.0
        vf = 0.0
        for k in range(n):
            Vm[k, k] = 1.0 / Bt[k, k]
            for i in range(k - 1, -1, -1):
                s = 0.0
                for l in range(i + 1, k + 1):
                    s += Bt[l, i] * Vm[l, k]
                Vm[i, k] = -s / Bt[i, i]
            for i in range(k + 1):
                rf += Bt[k, i] * Bt[k, i]
                vf += Vm[i, k] * Vm[i, k]
        if math.sqrt(rf) * math.sqrt(vf) * rcond <= QR_SAFETY:       # false for inf and nan
            for i in range(n - 1, -1, -1):
                s = b[i]
                for l in range(i + 1, n):
                    s -= Bt[l, i] * x[off + l]
                x[off + i] = s / Bt[i, i]
            return
    _jacobi_min_norm(Bt, n, n, b, Vm, rcond, x, off)


@_jit
def _jacobi_min_norm(Bt: F64, m: int, n: int, b: F64, Vm: F64, rcond: float, x: F64, off: int) -> None:
    """The minimum-norm least-squares solution by a one-sided Jacobi SVD (Hestenes; Demmel,
    Applied Numerical Linear Algebra, alg. 5.13): plane rotations of column pairs, in a fixed order,
    until every pair is orthogonal to ``m eps``; then ``B V = U S`` and
    ``x = sum_k V_k (u_k . b) / s_k`` over ``s_k > rcond * s_max``. Small singular values come out
    with high relative accuracy (unlike the normal equations, which square the condition number);
    an all-zero B gives x = 0. Arguments as :func:`_lstsq` (``Bt`` overwritten, ``rcond >= 0``).
    """
    tol = _EPS * m
    for k in range(n):
        for i in range(n):
            Vm[k, i] = 0.0
        Vm[k, k] = 1.0
    for sweep in range(_MAX_SWEEPS):
        rotated = False
        for i in range(n - 1):
            for k in range(i + 1, n):
                alpha = 0.0
                beta = 0.0
                gamma = 0.0
                for r in range(m):
                    alpha += Bt[i, r] * Bt[i, r]
                    beta += Bt[k, r] * Bt[k, r]
                    gamma += Bt[i, r] * Bt[k, r]
                if abs(gamma) <= tol * math.sqrt(alpha) * math.sqrt(beta):
                    continue
                rotated = True
                zeta = (beta - alpha) / (2.0 * gamma)
                az = abs(zeta)
                if az > 1.0:                   # sqrt(1 + zeta^2) without overflow
                    t = 1.0 / (az * (1.0 + math.sqrt(1.0 + (1.0 / az) * (1.0 / az))))
                else:
                    t = 1.0 / (az + math.sqrt(1.0 + az * az))
                if zeta < 0.0:
                    t = -t
                cs = 1.0 / math.sqrt(1.0 + t * t)
                sn = cs * t
                for r in range(m):
                    bi = Bt[i, r]
                    bk = Bt[k, r]
                    Bt[i, r] = cs * bi - sn * bk
                    Bt[k, r] = sn * bi + cs * bk
                for r in range(n):
                    vi = Vm[i, r]
                    vk = Vm[k, r]
                    Vm[i, r] = cs * vi - sn * vk
                    Vm[k, r] = sn * vi + cs * vk
        if not rotated:
            break
    smax = 0.0
    for k in range(n):
        ss = 0.0
        for r in range(m):
            ss += Bt[k, r] * Bt[k, r]
        smax = max(smax, math.sqrt(ss))
    for i in range(n):
        x[off + i] = 0.0
    for k in range(n):
        ss = 0.0
        ub = 0.0
        for r in range(m):
            ss += Bt[k, r] * Bt[k, r]
            ub += Bt[k, r] * b[r]
        if math.sqrt(ss) > rcond * smax:
            d = ub / ss
            for i in range(n):
                x[off + i] += Vm[k, i] * d


def lstsq_min_norm(a: np.ndarray, b: np.ndarray, rcond: float | None = None, qr: bool = True) -> np.ndarray:
    """The kernel's least squares on its own: ``np.linalg.lstsq(a, b, rcond)[0]`` for ``a`` (m, n),
    ``b`` (m,). ``qr=False`` forces the Jacobi SVD (both paths are tested against LAPACK)."""
    a = np.asarray(a, dtype=float)
    m, n = a.shape
    x = np.empty(n)
    Bt = np.array(a.T, order="C")
    bb = np.array(b, dtype=float)
    rc = -1.0 if rcond is None else float(rcond)
    if qr:
        _lstsq(Bt, m, n, bb, np.empty((n, n)), np.empty(m), rc, x, 0)
    else:
        _jacobi_min_norm(Bt, m, n, bb, np.empty((n, n)), _EPS * max(m, n) if rc < 0.0 else rc, x, 0)
    return x


# --- the epoch -------------------------------------------------------------------------------------

@_jit
def _chain_start(a_s: F64, dw_s: F64, g: F64, A: F64, G: F64) -> None:
    """A = the base's spatial acceleration at C (a_s, dw_s); G = the arm's sensor wrench at C."""
    for k in range(3):
        A[k] = a_s[k]
        A[3 + k] = dw_s[k]
    for k in range(6):
        G[k] = g[k]


@_jit
def _epoch(arm_n: I64, arm_col: I64, sensor: F64, link: F64, base: F64, wt: F64, rcond: float, q: F64, dq: F64,
           ft: F64, thr: F64, w_s: F64, simp: F64, ddq: F64, full: F64, a_s: F64, dw_s: F64, arm_w: F64,
           gc: F64, per: F64, U: F64, FU: F64, W: F64, Bt: F64, Vm: F64, cs: F64, vec: F64,
           dt: float, ft_ok: I64, rate_ok: I64, fst: F64, fP: F64, fc: F64, fh: F64) -> None:
    """One epoch into the output rows; ``gc`` .. ``vec`` are scratch (see :func:`_scratch`).

    The joint filter (:mod:`.joint_filter`, on when ``fc[C_ON]``): ``dt`` (s) since the last
    epoch, ``ft_ok`` (p,) / ``rate_ok`` (n_joints,) nonzero where this epoch's F/T sample / encoder
    rate may be applied, ``fst`` (p, ROW) and ``fP`` (p, MAX_STATE, MAX_STATE) its state,
    ``fc`` its constants, ``fh`` (SCRATCH_ROWS, MAX_STATE) scratch."""
    p = arm_n.shape[0]
    # the arms' wrench on the spacecraft and the base motion
    for k in range(6):
        arm_w[k] = 0.0
    if not (dt > 0.0 and dt <= fc[jf.C_MAX_DT]):       # the first epoch, or after a silence: start again
        for j in range(p):
            fst[j, jf.S_STARTED] = 0.0
    for j in range(p):
        _sensor_to_c(sensor[j], ft[j], gc[j])
        for k in range(6):
            arm_w[k] += gc[j, k]
    for k in range(6):
        arm_w[k] = -arm_w[k]
    # the base motion from the arms' wrench less the F/T biases the joint filter has learnt up to
    # the last epoch: an arm's bias moves the base's acceleration in the model, and with it that
    # arm's predicted wrench by a comparable amount (an arm's inertia about C can exceed the
    # spacecraft's), which would leave the bias all but unobservable. arm_w itself, for the
    # thruster filter (which has bias states of its own), stays the measured one.
    V, A, G, Gd, tmp, bw, hv = vec[0], vec[1], vec[2], vec[3], vec[4], vec[5], vec[6]
    for k in range(6):
        bw[k] = arm_w[k]
    if fc[jf.C_ON] != 0.0:
        for j in range(p):
            if fst[j, jf.S_STARTED] != 0.0:
                _sensor_to_c(sensor[j], fst[j, 2 * arm_n[j]:2 * arm_n[j] + 6], tmp)
                for k in range(6):
                    bw[k] += tmp[k]
    m_s = base[0]
    for k in range(3):
        a_s[k] = (thr[k] + bw[k]) / m_s
    w0, w1, w2 = w_s[0], w_s[1], w_s[2]
    i0 = base[1] * w0 + base[2] * w1 + base[3] * w2
    i1 = base[4] * w0 + base[5] * w1 + base[6] * w2
    i2 = base[7] * w0 + base[8] * w1 + base[9] * w2
    t0 = (thr[3] + bw[3]) - (w1 * i2 - w2 * i1)
    t1 = (thr[4] + bw[4]) - (w2 * i0 - w0 * i2)
    t2 = (thr[5] + bw[5]) - (w0 * i1 - w1 * i0)
    for k in range(3):
        dw_s[k] = base[10 + 3 * k] * t0 + base[11 + 3 * k] * t1 + base[12 + 3 * k] * t2

    for j in range(p):
        n = arm_n[j]
        c0 = arm_col[j]
        lks = link[j]
        # 1. forward, ddq = 0: the base twist (linear velocity of C zero: forces do not depend on it)
        for k in range(3):
            V[k] = 0.0
            V[3 + k] = w_s[k]
        _chain_start(a_s, dw_s, gc[j], A, G)
        for i in range(n):
            lk = lks[i]
            col = c0 + i
            qd = dq[col]
            c = math.cos(q[col])
            s = math.sin(q[col])
            cs[i, 0] = c
            cs[i, 1] = s
            _motion_to_child(lk, c, s, V, V)
            V[5] += qd
            _motion_to_child(lk, c, s, A, A)
            _joint_motion(V, qd, A)
            _force_to_child(lk, c, s, G, G)
            simp[col] = G[5]
            Vi, Fb, F0 = per[i, 0], per[i, 1], per[i, 2]
            for k in range(6):
                Vi[k] = V[k]
            _velocity_product(lk, V, tmp, Fb)
            _inertia(lk, A, F0)
            for k in range(6):
                F0[k] += Fb[k]
            # unit acceleration of each proximal joint k (zero velocity): carried like A
            for k in range(i):
                _motion_to_child(lk, c, s, U[k], U[k])
            for k in range(5):
                U[i, k] = 0.0
            U[i, 5] = 1.0
            for k in range(i + 1):
                _inertia(lk, U[k], FU[i, k])
        # 2. backward: W[k] = sum over links of the wrench of unit ddq_k, W[n] = the model's
        # wrench with ddq = 0; each carried from the tip to C, then to the sensor frame
        for k in range(n + 1):
            for r in range(6):
                W[k, r] = 0.0
        contact = fc[jf.C_ON] != 0.0 and fc[jf.C_CONTACT] != 0.0
        if contact:                            # unit forces at the end effector, the last link's axes
            pe = sensor[j, 12:15]
            for k in range(3):
                U3 = fh[jf.R_UNIT + k]
                for r in range(6):
                    U3[r] = 0.0
                U3[k] = 1.0
            fh[jf.R_UNIT, 4] = pe[2]           # moment about the joint origin: pe x e_k
            fh[jf.R_UNIT, 5] = -pe[1]
            fh[jf.R_UNIT + 1, 3] = -pe[2]
            fh[jf.R_UNIT + 1, 5] = pe[0]
            fh[jf.R_UNIT + 2, 3] = pe[1]
            fh[jf.R_UNIT + 2, 4] = -pe[0]
        for i in range(n - 1, -1, -1):
            lk = lks[i]
            for k in range(i + 1):
                for r in range(6):
                    W[k, r] += FU[i, k, r]
            for r in range(6):
                W[n, r] += per[i, 2, r]
            for k in range(n):                 # the distal torque's response to each ddq (fusion)
                fh[2 + i, k] = W[k, 5]
            for k in range(n + 1):
                _force_to_parent(lk, cs[i, 0], cs[i, 1], W[k], W[k])
            if contact:
                for k in range(3):
                    _force_to_parent(lk, cs[i, 0], cs[i, 1], fh[jf.R_UNIT + k], fh[jf.R_UNIT + k])
        for k in range(n + 1):
            _c_to_sensor(sensor[j], W[k], W[k])
        if contact:
            _contact_columns(sensor[j], fh[jf.R_UNIT:jf.R_UNIT + 3], fh[jf.R_G:jf.R_G + 6], fh[jf.R_EE], tmp)
        # 3. weighted least squares J ddq = w - w0, per channel weight
        for k in range(n):
            for r in range(6):
                Bt[k, r] = wt[r] * W[k, r]
        for r in range(6):
            bw[r] = wt[r] * (ft[j, r] - W[n, r])
        _lstsq(Bt, 6, n, bw, Vm, hv, rcond, ddq, c0)
        # 3b. the joint filter: ddq and the F/T bias from every sensor of the arm; the torques
        # are then the distal side, the model's wrench for the filtered ddq carried down the chain
        fused = False
        Ge = fh[jf.R_G:jf.R_G + 6]           # the contact's columns (when contact detection is on)
        if fc[jf.C_ON] != 0.0:
            st = fst[j]
            Pj = fP[j]
            if st[jf.S_STARTED] != 0.0:
                K = 2 * n + 6
                jf.predict(st, Pj, n, K + 6 if st[jf.S_MODE] != 0.0 else K, dt, fc)
                if contact:                    # may start or end a contact: the state gains or loses e
                    jf.contact_test(st, Pj, n, dt, W, ft[j], ft_ok[j] != 0, dq[c0:c0 + n], rate_ok[c0:c0 + n],
                                    sensor[j], fh[jf.R_EE], fc, tmp, fh[jf.R_S:jf.R_S + 6])
                jf.update(st, Pj, n, K + 6 if st[jf.S_MODE] != 0.0 else K, W, Ge, ft[j], ft_ok[j] != 0,
                          dq[c0:c0 + n], rate_ok[c0:c0 + n], fc, fh[0], fh[1])
                for i in range(n):
                    ddq[c0 + i] = st[n + i]
                fused = True
            elif ft_ok[j] != 0:
                jf.start(st, Pj, n, dq[c0:c0 + n], ddq[c0:c0 + n], fc)
                fused = True
            else:
                st[jf.S_STARTED] = 0.0
            ke = 2 * n + 6
            in_contact = st[jf.S_MODE] != 0.0 and fused
            for r in range(6):
                s_ = W[n, r]
                for k in range(n):
                    s_ += W[k, r] * ddq[c0 + k]
                if in_contact:                 # the contact is part of the distal side's wrench
                    for k in range(6):
                        s_ += Ge[k, r] * st[ke + k]
                bw[r] = s_
        # 4. forward with ddq: the wrench down the chain, proximal inertial wrenches off. Without
        # the filter, the measured one (the sensor side); with it, also the model's wrench for the
        # filtered ddq (the distal side) and the measured one less the bias, fused per joint
        if fused:
            for r in range(6):
                hv[r] = ft[j, r] - fst[j, 2 * n + r]
            _sensor_to_c(sensor[j], hv, tmp)
            _chain_start(a_s, dw_s, tmp, A, G)
            _sensor_to_c(sensor[j], bw, Gd)
            for r in range(6):                 # the rows of A_tau: unit wrenches down the chain
                for k in range(6):
                    bw[k] = 0.0
                bw[r] = 1.0
                _sensor_to_c(sensor[j], bw, tmp)
                for i in range(n):
                    _force_to_child(lks[i], cs[i, 0], cs[i, 1], tmp, tmp)
                    fh[8 + i, r] = tmp[5]
        else:
            _chain_start(a_s, dw_s, gc[j], A, G)
        for i in range(n):
            lk = lks[i]
            col = c0 + i
            c = cs[i, 0]
            s = cs[i, 1]
            _force_to_child(lk, c, s, G, G)
            full[col] = G[5]
            if fused:
                _force_to_child(lk, c, s, Gd, Gd)
                fh[0, i] = Gd[5]
                fh[1, i] = G[5]
            _motion_to_child(lk, c, s, A, A)
            _joint_motion(per[i, 0], dq[col], A)
            A[5] += ddq[col]
            _inertia(lk, A, tmp)
            for k in range(6):
                G[k] -= tmp[k] + per[i, 1, k]
                if fused:
                    Gd[k] -= tmp[k] + per[i, 1, k]
        if fused:
            jf.fuse(fst[j], fP[j], n, fc, fh[2:8], fh[8:14], W, Ge, hv, fh[0], fh[1], full[c0:c0 + n], fh[14])


@_jit
def _contact_columns(sr: F64, unit: F64, G: F64, pe: F64, w: F64) -> None:
    """``G`` (6, 6): the sensor wrench (sensor frame, the sign of a measured ``ft``) of each unit
    component of a contact wrench on the end effector: force along the body axes x, y, z, then
    moment about them, the moment about the end effector's point.

    ``unit`` (3, 6): unit forces along the last link's axes at the end effector, carried to C
    (body frame): their forces are the columns ``r_k`` of the rotation, their moments ``p x r_k``
    with ``p`` the end effector from C, so ``p = (sum_k r_k x (p x r_k)) / 2`` (into ``pe``). The
    F/T sensor measures what the spacecraft exerts on the arm: a contact on the arm enters it with
    a minus."""
    p0 = 0.0
    p1 = 0.0
    p2 = 0.0
    for k in range(3):
        r0, r1, r2 = unit[k, 0], unit[k, 1], unit[k, 2]
        m0, m1, m2 = unit[k, 3], unit[k, 4], unit[k, 5]
        p0 += r1 * m2 - r2 * m1
        p1 += r2 * m0 - r0 * m2
        p2 += r0 * m1 - r1 * m0
    p0 *= 0.5
    p1 *= 0.5
    p2 *= 0.5
    pe[0] = p0
    pe[1] = p1
    pe[2] = p2
    for k in range(6):
        for r in range(6):
            w[r] = 0.0
        w[k] = -1.0
        if k < 3:                              # -(e_k, p x e_k)
            f0, f1, f2 = w[0], w[1], w[2]
            w[3] = p1 * f2 - p2 * f1
            w[4] = p2 * f0 - p0 * f2
            w[5] = p0 * f1 - p1 * f0
        _c_to_sensor(sr, w, G[k])


@_jit_alloc
def _scratch(p: int, L: int) -> tuple[F64, F64, F64, F64, F64, F64, F64, F64, F64]:
    # one allocation, carved into the views _epoch uses
    sizes = (p * 6, L * 18, L * 6, L * L * 6, (L + 1) * 6, L * 6, L * L, L * 2, 42)
    total = 0
    for k in sizes:
        total += k
    buf = np.empty(total)
    o = 0
    gc = buf[o:o + sizes[0]].reshape((p, 6))
    o += sizes[0]
    per = buf[o:o + sizes[1]].reshape((L, 3, 6))    # per link: twist, v x* I v, inertial wrench at ddq = 0
    o += sizes[1]
    U = buf[o:o + sizes[2]].reshape((L, 6))
    o += sizes[2]
    FU = buf[o:o + sizes[3]].reshape((L, L, 6))
    o += sizes[3]
    W = buf[o:o + sizes[4]].reshape((L + 1, 6))
    o += sizes[4]
    Bt = buf[o:o + sizes[5]].reshape((L, 6))
    o += sizes[5]
    Vm = buf[o:o + sizes[6]].reshape((L, L))
    o += sizes[6]
    cs = buf[o:o + sizes[7]].reshape((L, 2))
    o += sizes[7]
    vec = buf[o:o + sizes[8]].reshape((7, 6))       # twist, acceleration, wrenches (2), scratch, rhs, Householder
    return gc, per, U, FU, W, Bt, Vm, cs, vec


@_jit
def _check_shapes(arm_n: I64, arm_col: I64, link: F64, wt: F64, nj: int, q: F64, dq: F64, ft: F64, thr: F64,
                  w_s: F64) -> None:
    p = arm_n.shape[0]
    if q.shape[-1] != nj or dq.shape[-1] != nj:
        raise ValueError("q and dq must have n_joints columns")
    if ft.shape[-2] != p or ft.shape[-1] != 6 or thr.shape[-1] != 6 or w_s.shape[-1] != 3 or wt.shape[0] != 6:
        raise ValueError("ft must be (p, 6), thr (6,), w_s (3,), weights (6,)")
    for j in range(p):
        if arm_n[j] < 0 or arm_n[j] > link.shape[1] or arm_col[j] < 0 or arm_col[j] + arm_n[j] > nj:
            raise ValueError("arm_n/arm_col do not fit the joint vectors")


@_jit_alloc
def epoch_kernel(arm_n: I64, arm_col: I64, sensor: F64, link: F64, base: F64, wt: F64, rcond: float, q: F64,
                 dq: F64, ft: F64, thr: F64, w_s: F64, simp: F64, ddq: F64, full: F64, a_s: F64, dw_s: F64,
                 arm_w: F64, dt: float, ft_ok: I64, rate_ok: I64, fst: F64, fP: F64, fc: F64) -> None:
    """One epoch: inputs ``q``, ``dq`` (n_joints,), ``ft`` (p, 6), ``thr`` (6,), ``w_s`` (3,);
    writes ``simp``, ``ddq``, ``full`` (n_joints,), ``a_s``, ``dw_s`` (3,), ``arm_w`` (6,); the
    joint filter's arguments as :func:`_epoch`."""
    nj = simp.shape[0]
    _check_shapes(arm_n, arm_col, link, wt, nj, q, dq, ft, thr, w_s)
    if ddq.shape[0] != nj or full.shape[0] != nj or a_s.shape[0] != 3 or dw_s.shape[0] != 3 or arm_w.shape[0] != 6:
        raise ValueError("output shapes")
    _check_filter(arm_n.shape[0], nj, ft_ok, rate_ok, fst, fP, fc)
    gc, per, U, FU, W, Bt, Vm, cs, vec = _scratch(arm_n.shape[0], link.shape[1])
    fh = np.empty((jf.SCRATCH_ROWS, jf.MAX_STATE))
    _epoch(arm_n, arm_col, sensor, link, base, wt, rcond, q, dq, ft, thr, w_s,
           simp, ddq, full, a_s, dw_s, arm_w, gc, per, U, FU, W, Bt, Vm, cs, vec, dt, ft_ok, rate_ok, fst, fP, fc, fh)


@_jit_alloc
def batch_kernel(arm_n: I64, arm_col: I64, sensor: F64, link: F64, base: F64, wt: F64, rcond: float, q: F64,
                 dq: F64, ft: F64, thr: F64, w_s: F64, simp: F64, ddq: F64, full: F64, a_s: F64, dw_s: F64,
                 arm_w: F64, dt: float, ft_ok: I64, rate_ok: I64, fst: F64, fP: F64, fc: F64) -> None:
    """B epochs (leading axis of every input and output), each exactly as :func:`epoch_kernel`, in
    order, ``dt`` apart, every sample applied (``ft_ok``, ``rate_ok`` as for one epoch)."""
    B = q.shape[0]
    nj = simp.shape[1]
    _check_shapes(arm_n, arm_col, link, wt, nj, q, dq, ft, thr, w_s)
    for x in (dq.shape[0], ft.shape[0], thr.shape[0], w_s.shape[0], simp.shape[0], ddq.shape[0],
              full.shape[0], a_s.shape[0], dw_s.shape[0], arm_w.shape[0]):
        if x != B:
            raise ValueError("every input and output needs the same leading (batch) size")
    if ddq.shape[1] != nj or full.shape[1] != nj or a_s.shape[1] != 3 or dw_s.shape[1] != 3 or arm_w.shape[1] != 6:
        raise ValueError("output shapes")
    _check_filter(arm_n.shape[0], nj, ft_ok, rate_ok, fst, fP, fc)
    gc, per, U, FU, W, Bt, Vm, cs, vec = _scratch(arm_n.shape[0], link.shape[1])
    fh = np.empty((jf.SCRATCH_ROWS, jf.MAX_STATE))
    for b in range(B):
        _epoch(arm_n, arm_col, sensor, link, base, wt, rcond, q[b], dq[b], ft[b], thr[b], w_s[b],
               simp[b], ddq[b], full[b], a_s[b], dw_s[b], arm_w[b], gc, per, U, FU, W, Bt, Vm, cs, vec,
               dt, ft_ok, rate_ok, fst, fP, fc, fh)


@_jit
def _check_filter(p: int, nj: int, ft_ok: I64, rate_ok: I64, fst: F64, fP: F64, fc: F64) -> None:
    if ft_ok.shape[0] != p or rate_ok.shape[0] != nj or fc.shape[0] != jf.N_CONST:
        raise ValueError("ft_ok must be (p,), rate_ok (n_joints,), the filter constants (N_CONST,)")
    if fst.shape[0] < p or fst.shape[1] != jf.ROW or fP.shape[0] < p or fP.shape[1] != jf.MAX_STATE \
            or fP.shape[2] != jf.MAX_STATE:
        raise ValueError("the joint filter's state must be (p, ROW) and (p, MAX_STATE, MAX_STATE)")


class EpochKernel:
    """The compiled epoch for one model: :meth:`epoch` (live, one epoch) and :meth:`batch` (replay).

    ``weights`` (6,): 1/sigma of the F/T channels for the acceleration least squares (default
    :data:`WEIGHTS`); ``rcond``: singular values of the weighted ``J`` below ``rcond * s_max``
    count as zero (``None``: ``eps * max(6, n)``, as ``np.linalg.lstsq(rcond=None)``).
    ``joint_filter``: the joint filter's settings (:mod:`.joint_filter`; ``enabled=False``: the
    least-squares accelerations and the sensor-side torques, no state); its state carries from
    one call to the next, epochs ``dt`` seconds apart (:meth:`reset` starts it again).
    """

    def __init__(self, model: EstimatorModel, weights: Sequence[float] | np.ndarray = WEIGHTS,
                 rcond: float | None = None, joint_filter: jf.JointFilterSettings | None = None, dt: float = 1e-3):
        self.model = model
        self.arrays = pack(model)
        wt = np.array(weights, dtype=float)
        if wt.shape != (6,):
            raise ValueError(f"weights must be 6 numbers, got shape {wt.shape}")
        wt.setflags(write=False)
        self.weights = wt
        self.rcond = -1.0 if rcond is None else float(rcond)
        self.n_joints, self.n_arms = model.n_joints, model.n_arms
        self.joint_filter = joint_filter or jf.JointFilterSettings()
        if not (dt > 0 and math.isfinite(dt)):
            raise ValueError(f"dt must be a time > 0 in seconds, got {dt!r}")
        self.dt = float(dt)
        self._ft_ok = np.ones(self.n_arms, dtype=np.int64)
        self._rate_ok = np.ones(self.n_joints, dtype=np.int64)
        self._fc = self.joint_filter.constants()
        self.reset()
        # private writeable copies: numba's dispatcher types read-only arrays on a slower path
        # (~0.05 us each per call) and compiles a second specialization for them
        a = self.arrays
        self._args = (a.arm_n.copy(), a.arm_col.copy(), a.sensor.copy(), a.link.copy(), a.base.copy(), wt.copy(),
                      self.rcond)

    def reset(self) -> None:
        """Forget the joint filter's state: the next epoch starts it again."""
        self.filter_state, self.filter_cov = jf.new_state(self.n_arms)

    def _filter_args(self) -> tuple[float, I64, I64, F64, F64, F64]:
        return (self.dt, self._ft_ok, self._rate_ok, self.filter_state, self.filter_cov, self._fc)

    def epoch(self, q: np.ndarray, dq: np.ndarray, ft: np.ndarray, thr: np.ndarray, w_s: np.ndarray,
              out: Outputs | None = None) -> Outputs:
        """``(simp, ddq, full, a_s, dw_s, arm_w)`` for one epoch.

        Inputs float64 arrays: ``q`` (rad), ``dq`` (rad/s) (n_joints,); ``ft`` (p, 6) sensor
        frames (N, N m); ``thr`` (6,) thruster wrench, body frame about C (N, N m); ``w_s`` (3,)
        spacecraft rate, body frame (rad/s). Outputs: torques N m, ``ddq`` rad/s^2, ``a_s`` m/s^2,
        ``dw_s`` rad/s^2, ``arm_w`` N, N m (body frame about C). Bit-identical to :meth:`batch`.

        New arrays, or ``out`` (such a 6-tuple from :meth:`outputs`) filled and returned: allocating
        the six outputs is a fifth of a live call.
        """
        if out is None:
            out = self.outputs()
        epoch_kernel(*self._args, q, dq, ft, thr, w_s, *out, *self._filter_args())
        return out

    def outputs(self) -> Outputs:
        """Output arrays for ``epoch(..., out=)``."""
        nj = self.n_joints
        return (np.empty(nj), np.empty(nj), np.empty(nj), np.empty(3), np.empty(3), np.empty(6))

    def batch(self, q: np.ndarray, dq: np.ndarray, ft: np.ndarray, thr: np.ndarray, w_s: np.ndarray) -> Outputs:
        """:meth:`epoch` over a leading axis B: ``q``, ``dq`` (B, n_joints), ``ft`` (B, p, 6),
        ``thr`` (B, 6), ``w_s`` (B, 3); outputs with the same leading axis."""
        q, dq, ft, thr, w_s = (np.ascontiguousarray(x, dtype=np.float64) for x in (q, dq, ft, thr, w_s))
        B, nj = q.shape[0], self.n_joints
        want = {"q": (B, nj), "dq": (B, nj), "ft": (B, self.n_arms, 6), "thr": (B, 6), "w_s": (B, 3)}
        for name, x in zip(want, (q, dq, ft, thr, w_s)):
            if x.shape != want[name]:
                raise ValueError(f"{name} must be {want[name]}, got {x.shape}")
        out = (np.empty((B, nj)), np.empty((B, nj)), np.empty((B, nj)), np.empty((B, 3)),
               np.empty((B, 3)), np.empty((B, 6)))
        batch_kernel(*self._args, q, dq, ft, thr, w_s, *out, *self._filter_args())
        return out
