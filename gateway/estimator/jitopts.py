"""How the estimator's kernels are compiled: one place for the options of every kernel module.

Every kernel is cached (``cache=True``, :mod:`drivers.jitcache` names the directory), IEEE
semantics without fast-math (the bits are fixed, live and offline, whatever the batch), numpy's
error model (division by zero gives inf, no check) and without the GIL.

:data:`jit` compiles without numba's reference counting (its ``_nrt`` option, which numba's type
stubs do not list): the kernels work in place on arrays their callers own, and counting every
array argument of every call, an atomic increment and decrement each, cost more than their
arithmetic (perf of a replay of the demo log, 2026-11-26: over half the estimator's time; the
same bits without it). A kernel that allocates a temporary or returns a view is compiled with it
(:data:`jit_alloc`, set explicitly: numba would otherwise take the calling kernel's setting).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

from numba import njit

if TYPE_CHECKING:
    from numba.core.decorators import _JITWrapper

_OPTIONS: dict[str, Any] = {"cache": True, "fastmath": False, "error_model": "numpy", "nogil": True}
_COUNTED: dict[str, Any] = {"_nrt": True}
_UNCOUNTED: dict[str, Any] = {"_nrt": False}

jit: _JITWrapper = njit(**_OPTIONS, **_UNCOUNTED)
jit_alloc: _JITWrapper = njit(**_OPTIONS, **_COUNTED)
inline: _JITWrapper = njit(**_OPTIONS, **_UNCOUNTED, inline="always")
