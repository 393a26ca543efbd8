"""What the compensator publishes: the joint drives' command (its zenoh keys are in :mod:`gateway.keys`).

The thruster loop's records, :class:`ValveWrenches` (in: the learned per-valve wrenches) and
:class:`ThrusterValves` (out: one step's valves), are not on zenoh yet (docs/control.md).

``bsc/<robot>/commands/drives/<arm>`` (``keys.drive_command``): a :class:`DriveCommand` per arm,
the command the drives should apply. Only the controller role may publish under
``bsc/<robot>/commands/**`` (deploy/zenoh/router.json5); the gateway never does.
``bsc/<robot>/commands/status`` (``keys.control_status``): the compensator's loop transitions (open
<-> closed, per arm) as :class:`gateway.efforts.Alert` records, under the controller's key space
because that role may publish nowhere else.

Payloads are the house's JSON form (:func:`gateway.log.schema.record_of`:
``{"type": "DriveCommand", "v": 1, ...}``), decoded strictly by :func:`decode_drive_command`.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, fields

from gateway.errors import GatewayError
from gateway.log.schema import FORM_VERSION, record_of


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
class ValveWrenches:
    """The gateway's learned per-valve wrenches at sensor time ``t_ns`` (the thruster filter's
    state, :mod:`gateway.estimator.thrusters`): ``wrench`` the n x 6 numbers, valve by valve, of
    what each valve exerts while open ``[force (N); moment about C (N m)]``, body frame;
    ``force_sigma_n`` (n,) each one's force uncertainty (1 sigma, N: the root of its force
    covariance's trace); ``good`` and ``flags`` those of the thruster efforts of the same epoch.
    What the thruster loop (:mod:`gateway.control.thrusters`) allocates with."""

    t_ns: int
    wrench: tuple[float, ...]
    force_sigma_n: tuple[float, ...]
    good: bool
    flags: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class ThrusterValves:
    """The thruster loop's valve command for the step at sensor time ``t_ns``: ``valves`` bit i =
    thruster i open; ``duty`` (n,) the allocation it times (fractions of full opening);
    ``closed``: False when the allocation used the NOMINAL wrenches (``flags`` says why:
    ``no-estimate``, ``stale:efforts``, ``estimate:not-good (<its flags>)``, ``disabled``; closed:
    ``limited:rate``, ``limited:magnitude``); ``saturated``: the commanded wrench needed more than
    full opening (scaled down, direction kept); ``fault:thruster<i>``: thruster i excluded."""

    t_ns: int
    valves: int
    duty: tuple[float, ...]
    closed: bool
    flags: tuple[str, ...] = ()


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
