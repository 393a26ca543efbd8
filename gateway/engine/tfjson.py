"""The robot's frame tree (``foxglove.FrameTransforms`` on ``/tf``) written as JSON by a compiled
kernel (numba), for a batch of snapshots at once: the bytes :class:`gateway.log.foxglove.FrameTransforms`'s
messages get from the recorder's JSON encoder, without building them.

A message is literal text (frame ids, translations, a fixed joint's rotation: written once, by
the recorder's own encoder) around the values of one snapshot: the log time, the spacecraft's
attitude and each moving joint's rotation, computed as :mod:`gateway.log.foxglove` computes them
(the same IEEE operations in the same order, no fast-math), rounded to its ``DIGITS`` decimals as
Python's ``round`` rounds (:func:`round_digits`) and written with CPython's ``repr``
(:mod:`gateway.engine.floatrepr`). ``tests/gateway/engine/test_tfjson.py`` compares the bytes
with the Python writer's over a simulated session.
"""
from __future__ import annotations

import math

import numpy as np

from gateway.estimator.jitopts import jit
from gateway.log.schema import encode_json

from .encode import _Builder, _lit
from .floatrepr import write_float, write_int

_jit = jit   # numba's njit with the estimator kernels' options: no reference counting (they allocate nothing)

_SPLIT = 134217729.0          # 2**27 + 1: Veltkamp's split of a double into two 26-bit halves
LIMIT = 1e6                   # |values| rounded here (a quaternion's are at most 1); larger: the Python writer


@_jit
def round_digits(x, scale):
    """``round(x, d)`` as CPython rounds it (the nearest multiple of ``10**-d``, ties to even, on
    the exact binary value), ``scale = 10.0**d`` (exact: d <= 22), for finite ``|x| * scale`` below
    2**52. CPython writes the correctly rounded decimal and reads it back; here the exact product
    ``|x| * scale`` is ``p + e`` (Dekker's product: ``e`` the rounding error of ``p``), its nearest
    integer ``f`` is decided on ``p``'s fraction and ``e``'s sign, and ``f / scale`` (IEEE: the
    correctly rounded quotient) is the double CPython reads back."""
    a = abs(x)
    p = a * scale
    c = _SPLIT * a
    ah = c - (c - a)
    al = a - ah
    c = _SPLIT * scale
    sh = c - (c - scale)
    sl = scale - sh
    e = ((ah * sh - p) + ah * sl + al * sh) + al * sl
    f = math.floor(p)
    fr = p - f                                        # exact: p < 2**52
    # fr is a multiple of p's ulp and |e| at most half of one: only at fr == 0.5 does e decide
    if fr > 0.5 or (fr == 0.5 and (e > 0.0 or (e == 0.0 and f - 2.0 * math.floor(f / 2.0) == 1.0))):
        f += 1.0
    return math.copysign(f / scale, x)


@_jit
def _qmul(aw, ax, ay, az, bw, bx, by, bz):
    """gateway.log.foxglove._qmul, term for term."""
    return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)


@_jit
def _quat(qw, qx, qy, qz, scale, buf, o, lit, keys):
    """``{"x":..,"y":..,"z":..,"w":..}`` of the quaternion, each value rounded; -1 if one is not
    finite or beyond :data:`LIMIT`. ``keys``: the four keys' literals (start, length)."""
    for k in range(4):
        v = qx if k == 0 else qy if k == 1 else qz if k == 2 else qw
        if not (abs(v) < LIMIT):
            return -1
        o = _lit(buf, o, lit, keys[k, 0], keys[k, 1])
        o = write_float(round_digits(v, scale), buf, o)
    buf[o] = 125                                      # '}'
    return o + 1


@_jit
def _encode(snap_t, snap_a, snap_q, m, imu_conj, angle_of, q0, axis, seg, heads, lit, keys, scale, buf, offsets):
    """Messages of snapshots ``0..m`` into ``buf`` (message k = ``buf[offsets[k]:offsets[k + 1]]``);
    returns the bytes written, or -1 (a value the kernel does not round: the caller writes the
    batch in Python). Transform 0 is world -> spacecraft (from ``snap_q``; left out while NaN),
    then the URDF joints (``angle_of[j]``: the snapshot's angle column, left out while NaN, or -1
    for a fixed joint). ``seg[j]``: transform j's text from after its nsec up to its rotation,
    then a fixed joint's rotation (start, length each); ``heads``: the message's head, a
    transform's up to its sec, between sec and nsec, the message's tail."""
    o = 0
    for r in range(m):
        offsets[r] = o
        t = snap_t[r]
        if t < 0:
            t = 0
        sec = t // 1_000_000_000
        nsec = t - sec * 1_000_000_000
        o = _lit(buf, o, lit, heads[0, 0], heads[0, 1])
        first = True
        for j in range(angle_of.shape[0]):
            fixed = False
            if j == 0:
                if snap_q[r, 0] != snap_q[r, 0]:
                    continue
                qw, qx, qy, qz = _qmul(snap_q[r, 0], snap_q[r, 1], snap_q[r, 2], snap_q[r, 3],
                                       imu_conj[0], imu_conj[1], imu_conj[2], imu_conj[3])
            elif angle_of[j] >= 0:
                a = snap_a[r, angle_of[j]]
                if a != a:
                    continue
                s = math.sin(a / 2)
                qw, qx, qy, qz = _qmul(q0[j, 0], q0[j, 1], q0[j, 2], q0[j, 3],
                                       math.cos(a / 2), axis[j, 0] * s, axis[j, 1] * s, axis[j, 2] * s)
            else:
                fixed = True
                qw = qx = qy = qz = 0.0
            if not first:
                buf[o] = 44                           # ','
                o += 1
            first = False
            o = _lit(buf, o, lit, heads[1, 0], heads[1, 1])
            o = write_int(sec, buf, o)
            o = _lit(buf, o, lit, heads[2, 0], heads[2, 1])
            o = write_int(nsec, buf, o)
            o = _lit(buf, o, lit, seg[j, 0], seg[j, 1])
            if fixed:
                o = _lit(buf, o, lit, seg[j, 2], seg[j, 3])
            else:
                o = _quat(qw, qx, qy, qz, scale, buf, o, lit, keys)
                if o < 0:
                    return -1
            buf[o] = 125                              # '}': the transform's
            o += 1
        o = _lit(buf, o, lit, heads[3, 0], heads[3, 1])
    offsets[m] = o
    return o


class TransformJson:
    """Writes the messages of a :class:`gateway.log.foxglove.FrameTransforms` from its snapshots
    (:meth:`~gateway.log.foxglove.FrameTransforms.snapshots`), as its recorder records them."""

    def __init__(self, tf):
        from gateway.log.foxglove import DIGITS, WORLD_FRAME, _ORIGIN

        b = _Builder()
        # transform 0 is world -> spacecraft; the joints follow (the row of seg is the transform)
        joints = [(WORLD_FRAME, "spacecraft", _ORIGIN, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), -2, None)]
        joints += tf._joints
        n = len(joints)
        seg = np.zeros((n, 4), dtype=np.int64)
        q0 = np.zeros((n, 4))
        axis = np.zeros((n, 3))
        angle_of = np.full(n, -1, dtype=np.int64)
        for j, (parent, child, xyz, q, ax, k, fixed) in enumerate(joints):
            seg[j, 0:2] = b.literal("}," + encode_json({"parent_frame_id": parent, "child_frame_id": child,
                                                        "translation": xyz})[1:-1] + ',"rotation":')
            if j > 0 and k < 0:
                seg[j, 2:4] = b.literal(encode_json(fixed))
            q0[j] = q
            axis[j] = ax
            angle_of[j] = k
        heads = np.array([b.literal(t) for t in ('{"transforms":[', '{"timestamp":{"sec":', ',"nsec":', "]}")],
                         dtype=np.int64)
        self._keys = np.array([b.literal(f'{"," if i else "{"}"{c}":') for i, c in enumerate("xyzw")],
                              dtype=np.int64)
        a, bb, c, d = tf._q_imu_in_body
        self._imu_conj = np.array([a, -bb, -c, -d], dtype=np.float64)
        self._seg, self._heads, self._q0, self._axis, self._angle_of = seg, heads, q0, axis, angle_of
        self._lit = np.frombuffer(bytes(b.lit), dtype=np.uint8).copy()
        self._scale = float(10 ** DIGITS)
        # a message: its head and tail, per transform its text, two ints and four floats (24 bytes each)
        self._max_len = 64 + int(seg[:, 1].sum() + seg[:, 3].sum()) + n * (64 + 4 * 32)

    def messages(self, snap_t, snap_a, snap_q, m: int) -> list[bytes] | None:
        """The JSON of snapshots ``0..m``, or None when a value is beyond what the kernel rounds
        (the caller then writes them as objects)."""
        buf = np.empty(max(1, m * self._max_len), dtype=np.uint8)
        off = np.empty(m + 1, dtype=np.int64)
        end = _encode(snap_t, snap_a, snap_q, m, self._imu_conj, self._angle_of, self._q0, self._axis,
                      self._seg, self._heads, self._lit, self._keys, self._scale, buf, off)
        if end < 0:
            return None
        raw = buf[:end].tobytes()
        o = off.tolist()
        return [raw[o[k]:o[k + 1]] for k in range(m)]
