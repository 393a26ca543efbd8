"""Fixtures of the firmware tests: the bus tiers one integration test runs over.

``bus_tier`` gives ``(interface, channels(bus_names) -> channel spec, stamps_preserved)``:
``virtual`` (in-process, unique channel names per test) always; ``socketcan`` on vcan0..N-1
under the ``vcan`` marker, skipped where those interfaces do not exist (the VM tier creates
them, .ci/vcan-tier.sh).
"""
from __future__ import annotations

import uuid
from pathlib import Path

import pytest


def _virtual(buses):
    return f"bsc-fw-{uuid.uuid4().hex[:12]}"          # a prefix: <prefix>-<bus>


def _vcan(buses):
    missing = [f"vcan{i}" for i in range(len(buses)) if not Path(f"/sys/class/net/vcan{i}").exists()]
    if missing:
        pytest.skip(f"needs SocketCAN {', '.join(missing)} (one vcan per bus; the vcan VM tier creates them)")
    return {b: f"vcan{i}" for i, b in enumerate(buses)}


@pytest.fixture(params=[pytest.param(("virtual", _virtual, True), id="virtual"),
                        pytest.param(("socketcan", _vcan, False), id="vcan", marks=pytest.mark.vcan)])
def bus_tier(request):
    if request.param[0] == "socketcan" and not Path("/sys/class/net/vcan0").exists():
        pytest.skip("needs SocketCAN vcan0 (not in this kernel; run the vcan VM tier, .ci/vcan-tier.sh)")
    return request.param
