"""Python's ``repr(float)`` in compiled code: the shortest decimal that reads back as the same
double, laid out as CPython lays it out.

The efforts and samples the gateway publishes and records are JSON, and JSON writes a float with
``repr``: the shortest round-tripping digits. CPython gets them from David Gay's ``dtoa`` (big
integers, about 0.6 us a float); at 13 floats an effort message and 24 000 messages per 8 s
of log, that alone would cap an offline replay far below 100x. This module computes the same
digits with Ulf Adams's Ryu algorithm ("Ryu: fast float-to-string conversion", PLDI 2018): the
decimal interval of the doubles that round to the value is scaled by a precomputed power of five
(a 128-bit multiply, done in LLVM's i128), and digits are removed while the interval still holds
one decimal; ties and the interval's closed ends follow IEEE round-half-even, as Gay's does. The
result is then formatted as CPython's ``format_float_short`` does for ``repr``: fixed notation
when the decimal exponent is in [-4, 16), else ``d.ddde+XX`` with at least two exponent digits,
``.0`` after an integer, ``-0.0`` for negative zero.

Tested against ``repr`` on millions of random bit patterns and every boundary case
(tests/gateway/engine/test_floatrepr.py). Non-finite values are the caller's to avoid (JSON has none):
:func:`write_float` writes nothing and returns -1 for them.
"""
from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from gateway.estimator.jitopts import jit

_jit = jit   # numba's njit with the estimator kernels' options: no reference counting (they allocate nothing)

_POW5_INV_BITCOUNT = 125
_POW5_BITCOUNT = 125


def _tables() -> tuple[np.ndarray, np.ndarray]:
    """(342, 2) and (326, 2) uint64 (low, high) halves of Ryu's 125-bit scaled powers of five:
    ``inv[q] = floor(2**(len(5**q) - 1 + 125) / 5**q) + 1`` and ``pow[i]`` = ``5**i`` scaled
    to exactly 125 bits (truncated)."""
    inv = np.zeros((342, 2), dtype=np.uint64)
    for q in range(342):
        p = 5 ** q
        v = (1 << (p.bit_length() - 1 + _POW5_INV_BITCOUNT)) // p + 1
        inv[q] = (v & ((1 << 64) - 1), v >> 64)
    pw = np.zeros((326, 2), dtype=np.uint64)
    for i in range(326):
        p = 5 ** i
        shift = p.bit_length() - _POW5_BITCOUNT
        v = p >> shift if shift >= 0 else p << -shift
        pw[i] = (v & ((1 << 64) - 1), v >> 64)
    return inv, pw


POW5_INV_SPLIT, POW5_SPLIT = _tables()


@intrinsic
def _mul_shift(typingctx, m, lo, hi, j):
    """``(m * (hi * 2**64 + lo)) >> j`` for a 64-bit ``m`` and 64 <= j < 192, in i128."""
    sig = types.uint64(types.uint64, types.uint64, types.uint64, types.int64)

    def codegen(context, builder, signature, args):
        i128 = ir.IntType(128)
        m_, lo_, hi_, j_ = args
        mw = builder.zext(m_, i128)
        b0 = builder.mul(mw, builder.zext(lo_, i128))
        b2 = builder.mul(mw, builder.zext(hi_, i128))
        s = builder.add(builder.lshr(b0, ir.Constant(i128, 64)), b2)
        r = builder.lshr(s, builder.zext(builder.sub(j_, ir.Constant(ir.IntType(64), 64)), i128))
        return builder.trunc(r, ir.IntType(64))

    return sig, codegen


@intrinsic
def _bits(typingctx, x):
    """The IEEE bits of a float64 as uint64."""
    sig = types.uint64(types.float64)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return sig, codegen


@_jit
def _pow5bits(e):
    return ((e * 1217359) >> 19) + 1


@_jit
def _log10_pow2(e):
    return (e * 78913) >> 18


@_jit
def _log10_pow5(e):
    return (e * 732923) >> 20


@_jit
def _pow5_factor(v):
    count = 0
    while v != 0 and v % np.uint64(5) == 0:
        v //= np.uint64(5)
        count += 1
    return count


@_jit
def shortest(x):
    """``(digits, exponent)`` with ``x == digits * 10**exponent`` as the shortest decimal that
    rounds back to ``|x|`` (``x`` finite; ``(0, 0)`` for zero)."""
    bits = _bits(x)
    mant = bits & np.uint64((1 << 52) - 1)
    expo = np.int64((bits >> np.uint64(52)) & np.uint64(0x7FF))
    if expo == 0 and mant == 0:
        return np.uint64(0), np.int64(0)
    if expo == 0:
        e2 = np.int64(1 - 1023 - 52 - 2)
        m2 = mant
    else:
        e2 = expo - 1023 - 52 - 2
        m2 = (np.uint64(1) << np.uint64(52)) | mant
    even = (m2 & np.uint64(1)) == 0
    accept = even
    mv = np.uint64(4) * m2
    mm_shift = np.uint64(1) if (mant != 0 or expo <= 1) else np.uint64(0)
    vm_tz = False
    vr_tz = False
    if e2 >= 0:
        q = _log10_pow2(e2) - (1 if e2 > 3 else 0)
        e10 = q
        k = _POW5_INV_BITCOUNT + _pow5bits(q) - 1
        i = -e2 + q + k
        lo, hi = POW5_INV_SPLIT[q, 0], POW5_INV_SPLIT[q, 1]
        vr = _mul_shift(mv, lo, hi, i)
        vp = _mul_shift(mv + np.uint64(2), lo, hi, i)
        vm = _mul_shift(mv - np.uint64(1) - mm_shift, lo, hi, i)
        if q <= 21:
            if mv % np.uint64(5) == 0:
                vr_tz = _pow5_factor(mv) >= q
            elif accept:
                vm_tz = _pow5_factor(mv - np.uint64(1) - mm_shift) >= q
            else:
                vp -= np.uint64(1) if _pow5_factor(mv + np.uint64(2)) >= q else np.uint64(0)
    else:
        q = _log10_pow5(-e2) - (1 if -e2 > 1 else 0)
        e10 = q + e2
        i = -e2 - q
        k = _pow5bits(i) - _POW5_BITCOUNT
        j = q - k
        lo, hi = POW5_SPLIT[i, 0], POW5_SPLIT[i, 1]
        vr = _mul_shift(mv, lo, hi, j)
        vp = _mul_shift(mv + np.uint64(2), lo, hi, j)
        vm = _mul_shift(mv - np.uint64(1) - mm_shift, lo, hi, j)
        if q <= 1:
            vr_tz = True
            if accept:
                vm_tz = mm_shift == 1
            else:
                vp -= np.uint64(1)
        elif q < 63:
            vr_tz = (mv & ((np.uint64(1) << np.uint64(q)) - np.uint64(1))) == 0
    removed = 0
    last = np.uint64(0)
    ten = np.uint64(10)
    if vm_tz or vr_tz:
        while vp // ten > vm // ten:
            vm_tz = vm_tz and vm % ten == 0
            vr_tz = vr_tz and last == 0
            last = vr % ten
            vr //= ten
            vp //= ten
            vm //= ten
            removed += 1
        if vm_tz:
            while vm % ten == 0:
                vr_tz = vr_tz and last == 0
                last = vr % ten
                vr //= ten
                vp //= ten
                vm //= ten
                removed += 1
        if vr_tz and last == 5 and vr % np.uint64(2) == 0:
            last = np.uint64(4)                      # a tie: round half to even
        up = (vr == vm and (not accept or not vm_tz)) or last >= 5
        out = vr + (np.uint64(1) if up else np.uint64(0))
    else:
        up = False
        hundred = np.uint64(100)
        if vp // hundred > vm // hundred:
            up = vr % hundred >= 50
            vr //= hundred
            vp //= hundred
            vm //= hundred
            removed += 2
        while vp // ten > vm // ten:
            up = vr % ten >= 5
            vr //= ten
            vp //= ten
            vm //= ten
            removed += 1
        out = vr + (np.uint64(1) if (vr == vm or up) else np.uint64(0))
    return out, np.int64(e10 + removed)


_DIGITS2 = np.frombuffer("".join(f"{i:02d}" for i in range(100)).encode(), dtype=np.uint8).copy()
_POW10 = np.array([10 ** k for k in range(20)], dtype=np.uint64)


@_jit
def _n_digits(u):
    """Decimal digits of ``u`` (at least 1), by comparison (no division)."""
    n = 1
    while n < 20 and u >= _POW10[n]:
        n += 1
    return n


@_jit
def write_int(v, buf, o):
    """The decimal digits of int64 ``v`` into ``buf`` at ``o``; returns the new offset."""
    if v < 0:
        buf[o] = 45                                  # '-'
        o += 1
        u = np.uint64(-(v + 1)) + np.uint64(1)       # |INT64_MIN| has no int64
    else:
        u = np.uint64(v)
    n = _n_digits(u)
    _put_digits(buf, u, n, o, -1)
    return o + n


@_jit
def _put_fixed(buf, u, n, base):
    """Exactly ``n`` decimal digits of ``u`` (leading zeros) into ``buf[base:base + n]``, two per
    division (a table of "00".."99")."""
    hundred = np.uint64(100)
    i = base + n - 1
    while i > base:
        r = np.int64(u % hundred) * 2
        u //= hundred
        buf[i] = _DIGITS2[r + 1]
        buf[i - 1] = _DIGITS2[r]
        i -= 2
    if i == base:
        buf[i] = 48 + np.uint8(u % np.uint64(10))


@_jit
def _put_digits(buf, digits, n, base, dot):
    """The ``n`` decimal digits of ``digits`` into ``buf``, the first at ``base``; digits at
    index ``dot`` and after are shifted one place right (room for a decimal point; -1: none)."""
    if dot < 0 or dot >= n:
        _put_fixed(buf, digits, n, base)
        return
    tail = n - dot
    _put_fixed(buf, digits % _POW10[tail], tail, base + dot + 1)
    _put_fixed(buf, digits // _POW10[tail], dot, base)


@_jit
def write_float(x, buf, o):
    """``repr(x)`` into ``buf`` at ``o`` (ASCII); returns the new offset, or -1 for a
    non-finite ``x`` (nothing written). ``buf`` needs room for 24 bytes."""
    if not np.isfinite(x):
        return -1
    if _bits(x) >> np.uint64(63):
        buf[o] = 45                                  # '-'
        o += 1
    digits, e = shortest(x)
    if digits == 0:
        buf[o] = 48
        buf[o + 1] = 46
        buf[o + 2] = 48
        return o + 3
    n = _n_digits(digits)
    decpt = n + e                                    # the decimal point's place after the first digit
    if -4 < decpt <= 16:                             # CPython's repr: fixed notation
        if decpt <= 0:                               # 0.000ddd
            buf[o] = 48
            buf[o + 1] = 46
            for k in range(-decpt):
                buf[o + 2 + k] = 48
            _put_digits(buf, digits, n, o + 2 - decpt, -1)
            return o + 2 - decpt + n
        if decpt >= n:                               # ddd000.0
            _put_digits(buf, digits, n, o, -1)
            o += n
            for _ in range(decpt - n):
                buf[o] = 48
                o += 1
            buf[o] = 46
            buf[o + 1] = 48
            return o + 2
        _put_digits(buf, digits, n, o, decpt)        # dd.ddd
        buf[o + decpt] = 46
        return o + n + 1
    if n > 1:                                        # d.ddde+XX
        _put_digits(buf, digits, n, o, 1)
        buf[o + 1] = 46
        o += n + 1
    else:
        _put_digits(buf, digits, 1, o, -1)
        o += 1
    buf[o] = 101                                     # 'e'
    x10 = decpt - 1
    if x10 < 0:
        buf[o + 1] = 45
        x10 = -x10
    else:
        buf[o + 1] = 43                              # '+'
    o += 2
    if x10 < 10:
        buf[o] = 48
        o += 1
    return write_int(x10, buf, o)
