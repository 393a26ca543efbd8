"""Counters behind the health reports: every rejected frame or sample is counted by reason.

Rejection reasons (the keys of ``rejected``):

=================  ===========================================================================
bus level (:class:`BusCounters`, frames no driver owns)
``error_frame``    an error frame
``extended_id``    a 29-bit id (this contract uses 11-bit ids only)
``unknown_id``     an 11-bit id not used by this robot on this bus
``dlc``            a heartbeat with the wrong length
``remote_frame``   a remote frame with a heartbeat id
``fd_on_classic``  an FD frame with a heartbeat id on a classic bus
device level (:class:`DeviceCounters`, frames of the device's own ids)
``dlc``            data length differs from the DBC
``remote_frame``   a remote (RTR) frame
``fd_on_classic``  a CAN FD frame on a bus configured classic
``duplicate``      a frame repeated within one sample, or a sample counter seen just before
``late``           a sample counter behind the last one (reordered or very late; dropped)
``incomplete``     a partly assembled multi-frame sample dropped (a part never came, or
                   parts of different counters met)
=================  ===========================================================================

``lost`` is not a rejection but the number of counter values skipped (samples never seen).
Counters are plain ints updated by the notifier thread; snapshots read them from any thread
(each read is atomic under the GIL; a snapshot may straddle one update).
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

from drivers.errors import DriverError
from drivers.samples import BusHealth, DeviceHealth

REASONS = ("error_frame", "extended_id", "unknown_id", "dlc", "remote_frame", "fd_on_classic",
           "duplicate", "late", "incomplete")
DEFAULT_STALE_PERIODS = 10
RESYNC_PERIODS = 100   # a device silent for longer has resumed: trust the time, not the counter alone
DEVICE_CLOCK_WRAP_NS = (1 << 32) * 1000     # a device's u32 microsecond sample time wraps after 71.6 min
MAX_RATE = 1e6         # device seconds per second: beyond, no source (a million times real time)


class SourceTimingError(DriverError, ValueError):
    """A source timing that cannot be: a rate or a stale count out of range."""


@dataclass(frozen=True, slots=True)
class SourceTiming:
    """How the receiver's frame timestamps relate to the devices' sample clocks.

    ``rate``: device seconds per timestamp second. 1.0 (default) for real devices, which sample
    on their own clocks at their nominal periods, for a simulator run in real time, and for frames
    stamped with simulation time (``bsc demo``, offline replay); 2.0 for a log played back at twice
    its speed. ``None``: unknown, a simulation paced by its computation on a bus whose frames the
    receiver stamps (lockstep over SocketCAN): a silence then hides an unknown multiple of 256
    samples, which the health says (``lost_at_least``) instead of guessing.
    ``stale_periods``: a device with no sample for this many nominal periods is stale.
    """

    rate: float | None = 1.0
    stale_periods: int = DEFAULT_STALE_PERIODS

    def __post_init__(self) -> None:
        if self.rate is not None and not (math.isfinite(self.rate) and 0 < self.rate <= MAX_RATE):
            raise SourceTimingError(f"source rate {self.rate!r}: must be a positive number of device seconds per "
                             f"second, at most {MAX_RATE:g}")
        if self.stale_periods < 1:
            raise SourceTimingError(f"stale periods {self.stale_periods!r}: must be at least 1")


DEFAULT_TIMING = SourceTiming()


class DeviceCounters:
    """Per-device counters and the sample-counter sequence check (8-bit counters).

    Samples lost across a silence (:meth:`sequence`): the 8-bit counter gives the count modulo
    256; which multiple of 256 is decided from what the receiver knows, best first:

    1. the device's own sample time, when its frames carry one (the IMU's ``time_us``): exact;
    2. the frame timestamps at the declared :class:`SourceTiming` ``rate``: the count congruent
       to the counter step nearest ``gap * rate / period``, exact while the timestamps are off by
       less than 128 periods over the silence;
    3. rate unknown: the smallest count the counter allows, flagged ``lost_at_least``.

    Never from an observed spacing between samples: an outage, a VM pausing or a loaded sender
    change the spacing, and a smoothed spacing turned a 280-period outage into 24 lost.
    """

    __slots__ = ("device", "bus", "period_ns", "stale_periods", "rate", "fault_mask", "samples", "lost",
                 "lost_at_least", "saturated", "rejected", "last_t_ns", "last_counter", "last_device_ns", "status")

    def __init__(self, device: str, bus: str, period_ns: int, fault_mask: int = 0,
                 timing: SourceTiming = DEFAULT_TIMING):
        self.device, self.bus = device, bus
        self.period_ns, self.fault_mask = period_ns, fault_mask
        self.stale_periods, self.rate = timing.stale_periods, timing.rate
        self.samples = self.lost = self.saturated = 0
        self.lost_at_least = False
        self.rejected: Counter[str] = Counter()
        self.last_t_ns = 0
        self.last_counter: int | None = None
        self.last_device_ns: int | None = None
        self.status = 0

    def reject(self, reason: str, n: int = 1) -> None:
        self.rejected[reason] += n

    def sequence(self, counter: int, t_ns: int | None = None, device_ns: int | None = None) -> bool:
        """Check a completed sample's counter; False (and counted) if it must be dropped.

        ``t_ns``: the sample's timestamp (receiver clock); ``device_ns``: the device's own sample
        time, modulo :data:`DEVICE_CLOCK_WRAP_NS`, when its frames carry one. The 8-bit counter
        alone tells a gap, a duplicate and a late (reordered) sample apart only within half its
        range. A sample more than :data:`RESYNC_PERIODS` periods after the previous one ends a
        silence: it is kept, and the samples lost are counted as the class docstring says.
        """
        last = self.last_counter
        if last is not None:
            d = (counter - last) & 0xFF
            if t_ns is not None and self.samples:
                gap = t_ns - self.last_t_ns
                rate = self.rate
                limit = RESYNC_PERIODS * self.period_ns
                if (gap if rate is None else gap * rate) > limit:
                    steps = None                     # device periods elapsed, when known
                    if device_ns is not None and self.last_device_ns is not None:
                        away = (device_ns - self.last_device_ns) % DEVICE_CLOCK_WRAP_NS
                        if away >= DEVICE_CLOCK_WRAP_NS // 2:   # sampled before the last one
                            self.rejected["late"] += 1
                            return False
                        steps = away / self.period_ns
                    elif rate is not None:
                        steps = gap * rate / self.period_ns
                    if steps is None or steps > RESYNC_PERIODS:
                        if steps is None:            # the counter alone: at least this many
                            n = d or 256
                            self.lost_at_least = True
                        else:
                            n = d + 256 * max(0, round((steps - d) / 256))
                            if n == 0:               # the sample is kept, so it is a new one:
                                n = 256              # an unmoved counter means 256 periods on
                        self.lost += n - 1
                        self.last_counter = counter
                        if device_ns is not None:
                            self.last_device_ns = device_ns
                        return True
            if d == 0:
                self.rejected["duplicate"] += 1
                return False
            if d >= 128:
                self.rejected["late"] += 1
                return False
            self.lost += d - 1
        self.last_counter = counter
        if device_ns is not None:
            self.last_device_ns = device_ns
        return True

    def admit(self, counter: int, t_ns: int, saturated: bool, status: int, device_ns: int | None = None) -> bool:
        """:meth:`sequence` then, if the sample is kept, :meth:`accept`: one call per sample."""
        if not self.sequence(counter, t_ns, device_ns):
            return False
        self.samples += 1
        self.last_t_ns = t_ns
        self.status = status
        if saturated:
            self.saturated += 1
        return True

    def accept(self, t_ns: int, saturated: bool, status: int) -> None:
        self.samples += 1
        self.last_t_ns = t_ns
        self.status = status
        if saturated:
            self.saturated += 1

    def snapshot(self, now_ns: int) -> DeviceHealth:
        quiet: float = now_ns - self.last_t_ns             # timestamp ns, then device ns at a rate
        if self.rate is not None:
            quiet *= self.rate
        stale = self.samples == 0 or quiet > self.stale_periods * self.period_ns
        return DeviceHealth(device=self.device, bus=self.bus, t_ns=now_ns, samples=self.samples, lost=self.lost,
                            saturated=self.saturated, rejected=tuple(sorted(self.rejected.items())),
                            last_t_ns=self.last_t_ns, stale=stale, status=self.status,
                            faults=self.status & self.fault_mask, lost_at_least=self.lost_at_least)


class BusCounters:
    """Per-bus counters: frames, worst-case bit time (for the measured load), bus-level rejections."""

    __slots__ = ("bus", "frames", "busy_s", "rejected", "nodes", "_busy_at_snap", "_snap_ns")

    def __init__(self, bus: str):
        self.bus = bus
        self.frames = 0
        self.busy_s = 0.0
        self.rejected: Counter[str] = Counter()
        self.nodes: dict[str, int] = {}
        self._busy_at_snap = 0.0
        self._snap_ns: int | None = None

    def snapshot(self, now_ns: int) -> BusHealth:
        """Load = worst-case bus time of the frames seen since the previous snapshot / elapsed."""
        busy, prev = self.busy_s, self._snap_ns
        load = 0.0
        if prev is not None and now_ns > prev:
            load = (busy - self._busy_at_snap) / ((now_ns - prev) * 1e-9)
        self._busy_at_snap, self._snap_ns = busy, now_ns
        return BusHealth(bus=self.bus, t_ns=now_ns, frames=self.frames, rejected=tuple(sorted(self.rejected.items())),
                         load=load, nodes=tuple(sorted(self.nodes.items())))
