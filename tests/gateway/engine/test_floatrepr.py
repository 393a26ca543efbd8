"""The compiled float formatting against CPython's repr, which JSON uses: every float the
gateway writes must read back as the same double and be the bytes Python would have written."""
from __future__ import annotations

import math

import numpy as np
import pytest

from gateway.engine.floatrepr import write_float, write_int
from numba import njit


@njit(cache=True)
def _write_all(vals, buf, offsets):
    o = 0
    for k in range(vals.shape[0]):
        offsets[k] = o
        o = write_float(vals[k], buf, o)
    offsets[vals.shape[0]] = o
    return o


def _check(vals: np.ndarray) -> None:
    vals = np.ascontiguousarray(vals, dtype=np.float64)
    vals = vals[np.isfinite(vals)]
    buf = np.zeros(24 * len(vals) + 24, dtype=np.uint8)
    off = np.zeros(len(vals) + 1, dtype=np.int64)
    _write_all(vals, buf, off)
    text = buf.tobytes()
    offs = off.tolist()
    for k, v in enumerate(vals.tolist()):
        got = text[offs[k]:offs[k + 1]].decode("ascii")
        assert got == repr(v), (v.hex(), got, repr(v))


def test_random_bit_patterns():
    rng = np.random.default_rng(0)
    _check(rng.integers(0, 1 << 64, size=1_000_000, dtype=np.uint64).view(np.float64))


@pytest.mark.slow
def test_ten_million_random_bit_patterns():
    rng = np.random.default_rng(1)
    for _ in range(10):
        _check(rng.integers(0, 1 << 64, size=1_000_000, dtype=np.uint64).view(np.float64))


def test_every_decimal_exponent_and_the_notation_thresholds():
    rng = np.random.default_rng(2)
    mant = rng.uniform(1.0, 10.0, size=300_000)
    exps = rng.integers(-325, 309, size=300_000)
    with np.errstate(over="ignore"):                 # the largest exponents overflow: skipped
        v = mant * 10.0 ** exps.astype(float)
    _check(np.concatenate([v, -v]))
    edges = []
    for p in range(-330, 310):
        for base in (1.0, 5.0, 9.999999999999999):
            v = float(f"{base!r}e{p}")
            if math.isfinite(v):
                edges += [v, np.nextafter(v, 0), np.nextafter(v, math.inf)]
    edges += [1e-4, 1e-5, 9.99999e-5, 1e16, 9999999999999998.0, 1e15, 123456789012345678.0, 0.1, 0.2, 0.3,
              1 / 3, 2 / 3, 100.0, 5.0, 0.0, -0.0, 5e-324, 2.2250738585072014e-308, 2.225073858507201e-308,
              1.7976931348623157e308, 4.35, 0.5, 2.5, 1e21, 1e22, 1e23]
    _check(np.array(edges))


def test_powers_of_two_integers_and_subnormals():
    vals = [2.0 ** e for e in range(-1074, 1024)]
    vals += [float(n) for n in range(-1000, 1000)] + [float(2 ** 53 + k) for k in range(-3, 4)]
    vals += [float(10 ** k) for k in range(23)] + [float(3 ** k) for k in range(40)]
    sub = np.arange(1, 200_000, dtype=np.uint64).view(np.float64)
    _check(np.concatenate([np.array(vals), -np.array(vals), sub, np.nextafter(np.array(vals), math.inf)]))


def test_non_finite_writes_nothing():
    buf = np.zeros(32, dtype=np.uint8)
    for v in (math.nan, math.inf, -math.inf):
        assert write_float(v, buf, 3) == -1
    assert not buf.any()


def test_integers():
    buf = np.zeros(32, dtype=np.uint8)
    for v in (0, 7, -7, 10, 1_700_000_000_123_456_789, -(2 ** 63), 2 ** 63 - 1):
        n = write_int(v, buf, 0)
        assert buf[:n].tobytes().decode() == str(v)
