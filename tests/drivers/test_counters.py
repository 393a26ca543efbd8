"""The 8-bit sample-counter check of drivers.health.DeviceCounters, including a device that comes
back after a silence longer than half the counter range."""
from __future__ import annotations

import pytest

from drivers.health import RESYNC_PERIODS, DeviceCounters

MS = 1_000_000


def feed(dev: DeviceCounters, ks) -> list[bool]:
    """Samples number k of a 1 kHz device: counter k mod 256, sample time k ms."""
    return [dev.admit(k & 0xFF, k * MS, False, 0) for k in ks]


def test_gaps_duplicates_and_late_samples_by_counter():
    dev = DeviceCounters("arm0", "arm0", MS)
    assert feed(dev, [0, 1, 2, 5, 6]) == [True] * 5
    assert dev.lost == 2
    assert dev.admit(6, 6 * MS, False, 0) is False and dev.rejected["duplicate"] == 1
    assert dev.admit(4, 7 * MS, False, 0) is False and dev.rejected["late"] == 1     # reordered


@pytest.mark.parametrize("away_ms", [90, 130, 200, 256, 300, 700, 5000])
def test_a_device_back_from_a_long_silence_is_kept_and_the_gap_counted(away_ms):
    dev = DeviceCounters("arm0", "arm0", MS)
    feed(dev, range(10))
    back = 9 + away_ms + 1                      # samples 10 .. 9 + away_ms were never sent
    assert feed(dev, range(back, back + 20)) == [True] * 20
    assert dev.lost == away_ms and not dev.rejected
    assert dev.samples == 30


def test_resync_needs_a_real_silence():
    # within RESYNC_PERIODS a counter going backwards is a late sample, whatever the clock says
    dev = DeviceCounters("arm0", "arm0", MS)
    feed(dev, range(10))
    assert dev.admit(3, (9 + RESYNC_PERIODS - 1) * MS, False, 0) is False
    assert dev.rejected["late"] == 1 and dev.lost == 0


@pytest.mark.parametrize("slow", [1, 20, 250])
def test_a_source_slower_than_real_time_is_not_an_outage(slow):
    """Samples stamped at arrival from a source running ``slow`` x slower than real time (a
    lockstep simulator in a VM): nothing lost; a real gap is still counted by counter."""
    dev = DeviceCounters("arm0", "arm0", MS)
    ks = list(range(600)) + list(range(603, 1000))          # samples 600..602 lost
    assert all(dev.admit(k & 0xFF, k * MS * slow, False, 0) for k in ks)
    assert dev.lost == 3 and not dev.rejected


def test_a_slow_source_back_from_an_outage_with_its_counter_ahead():
    """Samples came 3x slower than nominal, then the bus was down for 150 ms while the device went
    on counting at its nominal period: the counter step (150) reads 'behind' mod 256, yet it is
    an outage, counted exactly (the vcan bus down/up test under QEMU)."""
    dev = DeviceCounters("arm1", "arm1", MS)
    assert all(dev.admit(k, 3 * k * MS, False, 0) for k in range(100))
    t_down = 3 * 99 * MS
    first = 99 + 150
    assert all(dev.admit((first + i) & 0xFF, t_down + 150 * MS + 3 * i * MS, False, 0) for i in range(50))
    assert dev.lost == 149 and not dev.rejected
