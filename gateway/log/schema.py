"""The JSON form of a logged record and its JSON schema, from the record's dataclass.

Every channel of a session log is JSON with a JSON schema (draft 2020-12, the subset Foxglove's
loader takes: one scalar type per field, vectors as ``items``, named values as arrays of
``{"name", "value"}`` objects). The zenoh payloads (:mod:`gateway.codec`) use the same field
forms and schemas.
"""
from __future__ import annotations

import base64
import collections
import dataclasses
import enum
import json
import types
import typing
from collections.abc import Mapping
from typing import Any


FORM_VERSION = 1      # "v" of a record: the version of this JSON form


def json_schema_for(cls: type, *, envelope: bool = True) -> dict[str, Any]:
    """A JSON schema (draft 2020-12 subset that Foxglove reads) from a dataclass's type hints: the
    record :func:`dataclass_json` writes, its ``type`` and ``v`` first (``envelope``)."""
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise TypeError(f"{cls!r} is not a dataclass type")
    hints = typing.get_type_hints(cls)
    props = {f.name: PAIRS_SCHEMA[pair_value_type(hints[f.name])] if pair_value_type(hints.get(f.name)) else
             _type_schema(hints.get(f.name, Any)) for f in dataclasses.fields(cls)}
    if envelope:
        props = {"type": {"type": "string", "description": f"the record's type: {cls.__name__}"},
                 "v": {"type": "integer", "description": f"the version of its JSON form: {FORM_VERSION}"},
                 **props}
    schema: dict[str, Any] = {"title": qualname(cls), "type": "object", "properties": props,
                              "required": list(props)}
    doc = (cls.__doc__ or "").strip()
    if doc and not doc.startswith(cls.__name__ + "("):   # skip dataclass's generated signature
        schema["description"] = doc.split("\n\n")[0].replace("\n", " ")
    return schema


def _type_schema(tp: Any) -> dict[str, Any]:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is bool:
        return {"type": "boolean"}
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return {"enum": [m.value for m in tp]}
    if tp is int:
        return {"type": "integer"}
    if tp is float:
        return {"type": "number"}
    if tp is str:
        return {"type": "string"}
    if tp in (bytes, bytearray):
        return {"type": "string", "contentEncoding": "base64"}
    if tp is type(None):
        return {"type": "null"}
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return json_schema_for(tp, envelope=False)
    if origin in (typing.Union, types.UnionType):
        return {"anyOf": [_type_schema(a) for a in args]}
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return {"type": "array", "items": _type_schema(args[0])}
        if args:
            items = [_type_schema(a) for a in args]
            out: dict[str, Any] = {"type": "array", "minItems": len(args), "maxItems": len(args)}
            if all(i == items[0] for i in items):
                out["items"] = items[0]          # a vector: Foxglove reads items, not prefixItems
            else:
                out["items"] = {}
                out["prefixItems"] = items
            return out
        return {"type": "array"}
    if origin in (list, collections.abc.Sequence, set, frozenset):
        return {"type": "array", "items": _type_schema(args[0]) if args else {}}
    if origin in (dict, collections.abc.Mapping):
        return {"type": "object"}
    return {}


def pair_value_type(hint) -> type | None:
    """``T`` when ``hint`` is ``tuple[tuple[str, T], ...]`` (named counts and values such as a
    health's ``rejected`` or an alert's ``evidence``), else None. Such a field is written in JSON
    as an array of ``{"name", "value"}`` objects (:func:`pairs_json`), not of two-item arrays:
    Foxglove's schema loader takes no array of arrays."""
    if typing.get_origin(hint) is not tuple:
        return None
    args = typing.get_args(hint)
    if len(args) != 2 or args[1] is not Ellipsis or typing.get_origin(args[0]) is not tuple:
        return None
    inner = typing.get_args(args[0])
    return inner[1] if len(inner) == 2 and inner[0] is str and inner[1] in (int, float) else None


PAIRS_SCHEMA = {t: {"type": "array", "items": {
    "type": "object", "properties": {"name": {"type": "string"}, "value": {"type": kind}},
    "required": ["name", "value"]}} for t, kind in ((int, "integer"), (float, "number"))}


def pairs_json(pairs) -> list[dict[str, Any]]:
    return [{"name": k, "value": v} for k, v in pairs]


def pairs_from_json(value) -> tuple:
    """Back from :func:`pairs_json` (also the two-item arrays of a log written before it)."""
    return tuple((d["name"], d["value"]) if isinstance(d, dict) else tuple(d) for d in value)


def dict_schema(example: Mapping[str, Any], name: str) -> dict[str, Any]:
    kinds = {bool: "boolean", int: "integer", float: "number", str: "string",
             list: "array", tuple: "array", dict: "object", type(None): "null"}
    props = {str(k): ({"type": kinds[type(v)]} if type(v) in kinds else {})
             for k, v in example.items()}
    return {"title": name, "type": "object", "properties": props}


def qualname(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def json_default(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        hints = typing.get_type_hints(type(obj))
        return {f.name: pairs_json(getattr(obj, f.name)) if pair_value_type(hints.get(f.name))
                else getattr(obj, f.name) for f in dataclasses.fields(obj)}
    if isinstance(obj, (bytes, bytearray, memoryview)):
        return base64.b64encode(bytes(obj)).decode("ascii")
    if isinstance(obj, enum.Enum):
        return obj.value
    if hasattr(obj, "tolist"):           # numpy arrays and scalars
        return obj.tolist()
    raise TypeError(f"cannot record a {type(obj).__name__} as JSON")


# Non-finite floats are written as the NaN/Infinity tokens (Python's json) rather than refused:
# a recording keeps what the gateway saw, and our reader reads them back.
_ENCODER = json.JSONEncoder(separators=(",", ":"), default=json_default)
encode_json = _ENCODER.encode

try:    # the C encoder JSONEncoder.encode builds on every call, built once (no cycle check: the
        # records are flat frozen dataclasses); same bytes as encode_json
    from json.encoder import c_make_encoder as _c_make_encoder, encode_basestring_ascii as _ascii

    _c_encode = _c_make_encoder(None, json_default, _ascii, None, ":", ",", False, False, True) \
        if _c_make_encoder is not None else None
except ImportError:  # pragma: no cover - CPython always has it
    _c_encode = None
_DATACLASS_JSON: dict[type, Any] = {}


def record_of(sample: Any) -> dict[str, Any]:
    """The JSON-ready record of a dataclass instance: ``{"type": <class name>, "v": FORM_VERSION,
    <field>: <value>, ...}``, named values as ``{"name", "value"}`` objects. One form for a sample
    everywhere: a zenoh payload (:func:`gateway.codec.encode`) and a log message are these bytes."""
    cls = type(sample)
    names = field_names(cls)
    pairs = _pair_fields(cls)
    return {"type": cls.__name__, "v": FORM_VERSION,
            **{n: pairs_json(getattr(sample, n)) if n in pairs else getattr(sample, n) for n in names}}


_PAIR_FIELDS: dict[type, frozenset[str]] = {}


def _pair_fields(cls: type) -> frozenset[str]:
    out = _PAIR_FIELDS.get(cls)
    if out is None:
        hints = typing.get_type_hints(cls)
        out = _PAIR_FIELDS[cls] = frozenset(n for n in field_names(cls) if pair_value_type(hints.get(n)))
    return out


def dataclass_json(cls: type):
    """``f(sample) -> str``: ``encode_json(record_of(sample))`` for one dataclass type, built once
    per type (the C encoder called on the fields directly: about 2x faster, the same text)."""
    f = _DATACLASS_JSON.get(cls)
    if f is None:
        names = field_names(cls)
        pairs = _pair_fields(cls)
        if _c_encode is None or not all(n.isidentifier() for n in names):
            def f(sample):
                return encode_json(record_of(sample))
        else:
            ns = {"c": _c_encode, "join": "".join, "p": pairs_json}
            head = f"'type': {cls.__name__!r}, 'v': {FORM_VERSION}, "
            exec("def f(o):\n    return join(c({" + head + ", ".join(  # noqa: S102
                f"{n!r}: p(o.{n})" if n in pairs else f"{n!r}: o.{n}" for n in names) + "}, 0))\n", ns)
            f = ns["f"]
        _DATACLASS_JSON[cls] = f
    return f


_FIELD_NAMES: dict[type, tuple[str, ...]] = {}


def field_names(cls: type) -> tuple[str, ...]:
    names = _FIELD_NAMES.get(cls)
    if names is None:
        names = _FIELD_NAMES[cls] = tuple(f.name for f in dataclasses.fields(cls))
    return names
