"""What the compensator publishes: the joint drives' command and the thrusters' valves (their zenoh
keys are in :mod:`gateway.keys`).

``bsc/<robot>/commands/drives/<arm>`` (``keys.drive_command``): a :class:`DriveCommand` per arm,
the command the drives should apply. ``bsc/<robot>/commands/thrusters``
(``keys.thruster_valves``): a :class:`ThrusterValves`, the valves of the steps until the next
commanded wrench. Only the controller role may publish under ``bsc/<robot>/commands/**``
(deploy/zenoh/router.json5); the gateway never does.
``bsc/<robot>/commands/status`` (``keys.control_status``): the compensator's loop transitions (open
<-> closed, per arm) as :class:`gateway.efforts.Alert` records, under the controller's key space
because that role may publish nowhere else.

Payloads are the house's JSON form (:func:`gateway.log.schema.record_of`:
``{"type": "DriveCommand", "v": 1, ...}``), decoded strictly by :func:`decode_drive_command` and
:func:`decode_thruster_valves`. What the thruster loop takes in, the gateway's learned per-valve
wrenches, is :class:`gateway.efforts.ValveWrenches` (``bsc/<robot>/efforts/valves``; re-exported
here).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, fields

from gateway.efforts import ValveWrenches
from gateway.errors import GatewayError
from gateway.log.schema import FORM_VERSION, record_of

__all__ = ["ControlError", "DriveCommand", "ThrusterValves", "ValveWrenches", "decode_drive_command",
           "decode_thruster_valves", "encode_drive_command", "encode_thruster_valves"]


class ControlError(GatewayError, ValueError):
    """Root of the compensator's errors: bad settings, a payload that is not a drive command."""


@dataclass(frozen=True, slots=True)
class DriveCommand:
    """The motor torque command for one arm's joint drives, N m, joint order proximal first.

    ``t_ns``: sensor time of the outer loop's command it corrects (the desired torques observed on
    the arm bus). ``torque_nm`` = ``desired_nm`` + ``correction_nm``, saturated at each joint's
    torque limit. ``closed``: False when the compensator is open loop for this arm
    (``correction_nm`` all zero, ``torque_nm`` = the desired torques); ``flags`` says why
    (open: ``no-estimate``, ``stale:efforts``, ``estimate:not-good (<its flags>)``, ``disabled``;
    closed: ``limited:rate``, ``limited:magnitude``, ``saturated``).
    """

    arm: str
    t_ns: int
    joints: tuple[str, ...]
    torque_nm: tuple[float, ...]
    desired_nm: tuple[float, ...]
    correction_nm: tuple[float, ...]
    closed: bool
    flags: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class ThrusterValves:
    """The thruster loop's valve command for the step at sensor time ``t_ns``: ``valves`` bit i =
    thruster i open; ``duty`` (n,) the allocation it times (fractions of full opening);
    ``closed``: False when the allocation used the NOMINAL wrenches (``flags`` says why:
    ``no-estimate``, ``stale:efforts``, ``estimate:not-good (<its flags>)``, ``disabled``; closed:
    ``limited:rate``, ``limited:magnitude``); ``saturated``: the commanded wrench needed more than
    full opening (scaled down, direction kept); ``fault:thruster<i>``: thruster i excluded.

    ``following``: the valve masks of the next steps, ``step_ns`` apart (``bsc control`` sends the
    valves up to the next commanded wrench at once, :meth:`gateway.control.ThrusterCompensator.schedule`);
    ``()`` for one step. :meth:`masks` gives them all, the first step's first."""

    t_ns: int
    valves: int
    duty: tuple[float, ...]
    closed: bool
    flags: tuple[str, ...] = ()
    following: tuple[int, ...] = ()
    step_ns: int = 0

    def masks(self) -> tuple[int, ...]:
        """The valve mask of every step, from ``t_ns`` on, ``step_ns`` apart."""
        return (self.valves, *self.following)


def encode_drive_command(cmd: DriveCommand) -> bytes:
    """The JSON payload; a non-finite torque is refused (JSON has none)."""
    try:
        return json.dumps(record_of(cmd), allow_nan=False, separators=(",", ":")).encode()
    except ValueError as exc:
        raise ControlError(f"DriveCommand: {exc}") from None


_NAMES = tuple(f.name for f in fields(DriveCommand))


def decode_drive_command(payload: bytes | bytearray | memoryview | str) -> DriveCommand:
    """Bytes -> :class:`DriveCommand`; :class:`ControlError` on anything else (strict: every field
    present with its type, the torque vectors as long as the joint list, finite numbers)."""
    try:
        obj = json.loads(bytes(payload) if not isinstance(payload, str) else payload)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ControlError(f"drive command: not JSON: {exc}") from None
    if not isinstance(obj, dict) or obj.get("type") != "DriveCommand":
        raise ControlError("drive command: not a DriveCommand record")
    if obj.get("v") != FORM_VERSION:
        raise ControlError(f"drive command: unsupported version {obj.get('v')!r}")
    extra = set(obj) - {"type", "v"} - set(_NAMES)
    missing = set(_NAMES) - {"flags"} - set(obj)
    if extra or missing:
        raise ControlError(f"drive command: unknown fields {sorted(extra)}, missing {sorted(missing)}")

    def strings(name):
        v = obj.get(name, [])
        if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
            raise ControlError(f"drive command: {name} must be an array of strings")
        return tuple(v)

    joints = strings("joints")

    def numbers(name):
        v = obj[name]
        if (not isinstance(v, list) or len(v) != len(joints)
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
            raise ControlError(f"drive command: {name} must be {len(joints)} finite numbers")
        return tuple(float(x) for x in v)

    if not isinstance(obj["arm"], str) or not obj["arm"]:
        raise ControlError("drive command: arm must be a name")
    if not isinstance(obj["t_ns"], int) or isinstance(obj["t_ns"], bool):
        raise ControlError("drive command: t_ns must be an integer")
    if not isinstance(obj["closed"], bool):
        raise ControlError("drive command: closed must be true or false")
    return DriveCommand(obj["arm"], obj["t_ns"], joints, numbers("torque_nm"), numbers("desired_nm"),
                        numbers("correction_nm"), obj["closed"], strings("flags"))


def encode_thruster_valves(v: ThrusterValves) -> bytes:
    """The JSON payload; a non-finite duty is refused (JSON has none)."""
    try:
        return json.dumps(record_of(v), allow_nan=False, separators=(",", ":")).encode()
    except ValueError as exc:
        raise ControlError(f"ThrusterValves: {exc}") from None


def decode_thruster_valves(payload: bytes | bytearray | memoryview | str) -> ThrusterValves:
    """Bytes -> :class:`ThrusterValves`; :class:`ControlError` on anything else (strict: the
    record's fields with their types (:func:`gateway.codec.decode`), duties finite in [0, 1],
    masks not negative, a positive ``step_ns`` when there are following steps)."""
    from gateway import codec

    try:
        v = codec.decode(payload, {"ThrusterValves": ThrusterValves})
    except codec.CodecError as exc:
        raise ControlError(f"thruster valves: {exc}") from None
    if not all(math.isfinite(d) and 0.0 <= d <= 1.0 for d in v.duty):
        raise ControlError("thruster valves: duty must be fractions in [0, 1]")
    if v.valves < 0 or any(m < 0 for m in v.following):
        raise ControlError("thruster valves: valve masks cannot be negative")
    if v.following and v.step_ns <= 0:
        raise ControlError("thruster valves: following steps need a positive step_ns")
    return v
