"""The VM tier's CPU computes what the host's does.

Under QEMU 7.2's TCG with ``-cpu max``, numpy's AVX2 argsort returned index arrays that were not
permutations, and the gateway died of SIGSEGV in ``np.argsort`` (the recorder's thread). The VM
now runs without AVX2 (``.ci/vcan-vm.sh``); this check fails if an emulated CPU feature breaks
numpy's sorts again. Marked ``vcan``: it runs in the tier (and is harmless anywhere).
"""
from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.vcan
@pytest.mark.parametrize("dtype", ["int64", "float64", "int32", "float32"])
def test_numpy_sorts_are_permutations(dtype):
    wrong = []
    for n in range(1, 300):
        a = np.random.default_rng(n).permutation(n).astype(dtype)
        order = np.argsort(a)
        if not (np.array_equal(np.sort(order), np.arange(n)) and np.all(np.diff(a[order]) >= 0)):
            wrong.append(n)
        if not np.array_equal(np.sort(a), np.arange(n).astype(dtype)):
            wrong.append(-n)
    assert not wrong, f"numpy's sorts of {dtype} are wrong here for sizes {wrong[:10]} (negative: np.sort)"
