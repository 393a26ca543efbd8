"""The drivers' per-frame work as one compiled (numba) kernel, with exactly the behaviour of the
Python drivers of :mod:`drivers.devices` (``BusMonitor`` + every device driver of every bus, as
``BusDispatcher`` runs them): same counters, same rejections, same samples in the same order,
same health snapshots, same float bits. Live (a few frames per call) and offline replay (100 k
per call) share it: all state lives in arrays, every frame is processed by the same scalar code in
arrival order, so any split of a batch gives the same events and the same state.

Usage::

    core = DriverCore(WireMap.from_robot(robot), fd=False, timing=SourceTiming())
    cols = columns_from_messages([(bus_index, msg), ...])   # or fill a FRAME_DTYPE array directly
    events = core.feed(cols)          # SampleEvents (a view, valid until the next feed)
    samples = core.to_samples(events)  # the dataclasses the Python drivers would have emitted
    buses, devices = core.health(now_ns)

Input: :data:`FRAME_DTYPE`, one 80-byte record per frame (``bus`` = index into the WireMap's bus
order, ``wire_map.buses``)::

    offset  0         8           12       13         14       15          16              80
            | t_ns i8 | can_id u4 | bus u1 | flags u1 | dlc u1 | length u1 | data u1[64]   |

    t_ns    round(msg.timestamp * 1e9), the drivers' _t_ns
    flags   bit 0 extended id | 1 remote | 2 error frame | 3 FD | 4 bit-rate switch |
            5 error state indicator (4 and 5 are kept for recording, never read here)
    dlc     msg.dlc (a value outside 0..255 is stored as 255: it behaves as the drivers' any
            dlc > 8, i.e. 8 bytes of bus time and never the DBC length)
    length  len(msg.data) (0 for None); lengths above 255 are not CAN frames (FD: 64 at most)
    data    the payload (up to 64 bytes), zero padded

The kernel reads at most the first 8 data bytes: a payload is read only when its length equals
its DBC message's length (device frames: ``n == lay.length``; heartbeats: the same in
``BusMonitor.not_owned``), and every DBC length is at most 8 (checked at import). Longer FD
payloads are always rejected by length; their length still counts in the bus time
(``wire.fd_frame_time_s(length)``). A row holds the whole payload so that a frame read straight
from a socket can be recorded exactly.

Output: :data:`EVENT_DTYPE`, one 120-byte record per sample, in the order the drivers call their
sink (a torque command frame gives one row per named joint slot, slot order)::

    offset 0         8          16          24          32              112
           | t_ns i8 | frame i8 | valves i8 | status i8 | values f8[10] |
    offset 112         116       117          118           119   120
           | device i4 | kind u1 | counter u1 | saturated ? | pad |

    kind       device (index)             values                                       valves  status
    0 WRENCH   arm (arm_names)            force_n 3, torque_nm 3                       0       F/T u8
    1 JOINT    joint (joint_names)        angle_rad, rate_rad_s                        0       drive u8
    2 TORQUE   joint (joint_names)        torque_nm                                    0       0
    3 IMU      0                          quat_wxyz 4, rate_rad_s 3, accel_m_s2 3      0       IMU u32
    4 THRUSTER 0                          force_n 3, moment_nm 3                       mask    allowed
    5 VALVE    0                          -                                            mask    0

``t_ns`` is the sample's (a multi-frame sample's first frame, as the drivers' ``first_ns``);
``frame`` is the index, in this call's batch, of the frame that completed the sample; unused
values are 0.0. A thruster command's ``status`` is its keep-out mask (``THRUSTER_CMD_ALLOWED``),
-1 when its stream does not carry one. Every value is ``raw * scale`` in float64 with the DBC's per-signal scale, and
``saturated`` follows drivers/frames.py (a scaled field at +-(2**(n-1) - 1), or the device's
clipping bits).

State (:meth:`DriverCore.state`, :meth:`DriverCore.restore`): :data:`BUS_DTYPE` per bus (plus
one row counting frames of a bus index the map does not have) and :data:`DEV_DTYPE` per
:class:`~drivers.health.DeviceCounters` (the same rows, in ``Pipeline.health`` order), holding
the counters, the resync state and the multi-frame assemblers (a bit mask of the parts present
and each part's 8 bytes as one little-endian word: byte k = ``(word >> 8k) & 0xFF``).

Constants go to the kernel as two arrays built once (``ci`` int64, ``cf`` float64), not as
globals from other modules: numba's cache would keep a stale copy of a value changed in
drivers/wire.py or drivers/health.py, since it only watches this file.
"""
from __future__ import annotations

import struct
import sys
from typing import Any, Callable, Iterable, NamedTuple

import can
import numpy as np
import numpy.typing as npt
from numba import njit

from drivers import frames, health, wire
from drivers.health import DEFAULT_TIMING, SourceTiming
from drivers.samples import (BusHealth, DeviceHealth, Health, ImuSample, JointSample, Sample, ThrusterCommand,
                             TorqueCommand, ValveCommand, WrenchSample)

# IEEE semantics, no reassociation: the same scalar operations as the Python drivers, same bits
_jit = njit(cache=True, fastmath=False, error_model="numpy", nogil=True)

# Kernel signatures: ``Ints``/``Floats`` are the constant tables; a structured array (frames,
# events, bus and device state) is a plain ``np.ndarray`` and one of its rows a ``Record``: a
# numba record view whose fields numpy's types cannot name (the dtypes above list them).
Ints = npt.NDArray[np.int64]
Floats = npt.NDArray[np.float64]
Record = Any
Flag = bool | np.bool_          # a boolean, Python's or numpy's: numba compiles both to one

# --- record layouts --------------------------------------------------------------------------

FRAME_DTYPE = np.dtype({"names": ["t_ns", "can_id", "bus", "flags", "dlc", "length", "data"],
                        "formats": ["<i8", "<u4", "u1", "u1", "u1", "u1", ("u1", (64,))],
                        "offsets": [0, 8, 12, 13, 14, 15, 16], "itemsize": 80})
"""One input frame (see the module docstring)."""

FLAG_EXTENDED, FLAG_REMOTE, FLAG_ERROR, FLAG_FD, FLAG_BRS, FLAG_ESI = 1, 2, 4, 8, 16, 32

EVENT_DTYPE = np.dtype({"names": ["t_ns", "frame", "valves", "status", "values", "device", "kind", "counter",
                                  "saturated"],
                        "formats": ["<i8", "<i8", "<i8", "<i8", ("<f8", (10,)), "<i4", "u1", "u1", "?"],
                        "offsets": [0, 8, 16, 24, 32, 112, 116, 117, 118], "itemsize": 120})
"""One sample event (see the module docstring). A batch of them is a :data:`SampleEvents`."""

SampleEvents = np.ndarray
"""A 1-D array of :data:`EVENT_DTYPE` records."""

WRENCH, JOINT, TORQUE, IMU, THRUSTER, VALVE = range(6)
KINDS = ("wrench", "joint", "torque", "imu", "thruster", "valve")

REASONS = ("error_frame", "extended_id", "unknown_id", "dlc", "remote_frame", "fd_on_classic",
           "duplicate", "late", "incomplete")
"""The kernel's order of the rejection counters (``rejected[k]``); health reports them by name."""
_R_ERROR, _R_EXT, _R_UNKNOWN, _R_DLC, _R_REMOTE, _R_FD, _R_DUP, _R_LATE, _R_INCOMPLETE = range(9)

MAX_NODES = 16          # heartbeat node slots per bus (an arm bus has 2 + MAX_JOINTS)
MAX_PARTS = 6           # frames per multi-frame sample (the IMU)

BUS_DTYPE = np.dtype([("frames", "<i8"), ("busy_s", "<f8"), ("busy_at_snap", "<f8"), ("snap_ns", "<i8"),
                      ("snapped", "<i8"), ("rejected", "<i8", (9,)), ("nodes", "<i8", (MAX_NODES,))])
"""Per bus, :class:`~drivers.health.BusCounters`: ``busy_s`` (worst-case bus time, s), the load
window (``busy_at_snap``, ``snap_ns`` valid when ``snapped``), ``rejected`` by :data:`REASONS`,
``nodes`` the last heartbeat state per node slot (-1: none yet)."""

DEV_DTYPE = np.dtype([("period_ns", "<i8"), ("samples", "<i8"), ("lost", "<i8"), ("lost_at_least", "<i8"),
                      ("saturated", "<i8"), ("last_t_ns", "<i8"), ("last_counter", "<i8"),
                      ("last_device_ns", "<i8"), ("status", "<i8"), ("rejected", "<i8", (9,)),
                      ("asm_counter", "<i8"), ("asm_mask", "<i8"), ("asm_first_ns", "<i8"),
                      ("parts", "<i8", (MAX_PARTS,)), ("asm_done", "<i8"), ("opt_seen", "<i8")])
"""Per :class:`~drivers.health.DeviceCounters`: its counters (``last_counter`` and
``last_device_ns`` -1 for None; ``period_ns`` is configuration) and its assembler (``asm_done``:
the counter of its last completed sample, -1 none; ``opt_seen``: the stream has carried the
sample's optional part, the thruster command's keep-out mask, so it completes only with it)."""

# --- constants handed to the kernel -----------------------------------------------------------
# ci (int64): header, per-value saturation limits, then the route codes of every bus (2048 ids each)
_CI_NBUS, _CI_FD, _CI_RATE_KNOWN, _CI_RESYNC, _CI_WRAP, _CI_FT_SAT, _CI_DRIVE_SAT, _CI_IMU_SAT = range(8)
_CI_LIM = 16
_NVAL = 25              # scaled values with their own scale and limit (below)
_CI_ROUTES = _CI_LIM + _NVAL
_IDS = 2048             # 11-bit ids; anything above is unknown on every bus
# cf (float64): classic frame times by dlc 0..8, FD frame times by length 0..255, scales, rate
_CF_FD = 9
_CF_SCALE = _CF_FD + 256
_CF_RATE = _CF_SCALE + _NVAL
_CF_SIZE = _CF_RATE + 1
# value slots (index into the scale and limit tables)
_V_FT, _V_JOINT, _V_TORQUE, _V_IMU, _V_THR = 0, 6, 8, 9, 19

# route code (int64), one per (bus, id):
#   bits 0-3 type | 4-7 part | 8-15 DBC length | 16-31 device row or node slot |
#   32-47 arm index (F/T) or joint index (joint state) | torque: 32-41, 42-51, 52-61 = joint + 1 per slot
_T_NONE, _T_HB, _T_FT, _T_JOINT, _T_TORQUE, _T_IMU, _T_THR, _T_VALVE = range(8)


def _check_layouts() -> None:
    """The kernel's byte decoders assume these DBC formats (as drivers/frames.py's docstring draws
    them): refuse to run on a DBC that changed under it."""
    expect = {"arm": {wire.FT_A_ID: ">BBhhh", wire.FT_B_ID: ">Bhhh"},
              "spacecraft": {wire.THRUSTER_FORCE_ID: ">Bhhh", wire.THRUSTER_MOMENT_ID: ">Bhhh",
                             wire.THRUSTER_VALVES_ID: ">BI", wire.VALVE_CMD_ID: ">BI", wire.IMU_TIME_ID: ">BI",
                             wire.IMU_STATUS_ID: ">BI", wire.IMU_QUAT_WX_ID: ">BbHbH", wire.IMU_QUAT_YZ_ID: ">BbHbH",
                             wire.IMU_RATE_ID: ">Bhhh", wire.IMU_ACCEL_ID: ">Bhhh"}}
    for j in range(wire.MAX_JOINTS):
        expect["arm"][wire.JOINT_STATE_BASE + j] = ">BBih"
    for g in range(-(-wire.MAX_JOINTS // wire.CMD_GROUP)):
        expect["arm"][wire.TORQUE_CMD_BASE + g] = ">Bhhh"
    for kind, ids in expect.items():
        lays = wire.layouts(kind)
        for i, fmt in ids.items():
            if lays[i].struct.format != fmt:
                raise wire.WireError(f"drivers.kernel: {lays[i].name} is {lays[i].struct.format}, "
                                     f"the kernel decodes {fmt}")
        for i, lay in lays.items():
            if lay.length > 8:
                raise wire.WireError(f"drivers.kernel: {lay.name} has {lay.length} bytes; the kernel keeps 8")
            if wire.HEARTBEAT_BASE <= i < wire.HEARTBEAT_BASE + 0x80 and lay.struct.format != ">BB":
                raise wire.WireError(f"drivers.kernel: {lay.name} is {lay.struct.format}, expected >BB")
    if set(REASONS) != set(health.REASONS):
        raise wire.WireError(f"drivers.kernel: rejection reasons {health.REASONS} changed")


_check_layouts()
if sys.byteorder != "little":       # pragma: no cover - the records are little-endian, read natively
    raise ImportError("drivers.kernel needs a little-endian host")


def _value_tables() -> tuple[list[float], list[int]]:
    """Scale and saturation limit of every scaled value, from the very layouts drivers/frames.py
    decodes with (joint states with slot 0's, torque commands with G0's slot 0 for all slots)."""
    f = frames
    pairs = ([(f.FT_A, k) for k in (2, 3, 4)] + [(f.FT_B, k) for k in (1, 2, 3)]
             + [(f.JOINT_STATE, 2), (f.JOINT_STATE, 3), (f.TORQUE_CMD, 1)]
             + [(f.IMU_QA, 1), (f.IMU_QA, 2), (f.IMU_QB, 1), (f.IMU_QB, 2)]
             + [(f.IMU_W, k) for k in (1, 2, 3)] + [(f.IMU_A, k) for k in (1, 2, 3)]
             + [(f.THR_F, k) for k in (1, 2, 3)] + [(f.THR_M, k) for k in (1, 2, 3)])
    assert len(pairs) == _NVAL
    return [lay.scale(k) for lay, k in pairs], [int(lay.sat_limit[k]) for lay, k in pairs]


# --- the kernel --------------------------------------------------------------------------------

@_jit
def _s16(w: np.int64, k: int) -> np.int64:
    """Signed big-endian 16 bits at byte k of a payload word."""
    v = (((w >> (8 * k)) & 0xFF) << 8) | ((w >> (8 * k + 8)) & 0xFF)
    return v - 0x10000 if v >= 0x8000 else v


@_jit
def _s24(w: np.int64, k: int) -> np.int64:
    v = (((w >> (8 * k)) & 0xFF) << 16) | (((w >> (8 * k + 8)) & 0xFF) << 8) | ((w >> (8 * k + 16)) & 0xFF)
    return v - 0x1000000 if v >= 0x800000 else v


@_jit
def _u32(w: np.int64, k: int) -> np.int64:
    return ((((w >> (8 * k)) & 0xFF) << 24) | (((w >> (8 * k + 8)) & 0xFF) << 16)
            | (((w >> (8 * k + 16)) & 0xFF) << 8) | ((w >> (8 * k + 24)) & 0xFF))


@_jit
def _s32(w: np.int64, k: int) -> np.int64:
    v = _u32(w, k)
    return v - 0x100000000 if v >= 0x80000000 else v


@_jit
def _at_limit(raw: np.int64, ci: Ints, slot: int) -> np.bool_:
    lim: np.int64 = ci[_CI_LIM + slot]
    return raw >= lim or raw <= -lim


@_jit
def _sequence(ds: Record, counter: np.int64, t_ns: np.int64, device_ns: np.int64 | int, ci: Ints,
              cf: Floats) -> bool:
    """DeviceCounters.sequence, line for line (device_ns -1 = None)."""
    last = ds.last_counter
    if last >= 0:
        d = (counter - last) & 0xFF
        if ds.samples != 0:
            gap = t_ns - ds.last_t_ns
            known = ci[_CI_RATE_KNOWN] != 0
            rate = cf[_CF_RATE]
            resync = ci[_CI_RESYNC]
            limit = resync * ds.period_ns
            # Python compares float and int exactly; limit is far below 2**53, so converting it is exact
            over = (gap * rate > limit) if known else (gap > limit)
            if over:
                have = False
                steps = 0.0
                if device_ns >= 0 and ds.last_device_ns >= 0:
                    wrap = ci[_CI_WRAP]
                    away = (device_ns - ds.last_device_ns) % wrap
                    if away >= wrap // 2:
                        ds.rejected[_R_LATE] += 1
                        return False
                    steps = away / ds.period_ns        # both exact in float64: Python's int/int
                    have = True
                elif known:
                    steps = gap * rate / ds.period_ns
                    have = True
                if not have or steps > resync:
                    if not have:
                        n = d if d != 0 else 256
                        ds.lost_at_least = 1
                    else:
                        x = np.rint((steps - d) / 256.0)   # Python's round(): half to even
                        # beyond 2**52 multiples of 256 (a rate so large that a silence spans
                        # more periods than int64 counts) Python's exact ints cannot be followed
                        if x > 4503599627370496.0:
                            x = 4503599627370496.0
                        k = np.int64(x) if x > 0 else 0
                        n = d + 256 * k
                        if n == 0:                 # a kept sample is a new one: 256 periods on
                            n = 256
                    ds.lost += n - 1
                    ds.last_counter = counter
                    if device_ns >= 0:
                        ds.last_device_ns = device_ns
                    return True
        if d == 0:
            ds.rejected[_R_DUP] += 1
            return False
        if d >= 128:
            ds.rejected[_R_LATE] += 1
            return False
        ds.lost += d - 1
    ds.last_counter = counter
    if device_ns >= 0:
        ds.last_device_ns = device_ns
    return True


@_jit
def _accept(ds: Record, t_ns: np.int64, saturated: Flag, status: np.int64 | int) -> None:
    ds.samples += 1
    ds.last_t_ns = t_ns
    ds.status = status
    if saturated:
        ds.saturated += 1


@_jit
def _assemble(ds: Record, part: int, n_parts: int, counter: np.int64, word: np.int64, t_ns: np.int64,
              optional: int) -> bool:
    """_Assembler.add: True when this part completes the sample (its parts are in ds.parts).
    ``optional``: the index of an optional last part (-1 none); see drivers.devices._Assembler."""
    if part == optional and ds.opt_seen == 0:
        ds.opt_seen = 1
        if ds.asm_mask == 0 and counter == ds.asm_done:
            return False                # its sample completed without it; from now on it is required
    if ds.opt_seen == 0 and optional >= 0:
        n_parts = optional
    if ds.asm_mask != 0 and counter != ds.asm_counter:
        ds.rejected[_R_INCOMPLETE] += 1
        ds.asm_mask = 0
    elif ds.asm_mask & (1 << part):
        ds.rejected[_R_DUP] += 1
        return False
    if ds.asm_mask == 0:
        ds.asm_first_ns = t_ns
    ds.asm_counter = counter
    ds.parts[part] = word
    ds.asm_mask |= 1 << part
    if ds.asm_mask == (1 << n_parts) - 1:
        ds.asm_mask = 0
        ds.asm_done = counter
        return True
    return False


@_jit
def _event(ev: Record, kind: int, device: np.int64 | int, t_ns: np.int64, counter: np.int64, saturated: Flag,
           status: np.int64 | int, valves: np.int64 | int, frame: int) -> None:
    ev.kind = kind
    ev.device = device
    ev.t_ns = t_ns
    ev.counter = counter
    ev.saturated = saturated
    ev.status = status
    ev.valves = valves
    ev.frame = frame
    for j in range(10):
        ev.values[j] = 0.0


@_jit
def _feed(fr: np.ndarray, start: int, ci: Ints, cf: Floats, bus: np.ndarray, dev: np.ndarray, out: np.ndarray,
          k: int) -> tuple[int, int]:
    """Frames ``fr[start:]`` -> events ``out[k:]``. Stops early, at a frame boundary, when fewer
    than 3 event rows (a torque command's worst case) are free. Returns (next frame, next event)."""
    n_bus = ci[_CI_NBUS]
    fd_ok = ci[_CI_FD] != 0
    cap = out.shape[0]
    for i in range(start, fr.shape[0]):
        if k + 3 > cap:
            return i, k
        f = fr[i]
        b = np.int64(f.bus)
        if b >= n_bus:
            bus[n_bus].frames += 1            # a bus this map does not have (Pipeline.unknown_bus)
            continue
        bs = bus[b]
        bs.frames += 1
        flags = np.int64(f.flags)
        dlc = np.int64(f.dlc)
        length = np.int64(f.length)
        # BusMonitor: worst-case bus time, the same float additions in the same order
        if flags & FLAG_FD:
            bs.busy_s += cf[_CF_FD + length]
        else:
            bs.busy_s += cf[min(dlc, 8)]  # type: ignore[call-overload]  # numpy's stubs: min(int64, int) has no type
        if flags & FLAG_ERROR:
            bs.rejected[_R_ERROR] += 1
            continue
        if flags & FLAG_EXTENDED:
            bs.rejected[_R_EXT] += 1
            continue
        cid = np.int64(f.can_id)
        code = ci[_CI_ROUTES + b * _IDS + cid] if cid < _IDS else 0
        typ = code & 0xF
        if typ == _T_NONE:
            bs.rejected[_R_UNKNOWN] += 1
            continue
        want = (code >> 8) & 0xFF
        is_fd = (flags & FLAG_FD) != 0
        if typ == _T_HB:                        # BusMonitor.not_owned
            if flags & FLAG_REMOTE:
                bs.rejected[_R_REMOTE] += 1
            elif is_fd and not fd_ok:
                bs.rejected[_R_FD] += 1
            elif length != want or dlc != want:
                bs.rejected[_R_DLC] += 1
            else:
                bs.nodes[(code >> 16) & 0xFFFF] = np.int64(f.data[1])
            continue
        ds = dev[(code >> 16) & 0xFFFF]         # Driver.on_message_received
        if flags & FLAG_REMOTE:
            ds.rejected[_R_REMOTE] += 1
            continue
        if is_fd and not fd_ok:
            ds.rejected[_R_FD] += 1
            continue
        if length != want or dlc != want:
            ds.rejected[_R_DLC] += 1
            continue
        w = np.int64(0)
        for j in range(8):
            w |= np.int64(f.data[j]) << (8 * j)
        t = f.t_ns
        ctr = w & 0xFF
        if typ == _T_JOINT:
            status = (w >> 8) & 0xFF
            ra, rr = _s32(w, 2), _s16(w, 6)
            sat = _at_limit(ra, ci, _V_JOINT) or _at_limit(rr, ci, _V_JOINT + 1) or (status & ci[_CI_DRIVE_SAT]) != 0
            if _sequence(ds, ctr, t, -1, ci, cf):
                _accept(ds, t, sat, status)
                ev = out[k]
                _event(ev, JOINT, (code >> 32) & 0xFFFF, t, ctr, sat, status, 0, i)
                ev.values[0] = ra * cf[_CF_SCALE + _V_JOINT]
                ev.values[1] = rr * cf[_CF_SCALE + _V_JOINT + 1]
                k += 1
        elif typ == _T_TORQUE:
            if _sequence(ds, ctr, t, -1, ci, cf):
                any_sat: Flag = False
                for s in range(3):
                    if (code >> (32 + 10 * s)) & 0x3FF:
                        any_sat = any_sat or _at_limit(_s16(w, 1 + 2 * s), ci, _V_TORQUE)
                _accept(ds, t, any_sat, 0)
                for s in range(3):
                    jp = (code >> (32 + 10 * s)) & 0x3FF
                    if jp:
                        r = _s16(w, 1 + 2 * s)
                        ev = out[k]
                        _event(ev, TORQUE, jp - 1, t, ctr, _at_limit(r, ci, _V_TORQUE), 0, 0, i)
                        ev.values[0] = r * cf[_CF_SCALE + _V_TORQUE]
                        k += 1
        elif typ == _T_VALVE:
            if _sequence(ds, ctr, t, -1, ci, cf):
                _accept(ds, t, False, 0)
                _event(out[k], VALVE, 0, t, ctr, False, 0, _u32(w, 1), i)
                k += 1
        else:                                   # a part of a multi-frame sample
            part = (code >> 4) & 0xF
            n_parts = 2 if typ == _T_FT else (6 if typ == _T_IMU else 4)
            if not _assemble(ds, part, n_parts, ctr, w, t, 3 if typ == _T_THR else -1):
                continue
            p = ds.parts
            t0 = ds.asm_first_ns
            if typ == _T_FT:
                a, c = p[0], p[1]
                status = (a >> 8) & 0xFF
                sat = (status & ci[_CI_FT_SAT]) != 0
                for j in range(3):
                    sat = (sat or _at_limit(_s16(a, 2 + 2 * j), ci, _V_FT + j)
                           or _at_limit(_s16(c, 1 + 2 * j), ci, _V_FT + 3 + j))
                if _sequence(ds, ctr, t0, -1, ci, cf):
                    _accept(ds, t0, sat, status)
                    ev = out[k]
                    _event(ev, WRENCH, (code >> 32) & 0xFFFF, t0, ctr, sat, status, 0, i)
                    for j in range(3):
                        ev.values[j] = _s16(a, 2 + 2 * j) * cf[_CF_SCALE + _V_FT + j]
                        ev.values[3 + j] = _s16(c, 1 + 2 * j) * cf[_CF_SCALE + _V_FT + 3 + j]
                    k += 1
            elif typ == _T_IMU:
                # parts in frames.IMU_PARTS order: time, status, quat wx, quat yz, rate, accel
                status = _u32(p[1], 1)
                sat = (status & ci[_CI_IMU_SAT]) != 0
                q = (_s24(p[2], 1), _s24(p[2], 4), _s24(p[3], 1), _s24(p[3], 4))
                for j in range(4):
                    sat = sat or _at_limit(q[j], ci, _V_IMU + j)
                for j in range(3):
                    sat = (sat or _at_limit(_s16(p[4], 1 + 2 * j), ci, _V_IMU + 4 + j)
                           or _at_limit(_s16(p[5], 1 + 2 * j), ci, _V_IMU + 7 + j))
                device_ns = _u32(p[0], 1) * 1000      # the IMU's time_us: its own clock
                if _sequence(ds, ctr, t0, device_ns, ci, cf):
                    _accept(ds, t0, sat, status)
                    ev = out[k]
                    _event(ev, IMU, 0, t0, ctr, sat, status, 0, i)
                    for j in range(4):
                        ev.values[j] = q[j] * cf[_CF_SCALE + _V_IMU + j]
                    for j in range(3):
                        ev.values[4 + j] = _s16(p[4], 1 + 2 * j) * cf[_CF_SCALE + _V_IMU + 4 + j]
                        ev.values[7 + j] = _s16(p[5], 1 + 2 * j) * cf[_CF_SCALE + _V_IMU + 7 + j]
                    k += 1
            else:
                # parts in frames.THRUSTER_PARTS order: force, moment, valves, keep-out (optional)
                sat = False
                for j in range(3):
                    sat = sat or _at_limit(_s16(p[0], 1 + 2 * j), ci, _V_THR + j)
                for j in range(3):
                    sat = sat or _at_limit(_s16(p[1], 1 + 2 * j), ci, _V_THR + 3 + j)
                if _sequence(ds, ctr, t0, -1, ci, cf):
                    _accept(ds, t0, sat, 0)
                    ev = out[k]
                    _event(ev, THRUSTER, 0, t0, ctr, sat, _u32(p[3], 1) if ds.opt_seen else -1, _u32(p[2], 1), i)
                    for j in range(3):
                        ev.values[j] = _s16(p[0], 1 + 2 * j) * cf[_CF_SCALE + _V_THR + j]
                        ev.values[3 + j] = _s16(p[1], 1 + 2 * j) * cf[_CF_SCALE + _V_THR + 3 + j]
                    k += 1
    return fr.shape[0], k


# --- input ---------------------------------------------------------------------------------------

_FRAME = struct.Struct("<qIBBBB64s")
assert _FRAME.size == FRAME_DTYPE.itemsize


def columns_from_messages(pairs: Iterable[tuple[int, can.Message]]) -> np.ndarray:
    """``[(bus_index, msg), ...]`` -> a :data:`FRAME_DTYPE` array, in the same order.

    Raises ``ValueError`` for what no CAN bus delivers and the record cannot hold: a bus index
    outside 0..255, a payload longer than 255 bytes. An id outside 0..2**32-1 is stored as
    0xFFFFFFFF (unknown to every driver, as the original id is)."""
    pairs = pairs if isinstance(pairs, list) else list(pairs)
    buf = bytearray(_FRAME.size * len(pairs))
    pack = _FRAME.pack_into
    off = 0
    for b, m in pairs:
        data = m.data
        n = len(data) if data is not None else 0
        if n > 255:
            raise ValueError(f"a payload of {n} bytes is not a CAN frame (FD carries at most 64)")
        if not 0 <= b <= 255:
            raise ValueError(f"bus index {b} outside 0..255")
        flags = ((FLAG_EXTENDED if m.is_extended_id else 0) | (FLAG_REMOTE if m.is_remote_frame else 0)
                 | (FLAG_ERROR if m.is_error_frame else 0) | (FLAG_FD if m.is_fd else 0)
                 | (FLAG_BRS if m.bitrate_switch else 0) | (FLAG_ESI if m.error_state_indicator else 0))
        dlc = m.dlc
        cid = m.arbitration_id
        pack(buf, off, int(round(m.timestamp * 1e9)), cid if 0 <= cid <= 0xFFFFFFFF else 0xFFFFFFFF, b, flags,
             dlc if 0 <= dlc <= 255 else 255, n, bytes(data[:64]) if n else b"")
        off += _FRAME.size
    return np.frombuffer(buf, FRAME_DTYPE)


# --- the core ------------------------------------------------------------------------------------

class CoreState(NamedTuple):
    """A snapshot of everything a :class:`DriverCore` carries from one call to the next."""

    bus: np.ndarray      # BUS_DTYPE, one row per bus + the unknown-bus row
    dev: np.ndarray      # DEV_DTYPE, one row per device counter


class _Device(NamedTuple):
    name: str
    bus: str             # as the Python driver names it (the spacecraft drivers: wire.SPACECRAFT_BUS)
    bus_index: int       # the bus it is fed from
    fault_mask: int


class DriverCore:
    """The monitor and the device drivers of every bus of ``wire_map`` in one compiled kernel.

    ``fd``/``timing`` as for :func:`drivers.devices.listeners_for`. Tables, in WireMap order:
    ``bus_names``; ``arm_names`` (a WRENCH event's ``device``); ``joint_names`` (``<arm>/<joint>``,
    a JOINT or TORQUE event's ``device``); ``device_names`` (the DeviceCounters, in
    ``Pipeline.health`` order: per bus F/T, joints, torque command groups / IMU, thrusters, valves).
    """

    def __init__(self, wire_map: wire.WireMap, fd: bool = False, timing: SourceTiming = DEFAULT_TIMING):
        self.wire_map, self.fd, self.timing = wire_map, fd, timing
        specs = list(wire_map.buses.values())
        self.bus_names = tuple(s.name for s in specs)
        n_bus = len(specs)
        if n_bus > 255:
            raise wire.WireError(f"{n_bus} buses; the frame record's bus index holds 255")
        scales, limits = _value_tables()
        ci = np.zeros(_CI_ROUTES + n_bus * _IDS, np.int64)
        ci[[_CI_NBUS, _CI_FD, _CI_RATE_KNOWN, _CI_RESYNC, _CI_WRAP, _CI_FT_SAT, _CI_DRIVE_SAT, _CI_IMU_SAT]] = (
            n_bus, int(fd), timing.rate is not None, health.RESYNC_PERIODS, health.DEVICE_CLOCK_WRAP_NS,
            wire.FT_SAT, wire.DRIVE_SAT, wire.IMU_SAT)
        ci[_CI_LIM:_CI_LIM + _NVAL] = limits
        cf = np.zeros(_CF_SIZE, np.float64)
        cf[:9] = [wire.frame_time_s(n) for n in range(9)]          # BusMonitor._classic_time
        cf[_CF_FD:_CF_FD + 256] = [wire.fd_frame_time_s(n) for n in range(256)]
        cf[_CF_SCALE:_CF_SCALE + _NVAL] = scales
        cf[_CF_RATE] = timing.rate if timing.rate is not None else 0.0
        arm_names: list[str] = []
        joint_names: list[str] = []
        devices: list[_Device] = []
        periods: list[int] = []
        self._nodes: list[list[str]] = []         # per bus: the sender of each node slot

        def add(name: str, bus: str, kind: str, frame_id: int, fault_mask: int) -> int:
            devices.append(_Device(name, bus, b, fault_mask))
            periods.append(wire.layouts(kind)[frame_id].cycle_ms * 1_000_000)     # devices._period_ns
            return len(devices) - 1

        for b, spec in enumerate(specs):
            routes = ci[_CI_ROUTES + b * _IDS:_CI_ROUTES + (b + 1) * _IDS]
            lays = wire.layouts(spec.kind)
            senders: list[str] = []
            for i in sorted(spec.ids):                    # BusMonitor._heartbeats
                if wire.HEARTBEAT_BASE <= i < wire.HEARTBEAT_BASE + 0x80:
                    lay = lays[i]
                    if lay.sender not in senders:
                        senders.append(lay.sender)
                    routes[i] = _T_HB | lay.length << 8 | senders.index(lay.sender) << 16
            if len(senders) > MAX_NODES:
                raise wire.WireError(f"bus {spec.name}: {len(senders)} heartbeat nodes, the kernel keeps {MAX_NODES}")
            self._nodes.append(senders)

            def own(i: int, code: int) -> None:           # a driver's id: the monitor leaves it alone
                if not 0 <= i < _IDS:
                    raise wire.WireError(f"id 0x{i:X} is not an 11-bit id")
                routes[i] = code | lays[i].length << 8

            if spec.kind == "arm":                        # devices.drivers_for
                arm = spec.arm_name
                a = len(arm_names)
                arm_names.append(arm)
                d = add(arm, arm, "arm", wire.FT_A_ID, wire.FT_FAULT)
                for p, i in enumerate(frames.FT_PARTS):
                    own(i, _T_FT | p << 4 | d << 16 | a << 32)
                names = [f"{arm}/{j}" for j in spec.joints]
                if len(names) > wire.MAX_JOINTS:
                    raise wire.WireError(f"arm {arm}: {len(names)} joints, the contract has {wire.MAX_JOINTS} slots")
                first = len(joint_names)
                joint_names += names
                for k, name in enumerate(names):
                    i = wire.JOINT_STATE_BASE + k
                    d = add(name, arm, "arm", i, wire.DRIVE_FAULT)
                    own(i, _T_JOINT | d << 16 | (first + k) << 32)
                ngroups = -(-len(names) // wire.CMD_GROUP)
                for g in range(ngroups):
                    i = wire.TORQUE_CMD_BASE + g
                    d = add(f"{arm}/torque_cmd" + (f"/{g}" if ngroups > 1 else ""), arm, "arm", i, 0)
                    code = _T_TORQUE | d << 16
                    for s in range(wire.CMD_GROUP):
                        k = g * wire.CMD_GROUP + s
                        if k < len(names):
                            code |= (first + k + 1) << (32 + 10 * s)
                    own(i, code)
            else:
                bus = wire.SPACECRAFT_BUS                 # the spacecraft drivers' own bus name
                d = add("imu", bus, "spacecraft", frames.IMU_PARTS[0], wire.IMU_FAULT)
                for p, i in enumerate(frames.IMU_PARTS):
                    own(i, _T_IMU | p << 4 | d << 16)
                d = add("thrusters", bus, "spacecraft", frames.THRUSTER_PARTS[0], 0)
                for p, i in enumerate(frames.THRUSTER_PARTS):
                    own(i, _T_THR | p << 4 | d << 16)
                d = add("valves", bus, "spacecraft", wire.VALVE_CMD_ID, 0)
                own(wire.VALVE_CMD_ID, _T_VALVE | d << 16)
        if len(joint_names) >= 0x3FF or len(devices) > 0xFFFF or len(arm_names) > 0xFFFF:
            raise wire.WireError("too many joints or devices for the kernel's route codes")
        self._ci, self._cf = ci, cf
        self.arm_names, self.joint_names = tuple(arm_names), tuple(joint_names)
        self._devices = tuple(devices)
        self.device_names = tuple(d.name for d in devices)
        self._bus = np.zeros(n_bus + 1, BUS_DTYPE)
        self._bus["nodes"] = -1
        self._dev = np.zeros(len(devices), DEV_DTYPE)
        self._dev["period_ns"] = periods
        self._dev["last_counter"] = -1
        self._dev["asm_done"] = -1
        self._dev["last_device_ns"] = -1
        self._out = np.zeros(256, EVENT_DTYPE)
        self._make: dict[int, Callable[..., Sample]] = {
            WRENCH: frames.builder(WrenchSample), JOINT: frames.builder(JointSample),
            TORQUE: frames.builder(TorqueCommand), IMU: frames.builder(ImuSample),
            THRUSTER: frames.builder(ThrusterCommand), VALVE: frames.builder(ValveCommand)}
        self._dev_health = frames.builder(DeviceHealth)

    # -- frames in, events out
    def feed(self, columns: np.ndarray) -> SampleEvents:
        """Process a batch of :data:`FRAME_DTYPE` frames in order; the samples they complete.

        The result is a VIEW of a buffer this core reuses: valid until the next ``feed`` (copy
        it to keep it). The buffer grows to the largest batch's events (120 bytes each): replay
        in chunks of ~100 k frames. Never raises on bad frames: they are counted by reason.
        A read-only array works but costs one more compiled specialisation (and its first compile)."""
        if columns.dtype != FRAME_DTYPE:
            raise TypeError(f"frames must be FRAME_DTYPE records, not {columns.dtype}")
        if not columns.flags.c_contiguous:              # one compiled specialisation, not two
            columns = np.ascontiguousarray(columns)
        out = self._out
        n = columns.shape[0]
        if out.shape[0] < n + n // 4 + 3:              # usually enough: below 1 event per frame
            out = self._grow(n + n // 4 + 3, 0)
        i, k = _feed(columns, 0, self._ci, self._cf, self._bus, self._dev, out, 0)
        while i < n:                                    # torque commands filled it: grow, go on
            out = self._grow(2 * out.shape[0], k)
            i, k = _feed(columns, i, self._ci, self._cf, self._bus, self._dev, out, k)
        return out[:k]

    def _grow(self, size: int, keep: int) -> np.ndarray:
        out = np.zeros(size, EVENT_DTYPE)
        out[:keep] = self._out[:keep]
        self._out = out
        return out

    @property
    def unknown_bus(self) -> int:
        """Frames with a bus index this wire map does not have (not counted on any bus)."""
        return int(self._bus["frames"][-1])

    # -- state
    def state(self) -> CoreState:
        """A copy of all the state (counters, resync, assemblers, load window)."""
        return CoreState(self._bus.copy(), self._dev.copy())

    def restore(self, state: CoreState) -> None:
        if state.bus.shape != self._bus.shape or state.dev.shape != self._dev.shape:
            raise ValueError("a state of another wire map")
        self._bus[...] = state.bus
        self._dev[...] = state.dev

    # -- health
    def health(self, now_ns: int) -> tuple[list[BusHealth], list[DeviceHealth]]:
        """``BusMonitor.health`` of every bus and ``Driver.health`` of every device, the same
        objects as the Python drivers give (resets the measured-load window, as they do)."""
        return self._bus_health(now_ns), self._device_health(now_ns)

    def health_list(self, now_ns: int) -> list[Health]:
        """The same snapshots in ``gateway.pipeline.Pipeline.health`` order: each bus, then its devices."""
        buses, devs = self.health(now_ns)
        out: list[Health] = []
        for b, h in enumerate(buses):
            out.append(h)
            out += [x for x, d in zip(devs, self._devices) if d.bus_index == b]
        return out

    def _bus_health(self, now_ns: int) -> list[BusHealth]:
        out = []
        rec = self._bus
        frames_, busy, at_snap = rec["frames"].tolist(), rec["busy_s"].tolist(), rec["busy_at_snap"].tolist()
        snap_ns, snapped = rec["snap_ns"].tolist(), rec["snapped"].tolist()
        rejected, nodes = rec["rejected"].tolist(), rec["nodes"].tolist()
        for b, name in enumerate(self.bus_names):
            # BusCounters.snapshot with Python ints and floats: the same arithmetic
            prev = snap_ns[b] if snapped[b] else None
            load = 0.0
            if prev is not None and now_ns > prev:
                load = (busy[b] - at_snap[b]) / ((now_ns - prev) * 1e-9)
            rec["busy_at_snap"][b] = busy[b]
            rec["snap_ns"][b] = now_ns
            rec["snapped"][b] = 1
            node = {s: nodes[b][k] for k, s in enumerate(self._nodes[b]) if nodes[b][k] >= 0}
            out.append(BusHealth(bus=name, t_ns=now_ns, frames=frames_[b], rejected=_rejected(rejected[b]),
                                 load=load, nodes=tuple(sorted(node.items()))))
        return out

    def _device_health(self, now_ns: int) -> list[DeviceHealth]:
        rec = self._dev
        rate, stale_periods = self.timing.rate, self.timing.stale_periods
        cols = [rec[f].tolist() for f in ("samples", "lost", "saturated", "last_t_ns", "status", "period_ns",
                                          "lost_at_least")]
        rejected = rec["rejected"].tolist()
        make = self._dev_health
        out = []
        for k, (d, samples, lost, sat, last_t, status, period, at_least) in enumerate(zip(self._devices, *cols)):
            quiet = now_ns - last_t                     # DeviceCounters.snapshot
            if rate is not None:
                quiet *= rate
            stale = samples == 0 or quiet > stale_periods * period
            out.append(make(d.name, d.bus, now_ns, samples, lost, sat, _rejected(rejected[k]), last_t, stale,
                            status, status & d.fault_mask, bool(at_least)))
        return out

    # -- events -> samples
    def to_samples(self, events: SampleEvents) -> list[Sample]:
        """The dataclasses of :mod:`drivers.samples` the Python drivers emit for these events, in
        order. Built kind by kind (one ``map`` over columns each), then put back in event order."""
        n = events.shape[0]
        kinds = events["kind"]
        present = np.bincount(kinds, minlength=len(KINDS)).tolist()
        out: list[Any] = [None] * n               # a Sample in every slot at the end: kinds partition events
        mk = self._make
        for kind, count in enumerate(present):
            if not count:
                continue
            if count == n:
                e, where = events, None
            else:
                sel = np.flatnonzero(kinds == kind)
                e, where = events[sel], sel.tolist()
            t, ctr = e["t_ns"].tolist(), e["counter"].tolist()
            v = e["values"]
            if kind == JOINT:
                names = self.joint_names
                objs = map(mk[JOINT], [names[d] for d in e["device"].tolist()], t, ctr, v[:, 0].tolist(),
                           v[:, 1].tolist(), e["saturated"].tolist(), e["status"].tolist())
            elif kind == TORQUE:
                names = self.joint_names
                objs = map(mk[TORQUE], [names[d] for d in e["device"].tolist()], t, ctr, v[:, 0].tolist(),
                           e["saturated"].tolist())
            elif kind == WRENCH:
                names = self.arm_names
                objs = map(mk[WRENCH], [names[d] for d in e["device"].tolist()], t, ctr,
                           map(tuple, v[:, 0:3].tolist()), map(tuple, v[:, 3:6].tolist()),
                           e["saturated"].tolist(), e["status"].tolist())
            elif kind == VALVE:
                objs = map(mk[VALVE], t, ctr, e["valves"].tolist())
            elif kind == IMU:
                objs = map(mk[IMU], t, ctr, map(tuple, v[:, 0:4].tolist()), map(tuple, v[:, 4:7].tolist()),
                           map(tuple, v[:, 7:10].tolist()), e["saturated"].tolist(), e["status"].tolist())
            else:
                objs = map(mk[THRUSTER], t, ctr, map(tuple, v[:, 0:3].tolist()), map(tuple, v[:, 3:6].tolist()),
                           e["valves"].tolist(), e["saturated"].tolist(), e["status"].tolist())
            if where is None:
                return list(objs)
            for i, o in zip(where, objs):
                out[i] = o
        return out


def _rejected(counts: list[int]) -> tuple[tuple[str, int], ...]:
    """A Counter's ``tuple(sorted(items()))``: the reasons counted at least once, by name."""
    return tuple(sorted((REASONS[k], c) for k, c in enumerate(counts) if c))
