"""The 8-bit sample-counter check of drivers.health.DeviceCounters, including a device that comes
back after a silence longer than half the counter range, from sources at real-time speed and
slower (a simulation in a VM), with the source's rate declared, unknown, or read from the
device's own sample time."""
from __future__ import annotations

import pytest

from drivers.health import DEVICE_CLOCK_WRAP_NS, RESYNC_PERIODS, DeviceCounters, SourceTiming

MS = 1_000_000
OUTAGES = [1, 127, 128, 255, 256, 257, 280, 1000]


def feed(dev: DeviceCounters, ks) -> list[bool]:
    """Samples number k of a 1 kHz device: counter k mod 256, sample time k ms."""
    return [dev.admit(k & 0xFF, k * MS, False, 0) for k in ks]


def run_outage(dev: DeviceCounters, outage: int, slow: float, device_clock: bool = False) -> None:
    """300 samples, then ``outage`` samples never delivered, then 300 more; the source produces a
    sample every ``slow`` ms of the receiver's clock (1: real time; 3: three times slower)."""
    ks = list(range(300)) + list(range(300 + outage, 600 + outage))
    for k in ks:
        ok = dev.admit(k & 0xFF, round(k * MS * slow), False, 0,
                       (k * MS) % DEVICE_CLOCK_WRAP_NS if device_clock else None)
        assert ok, k
    assert dev.samples == 600 and not dev.rejected


def test_gaps_duplicates_and_late_samples_by_counter():
    dev = DeviceCounters("arm0", "arm0", MS)
    assert feed(dev, [0, 1, 2, 5, 6]) == [True] * 5
    assert dev.lost == 2
    assert dev.admit(6, 6 * MS, False, 0) is False and dev.rejected["duplicate"] == 1
    assert dev.admit(4, 7 * MS, False, 0) is False and dev.rejected["late"] == 1     # reordered


@pytest.mark.parametrize("outage", OUTAGES)
def test_real_time_source_outage_is_counted_exactly(outage):
    """Devices on their own clocks at the nominal period (the default timing): every outage exact."""
    dev = DeviceCounters("arm0", "arm0", MS)
    run_outage(dev, outage, slow=1)
    assert (dev.lost, dev.lost_at_least) == (outage, False)


@pytest.mark.parametrize("slow", [3, 10])
@pytest.mark.parametrize("outage", OUTAGES)
def test_slow_source_with_declared_rate_is_counted_exactly(outage, slow):
    """A simulation running ``slow`` x slower than real time, declared (rate = 1/slow)."""
    dev = DeviceCounters("arm0", "arm0", MS, timing=SourceTiming(rate=1 / slow))
    run_outage(dev, outage, slow)
    assert (dev.lost, dev.lost_at_least) == (outage, False)


@pytest.mark.parametrize("slow", [1, 3, 10])
@pytest.mark.parametrize("outage", OUTAGES)
def test_device_clock_makes_any_outage_exact_whatever_the_rate(outage, slow):
    """A device that stamps its samples (the IMU's time_us): exact even with the rate unknown."""
    dev = DeviceCounters("imu", "spacecraft", MS, timing=SourceTiming(rate=None))
    run_outage(dev, outage, slow, device_clock=True)
    assert (dev.lost, dev.lost_at_least) == (outage, False)


@pytest.mark.parametrize("slow", [3, 10])
@pytest.mark.parametrize("outage", OUTAGES)
def test_unknown_rate_counts_what_the_counter_proves_and_says_so(outage, slow):
    """Lockstep over a receiver-stamped bus, rate unknown: up to 255 samples the counter step is
    exact; beyond, the count is the smallest the counter allows and the health says it is a lower
    bound. A silence too short to hide 256 samples is not flagged."""
    dev = DeviceCounters("arm0", "arm0", MS, timing=SourceTiming(rate=None))
    run_outage(dev, outage, slow)
    silence = (outage + 1) * slow > RESYNC_PERIODS
    assert dev.lost == ((outage + 1) % 256 or 256) - 1
    assert dev.lost_at_least is silence
    if outage < 256:
        assert dev.lost == outage


def test_rate_declared_wrong_is_wrong_by_multiples_of_256():
    """The documented limit: a slow source declared real time (rate 1) makes a 280-period outage
    that took 840 ms look like 840 periods: the count is off by a multiple of 256 (here +512).
    This is why a lockstep simulation on a receiver-stamped bus must be declared."""
    dev = DeviceCounters("arm1", "arm1", MS)
    run_outage(dev, 280, slow=3)
    assert dev.lost == 280 + 512 and not dev.lost_at_least


def test_resync_needs_a_real_silence():
    # within RESYNC_PERIODS a counter going backwards is a late sample, whatever the clock says
    dev = DeviceCounters("arm0", "arm0", MS)
    feed(dev, range(10))
    assert dev.admit(3, (9 + RESYNC_PERIODS - 1) * MS, False, 0) is False
    assert dev.rejected["late"] == 1 and dev.lost == 0


def test_device_clock_behind_is_a_late_sample_not_an_outage():
    """A device time behind the last one (a stale, reordered sample) is never read as 71 minutes
    away: the counter decides, as without a device clock."""
    dev = DeviceCounters("imu", "spacecraft", MS, timing=SourceTiming(rate=None))
    for k in range(10):
        assert dev.admit(k, k * MS, False, 0, k * MS)
    assert dev.admit(3, 200 * MS, False, 0, 3 * MS) is False       # a silence by the receiver's clock
    assert dev.rejected["late"] == 1 and dev.lost == 0 and dev.lost_at_least is False


@pytest.mark.parametrize("slow", [1, 20, 250])
def test_a_source_slower_than_real_time_is_not_an_outage(slow):
    """Samples stamped at arrival from a source running ``slow`` x slower than real time, its
    rate declared: nothing lost; a real gap is still counted by counter."""
    dev = DeviceCounters("arm0", "arm0", MS, timing=SourceTiming(rate=1 / slow))
    ks = list(range(600)) + list(range(603, 1000))          # samples 600..602 lost
    assert all(dev.admit(k & 0xFF, k * MS * slow, False, 0) for k in ks)
    assert dev.lost == 3 and not dev.rejected and not dev.lost_at_least


def test_a_slow_source_back_from_an_outage_with_its_counter_ahead():
    """Samples came 3x slower than nominal (a loaded sender), then the bus was down for 150 ms
    while the device went on counting at its nominal period: the counter step (150) reads
    'behind' mod 256, yet it is an outage, counted exactly (the vcan bus down/up test)."""
    dev = DeviceCounters("arm1", "arm1", MS)
    assert all(dev.admit(k, 3 * k * MS, False, 0) for k in range(100))
    t_down = 3 * 99 * MS
    first = 99 + 150
    assert all(dev.admit((first + i) & 0xFF, t_down + 150 * MS + 3 * i * MS, False, 0) for i in range(50))
    assert dev.lost == 149 and not dev.rejected


def test_staleness_follows_the_declared_rate():
    dev = DeviceCounters("arm0", "arm0", MS, timing=SourceTiming(rate=0.1, stale_periods=10))
    feed(dev, range(3))
    assert dev.snapshot(2 * MS + 99 * MS).stale is False           # 9.9 device periods
    assert dev.snapshot(2 * MS + 101 * MS).stale is True


def test_health_reports_a_lower_bound():
    dev = DeviceCounters("arm0", "arm0", MS, timing=SourceTiming(rate=None))
    run_outage(dev, 1000, slow=3)
    h = dev.snapshot(dev.last_t_ns)
    assert h.lost == dev.lost and h.lost_at_least is True


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_timing_rejects_a_meaningless_rate(bad):
    with pytest.raises(ValueError, match="source rate"):
        SourceTiming(rate=bad)


def test_an_unmoved_counter_after_a_silence_went_round_once():
    """A sample kept after a silence is a new one: a counter that did not move over 110 periods
    went round once (255 lost), not 0 (a duplicate would not be kept after a silence)."""
    dev = DeviceCounters("arm0", "arm0", MS)
    feed(dev, range(10))
    assert dev.admit(9, (9 + 110) * MS, False, 0) is True
    assert dev.lost == 255 and not dev.rejected


def test_timing_rejects_an_absurd_rate():
    with pytest.raises(ValueError, match="at most"):
        SourceTiming(rate=1e300)
