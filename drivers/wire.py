"""The CAN wire contract, read from the shipped DBC files (the single source of truth).

Two bus kinds, one DBC each (``drivers/dbc/``; the network attribute ``BscBus`` names the kind):

- ``bsc_arm.dbc``: one bus PER ARM (its F/T sensor, its joint drives, its torque commands).
  Every arm bus carries the same ids, so the file serves any number of arms. Joint ``j`` of an
  arm (0 = proximal, as in the robot description) owns the slot-``j`` messages:
  ``JOINT_STATE_J<j>`` at ``0x300 + j`` and slot ``j % 3`` of ``JOINT_TORQUE_CMD_G<j // 3>`` at
  ``0x100 + j // 3``. The DBC has slots for :data:`MAX_JOINTS` joints per arm.
- ``bsc_spacecraft.dbc``: the spacecraft bus (IMU, thruster commands).

Every message has a sender node and ``GenMsgCycleTime``. All multi-byte fields are big-endian
(Motorola), byte aligned, two's complement when signed: one precompiled :class:`struct.Struct`
per message is built from the DBC here and used by the live decoders and encoders.

Saturation rule: a signed scaled field at the end of its range (raw ``<= -(2**(n-1) - 1)`` or
``>= 2**(n-1) - 1``) means the value was clamped; encoders clamp, never wrap.

:class:`WireMap` lays a robot description over the buses: which bus carries which device, with
which ids. Bus load arithmetic (classic and FD, worst-case bit stuffing) lives here too.
"""
from __future__ import annotations

import functools
import math
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Protocol, Sequence

import cantools

from drivers.errors import DriverError

DBC_DIR = Path(__file__).parent / "dbc"
DBC_FILES = {"arm": DBC_DIR / "bsc_arm.dbc", "spacecraft": DBC_DIR / "bsc_spacecraft.dbc"}
SPACECRAFT_BUS = "spacecraft"

MAX_JOINTS = 8
CMD_GROUP = 3                      # joints per JOINT_TORQUE_CMD frame
BITRATE = 1_000_000
FD_DATA_BITRATE = 5_000_000
LOAD_LIMIT = 0.60

# Ids (also in the DBC; checked against it at import).
FT_A_ID = 0x200
FT_B_ID = 0x201
JOINT_STATE_BASE = 0x300
TORQUE_CMD_BASE = 0x100
HEARTBEAT_BASE = 0x700
THRUSTER_FORCE_ID = 0x180
THRUSTER_MOMENT_ID = 0x181
THRUSTER_VALVES_ID = 0x182
VALVE_CMD_ID = 0x183
THRUSTER_ALLOWED_ID = 0x184
IMU_TIME_ID = 0x405
IMU_STATUS_ID = 0x411
IMU_QUAT_WX_ID = 0x421
IMU_QUAT_YZ_ID = 0x422
IMU_RATE_ID = 0x432
IMU_ACCEL_ID = 0x434

# Status bits (DBC signal comments). *_FAULT: a device fault; *_SAT: the device reports clipping.
FT_SAT = 0x01
FT_FAULT = 0x0E
DRIVE_SAT = 0x08
DRIVE_FAULT = 0x17
IMU_SAT = 0x3F00
IMU_FAULT = 0x0003
HEARTBEAT_FAULT_STATE = 0x80


UDP_BASE_PORT = 43113              # python-can udp_multicast's default port, first bus


def udp_port(bus_index: int) -> int:
    """The UDP port of bus ``bus_index`` (WireMap order) over python-can ``udp_multicast``.

    The interface binds its port on every address, and Linux hands a socket the datagrams of
    every group joined on the host for that port (``IP_MULTICAST_ALL``): buses sharing a port
    would hear each other whatever their groups. So each bus gets its own port, from python-can's
    default up. The simulator's firmware and the gateway use the same rule.
    """
    return UDP_BASE_PORT + bus_index


class WireError(DriverError, ValueError):
    """The wire contract cannot describe this robot, or a DBC disagrees with the code."""


@dataclass(frozen=True, slots=True)
class Layout:
    """One message as the code uses it: id, length, Struct, and per-signal scaling from the DBC.

    ``unpack`` gives raw integers in signal order (24-bit fields are read as a signed high byte
    and an unsigned low word and joined in :meth:`raw`). ``scales[i]`` is ``None`` for integer
    signals (counters, status words), else the DBC factor; ``sat_limit[i]`` the raw magnitude
    that means "clamped" (0 for integer signals).
    """

    name: str
    frame_id: int
    length: int
    sender: str
    cycle_ms: int
    struct: struct.Struct
    signals: tuple[str, ...]
    bits: tuple[int, ...]
    signed: tuple[bool, ...]
    scales: tuple[float | None, ...]
    sat_limit: tuple[int, ...]
    has_i24: bool

    def raw(self, data: bytes) -> tuple[int, ...]:
        """Raw signal integers of a frame of exactly :attr:`length` bytes."""
        v = self.struct.unpack(data)
        if not self.has_i24:
            return v
        out: list[int] = []
        i = 0
        for b in self.bits:
            if b == 24:
                out.append((v[i] << 16) | v[i + 1])
                i += 2
            else:
                out.append(v[i])
                i += 1
        return tuple(out)

    def scale(self, i: int) -> float:
        """The DBC factor of signal ``i``, which must be a scaled one (a :class:`WireError` if
        the DBC made it an integer signal: the code would read it as a count)."""
        s = self.scales[i]
        if s is None:
            raise WireError(f"{self.name}.{self.signals[i]}: an integer signal where a scaled one is expected")
        return s

    def pack_raw(self, raw: Iterable[int]) -> bytes:
        if not self.has_i24:
            return self.struct.pack(*raw)
        flat: list[int] = []
        for b, r in zip(self.bits, raw):
            if b == 24:
                flat += [r >> 16, r & 0xFFFF]
            else:
                flat.append(r)
        return self.struct.pack(*flat)


_FMT = {(8, False): "B", (8, True): "b", (16, False): "H", (16, True): "h", (32, False): "I", (32, True): "i",
        (24, True): "bH", (24, False): "BH"}


def _layout(msg: cantools.database.can.Message) -> Layout:
    fmt, pos = ">", 0
    sigs = sorted(msg.signals, key=lambda s: s.start)
    for s in sigs:
        if (s.byte_order != "big_endian" or s.start % 8 != 7 or (s.start // 8) != pos
                or (s.length, s.is_signed) not in _FMT):
            raise WireError(f"{msg.name}.{s.name}: not a byte-aligned big-endian 8/16/24/32-bit field at byte {pos}")
        if s.offset != 0:
            raise WireError(f"{msg.name}.{s.name}: offsets are not used by this contract")
        fmt += _FMT[(s.length, s.is_signed)]
        pos += s.length // 8
    if pos != msg.length:
        raise WireError(f"{msg.name}: signals cover {pos} bytes, DLC is {msg.length}")
    scales = tuple(None if (s.scale == 1 and not s.is_signed) else float(s.scale) for s in sigs)
    return Layout(
        name=msg.name, frame_id=msg.frame_id, length=msg.length, sender=msg.senders[0],
        cycle_ms=int(msg.cycle_time or 0), struct=struct.Struct(fmt), signals=tuple(s.name for s in sigs),
        bits=tuple(s.length for s in sigs), signed=tuple(s.is_signed for s in sigs), scales=scales,
        sat_limit=tuple((1 << (s.length - 1)) - 1 if s.is_signed else 0 for s in sigs),
        has_i24=any(s.length == 24 for s in sigs))


@functools.cache
def database(kind: str) -> cantools.database.can.Database:
    """The cantools database of a bus kind (``"arm"`` or ``"spacecraft"``)."""
    try:
        path = DBC_FILES[kind]
    except KeyError:
        raise WireError(f"unknown bus kind {kind!r} (known: {', '.join(DBC_FILES)})") from None
    db = cantools.database.load_file(str(path))
    if not isinstance(db, cantools.database.can.Database):
        raise WireError(f"{path.name}: not a CAN database")
    bus = db.dbc.attributes.get("BscBus") if db.dbc is not None else None
    if bus is None or bus.value != kind:
        raise WireError(f"{path.name}: BscBus attribute is not {kind!r}")
    return db


@functools.cache
def layouts(kind: str) -> dict[int, Layout]:
    """Frame id -> :class:`Layout` for every message of a bus kind."""
    return {m.frame_id: _layout(m) for m in database(kind).messages}


def layout(kind: str, name: str) -> Layout:
    for lay in layouts(kind).values():
        if lay.name == name:
            return lay
    raise WireError(f"no message {name!r} on the {kind} bus")


def _check_ids() -> None:
    arm, sc = layouts("arm"), layouts("spacecraft")
    expect = {FT_A_ID: "FT_SG_A", FT_B_ID: "FT_SG_B"}
    expect.update({JOINT_STATE_BASE + j: f"JOINT_STATE_J{j}" for j in range(MAX_JOINTS)})
    expect.update({TORQUE_CMD_BASE + g: f"JOINT_TORQUE_CMD_G{g}" for g in range(-(-MAX_JOINTS // CMD_GROUP))})
    for i, n in expect.items():
        if i not in arm or arm[i].name != n:
            raise WireError(f"bsc_arm.dbc: expected {n} at 0x{i:03X}")
    expect = {THRUSTER_FORCE_ID: "THRUSTER_CMD_FORCE", THRUSTER_MOMENT_ID: "THRUSTER_CMD_MOMENT",
              THRUSTER_VALVES_ID: "THRUSTER_CMD_VALVES", VALVE_CMD_ID: "THRUSTER_VALVE_CMD",
              THRUSTER_ALLOWED_ID: "THRUSTER_CMD_ALLOWED",
              IMU_TIME_ID: "IMU_SAMPLE_TIME", IMU_STATUS_ID: "IMU_STATUS",
              IMU_QUAT_WX_ID: "IMU_QUAT_WX", IMU_QUAT_YZ_ID: "IMU_QUAT_YZ", IMU_RATE_ID: "IMU_RATE_OF_TURN",
              IMU_ACCEL_ID: "IMU_ACCELERATION"}
    for i, n in expect.items():
        if i not in sc or sc[i].name != n:
            raise WireError(f"bsc_spacecraft.dbc: expected {n} at 0x{i:03X}")


_check_ids()


# --- bus load ----------------------------------------------------------------------------------

def frame_bits(dlc: int) -> int:
    """Worst-case bits of a classic CAN frame with an 11-bit id and ``dlc`` data bytes, with
    stuff bits and the 3-bit interframe space: ``8n + 47 + floor((34 + 8n - 1) / 4)``."""
    return 8 * dlc + 47 + (34 + 8 * dlc - 1) // 4


def fd_frame_time_s(nbytes: int, bitrate: int = BITRATE, data_bitrate: int = FD_DATA_BITRATE) -> float:
    """Worst-case duration of a CAN FD frame (11-bit id, bit-rate switch), seconds.

    A conservative estimate: arbitration phase SOF..BRS (17 bits, up to 4 stuff bits) and
    CRC delimiter..IFS (ACK 2, EOF 7, IFS 3) at ``bitrate``; ESI, DLC, data, stuff count (4 + 1
    fixed stuff), CRC-17 (CRC-21 above 16 bytes) with a fixed stuff bit per 4 bits, and dynamic
    stuffing of ESI+DLC+data (one per 4 bits) at ``data_bitrate``.
    """
    crc = 17 if nbytes <= 16 else 21
    nominal = 17 + 4 + 12
    data = 1 + 4 + 8 * nbytes + (5 + 8 * nbytes - 1) // 4 + 5 + crc + math.ceil(crc / 4) + 1
    return nominal / bitrate + data / data_bitrate


def frame_time_s(dlc: int, fd: bool = False) -> float:
    return fd_frame_time_s(dlc) if fd else frame_bits(dlc) / BITRATE


# --- the robot laid over the buses ---------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class BusSpec:
    """One physical bus: its name (``<arm>`` or ``spacecraft``), kind, and the messages in use.

    ``ids`` are the frame ids the robot actually uses on this bus (a 2-joint arm uses
    ``JOINT_STATE_J0``/``J1`` only); a frame with any other id is counted as ``unknown_id``.
    """

    name: str
    kind: str
    arm: str | None = None
    joints: tuple[str, ...] = ()          # joint names (without the arm prefix), proximal first
    ids: frozenset[int] = frozenset()

    @property
    def arm_name(self) -> str:
        """The arm an arm bus serves (:attr:`arm`); a :class:`WireError` for a bus that serves none."""
        if self.arm is None:
            raise WireError(f"bus {self.name} ({self.kind}) serves no arm")
        return self.arm

    @property
    def layouts(self) -> dict[int, Layout]:
        return {i: lay for i, lay in layouts(self.kind).items() if i in self.ids}

    def nominal_rate_hz(self, frame_id: int) -> float:
        lay = layouts(self.kind)[frame_id]
        return 1000.0 / lay.cycle_ms if lay.cycle_ms else 0.0


def arm_ids(n_joints: int) -> frozenset[int]:
    """The ids an arm bus uses for an arm of ``n_joints`` joints."""
    if not 1 <= n_joints <= MAX_JOINTS:
        raise WireError(f"an arm needs 1..{MAX_JOINTS} joints for this wire contract, not {n_joints}")
    nodes = [1, 2] + [0x10 + j for j in range(n_joints)]
    return frozenset([FT_A_ID, FT_B_ID]
                     + [JOINT_STATE_BASE + j for j in range(n_joints)]
                     + [TORQUE_CMD_BASE + g for g in range(-(-n_joints // CMD_GROUP))]
                     + [HEARTBEAT_BASE + n for n in nodes])


SPACECRAFT_IDS = frozenset(layouts("spacecraft"))


class ArmLike(Protocol):
    """What :meth:`WireMap.from_robot` reads of an arm (:class:`robot_description.Arm`)."""

    @property
    def name(self) -> str: ...

    @property
    def joint_names(self) -> Sequence[str]: ...


class RobotLike(Protocol):
    """What :meth:`WireMap.from_robot` reads of a robot (:class:`robot_description.Robot`)."""

    @property
    def name(self) -> str: ...

    @property
    def arms(self) -> Sequence[ArmLike]: ...


@dataclass(frozen=True, slots=True)
class WireMap:
    """Which bus carries which device, for one robot. ``buses`` is ordered: arms, then spacecraft.

    Devices are named as in the samples: ``<arm>`` (F/T), ``<arm>/<joint>`` (drive, torque
    command), ``imu``, ``thrusters``.
    """

    robot: str
    buses: dict[str, BusSpec]

    @classmethod
    def from_robot(cls, robot: RobotLike) -> "WireMap":
        """From a :class:`robot_description.Robot` (or anything with ``name`` and ``arms`` whose
        items have ``name`` and ``joint_names``)."""
        buses: dict[str, BusSpec] = {}
        for arm in robot.arms:
            if arm.name == SPACECRAFT_BUS:
                raise WireError(f"an arm may not be named {SPACECRAFT_BUS!r}")
            buses[arm.name] = BusSpec(name=arm.name, kind="arm", arm=arm.name, joints=tuple(arm.joint_names),
                                      ids=arm_ids(len(arm.joint_names)))
        buses[SPACECRAFT_BUS] = BusSpec(name=SPACECRAFT_BUS, kind="spacecraft", ids=SPACECRAFT_IDS)
        return cls(robot=robot.name, buses=buses)

    def bus_of(self, device: str) -> str:
        """The bus that carries ``device`` (``"imu"``, ``"thrusters"``, ``"<arm>"``, ``"<arm>/<joint>"``)."""
        if device in ("imu", "thrusters"):
            return SPACECRAFT_BUS
        arm = device.split("/", 1)[0]
        if arm not in self.buses or arm == SPACECRAFT_BUS:
            raise WireError(f"no device {device!r} on robot {self.robot}")
        return arm

    def joint_index(self, device: str) -> int:
        """Slot of ``<arm>/<joint>`` on its arm bus (0 = proximal)."""
        arm, _, joint = device.partition("/")
        try:
            return self.buses[arm].joints.index(joint)
        except (KeyError, ValueError):
            raise WireError(f"no joint {device!r} on robot {self.robot}") from None


def channel_name(prefix: str, bus: str) -> str:
    """The channel of bus ``bus`` when all buses share a prefix (``bsc`` -> ``bsc-arm0``)."""
    return f"{prefix}-{bus}"


@dataclass(frozen=True, slots=True)
class BudgetRow:
    bus: str
    message: str
    frame_id: int
    dlc: int
    rate_hz: float
    time_per_frame_us: float
    load: float


def budget(wire: WireMap, fd: bool = False, command_hz: float | None = None) -> dict[str, list[BudgetRow]]:
    """Worst-case load of every bus at the DBC's nominal rates (``command_hz`` overrides the
    joint torque command rate). Returns rows per bus; sum ``load`` for the bus load (fraction)."""
    out = {}
    for name, spec in wire.buses.items():
        rows = []
        for i in sorted(spec.ids):
            lay = layouts(spec.kind)[i]
            rate = spec.nominal_rate_hz(i)
            if command_hz is not None and lay.name.startswith("JOINT_TORQUE_CMD"):
                rate = command_hz
            t = frame_time_s(lay.length, fd)
            rows.append(BudgetRow(name, lay.name, i, lay.length, rate, t * 1e6, t * rate))
        out[name] = rows
    return out
