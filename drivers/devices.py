"""The drivers: one python-can ``Listener`` per device type, given a bus, never opening one.

Put them under a ``can.Notifier`` (see :func:`listeners_for`). Each driver dispatches by
arbitration id to its own frames and ignores the rest; :class:`BusMonitor` counts every frame,
measures the load, reads heartbeats and counts the frames no driver owns (unknown ids, error
frames, 29-bit ids). So each frame is counted once: by its owner, or by the monitor.

Decoded samples go to ``sink(sample)``, called on the notifier thread in arrival order (FIFO:
the sink decides whether to queue, drop or publish). A frame can never raise out of a driver:
everything a bus can deliver is validated first and rejected by reason (drivers/health.py);
an exception from the sink is a programming error and propagates (python-can's Notifier then
calls ``on_error``, which logs it).

Multi-frame samples (F/T 2 frames, IMU 6, thruster command 3) are assembled by counter in any
order, and complete only when every part carries the same counter. The completed sample's
``t_ns`` is the timestamp of its first frame (closest to when the device sampled).
"""
from __future__ import annotations

import logging
from typing import Callable, Iterable, Sequence

import can

from drivers import frames, wire
from drivers.health import DEFAULT_TIMING, BusCounters, DeviceCounters, SourceTiming
from drivers.samples import BusHealth, DeviceHealth, ImuSample, Sample, ThrusterCommand

log = logging.getLogger(__name__)

Sink = Callable[[Sample], None]
Handler = Callable[[can.Message, bytes], None]
"""A driver's work on one validated frame of its own: ``handler(msg, payload)``."""


def _t_ns(msg: can.Message) -> int:
    return int(round(msg.timestamp * 1e9))


class _Assembler:
    """Collects the parts of one multi-frame sample. Frame ids -> payloads, for one counter.

    ``first_ns``: the timestamp of the sample's first frame, which is its ``t_ns``: the closest
    to when the device sampled (on a loaded bus the last frame can come most of a period later).

    ``optional``: the id of an optional part (the thruster command's keep-out mask). A stream that
    has never carried it completes on the others; from its first one on, the part is required
    (a frame of it lost makes the sample incomplete, as any part). If that first one arrives after
    its sample completed without it, it is dropped, uncounted.
    """

    __slots__ = ("n", "counter", "parts", "first_ns", "optional", "done")

    def __init__(self, n: int, optional: int | None = None):
        self.n = n if optional is None else n - 1
        self.optional = optional
        self.counter = -1
        self.done = -1                  # the counter of the last completed sample
        self.parts: dict[int, bytes] = {}
        self.first_ns = 0

    def add(self, frame_id: int, counter: int, data: bytes, dev: DeviceCounters,
            t_ns: int) -> dict[int, bytes] | None:
        parts = self.parts
        if frame_id == self.optional:
            self.optional = None
            self.n += 1
            if not parts and counter == self.done:
                return None
        if parts and counter != self.counter:
            dev.reject("incomplete")
            parts = self.parts = {}
        elif frame_id in parts:
            dev.reject("duplicate")
            return None
        if not parts:
            self.first_ns = t_ns
        self.counter = counter
        parts[frame_id] = data
        if len(parts) == self.n:
            self.parts = {}
            self.done = counter
            return parts
        return None


class Driver(can.Listener):
    """Base of the device drivers: id dispatch and frame validation against the DBC.

    Subclasses fill ``self._route``: frame id -> (Layout, DeviceCounters, handler(msg, data)).
    ``fd=True`` accepts CAN FD frames as well as classic ones (the FD option keeps the payloads).
    """

    def __init__(self, bus: str, sink: Sink, fd: bool = False):
        self.bus, self.sink, self.fd = bus, sink, fd
        self._route: dict[int, tuple[wire.Layout, DeviceCounters, Handler]] = {}
        self.errors = 0

    @property
    def ids(self) -> frozenset[int]:
        return frozenset(self._route)

    def on_message_received(self, msg: can.Message) -> None:
        route = self._route.get(msg.arbitration_id)
        if route is None or msg.is_error_frame or msg.is_extended_id:
            return                                  # not ours: the BusMonitor counts it
        lay, dev, handler = route
        if msg.is_remote_frame:
            dev.rejected["remote_frame"] += 1
            return
        if msg.is_fd and not self.fd:
            dev.rejected["fd_on_classic"] += 1
            return
        data = msg.data
        if data is None or len(data) != lay.length or msg.dlc != lay.length:
            dev.rejected["dlc"] += 1
            return
        handler(msg, bytes(data))

    def on_error(self, exc: Exception) -> None:
        self.errors += 1
        log.error("%s on bus %s: %r", type(self).__name__, self.bus, exc)

    def stop(self) -> None:
        """Nothing to release (the bus belongs to the caller); harmless twice."""

    def counters(self) -> list[DeviceCounters]:
        seen: dict[int, DeviceCounters] = {}
        for _, dev, _ in self._route.values():
            seen.setdefault(id(dev), dev)
        return list(seen.values())

    def health(self, now_ns: int) -> list[DeviceHealth]:
        return [d.snapshot(now_ns) for d in self.counters()]


def _period_ns(kind: str, frame_id: int) -> int:
    return wire.layouts(kind)[frame_id].cycle_ms * 1_000_000


class FtDriver(Driver):
    """The six-axis F/T sensor of one arm (``FT_SG_A`` + ``FT_SG_B``) -> :class:`WrenchSample`."""

    def __init__(self, arm: str, sink: Sink, fd: bool = False, timing: SourceTiming = DEFAULT_TIMING):
        super().__init__(arm, sink, fd)
        self.device = arm
        self.dev = DeviceCounters(arm, arm, _period_ns("arm", wire.FT_A_ID), wire.FT_FAULT, timing)
        self._asm = _Assembler(2)
        for i in frames.FT_PARTS:
            self._route[i] = (wire.layouts("arm")[i], self.dev, self._part)

    def _part(self, msg: can.Message, data: bytes) -> None:
        parts = self._asm.add(msg.arbitration_id, data[0], data, self.dev, _t_ns(msg))
        if parts is None:
            return
        s = frames.decode_wrench(parts[wire.FT_A_ID], parts[wire.FT_B_ID], self.device, self._asm.first_ns)
        if self.dev.admit(s.counter, s.t_ns, s.saturated, s.status):
            self.sink(s)


class JointDriver(Driver):
    """The joint drives of one arm (``JOINT_STATE_J<j>``) -> :class:`JointSample` per joint."""

    def __init__(self, arm: str, joints: Iterable[str], sink: Sink, fd: bool = False,
                 timing: SourceTiming = DEFAULT_TIMING):
        super().__init__(arm, sink, fd)
        self.devices = [f"{arm}/{j}" for j in joints]
        if len(self.devices) > wire.MAX_JOINTS:
            raise wire.WireError(f"arm {arm}: {len(self.devices)} joints, the contract has {wire.MAX_JOINTS} slots")
        lays = wire.layouts("arm")
        for k, name in enumerate(self.devices):
            i = wire.JOINT_STATE_BASE + k
            dev = DeviceCounters(name, arm, _period_ns("arm", i), wire.DRIVE_FAULT, timing)
            self._route[i] = (lays[i], dev, self._make(name, dev))

    def _make(self, name: str, dev: DeviceCounters) -> Handler:
        def handle(msg: can.Message, data: bytes) -> None:
            s = frames.decode_joint(data, name, _t_ns(msg))
            if dev.admit(s.counter, s.t_ns, s.saturated, s.status):
                self.sink(s)
        return handle


class TorqueCommandDriver(Driver):
    """The joint torque commands of one arm (``JOINT_TORQUE_CMD_G<g>``) -> :class:`TorqueCommand`.

    One health entry ``<arm>/torque_cmd`` per command frame group ``g`` (``<arm>/torque_cmd/g``
    when the arm has more than 3 joints).
    """

    def __init__(self, arm: str, joints: Iterable[str], sink: Sink, fd: bool = False,
                 timing: SourceTiming = DEFAULT_TIMING):
        super().__init__(arm, sink, fd)
        names = [f"{arm}/{j}" for j in joints]
        lays = wire.layouts("arm")
        ngroups = -(-len(names) // wire.CMD_GROUP)
        for g in range(ngroups):
            i = wire.TORQUE_CMD_BASE + g
            slots: list[str | None] = list(names[g * wire.CMD_GROUP:(g + 1) * wire.CMD_GROUP])
            slots += [None] * (wire.CMD_GROUP - len(slots))
            dname = f"{arm}/torque_cmd" + (f"/{g}" if ngroups > 1 else "")
            dev = DeviceCounters(dname, arm, _period_ns("arm", i), 0, timing)
            self._route[i] = (lays[i], dev, self._make(slots, dev))

    def _make(self, slots: Sequence[str | None], dev: DeviceCounters) -> Handler:
        def handle(msg: can.Message, data: bytes) -> None:
            cmds = frames.decode_torque_commands(data, slots, _t_ns(msg))
            if dev.sequence(data[0], _t_ns(msg)):
                dev.accept(_t_ns(msg), any(c.saturated for c in cmds), 0)
                for c in cmds:
                    self.sink(c)
        return handle


class _MultiFrameDriver(Driver):
    _parts: tuple[int, ...] = ()
    _optional: int | None = None

    def __init__(self, device: str, sink: Sink, fd: bool, timing: SourceTiming, fault_mask: int):
        super().__init__(wire.SPACECRAFT_BUS, sink, fd)
        self.device = device
        lays = wire.layouts("spacecraft")
        self.dev = DeviceCounters(device, self.bus, _period_ns("spacecraft", self._parts[0]), fault_mask, timing)
        self._asm = _Assembler(len(self._parts), self._optional)
        for i in self._parts:
            self._route[i] = (lays[i], self.dev, self._part)

    def _decode(self, parts: dict[int, bytes], t_ns: int) -> ImuSample | ThrusterCommand:
        raise NotImplementedError

    def _part(self, msg: can.Message, data: bytes) -> None:
        parts = self._asm.add(msg.arbitration_id, data[0], data, self.dev, _t_ns(msg))
        if parts is None:
            return
        s = self._decode(parts, self._asm.first_ns)
        if self.dev.admit(s.counter, s.t_ns, s.saturated, getattr(s, "status", 0), self._device_ns(parts)):
            self.sink(s)

    def _device_ns(self, parts: dict[int, bytes]) -> int | None:
        """The device's own sample time (ns, modulo its clock's wrap), when its frames carry one."""
        return None


class ImuDriver(_MultiFrameDriver):
    """The spacecraft IMU (six frames per sample) -> :class:`ImuSample`."""

    _parts = frames.IMU_PARTS

    def __init__(self, sink: Sink, fd: bool = False, timing: SourceTiming = DEFAULT_TIMING):
        super().__init__("imu", sink, fd, timing, wire.IMU_FAULT)

    def _decode(self, parts: dict[int, bytes], t_ns: int) -> ImuSample:
        return frames.decode_imu(parts, t_ns)

    def _device_ns(self, parts: dict[int, bytes]) -> int:
        # IMU_SAMPLE_TIME: ctr u8, time_us u32 big-endian (the IMU's clock; exact loss counts)
        return int.from_bytes(parts[wire.IMU_TIME_ID][1:5], "big") * 1000


class ThrusterCommandDriver(_MultiFrameDriver):
    """The thruster commands (three frames per control cycle, four with the keep-out mask) ->
    :class:`ThrusterCommand`."""

    _parts = frames.THRUSTER_PARTS
    _optional = wire.THRUSTER_ALLOWED_ID

    def __init__(self, sink: Sink, fd: bool = False, timing: SourceTiming = DEFAULT_TIMING):
        super().__init__("thrusters", sink, fd, timing, 0)

    def _decode(self, parts: dict[int, bytes], t_ns: int) -> ThrusterCommand:
        return frames.decode_thruster(parts, t_ns)


class ValveCommandDriver(Driver):
    """The 1 kHz valve commands of the PWPFM modulator (``THRUSTER_VALVE_CMD``) -> :class:`ValveCommand`."""

    def __init__(self, sink: Sink, fd: bool = False, timing: SourceTiming = DEFAULT_TIMING):
        super().__init__(wire.SPACECRAFT_BUS, sink, fd)
        self.device = "valves"
        self.dev = DeviceCounters("valves", self.bus, _period_ns("spacecraft", wire.VALVE_CMD_ID), 0, timing)
        self._route[wire.VALVE_CMD_ID] = (wire.layouts("spacecraft")[wire.VALVE_CMD_ID], self.dev, self._frame)

    def _frame(self, msg: can.Message, data: bytes) -> None:
        s = frames.decode_valves(data, _t_ns(msg))
        if self.dev.admit(s.counter, s.t_ns, False, 0):
            self.sink(s)


class BusMonitor(can.Listener):
    """Counts every frame of one bus, measures its worst-case load, reads heartbeats, and counts
    the frames no driver owns. ``owned`` = the ids the drivers on this bus handle."""

    def __init__(self, spec: wire.BusSpec, owned: Iterable[int], fd: bool = False):
        self.spec, self.fd = spec, fd
        self.counters = BusCounters(spec.name)
        self._owned = frozenset(owned)
        lays = wire.layouts(spec.kind)
        self._heartbeats = {i: lays[i] for i in spec.ids if i >= wire.HEARTBEAT_BASE and i < wire.HEARTBEAT_BASE + 0x80}
        self._classic_time = [wire.frame_time_s(n) for n in range(9)]

    def on_message_received(self, msg: can.Message) -> None:
        c = self.counters
        c.frames += 1
        n = len(msg.data) if msg.data is not None else 0
        if msg.is_fd:
            c.busy_s += wire.fd_frame_time_s(n)
        else:
            c.busy_s += self._classic_time[min(msg.dlc if 0 <= msg.dlc <= 8 else 8, 8)]
        if msg.is_error_frame:
            c.rejected["error_frame"] += 1
            return
        i = msg.arbitration_id
        if msg.is_extended_id:
            c.rejected["extended_id"] += 1
            return
        if i in self._owned:
            return
        self.not_owned(msg, n)

    def not_owned(self, msg: can.Message, n: int) -> None:
        """A frame no driver owns: a heartbeat (its node state is kept) or a rejection by reason."""
        c = self.counters
        lay = self._heartbeats.get(msg.arbitration_id)
        if lay is None:
            c.rejected["unknown_id"] += 1
        elif msg.is_remote_frame:
            c.rejected["remote_frame"] += 1
        elif msg.is_fd and not self.fd:
            c.rejected["fd_on_classic"] += 1
        elif n != lay.length or msg.dlc != lay.length:
            c.rejected["dlc"] += 1
        else:
            c.nodes[lay.sender] = msg.data[1]

    def on_error(self, exc: Exception) -> None:
        log.error("bus monitor %s: %r", self.spec.name, exc)

    def stop(self) -> None:
        """Nothing to release; harmless twice."""

    def health(self, now_ns: int) -> BusHealth:
        return self.counters.snapshot(now_ns)


class BusDispatcher:
    """The monitor and the drivers of one bus as ONE function per frame: :meth:`feed` counts,
    rejects and decodes exactly as calling ``on_message_received`` of the monitor and then of each
    driver would (same counters, same samples, same order), with one id lookup instead of every
    listener looking at every frame. For a single-threaded owner such as
    :class:`gateway.pipeline.Pipeline`; under a python-can ``Notifier`` use the listeners.
    """

    __slots__ = ("monitor", "drivers", "feed", "_table")

    def __init__(self, monitor: BusMonitor, drivers: Iterable[Driver]):
        self.monitor, self.drivers = monitor, list(drivers)
        table: dict[int, tuple[int, DeviceCounters, Handler, bool]] = {}
        merged = True
        for d in self.drivers:
            for i, (lay, dev, handler) in d._route.items():
                if i in table:
                    merged = False
                table[i] = (lay.length, dev, handler, d.fd)
        if set(table) != set(monitor._owned) or type(monitor).on_message_received is not BusMonitor.on_message_received:
            merged = False
        if any(type(d).on_message_received is not Driver.on_message_received for d in self.drivers):
            merged = False
        self._table = table
        self.feed = self._feed if merged else self._feed_each

    def _feed_each(self, msg: can.Message) -> None:
        self.monitor.on_message_received(msg)
        for d in self.drivers:
            d.on_message_received(msg)

    def _feed(self, msg: can.Message) -> None:
        mon = self.monitor
        c = mon.counters
        c.frames += 1
        data = msg.data
        n = len(data) if data is not None else 0
        if msg.is_fd:
            c.busy_s += wire.fd_frame_time_s(n)
        else:
            dlc = msg.dlc
            c.busy_s += mon._classic_time[min(dlc if 0 <= dlc <= 8 else 8, 8)]
        if msg.is_error_frame:
            c.rejected["error_frame"] += 1
            return
        if msg.is_extended_id:
            c.rejected["extended_id"] += 1
            return
        route = self._table.get(msg.arbitration_id)
        if route is None:                       # the monitor's part: heartbeats, unknown ids
            mon.not_owned(msg, n)
            return
        length, dev, handler, fd = route       # the owning driver's part
        if msg.is_remote_frame:
            dev.rejected["remote_frame"] += 1
            return
        if msg.is_fd and not fd:
            dev.rejected["fd_on_classic"] += 1
            return
        if data is None or n != length or msg.dlc != length:
            dev.rejected["dlc"] += 1
            return
        handler(msg, bytes(data))


def drivers_for(spec: wire.BusSpec, sink: Sink, fd: bool = False,
                timing: SourceTiming = DEFAULT_TIMING) -> list[Driver]:
    """The device drivers for one bus of a :class:`~drivers.wire.WireMap`."""
    if spec.kind == "arm":
        arm = spec.arm_name
        return [FtDriver(arm, sink, fd, timing),
                JointDriver(arm, spec.joints, sink, fd, timing),
                TorqueCommandDriver(arm, spec.joints, sink, fd, timing)]
    return [ImuDriver(sink, fd, timing), ThrusterCommandDriver(sink, fd, timing),
            ValveCommandDriver(sink, fd, timing)]


def listeners_for(spec: wire.BusSpec, sink: Sink, fd: bool = False,
                  timing: SourceTiming = DEFAULT_TIMING) -> tuple[BusMonitor, list[Driver]]:
    """The monitor and the drivers of one bus, ready for ``can.Notifier(bus, [monitor, *drivers])``."""
    drivers = drivers_for(spec, sink, fd, timing)
    owned = set().union(*(d.ids for d in drivers))
    return BusMonitor(spec, owned, fd), drivers
