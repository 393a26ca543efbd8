"""The one payload codec of the zenoh side: samples and health as UTF-8 JSON objects.

Format: ``{"type": "<dataclass name>", "v": 1, <field>: <value>, ...}``; tuples become JSON
arrays, floats are written with Python's shortest round-tripping repr, so ``decode(encode(x)) ==
x`` for every sample, health, effort and alert dataclass. Decoding is safe: ``json.loads`` only, the type is
looked up in a fixed table, every field is checked for presence and type; nothing is evaluated
or unpickled. Non-finite floats (never produced by the drivers) are refused.

Publishing (:func:`declare_publisher`, :func:`put`): every bsc publisher sends the publish time as
the zenoh attachment ``publish_ns`` (decimal ASCII ns), so payloads of the same sample are equal
bytes whenever they are sent. Efforts, alerts and health go with congestion control BLOCK
(zenoh's default, DROP, loses them silently when its send queue is full: a slow consumer must
slow the producer, whose own queue counts what it drops) and zenoh's ``express`` (sent at once,
not held for batching: a few messages per step; in the latency benchmark the hop's p99 went from
1.3-1.4 ms to 0.35-0.64 ms). Raw samples keep DROP and batching.
"""
from __future__ import annotations

import dataclasses
import json
import time
import types
import typing

from gateway.errors import GatewayError
from drivers.samples import (BusHealth, DeviceHealth, ImuSample, JointSample, ThrusterCommand, TorqueCommand,
                             ValveCommand, WrenchSample)
from gateway.efforts import Alert, JointEfforts, ThrusterEffort, ValveWrenches
from gateway.log.schema import FORM_VERSION, pair_value_type, record_of

VERSION = FORM_VERSION          # the "v" of every payload (the JSON form, gateway.log.schema)
ENCODING = "application/json"
TYPES: dict[str, type] = {t.__name__: t for t in (WrenchSample, ImuSample, JointSample, TorqueCommand,
                                                   ThrusterCommand, ValveCommand, DeviceHealth, BusHealth, JointEfforts,
                                                   ThrusterEffort, ValveWrenches, Alert)}


def declare_publisher(session, key: str):
    """A zenoh publisher for ``key`` with bsc's congestion policy (module docstring)."""
    import zenoh

    cc = zenoh.CongestionControl.DROP if "/sensors/" in key else zenoh.CongestionControl.BLOCK
    return session.declare_publisher(key, encoding=zenoh.Encoding.APPLICATION_JSON, congestion_control=cc,
                                     express=cc == zenoh.CongestionControl.BLOCK)


def wait_for_subscriber(session, key: str, timeout_s: float = 10.0) -> bool:
    """Until a subscriber matching ``key`` is known to ``session`` (zenoh's matching status), or
    ``timeout_s``: a put before that reaches nobody. False on timeout. For a caller that must not
    lose its first messages (a demo, a test), instead of sleeping for a guessed propagation time."""
    pub = session.declare_publisher(key)
    try:
        end = time.monotonic() + timeout_s
        while not pub.matching_status.matching:
            if time.monotonic() > end:
                return False
            time.sleep(0.001)
        return True
    finally:
        pub.undeclare()


def put(publisher, payload: bytes) -> None:
    """Send an encoded payload with the ``publish_ns`` attachment."""
    publisher.put(payload, attachment=str(time.time_ns()).encode())


class CodecError(GatewayError, ValueError):
    """A payload that is not a valid encoded sample."""


# --- schemas, queryable on zenoh --------------------------------------------------------------------

SCHEMA_ENCODING = "application/schema+json"


def payload_schema(cls: type) -> dict:
    """The JSON schema (draft 2020-12) of ``cls``'s payloads as :func:`encode` writes them: the
    dataclass's fields and the ``type`` and ``v`` of the envelope."""
    from gateway.log.names import JSON_SCHEMA_DIALECT
    from gateway.log.schema import json_schema_for

    s = json_schema_for(cls)                 # the log's schema of the same record, type and v first
    s["properties"] = {**s["properties"], "type": {"const": cls.__name__}, "v": {"const": VERSION}}
    return {"$schema": JSON_SCHEMA_DIALECT, **s}


def serve_schemas(session, robot: str):
    """Declare the queryable that answers ``bsc/<robot>/schemas/<Type>`` with the schema of every
    payload type a query's key expression matches (a client in any language can discover and
    decode what bsc publishes: ``get bsc/<robot>/schemas/**``). Returns the queryable (undeclare
    it when done)."""
    import zenoh

    from gateway import keys

    replies = [(zenoh.KeyExpr(keys.schema(robot, name)), json.dumps(payload_schema(cls)).encode())
               for name, cls in TYPES.items()]
    encoding = zenoh.Encoding(SCHEMA_ENCODING)

    def answer(query) -> None:
        try:
            for key, body in replies:
                if key.intersects(query.key_expr):
                    query.reply(key, body, encoding=encoding)
        except Exception:  # noqa: BLE001 - a failing reply must not take the session's thread down
            pass

    return session.declare_queryable(keys.schemas(robot), answer)


def fetch_schemas(session, robot: str, timeout_s: float = 5.0) -> dict[str, dict]:
    """``{type name: schema}`` of every payload type the gateways of ``robot`` serve."""
    from gateway import keys

    out = {}
    for reply in session.get(keys.schemas(robot), timeout=timeout_s):
        ok = getattr(reply, "ok", None)
        if ok is not None:
            out[str(ok.key_expr).rsplit("/", 1)[1]] = json.loads(ok.payload.to_bytes())
    return out


_FIELDS: dict[type, tuple[str, ...]] = {t: tuple(f.name for f in dataclasses.fields(t)) for t in TYPES.values()}
_ENCODER = json.JSONEncoder(allow_nan=False, separators=(",", ":"))   # json.dumps(obj, same options)


def encode(sample) -> bytes:
    """The payload of a sample, effort, health or alert: its record (:func:`gateway.log.schema.record_of`,
    the same bytes a log holds), refusing a non-finite number (JSON has none)."""
    cls = type(sample)
    if cls not in _FIELDS:
        raise TypeError(f"cannot encode {cls.__name__}")
    try:
        return _ENCODER.encode(record_of(sample)).encode()
    except ValueError as exc:
        raise CodecError(f"{cls.__name__}: {exc}") from None


_HINTS: dict[type, dict[str, object]] = {t: typing.get_type_hints(t) for t in TYPES.values()}


def _convert(value, hint, where: str):
    origin = typing.get_origin(hint)
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise CodecError(f"{where}: expected a number")
        return float(value)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise CodecError(f"{where}: expected an integer")
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise CodecError(f"{where}: expected true/false")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise CodecError(f"{where}: expected a string")
        return value
    if origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(value, list):
            raise CodecError(f"{where}: expected an array")
        vt = pair_value_type(hint)
        if vt is not None:                 # [{"name": ..., "value": ...}] (or [name, value] of older payloads)
            out = []
            for d in value:
                if isinstance(d, dict):
                    if set(d) != {"name", "value"}:
                        raise CodecError(f"{where}: expected objects with name and value")
                    d = [d["name"], d["value"]]
                if not isinstance(d, list) or len(d) != 2:
                    raise CodecError(f"{where}: expected objects with name and value")
                out.append((_convert(d[0], str, where), _convert(d[1], vt, where)))
            return tuple(out)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(v, args[0], where) for v in value)
        if len(value) != len(args):
            raise CodecError(f"{where}: expected {len(args)} items")
        return tuple(_convert(v, a, where) for v, a in zip(value, args))
    if origin in (typing.Union, types.UnionType):
        raise CodecError(f"{where}: unsupported field type")
    raise CodecError(f"{where}: unsupported field type {hint!r}")


def decode(payload: bytes | bytearray | memoryview | str, types: typing.Mapping[str, type] | None = None):
    """Bytes -> the sample or health dataclass; :class:`CodecError` on anything else. ``types``:
    the records to accept, by name (default :data:`TYPES`; e.g. the compensator's commands,
    :mod:`gateway.control.messages`), each checked the same way."""
    try:
        obj = json.loads(bytes(payload) if not isinstance(payload, str) else payload)
    except (ValueError, UnicodeDecodeError) as exc:
        raise CodecError(f"not JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise CodecError("not a JSON object")
    cls = (TYPES if types is None else types).get(obj.get("type"))  # type: ignore[arg-type]
    if cls is None:
        raise CodecError(f"unknown type {obj.get('type')!r}")
    if obj.get("v") != VERSION:
        raise CodecError(f"unsupported version {obj.get('v')!r}")
    hints = _HINTS.get(cls)
    if hints is None:
        hints = _HINTS[cls] = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name in obj:
            kwargs[f.name] = _convert(obj[f.name], hints[f.name], f"{cls.__name__}.{f.name}")
        elif f.default is dataclasses.MISSING:
            raise CodecError(f"{cls.__name__}: missing field {f.name!r}")
    extra = set(obj) - {"type", "v"} - set(hints)
    if extra:
        raise CodecError(f"{cls.__name__}: unknown fields {sorted(extra)}")
    return cls(**kwargs)
