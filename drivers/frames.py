"""Pure functions between frame payloads and typed samples, both ways.

Decoders: bytes -> frozen dataclasses of :mod:`drivers.samples`, SI units, ``t_ns`` given by the
caller (the timestamp of the frame that completed the sample). Encoders: samples -> frames, for
the simulator's sensor firmware (``encode_*`` give ``can.Message``; ``*_payloads`` give
``(frame_id, bytes)`` pairs). Layouts come from the DBC through :mod:`drivers.wire`; every field
is big-endian. Out-of-range values are clamped to the end of the range (which the decoder reads
as saturated), never wrapped; NaN is refused (:class:`EncodeError`).

Byte maps (``ctr`` = sample counter mod 256, identical in every frame of one sample;
``i16``/``i24``/``i32`` signed, ``u8``/``u32`` unsigned)::

    arm bus (one per arm; same ids on every arm bus)
    id            name                 DLC  0     1       2   3   4   5   6   7
    0x100+g       JOINT_TORQUE_CMD_Gg  7    ctr   tau_3g  ..  tau_3g+1 tau_3g+2       0.05 N m
    0x200         FT_SG_A              8    ctr   status  Fx      Fy      Fz          0.05 N
    0x201         FT_SG_B              7    ctr   Tx      ..  Ty      ..  Tz  ..      0.05 N m
    0x300+j       JOINT_STATE_Jj       8    ctr   status  angle i32 (1e-6 rad)  rate (2.5e-4 rad/s)
    0x700+node    HEARTBEAT_<node>     2    ctr   state

    spacecraft bus
    0x180         THRUSTER_CMD_FORCE   7    ctr   Fx      ..  Fy      ..  Fz  ..      0.05 N
    0x181         THRUSTER_CMD_MOMENT  7    ctr   Mx      ..  My      ..  Mz  ..      0.05 N m
    0x182         THRUSTER_CMD_VALVES  5    ctr   valves u32
    0x183         THRUSTER_VALVE_CMD   5    ctr   valves u32                          1 kHz
    0x184         THRUSTER_CMD_ALLOWED 5    ctr   allowed u32   (optional 4th THRUSTER_CMD frame)
    0x405         IMU_SAMPLE_TIME      5    ctr   time_us u32
    0x411         IMU_STATUS           5    ctr   status u32
    0x421         IMU_QUAT_WX          7    ctr   w i24           x i24               2^-22
    0x422         IMU_QUAT_YZ          7    ctr   y i24           z i24               2^-22
    0x432         IMU_RATE_OF_TURN     7    ctr   wx      ..  wy      ..  wz  ..      2^-14 rad/s
    0x434         IMU_ACCELERATION     7    ctr   ax      ..  ay      ..  az  ..      2^-13 m/s^2
"""
from __future__ import annotations

import math
from typing import Any, Callable, Mapping, Sequence, TypeVar

import can

from drivers.errors import DriverError  # noqa: F401 - re-exported: drivers.frames.DriverError
from drivers import wire
from drivers.samples import ImuSample, JointSample, ThrusterCommand, TorqueCommand, ValveCommand, WrenchSample




class DecodeError(DriverError, ValueError):
    """A payload that cannot become a sample (wrong length, parts that disagree)."""


class EncodeError(DriverError, ValueError):
    """A sample that cannot be put on the wire (NaN, status out of range, too many joints)."""


_ARM = wire.layouts("arm")
_SC = wire.layouts("spacecraft")
FT_A = _ARM[wire.FT_A_ID]
FT_B = _ARM[wire.FT_B_ID]
JOINT_STATE = _ARM[wire.JOINT_STATE_BASE]          # every slot has this layout
TORQUE_CMD = _ARM[wire.TORQUE_CMD_BASE]
HEARTBEAT = _ARM[wire.HEARTBEAT_BASE + 1]
THR_F, THR_M, THR_V = _SC[wire.THRUSTER_FORCE_ID], _SC[wire.THRUSTER_MOMENT_ID], _SC[wire.THRUSTER_VALVES_ID]
VALVE_CMD = _SC[wire.VALVE_CMD_ID]
THR_A = _SC[wire.THRUSTER_ALLOWED_ID]
IMU_T, IMU_S = _SC[wire.IMU_TIME_ID], _SC[wire.IMU_STATUS_ID]
IMU_QA, IMU_QB, IMU_W, IMU_A = (_SC[wire.IMU_QUAT_WX_ID], _SC[wire.IMU_QUAT_YZ_ID], _SC[wire.IMU_RATE_ID],
                                _SC[wire.IMU_ACCEL_ID])
IMU_PARTS = (wire.IMU_TIME_ID, wire.IMU_STATUS_ID, wire.IMU_QUAT_WX_ID, wire.IMU_QUAT_YZ_ID, wire.IMU_RATE_ID,
             wire.IMU_ACCEL_ID)
THRUSTER_PARTS = (wire.THRUSTER_FORCE_ID, wire.THRUSTER_MOMENT_ID, wire.THRUSTER_VALVES_ID,
                  wire.THRUSTER_ALLOWED_ID)
"""The thruster command's frames; the last (the keep-out mask) is optional: a stream that has
never carried it completes on the first three (``THRUSTER_REQUIRED``), one that has, on all four."""
THRUSTER_REQUIRED = 3
FT_PARTS = (wire.FT_A_ID, wire.FT_B_ID)

Values = tuple[Any, ...]
"""A frame's physical values in DBC order: ``int`` for integer signals, ``float`` for scaled ones
(which is which is the layout's, from the DBC: a type checker cannot tell)."""
FieldsFn = Callable[[bytes], tuple[Values, bool]]
T = TypeVar("T")


def decode_fields(lay: wire.Layout, data: bytes) -> tuple[Values, bool]:
    """Physical values of every signal of one frame (DBC order) and whether any was clamped.

    Integer signals (counters, status words) stay ``int``; scaled ones are ``raw * factor``
    (float64), exactly what :mod:`drivers.batch` computes.
    """
    if len(data) != lay.length:
        raise DecodeError(f"{lay.name}: {len(data)} bytes, expected {lay.length}")
    raw = lay.raw(bytes(data))
    out: list[int | float] = []
    sat = False
    for r, s, lim in zip(raw, lay.scales, lay.sat_limit):
        if s is None:
            out.append(r)
        else:
            if r >= lim or r <= -lim:
                sat = True
            out.append(r * s)
    return tuple(out), sat


# --- fast paths ---------------------------------------------------------------------------------

def builder(cls: type[T]) -> Callable[..., T]:
    """``make(*values)`` that builds the same object as ``cls(*values)`` (every field, in order)
    for a frozen slotted dataclass, about twice as fast: no ``__init__``, the slots are set
    directly (what the frozen ``__init__`` does through ``object.__setattr__``). Any class this
    does not fit (no slots, ``__post_init__``, defaults computed by factories...) gets ``cls``."""
    import dataclasses

    name = cls.__name__
    if not dataclasses.is_dataclass(cls):
        return cls
    fields = dataclasses.fields(cls)
    names = tuple(f.name for f in fields)
    slots = getattr(cls, "__slots__", None)
    if (slots is None or tuple(slots) != names or hasattr(cls, "__post_init__")
            or not all(f.init for f in fields) or any(not n.isidentifier() for n in names)
            or len(dataclasses.fields(cls)) != len(getattr(cls, "__dataclass_fields__", {}))):
        return cls
    args = ", ".join(f"a{i}" for i in range(len(names)))
    body = "; ".join(f"s{i}(o, a{i})" for i in range(len(names)))
    ns = {"new": object.__new__, "cls": cls, **{f"s{i}": cls.__dict__[n].__set__ for i, n in enumerate(names)}}
    exec(f"def make({args}):\n    o = new(cls); {body}\n    return o\n", ns)  # noqa: S102
    make: Callable[..., T] = ns["make"]
    make.__doc__ = f"Fast positional constructor of {name} (drivers.frames.builder)."
    return make


def _compile_fields(lay: wire.Layout) -> FieldsFn:
    """``f(data) -> (values, saturated)``: exactly :func:`decode_fields` for a payload of the
    right length (the caller checks it), as straight-line code for this one layout."""
    flat: list[str] = []
    vals: list[str] = []
    sat: list[tuple[str, str]] = []
    k = 0
    for i, (b, s, lim) in enumerate(zip(lay.bits, lay.scales, lay.sat_limit)):
        if b == 24:
            flat += [f"h{i}", f"l{i}"]
            raw = f"((h{i} << 16) | l{i})"
        else:
            flat.append(f"r{i}")
            raw = f"r{i}"
        if s is None:
            vals.append(raw)
        else:
            if b == 24:
                vals.append(f"r{i} * S{i}")
                pre = f"r{i} = {raw}; "
            else:
                vals.append(f"{raw} * S{i}")
                pre = ""
            sat.append((pre, f"r{i} >= L{i} or r{i} <= -L{i}"))
        k += 1
    lines = ["def f(data):", f"    {', '.join(flat)}, = unpack(data)"]
    for pre, _ in sat:
        if pre:
            lines.append("    " + pre.strip().rstrip(";"))
    lines.append(f"    return ({', '.join(vals)},), {' or '.join(c for _, c in sat) or 'False'}")
    ns: dict[str, Any] = {"unpack": lay.struct.unpack}
    for i, (s, lim) in enumerate(zip(lay.scales, lay.sat_limit)):
        if s is not None:
            ns[f"S{i}"], ns[f"L{i}"] = s, lim
    exec("\n".join(lines) + "\n", ns)  # noqa: S102
    f: FieldsFn = ns["f"]
    return f


def _checked(lay: wire.Layout) -> FieldsFn:
    f = _compile_fields(lay)
    length, name = lay.length, lay.name

    def fields(data: bytes) -> tuple[Values, bool]:
        if len(data) != length:
            raise DecodeError(f"{name}: {len(data)} bytes, expected {length}")
        return f(data)
    return fields


_F_FT_A, _F_FT_B, _F_JOINT = _checked(FT_A), _checked(FT_B), _checked(JOINT_STATE)
_F_TORQUE, _F_VALVES = _checked(TORQUE_CMD), _checked(VALVE_CMD)
_F_IMU = tuple(_checked(lay) for lay in (IMU_T, IMU_S, IMU_QA, IMU_QB, IMU_W, IMU_A))
_F_THR = tuple(_checked(lay) for lay in (THR_F, THR_M, THR_V, THR_A))
_WRENCH, _JOINT, _IMU = builder(WrenchSample), builder(JointSample), builder(ImuSample)
_TORQUE, _THRUSTER, _VALVE = builder(TorqueCommand), builder(ThrusterCommand), builder(ValveCommand)
_FT_SAT, _DRIVE_SAT, _IMU_SAT = wire.FT_SAT, wire.DRIVE_SAT, wire.IMU_SAT
_TORQUE_SCALE, _IMU_W_SCALE, _IMU_A_SCALE = TORQUE_CMD.scale(1), IMU_W.scale(1), IMU_A.scale(1)


# --- decoders: payloads -> samples -----------------------------------------------------------

def decode_wrench(a: bytes, b: bytes, device: str, t_ns: int) -> WrenchSample:
    """``FT_SG_A`` + ``FT_SG_B`` of one sample -> :class:`WrenchSample` (N, N m, sensor frame).

    ::

        FT_SG_A  0x200  | ctr u8 | status u8 | Fx i16 | Fy i16 | Fz i16 |   20 counts/N
        FT_SG_B  0x201  | ctr u8 | Tx i16 | Ty i16 | Tz i16 |             20 counts/(N m)

    Raises :class:`DecodeError` when the counters differ.
    """
    (ca, status, fx, fy, fz), sa = _F_FT_A(a)
    (cb, tx, ty, tz), sb = _F_FT_B(b)
    if ca != cb:
        raise DecodeError(f"F/T halves disagree: counter {ca} != {cb}")
    return _WRENCH(device, t_ns, ca, (fx, fy, fz), (tx, ty, tz), sa or sb or bool(status & _FT_SAT), status)


def decode_joint(data: bytes, device: str, t_ns: int) -> JointSample:
    """``JOINT_STATE_Jj`` -> :class:`JointSample`.

    ::

        0x300+j  | ctr u8 | status u8 | angle i32, 1e-6 rad | rate i16, 2.5e-4 rad/s |
    """
    (c, status, angle, rate), sat = _F_JOINT(data)
    return _JOINT(device, t_ns, c, angle, rate, sat or bool(status & _DRIVE_SAT), status)


def decode_torque_commands(data: bytes, devices: Sequence[str | None], t_ns: int) -> list[TorqueCommand]:
    """``JOINT_TORQUE_CMD_Gg`` -> one :class:`TorqueCommand` per named slot (``None`` = unused).

    ::

        0x100+g  | ctr u8 | tau slot0 i16 | tau slot1 i16 | tau slot2 i16 |   0.05 N m/count
    """
    lay = TORQUE_CMD
    raw = lay.raw(bytes(data)) if len(data) == lay.length else None
    if raw is None:
        raise DecodeError(f"{lay.name}: {len(data)} bytes, expected {lay.length}")
    c, scale, lim = raw[0], _TORQUE_SCALE, lay.sat_limit[1]
    return [_TORQUE(dev, t_ns, c, r * scale, r >= lim or r <= -lim)
            for dev, r in zip(devices, raw[1:]) if dev is not None]


def decode_imu(parts: Mapping[int, bytes], t_ns: int) -> ImuSample:
    """The six IMU frames of one sample (by id) -> :class:`ImuSample` (IMU frame).

    ::

        0x405 IMU_SAMPLE_TIME  | ctr u8 | time_us u32 |
        0x411 IMU_STATUS       | ctr u8 | status u32  |      bits 8-13 clipping -> saturated
        0x421 IMU_QUAT_WX      | ctr u8 | w i24 | x i24 |   2^-22
        0x422 IMU_QUAT_YZ      | ctr u8 | y i24 | z i24 |   2^-22
        0x432 IMU_RATE_OF_TURN | ctr u8 | wx i16 | wy i16 | wz i16 |  2^-14 rad/s
        0x434 IMU_ACCELERATION | ctr u8 | ax i16 | ay i16 | az i16 |  2^-13 m/s^2
    """
    ft, fs, fqa, fqb, fw, fa = _F_IMU
    try:
        (c0, _time), s0 = ft(parts[wire.IMU_TIME_ID])
        (c1, status), _ = fs(parts[wire.IMU_STATUS_ID])
        (c2, qw, qx), s2 = fqa(parts[wire.IMU_QUAT_WX_ID])
        (c3, qy, qz), s3 = fqb(parts[wire.IMU_QUAT_YZ_ID])
        (c4, *w), s4 = fw(parts[wire.IMU_RATE_ID])
        (c5, *a), s5 = fa(parts[wire.IMU_ACCEL_ID])
    except KeyError as exc:
        raise DecodeError(f"IMU sample lacks frame 0x{exc.args[0]:03X}") from None
    if not c0 == c1 == c2 == c3 == c4 == c5:
        raise DecodeError(f"IMU frames disagree on the counter: {(c0, c1, c2, c3, c4, c5)}")
    return _IMU(t_ns, c0, (qw, qx, qy, qz), tuple(w), tuple(a),
                s2 or s3 or s4 or s5 or bool(status & _IMU_SAT), status)


def decode_thruster(parts: Mapping[int, bytes], t_ns: int) -> ThrusterCommand:
    """The thruster command frames of one control cycle -> :class:`ThrusterCommand`.

    ::

        0x180 THRUSTER_CMD_FORCE   | ctr u8 | Fx i16 | Fy i16 | Fz i16 |   0.05 N, body frame
        0x181 THRUSTER_CMD_MOMENT  | ctr u8 | Mx i16 | My i16 | Mz i16 |   0.05 N m about C
        0x182 THRUSTER_CMD_VALVES  | ctr u8 | valves u32 |
        0x184 THRUSTER_CMD_ALLOWED | ctr u8 | allowed u32 |                 optional: allowed -1
    """
    ff, fm, fv, fa = _F_THR
    try:
        (c0, *f), s0 = ff(parts[wire.THRUSTER_FORCE_ID])
        (c1, *m), s1 = fm(parts[wire.THRUSTER_MOMENT_ID])
        (c2, valves), _ = fv(parts[wire.THRUSTER_VALVES_ID])
    except KeyError as exc:
        raise DecodeError(f"thruster command lacks frame 0x{exc.args[0]:03X}") from None
    c3, allowed = c2, -1
    if wire.THRUSTER_ALLOWED_ID in parts:
        (c3, allowed), _ = fa(parts[wire.THRUSTER_ALLOWED_ID])
    if not c0 == c1 == c2 == c3:
        raise DecodeError(f"thruster frames disagree on the counter: {(c0, c1, c2, c3)}")
    return _THRUSTER(t_ns, c0, tuple(f), tuple(m), valves, s0 or s1, allowed)


def decode_valves(data: bytes, t_ns: int) -> ValveCommand:
    """``THRUSTER_VALVE_CMD`` -> :class:`ValveCommand`.

    ::

        0x183  | ctr u8 | valves u32 |      bit i = thruster i commanded open, 1 kHz
    """
    (c, valves), _ = _F_VALVES(data)
    return _VALVE(t_ns, c, valves)


# --- encoders: samples -> payloads -----------------------------------------------------------

def _q(value: float, scale: float, lim: int) -> tuple[int, bool]:
    """Quantize to the nearest count, clamped to +-lim (clamped = saturated)."""
    if math.isnan(value):
        raise EncodeError("NaN cannot be encoded")
    x = value / scale
    if x >= lim:
        return lim, True
    if x <= -lim:
        return -lim, True
    r = round(x)
    return r, r >= lim or r <= -lim


def _u(value: int, bits: int, what: str) -> int:
    if not 0 <= value < (1 << bits):
        raise EncodeError(f"{what} {value} does not fit in {bits} unsigned bits")
    return value


def _pack_scaled(lay: wire.Layout, head: Sequence[int], values: Sequence[float]) -> tuple[bytes, bool]:
    n = len(head)
    raw, sat = list(head), False
    for v, s, lim, name in zip(values, lay.scales[n:], lay.sat_limit[n:], lay.signals[n:]):
        if s is None:
            raise EncodeError(f"{lay.name}.{name}: an integer signal where a scaled value is given")
        r, clamped = _q(float(v), s, lim)
        raw.append(r)
        sat |= clamped
    return lay.pack_raw(raw), sat


def wrench_payloads(sample: WrenchSample) -> list[tuple[int, bytes]]:
    """``[(0x200, FT_SG_A), (0x201, FT_SG_B)]``; sets status bit0 (overload) if anything clamps
    or ``sample.saturated``."""
    c = sample.counter & 0xFF
    a, sa = _pack_scaled(FT_A, (c, 0), sample.force_n)
    b, sb = _pack_scaled(FT_B, (c,), sample.torque_nm)
    status = _u(sample.status, 8, "F/T status") | (wire.FT_SAT if (sa or sb or sample.saturated) else 0)
    a = FT_A.pack_raw((c, status) + FT_A.raw(a)[2:])
    return [(wire.FT_A_ID, a), (wire.FT_B_ID, b)]


def joint_payload(sample: JointSample, joint_index: int) -> tuple[int, bytes]:
    """``(0x300 + joint_index, JOINT_STATE)``; sets status bit3 when clamped or ``saturated``."""
    if not 0 <= joint_index < wire.MAX_JOINTS:
        raise EncodeError(f"joint index {joint_index} outside 0..{wire.MAX_JOINTS - 1}")
    c = sample.counter & 0xFF
    body, sat = _pack_scaled(JOINT_STATE, (c, 0), (sample.angle_rad, sample.rate_rad_s))
    status = _u(sample.status, 8, "drive status") | (wire.DRIVE_SAT if (sat or sample.saturated) else 0)
    return wire.JOINT_STATE_BASE + joint_index, JOINT_STATE.pack_raw((c, status) + JOINT_STATE.raw(body)[2:])


def torque_payloads(commands: Sequence[TorqueCommand]) -> list[tuple[int, bytes]]:
    """Commands of one arm for one control cycle, proximal joint first (joint i = ``commands[i]``),
    -> ``JOINT_TORQUE_CMD_G0..`` (3 joints per frame, unused slots 0). Counter of ``commands[0]``."""
    if not 1 <= len(commands) <= wire.MAX_JOINTS:
        raise EncodeError(f"1..{wire.MAX_JOINTS} torque commands per arm, not {len(commands)}")
    c = commands[0].counter & 0xFF
    out: list[tuple[int, bytes]] = []
    for g in range(0, len(commands), wire.CMD_GROUP):
        taus = [cmd.torque_nm for cmd in commands[g:g + wire.CMD_GROUP]]
        taus += [0.0] * (wire.CMD_GROUP - len(taus))
        body, _ = _pack_scaled(TORQUE_CMD, (c,), taus)
        out.append((wire.TORQUE_CMD_BASE + g // wire.CMD_GROUP, body))
    return out


def imu_payloads(sample: ImuSample, time_us: int | None = None) -> list[tuple[int, bytes]]:
    """The six IMU frames; ``time_us`` defaults to ``t_ns // 1000`` mod 2**32. Clipping bits
    (8-10 accel x,y,z; 11-13 rate x,y,z) are set for clamped axes (all six if ``saturated`` and
    nothing clamped)."""
    c = sample.counter & 0xFF
    t = (sample.t_ns // 1000 if time_us is None else time_us) & 0xFFFFFFFF
    qa, sqa = _pack_scaled(IMU_QA, (c,), sample.quat_wxyz[:2])
    qb, sqb = _pack_scaled(IMU_QB, (c,), sample.quat_wxyz[2:])
    clip = 0
    w_raw = [c]
    for i, v in enumerate(sample.rate_rad_s):
        r, s = _q(float(v), _IMU_W_SCALE, IMU_W.sat_limit[1])
        w_raw.append(r)
        clip |= (1 << (11 + i)) if s else 0
    a_raw = [c]
    for i, v in enumerate(sample.accel_m_s2):
        r, s = _q(float(v), _IMU_A_SCALE, IMU_A.sat_limit[1])
        a_raw.append(r)
        clip |= (1 << (8 + i)) if s else 0
    if sample.saturated and not clip and not (sqa or sqb):
        clip = wire.IMU_SAT
    status = _u(sample.status, 32, "IMU status") | clip
    return [(wire.IMU_TIME_ID, IMU_T.pack_raw((c, t))), (wire.IMU_STATUS_ID, IMU_S.pack_raw((c, status))),
            (wire.IMU_QUAT_WX_ID, qa), (wire.IMU_QUAT_YZ_ID, qb),
            (wire.IMU_RATE_ID, IMU_W.pack_raw(w_raw)), (wire.IMU_ACCEL_ID, IMU_A.pack_raw(a_raw))]


def thruster_payloads(sample: ThrusterCommand) -> list[tuple[int, bytes]]:
    """The thruster command frames of one control cycle: the keep-out mask first when the sample
    has one (so that a receiver's first sample carries it too), then force, moment, valves."""
    c = sample.counter & 0xFF
    f, _ = _pack_scaled(THR_F, (c,), sample.force_n)
    m, _ = _pack_scaled(THR_M, (c,), sample.moment_nm)
    v = THR_V.pack_raw((c, _u(sample.valves, 32, "valve mask")))
    out = [(wire.THRUSTER_FORCE_ID, f), (wire.THRUSTER_MOMENT_ID, m), (wire.THRUSTER_VALVES_ID, v)]
    if sample.allowed >= 0:
        out.insert(0, (wire.THRUSTER_ALLOWED_ID, THR_A.pack_raw((c, _u(sample.allowed, 32, "keep-out mask")))))
    return out


def valves_payload(sample: ValveCommand) -> tuple[int, bytes]:
    """``(0x183, THRUSTER_VALVE_CMD)``."""
    return wire.VALVE_CMD_ID, VALVE_CMD.pack_raw((sample.counter & 0xFF, _u(sample.valves, 32, "valve mask")))


def heartbeat_payload(node_id: int, counter: int, state: int = 0x05) -> tuple[int, bytes]:
    """``(0x700 + node_id, | ctr u8 | state u8 |)``; state 0x05 = operational."""
    return wire.HEARTBEAT_BASE + _u(node_id, 7, "node id"), HEARTBEAT.pack_raw((counter & 0xFF, _u(state, 8, "state")))


def to_messages(payloads: Sequence[tuple[int, bytes]], t_ns: int | None = None, fd: bool = False) -> list[can.Message]:
    """``(id, bytes)`` pairs -> ``can.Message`` (11-bit ids; CAN FD with bit-rate switch if ``fd``)."""
    ts = 0.0 if t_ns is None else t_ns / 1e9
    return [can.Message(arbitration_id=i, data=d, is_extended_id=False, is_fd=fd, bitrate_switch=fd, timestamp=ts)
            for i, d in payloads]


def encode_wrench(sample: WrenchSample, fd: bool = False) -> list[can.Message]:
    """Two frames for the F/T sensor of ``sample.device``'s arm bus."""
    return to_messages(wrench_payloads(sample), sample.t_ns, fd)


def encode_joint(sample: JointSample, joint_index: int, fd: bool = False) -> can.Message:
    """One frame for joint ``joint_index`` (0 = proximal; see ``WireMap.joint_index``)."""
    return to_messages([joint_payload(sample, joint_index)], sample.t_ns, fd)[0]


def encode_torque_commands(commands: Sequence[TorqueCommand], fd: bool = False) -> list[can.Message]:
    return to_messages(torque_payloads(commands), commands[0].t_ns if commands else None, fd)


def encode_imu(sample: ImuSample, time_us: int | None = None, fd: bool = False) -> list[can.Message]:
    return to_messages(imu_payloads(sample, time_us), sample.t_ns, fd)


def encode_thruster(sample: ThrusterCommand, fd: bool = False) -> list[can.Message]:
    return to_messages(thruster_payloads(sample), sample.t_ns, fd)


def encode_valves(sample: ValveCommand, fd: bool = False) -> can.Message:
    return to_messages([valves_payload(sample)], sample.t_ns, fd)[0]


def encode_heartbeat(node_id: int, counter: int, state: int = 0x05, fd: bool = False) -> can.Message:
    return to_messages([heartbeat_payload(node_id, counter, state)], None, fd)[0]
