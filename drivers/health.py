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

from collections import Counter

from drivers.samples import BusHealth, DeviceHealth

REASONS = ("error_frame", "extended_id", "unknown_id", "dlc", "remote_frame", "fd_on_classic",
           "duplicate", "late", "incomplete")
DEFAULT_STALE_PERIODS = 10
RESYNC_PERIODS = 100   # a device silent for longer has resumed: trust the time, not the counter alone
SPACING_WARMUP = 8     # samples before the spacing is known (and a long gap can mean an outage)


class DeviceCounters:
    """Per-device counters and the sample-counter sequence check (8-bit counters)."""

    __slots__ = ("device", "bus", "period_ns", "stale_periods", "fault_mask", "samples", "lost", "saturated",
                 "rejected", "last_t_ns", "last_counter", "status", "spacing_ns")

    def __init__(self, device: str, bus: str, period_ns: int, fault_mask: int = 0,
                 stale_periods: int = DEFAULT_STALE_PERIODS):
        self.device, self.bus = device, bus
        self.period_ns, self.stale_periods, self.fault_mask = period_ns, stale_periods, fault_mask
        self.samples = self.lost = self.saturated = 0
        self.rejected: Counter[str] = Counter()
        self.last_t_ns = 0
        self.last_counter: int | None = None
        self.status = 0
        self.spacing_ns = period_ns       # smoothed time between consecutive samples, >= period_ns

    def reject(self, reason: str, n: int = 1) -> None:
        self.rejected[reason] += n

    def sequence(self, counter: int, t_ns: int | None = None) -> bool:
        """Check a completed sample's counter; False (and counted) if it must be dropped.

        The 8-bit counter alone tells a gap, a duplicate and a late (reordered) sample apart only
        within half its range. After a silence of more than :data:`RESYNC_PERIODS` sample steps (by
        the sample time ``t_ns``, when given) the device has resumed: the sample is kept and the
        samples lost are the count congruent to the counter step that best fits the time away. A
        sample step's time is the device's period, or the observed spacing when the samples come
        slower (a source slower than real time, e.g. a lockstep simulator in a VM, is no outage).
        """
        last = self.last_counter
        if last is not None:
            d = (counter - last) & 0xFF
            if t_ns is not None and self.samples:
                gap = t_ns - self.last_t_ns
                # a sample step's time here: a source slower than real time (a VM) is no outage.
                # A counter behind (or equal) after more than RESYNC_PERIODS nominal periods is no
                # reordered or duplicated frame either: the device went on counting while away.
                spacing = self.spacing_ns
                limit = RESYNC_PERIODS * (spacing if 0 < d < 128 else self.period_ns)
                if self.samples >= SPACING_WARMUP and gap > limit:
                    n = d + 256 * max(0, round((gap / spacing - d) / 256))
                    self.lost += max(n, 1) - 1
                    self.last_counter = counter
                    return True
                if 0 < d < 128 and gap > 0:      # follow the observed spacing per sample step
                    step = gap // d
                    self.spacing_ns = max(self.period_ns, step if self.samples < SPACING_WARMUP
                                          else spacing + (step - spacing) // 16)
            if d == 0:
                self.rejected["duplicate"] += 1
                return False
            if d >= 128:
                self.rejected["late"] += 1
                return False
            self.lost += d - 1
        self.last_counter = counter
        return True

    def admit(self, counter: int, t_ns: int, saturated: bool, status: int) -> bool:
        """:meth:`sequence` then, if the sample is kept, :meth:`accept`: one call per sample."""
        if not self.sequence(counter, t_ns):
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
        stale = self.samples == 0 or now_ns - self.last_t_ns > self.stale_periods * self.period_ns
        return DeviceHealth(device=self.device, bus=self.bus, t_ns=now_ns, samples=self.samples, lost=self.lost,
                            saturated=self.saturated, rejected=tuple(sorted(self.rejected.items())),
                            last_t_ns=self.last_t_ns, stale=stale, status=self.status,
                            faults=self.status & self.fault_mask)


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
