"""The robot's sensor firmware: simulator readings -> CAN frames on python-can buses.

Every simulated device speaks the wire contract of docs/wire.md through the drivers' own
encoders (:mod:`drivers.frames`); nothing here packs bytes by hand. Per 1 ms simulator step
(``Simulation.step()`` -> :class:`~simulator.engine.Readings`), in send order per bus::

    arm bus <arm>     JOINT_STATE_J0..Jn-1   every step (1 kHz), one counter per joint
                      JOINT_TORQUE_CMD_G*    every 2 ms (DBC cycle), the latest command set
                      FT_SG_A, FT_SG_B       every step (1 kHz), one counter per arm
                      HEARTBEAT_*            every 100 ms, one per node (FT, ARM_CTRL, DRIVE_Jj)
    spacecraft        IMU_* (6 frames)       when the IMU samples (``readings.imu``, 500 Hz)
                      THRUSTER_VALVE_CMD     every step (1 kHz), the PWPFM valve commands
                      THRUSTER_CMD_* (3)     every 10 ms (DBC cycle), the latest command, the
                                             valves open during that step
                      HEARTBEAT_IMU, _SC_CTRL every 100 ms

Joint states go before the F/T frames, so a wrench sample completes after the joint states of
the same epoch. Commands are sent at their DBC cycle time whatever the controller rate (the
controller's last output is held), so ``bsc budget`` describes what the wire carries.

Stamping: every frame of a step is stamped ``readings.t_ns`` (``msg.timestamp`` in seconds),
the simulated time (lockstep). :func:`run_on_buses` in real-time mode restamps each frame with
the wall clock at send.

Fault injection (:class:`Faults`): drop, duplicate, reorder, corrupt, bad DLC (random, seeded,
at most one per sample), a device silent for a while, counter jumps. :attr:`Firmware.counts`
says what was injected per device; docs/firmware.md gives the exact relation to what the
drivers' health then reports (:meth:`Firmware.expected_health` computes it).
"""
from __future__ import annotations

import contextlib
import ipaddress
import math
import random
import time
from collections import Counter, deque
from dataclasses import asdict, dataclass, fields, replace
from typing import Callable, Mapping

import can

from simulator.errors import SimulatorError
from drivers.wire import udp_port  # noqa: F401 - part of this module's API
from drivers import frames, wire
from drivers.samples import ImuSample, JointSample, ThrusterCommand, TorqueCommand, ValveCommand, WrenchSample

SEND_TIMEOUT_S = 1.0
HEARTBEAT_OPERATIONAL = 0x05
MAX_JUMP = 126                 # a larger skip would read as "late" (8-bit counters, half range)


class FirmwareError(SimulatorError, ValueError):
    """A fault or bus configuration the firmware cannot apply (unknown device, bad rate)."""


# --- faults ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Faults:
    """Fault injection knobs, all off by default.

    The five rates are per SAMPLE of a device (= per frame for single-frame devices): each
    sample draws once and gets at most one of the faults, so the rates must sum to <= 1. A
    frame-level fault hits one part of a multi-frame sample, chosen at random. Random faults
    apply to samples stamped before ``until_s`` (so a run can end clean and every injected
    fault become visible to the drivers). Heartbeats are never faulted (only silenced).

    ``silent``: ``(device, start_s, duration_s)``; the device's frames and its node's heartbeat
    are not sent during ``[start, start + duration)``, its counter keeps running.
    ``counter_jumps``: ``(device, at_s, jump)``; from the first sample at or after ``at_s`` the
    device's counter runs ``jump`` ahead (1..126).
    Devices: ``<arm>`` (its F/T sensor), ``<arm>/<joint>``, ``<arm>/torque_cmd`` (``/<g>`` when
    the arm has more than 3 joints), ``imu``, ``thrusters``.
    """

    drop_rate: float = 0.0        # probability a frame is not sent
    duplicate_rate: float = 0.0   # probability a frame is sent twice
    reorder_rate: float = 0.0     # probability a sample is sent after the device's next one
    corrupt_rate: float = 0.0     # probability a frame gets a flipped measurement byte
    bad_dlc_rate: float = 0.0     # probability a frame is truncated/extended
    silent: tuple[tuple[str, float, float], ...] = ()
    counter_jumps: tuple[tuple[str, float, int], ...] = ()
    seed: int = 0
    from_s: float = 0.0           # random faults only on samples stamped in [from_s, until_s)
    until_s: float = math.inf

    RATES = ("drop_rate", "duplicate_rate", "reorder_rate", "corrupt_rate", "bad_dlc_rate")

    def __post_init__(self):
        for name in self.RATES:
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.0 <= v <= 1.0):
                raise FirmwareError(f"faults: {name} must be a probability in [0, 1], got {v!r}")
        if sum(getattr(self, n) for n in self.RATES) > 1.0 + 1e-12:
            raise FirmwareError("faults: the five rates are exclusive per sample and must sum to <= 1")
        object.__setattr__(self, "silent", tuple((str(d), float(s), float(t)) for d, s, t in self.silent))
        object.__setattr__(self, "counter_jumps", tuple((str(d), float(a), int(j)) for d, a, j in self.counter_jumps))
        for d, s, t in self.silent:
            if s < 0 or t <= 0:
                raise FirmwareError(f"faults: silent {d}: start must be >= 0 and duration > 0 s")
        for d, a, j in self.counter_jumps:
            if a < 0 or not 1 <= j <= MAX_JUMP:
                raise FirmwareError(f"faults: counter jump {d}: time >= 0 s and jump 1..{MAX_JUMP}, got {a:g}, {j}")

    @property
    def any(self) -> bool:
        return bool(self.silent or self.counter_jumps or any(getattr(self, n) for n in self.RATES))

    @classmethod
    def from_table(cls, table: Mapping | None) -> "Faults":
        """From a scenario's ``[faults]`` table (keys = the field names; ``silent`` and
        ``counter_jumps`` as arrays of ``[device, start_s, duration_s]`` / ``[device, at_s, n]``)."""
        table = dict(table or {})
        known = {f.name for f in fields(cls)}
        unknown = set(table) - known
        if unknown:
            raise FirmwareError(f"faults: unknown key(s) {', '.join(sorted(unknown))} "
                                f"(known: {', '.join(sorted(known))})")
        for key, n in (("silent", 3), ("counter_jumps", 3)):
            rows = table.get(key, ())
            if any(not isinstance(r, (list, tuple)) or len(r) != n for r in rows):
                third = "duration_s" if key == "silent" else "jump"
                raise FirmwareError(f"faults: {key} rows are [device, time_s, {third}]")
            table[key] = tuple(tuple(r) for r in rows)
        return cls(**table)

    def replace(self, **changes) -> "Faults":
        return replace(self, **changes)


# --- per-device streams ----------------------------------------------------------------------

class _Stream:
    """One device's sample stream: its counter, pending reorder, silence and jumps."""

    __slots__ = ("device", "bus", "parts", "node", "seq", "offset", "held", "silent", "jumps")

    def __init__(self, device: str, bus: str, parts: int, node: int):
        self.device, self.bus, self.parts, self.node = device, bus, parts, node
        self.seq = 0              # samples produced so far (the counter keeps running while silent)
        self.offset = 0           # sum of counter jumps applied
        self.held: list[can.Message] = []   # a reordered sample waiting for the next one
        self.silent: list[tuple[int, int]] = []
        self.jumps: list[tuple[int, int]] = []

    def counter(self) -> int:
        return (self.seq + self.offset) & 0xFF

    def is_silent(self, t_ns: int) -> bool:
        return any(a <= t_ns < b for a, b in self.silent)


def _measurement_bytes(lay: wire.Layout, n_signals: int | None = None) -> tuple[int, ...]:
    """Byte offsets of the values a decoder returns (not the counter, a status word, the state
    of a heartbeat or the IMU clock): a flipped byte there always changes a decoded value and
    nothing else. ``n_signals`` limits them to the first signals (a torque command's used slots)."""
    out, pos = [], 0
    for i, (name, bits) in enumerate(zip(lay.signals, lay.bits)):
        if name not in _NOT_MEASUREMENTS and (n_signals is None or i < n_signals):
            out += range(pos, pos + bits // 8)
        pos += bits // 8
    return tuple(out)


_NOT_MEASUREMENTS = frozenset({"counter", "status", "state", "time_us"})


def _clone(msg: can.Message, data: bytes | None = None) -> can.Message:
    return can.Message(timestamp=msg.timestamp, arbitration_id=msg.arbitration_id, is_extended_id=False,
                       data=msg.data if data is None else data, is_fd=msg.is_fd, bitrate_switch=msg.bitrate_switch)


COUNT_KEYS = ("samples", "drop", "duplicate", "duplicate_last", "reorder", "corrupt", "bad_dlc", "silent", "jump")


class Firmware:
    """The devices of one robot putting their readings on the wire, one simulator step at a time.

    ``counts[device]``: what was produced and injected (:data:`COUNT_KEYS`): ``samples``
    produced (including those silenced), then per fault kind the number of samples it hit
    (``duplicate_last``: duplicates of the part that completes a multi-frame sample, also
    counted in ``duplicate``; ``silent``: samples not sent; ``jump``: counter values skipped).
    ``frames_sent[bus]``: frames handed out for each bus. ``pacing``: how late the steps of a
    real-time :func:`run_on_buses` went out.
    """

    def __init__(self, robot, *, fd: bool = False, faults: Faults | None = None):
        self.robot, self.fd = robot, fd
        self.faults = faults or Faults()
        self.wire = wire.WireMap.from_robot(robot)
        self._rng = random.Random(self.faults.seed)
        self._random = any(getattr(self.faults, n) for n in Faults.RATES)
        self._until_ns = math.inf if math.isinf(self.faults.until_s) else round(self.faults.until_s * 1e9)
        self._from_ns = round(self.faults.from_s * 1e9)
        self._streams: dict[str, _Stream] = {}
        self._joint_ix: dict[str, int] = {}          # "<arm>/<joint>" -> index into readings.joint_*
        self._torque_groups: dict[str, list[str]] = {}   # arm -> torque command device per group
        self._nodes: dict[str, list[int]] = {}       # bus -> heartbeat node ids
        self._hb_ctr: Counter = Counter()
        names = self.robot.joint_names
        for arm in robot.arms:
            spec = self.wire.buses[arm.name]
            for j, joint in enumerate(spec.joints):
                dev = f"{arm.name}/{joint}"
                self._add(dev, arm.name, 1, 0x10 + j)
                self._joint_ix[dev] = names.index(dev)
            ngroups = -(-len(spec.joints) // wire.CMD_GROUP)
            groups = [f"{arm.name}/torque_cmd" + (f"/{g}" if ngroups > 1 else "") for g in range(ngroups)]
            for g in groups:
                self._add(g, arm.name, 1, 2)
            self._torque_groups[arm.name] = groups
            self._add(arm.name, arm.name, 2, 1)
        self._add("imu", wire.SPACECRAFT_BUS, len(frames.IMU_PARTS), 1)
        self._add("valves", wire.SPACECRAFT_BUS, 1, 2)
        self._add("thrusters", wire.SPACECRAFT_BUS, len(frames.THRUSTER_PARTS), 2)
        for name, spec in self.wire.buses.items():
            self._nodes[name] = sorted(i - wire.HEARTBEAT_BASE for i in spec.ids
                                       if wire.HEARTBEAT_BASE <= i < wire.HEARTBEAT_BASE + 0x80)
        for dev, start, dur in self.faults.silent:
            self._stream(dev, "silent").silent.append((round(start * 1e9), round((start + dur) * 1e9)))
        for dev, at, jump in self.faults.counter_jumps:
            self._stream(dev, "counter_jumps").jumps.append((round(at * 1e9), jump))
        self.counts: dict[str, Counter] = {d: Counter({k: 0 for k in COUNT_KEYS}) for d in self._streams}
        self.frames_sent: Counter = Counter({b: 0 for b in self.wire.buses})
        self.pacing: Pacing | None = None        # set by run_on_buses(realtime=True)
        self._cycle_ns = {i: lay.cycle_ms * 1_000_000 for kind in ("arm", "spacecraft")
                          for i, lay in wire.layouts(kind).items()}
        self._torque: object = None                  # the controller's latest outputs (held)
        self._thruster: object = None
        self._allowed = -1                           # its keep-out mask (THRUSTER_CMD_ALLOWED; -1 none)
        lays = {**wire.layouts("arm"), **wire.layouts("spacecraft")}
        self._corruptible = {i: _measurement_bytes(lay) for i, lay in lays.items()}
        for arm in robot.arms:
            n = len(arm.joint_names)
            for g in range(-(-n // wire.CMD_GROUP)):
                used = min(wire.CMD_GROUP, n - g * wire.CMD_GROUP)
                self._corruptible[(arm.name, wire.TORQUE_CMD_BASE + g)] = _measurement_bytes(
                    lays[wire.TORQUE_CMD_BASE + g], 1 + used)

    # -- setup helpers
    def _add(self, device: str, bus: str, parts: int, node: int) -> None:
        self._streams[device] = _Stream(device, bus, parts, node)

    def _stream(self, device: str, what: str) -> _Stream:
        try:
            return self._streams[device]
        except KeyError:
            raise FirmwareError(f"faults: {what}: no device {device!r} on robot {self.robot.name} "
                                f"(devices: {', '.join(self._streams)})") from None

    @property
    def devices(self) -> list[str]:
        """Every device stream, in the order frames are produced within a bus."""
        return list(self._streams)

    # -- one step
    def frames(self, readings) -> list[tuple[str, can.Message]]:
        """(bus name, message) for one simulator step, in send order per bus (buses in WireMap
        order: arms, then spacecraft), each stamped ``readings.t_ns`` (seconds in
        ``msg.timestamp``)."""
        t = int(readings.t_ns)
        fd = self.fd
        out: list[tuple[str, can.Message]] = []
        if readings.torque_cmd is not None:
            self._torque = readings.torque_cmd
        if readings.thruster_cmd is not None:
            self._thruster = readings.thruster_cmd
            self._allowed = -1 if readings.thruster_allowed is None else valve_mask(readings.thruster_allowed)
        for k, arm in enumerate(self.robot.arms):
            for j, joint in enumerate(arm.joint_names):
                dev = f"{arm.name}/{joint}"
                ix = self._joint_ix[dev]
                st = self._streams[dev]
                s = JointSample(dev, t, self._counter(st, t), float(readings.joint_angle[ix]),
                                float(readings.joint_rate[ix]))
                self._emit(out, st, t, [frames.encode_joint(s, j, fd)])
            if self._torque is not None and t % self._cycle_ns[wire.TORQUE_CMD_BASE] == 0:
                taus = [float(self._torque[self._joint_ix[f"{arm.name}/{jn}"]]) for jn in arm.joint_names]
                for g, dev in enumerate(self._torque_groups[arm.name]):
                    st = self._streams[dev]
                    ctr = self._counter(st, t)
                    cmds = [TorqueCommand(f"{arm.name}/{jn}", t, ctr, tau) for jn, tau in zip(arm.joint_names, taus)]
                    # every group of an arm is encoded with this group's own counter (a jump may
                    # have put one group's counter ahead of the others)
                    msg = frames.encode_torque_commands(cmds, fd)[g]
                    self._emit(out, st, t, [msg], corrupt_key=(arm.name, msg.arbitration_id))
            st = self._streams[arm.name]
            ft = readings.ft[k]
            self._emit(out, st, t, frames.encode_wrench(WrenchSample(
                arm.name, t, self._counter(st, t), tuple(map(float, ft[:3])), tuple(map(float, ft[3:])),
                saturated=bool(readings.ft_saturated[k])), fd))
            self._heartbeats(out, arm.name, t)
        if readings.imu is not None:
            quat, rate, acc, sat = readings.imu
            st = self._streams["imu"]
            self._emit(out, st, t, frames.encode_imu(ImuSample(
                t, self._counter(st, t), tuple(map(float, quat)), tuple(map(float, rate)), tuple(map(float, acc)),
                saturated=bool(sat)), fd=fd))
        st = self._streams["valves"]
        valves = ValveCommand(t, self._counter(st, t), valve_mask(readings.valves))
        self._emit(out, st, t, [frames.encode_valves(valves, fd)])
        if self._thruster is not None and t % self._cycle_ns[wire.THRUSTER_FORCE_ID] == 0:
            w = self._thruster
            st = self._streams["thrusters"]
            self._emit(out, st, t, frames.encode_thruster(ThrusterCommand(
                t, self._counter(st, t), tuple(map(float, w[:3])), tuple(map(float, w[3:])),
                valves=valve_mask(readings.valves), allowed=self._allowed), fd))
        self._heartbeats(out, wire.SPACECRAFT_BUS, t)
        return out

    def flush(self) -> list[tuple[str, can.Message]]:
        """Frames still held back by a reorder at the end of a run (to send last, late)."""
        out = []
        for st in self._streams.values():
            out += [(st.bus, m) for m in st.held]
            self.frames_sent[st.bus] += len(st.held)
            st.held = []
        return out

    def _counter(self, st: _Stream, t: int) -> int:
        """The counter of the sample ``st`` is about to produce at ``t``, after any jump due."""
        if st.jumps and st.jumps[0][0] <= t:
            due = [j for at, j in st.jumps if at <= t]
            st.jumps = [(at, j) for at, j in st.jumps if at > t]
            st.offset += sum(due)
            self.counts[st.device]["jump"] += sum(due)
        return st.counter()

    def _heartbeats(self, out: list, bus: str, t: int) -> None:
        if t % self._cycle_ns[wire.HEARTBEAT_BASE + 1] != 0:
            return
        silent_nodes = {st.node for st in self._streams.values() if st.bus == bus and st.is_silent(t)}
        for node in self._nodes[bus]:
            if node in silent_nodes:
                continue
            key = (bus, node)
            msg = frames.encode_heartbeat(node, self._hb_ctr[key], HEARTBEAT_OPERATIONAL, self.fd)
            msg.timestamp = t / 1e9
            self._hb_ctr[key] = (self._hb_ctr[key] + 1) & 0xFF
            out.append((bus, msg))
            self.frames_sent[bus] += 1

    def _draw(self, st: _Stream, t: int) -> tuple[str | None, float, float]:
        """The random fault of one sample (or None) and two uniforms to place it. Always draws
        the same numbers per sample, so a fault window does not shift the random sequence."""
        if not self._random:
            return None, 0.0, 0.0
        u, v, w = self._rng.random(), self._rng.random(), self._rng.random()
        # the sample that overtakes a reordered one goes clean
        if not self._from_ns <= t < self._until_ns or st.held:
            return None, v, w
        acc = 0.0
        for name in Faults.RATES:
            acc += getattr(self.faults, name)
            if u < acc:
                return name[:-5], v, w
        return None, v, w

    def _emit(self, out: list, st: _Stream, t: int, msgs: list[can.Message], corrupt_key=None) -> None:
        """Send one sample of ``st`` (its frames in ``msgs``), applying silence and faults, then
        any sample of ``st`` held back by a reorder."""
        c = self.counts[st.device]
        c["samples"] += 1
        st.seq += 1
        if st.is_silent(t):
            c["silent"] += 1
            return
        kind, v, w = self._draw(st, t)
        part = min(int(v * len(msgs)), len(msgs) - 1)
        sent = msgs
        if kind == "reorder":
            st.held, sent = msgs, []
        elif kind == "drop":
            sent = msgs[:part] + msgs[part + 1:]
        elif kind == "duplicate":
            sent = msgs[:part + 1] + [_clone(msgs[part])] + msgs[part + 1:]
            if st.parts > 1 and part == len(msgs) - 1:
                c["duplicate_last"] += 1
        elif kind == "corrupt":
            cand = [(i, self._corruptible[corrupt_key or m.arbitration_id]) for i, m in enumerate(msgs)
                    if self._corruptible[corrupt_key or m.arbitration_id]]
            i, where = cand[min(int(v * len(cand)), len(cand) - 1)]
            data = bytearray(msgs[i].data)
            data[where[min(int(w * len(where)), len(where) - 1)]] ^= 1 + int(w * 997) % 255
            sent = msgs[:i] + [_clone(msgs[i], bytes(data))] + msgs[i + 1:]
        elif kind == "bad_dlc":
            m = msgs[part]
            lengths = [n for n in range(9) if n != len(m.data)]
            n = lengths[min(int(w * len(lengths)), len(lengths) - 1)]
            data = bytes(m.data[:n]) + bytes(max(0, n - len(m.data)))
            sent = msgs[:part] + [_clone(m, data)] + msgs[part + 1:]
        if kind is not None:
            c[kind] += 1
        if kind != "reorder" and st.held:
            sent = sent + st.held
            st.held = []
        out += [(st.bus, m) for m in sent]
        self.frames_sent[st.bus] += len(sent)

    # -- the documented relation to driver health
    def expected_health(self, device: str) -> dict[str, int]:
        """What the drivers' health of ``device`` must report after this run (docs/firmware.md),
        provided every fault was preceded and followed by a sample of the same device that
        arrived intact (``Faults.from_s``/``until_s`` and silences that start after the first
        sample and end before the run does ensure it), and no gap reaches 128 samples (an
        8-bit counter cannot tell a longer gap from a late sample)::

            samples    = samples - drop - bad_dlc - silent - reorder
            lost       = drop + bad_dlc + reorder + silent + jump
            late       = reorder
            duplicate  = duplicate - duplicate_last
            incomplete = drop + bad_dlc + duplicate_last        (multi-frame devices; else 0)
            dlc        = bad_dlc
        """
        c = self.counts[device]
        multi = self._streams[device].parts > 1
        return {"samples": c["samples"] - c["drop"] - c["bad_dlc"] - c["silent"] - c["reorder"],
                "lost": c["drop"] + c["bad_dlc"] + c["reorder"] + c["silent"] + c["jump"],
                "late": c["reorder"],
                "duplicate": c["duplicate"] - c["duplicate_last"],
                "incomplete": (c["drop"] + c["bad_dlc"] + c["duplicate_last"]) if multi else 0,
                "dlc": c["bad_dlc"]}


def valve_mask(valves) -> int:
    """Bit i set when thruster i is open."""
    m = 0
    for i, v in enumerate(valves):
        if v:
            m |= 1 << i
    return m


# --- buses -----------------------------------------------------------------------------------

class BusSet(dict):
    """Bus name -> open ``can.BusABC``; a context manager that shuts every bus down (twice is
    harmless)."""

    def close(self) -> None:
        for bus in self.values():
            with contextlib.suppress(Exception):
                bus.shutdown()

    def __enter__(self) -> "BusSet":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def bus_channels(robot, channel: str | Mapping[str, str]) -> dict[str, str]:
    """Bus name -> python-can channel: a prefix maps via :func:`drivers.wire.channel_name`, a
    mapping must name every bus of the robot."""
    names = list(wire.WireMap.from_robot(robot).buses)
    if isinstance(channel, str):
        return {b: wire.channel_name(channel, b) for b in names}
    chans = dict(channel)
    if set(chans) != set(names):
        raise FirmwareError(f"channels must name every bus ({', '.join(names)}), got {', '.join(chans) or 'none'}")
    return {b: chans[b] for b in names}


def open_buses(robot, interface: str, channel: str | Mapping[str, str], fd: bool = False, options=None,
               **kw) -> BusSet:
    """One python-can bus per bus of the robot (WireMap order), opened with
    ``ignore_config=True``, or (``options``, a :class:`drivers.canbus.BusOptions`: a command
    line's) with its bit rates and adapter arguments over python-can's configuration. ``virtual``
    buses keep the frames' timestamps (``preserve_timestamps=True``); ``udp_multicast`` buses get
    one port each (:func:`udp_port`) unless ``port`` is given. Extra keyword arguments go to
    every ``can.Bus``. On failure the buses already open are shut down and the python-can error
    propagates."""
    chans = bus_channels(robot, channel)
    buses = BusSet()
    try:
        for i, (name, ch) in enumerate(chans.items()):
            opts = dict(kw)
            if fd:
                opts["fd"] = True
            if interface == "virtual":
                opts.setdefault("preserve_timestamps", True)
            elif interface == "udp_multicast":
                try:
                    multicast = ipaddress.ip_address(ch).is_multicast
                except ValueError:
                    multicast = False
                if not multicast:
                    raise FirmwareError(f"udp_multicast: channel of bus {name} must be a multicast group address "
                                        f"such as 239.74.163.1, not {ch!r} (give BUS=GROUP for every bus)")
                opts.setdefault("port", udp_port(i))
            if options is not None:
                from drivers.canbus import open_bus

                opts.pop("fd", None)
                buses[name] = open_bus(interface, ch, options, fd=fd, **opts)
            else:
                buses[name] = can.Bus(interface=interface, channel=ch, ignore_config=True, **opts)
    except BaseException:
        buses.close()
        raise
    return buses


LOOKAHEAD_STEPS = 50          # real time: how far the simulation may run ahead of the wire (steps)
COMPUTE_MARGIN_S = 0.0004     # real time: compute one more step only if the next send is this far off


def run_on_buses(sim, buses: Mapping[str, can.BusABC], *, firmware: Firmware | None = None, realtime: bool = False,
                 progress: bool = False, on_step: Callable | None = None, lookahead_steps: int = LOOKAHEAD_STEPS,
                 compute_lead_s: float | None = None):
    """Step ``sim`` to its end and send every frame of every step on its bus; returns the
    truth :class:`~simulator.truth.Trace`.

    Lockstep (default): as fast as possible, frames keep their simulated-time stamps, so a run
    is byte-for-byte and stamp-for-stamp reproducible. Real time: step ``k`` is sent no earlier
    than ``k`` ms after the start on the monotonic clock, and each frame is stamped with the
    wall clock (``time.time()``, python-can's time base) when it is sent; a step that falls
    behind is sent at once (no catch-up pause). The simulation runs up to
    :data:`LOOKAHEAD_STEPS` ahead of the wire, so one slow step does not delay the sends.
    ``on_step(readings)`` runs after each step's frames went out. Frames still held by a reorder
    fault are sent at the end.

    A closed loop through the robot's buses (drive commands that come back from outside and go
    into ``sim`` from ``on_step``) needs each step computed just before it is due:
    ``lookahead_steps=1`` computes one step at a time, and ``compute_lead_s`` waits until the
    step is that close to its due time before computing it (so that a command arriving in the
    meantime is in it).

    In real time the firmware's :attr:`Firmware.pacing` says how late the steps went out (a
    :class:`Pacing`): a receiver that stamps frames on arrival (SocketCAN, udp_multicast) sees
    a step whose last frame left more than half a period late in the next step's slot.
    """
    fw = firmware or Firmware(sim.robot)
    missing = set(fw.wire.buses) - set(buses)
    if missing:
        raise FirmwareError(f"no bus given for {', '.join(sorted(missing))}")
    from simulator.engine import DT_S
    from simulator.progress import SimProgress

    bar = SimProgress(sim.scenario.name, sim.n_steps, DT_S, enabled=progress)
    t0 = time.perf_counter()
    late_us: list[float] = []

    def send(batch):
        for name, msg in batch:
            if realtime:
                msg.timestamp = time.time()
            buses[name].send(msg, timeout=SEND_TIMEOUT_S)

    ahead: deque = deque()            # real time: steps computed, waiting for their due time

    def compute() -> None:
        r = sim.step()
        ahead.append((t0 + r.t_ns * 1e-9, fw.frames(r), r))

    while sim.k < sim.n_steps or ahead:
        if not realtime:
            compute()
        else:
            # the simulated robot runs ahead of the wire (its controller is inside the
            # simulation): a slow step delays nothing as long as the lookahead lasts; a step is
            # computed only while the next send is at least COMPUTE_MARGIN_S away
            if compute_lead_s is not None and not ahead and sim.k < sim.n_steps:
                lead = t0 + sim.k * DT_S - compute_lead_s - time.perf_counter()
                if lead > 0:
                    time.sleep(lead)
            while (sim.k < sim.n_steps and len(ahead) < lookahead_steps
                   and (not ahead or ahead[0][0] - time.perf_counter() > COMPUTE_MARGIN_S)):
                compute()
        due, batch, r = ahead.popleft()
        if realtime:
            delay = due - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            send(batch)
            late_us.append((time.perf_counter() - due) * 1e6)      # when its last frame left
        else:
            send(batch)
        if on_step is not None:
            on_step(r)
        bar.update(r.t_ns // 1_000_000 + 1)
    send(fw.flush())
    bar.close()
    if realtime:

        fw.pacing = Pacing.of(late_us, DT_S * 1e6)
    return sim.trace


@dataclass(frozen=True)
class Pacing:
    """How late a real-time run's steps went out: from each step's due time to the moment its
    last frame was sent, us. ``late_steps``: steps later than half a period (their frames fall in
    the next step's slot of a receiver that stamps on arrival)."""

    steps: int
    p50_us: float
    p99_us: float
    max_us: float
    late_steps: int
    period_us: float

    @classmethod
    def of(cls, late_us: list[float], period_us: float) -> "Pacing":
        if not late_us:
            return cls(0, 0.0, 0.0, 0.0, 0, period_us)
        x = sorted(late_us)
        pick = lambda q: round(x[min(len(x) - 1, int(q * len(x)))], 1)  # noqa: E731
        return cls(len(x), pick(0.5), pick(0.99), round(x[-1], 1),
                   sum(v > period_us / 2 for v in x), period_us)

    def as_dict(self) -> dict:
        return asdict(self)
