"""The one CAN-frame codec of a session log: a python-can ``Message`` <-> a ``bsc.CanFrame``
JSON record, on topic ``/can/<bus>``.

The record's fields, in the order they are written (:data:`FIELDS`), make every form here and
in the compiled chunk reader (:mod:`gateway.log.frames`): the dict (:func:`can_frame_to_record`,
:func:`can_frame_from_record`), the JSON bytes from a message or from frame rows read straight
from a socket (:func:`can_frame_json`, :func:`can_frame_json_rows`: the same bytes as the dict
through the log's JSON encoder), and the fast reader of those bytes (:func:`can_frame_from_json`,
a record in any other form goes through ``json``). Tests hold every pair of forms to each other.
"""
from __future__ import annotations

import base64
import json
import re
from collections.abc import Mapping
from typing import Any

from gateway.log.names import CAN_SCHEMA_NAME, CAN_TOPIC_PREFIX
from gateway.log.schema import encode_json

FIELDS = ("t_ns", "arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame", "is_fd",
          "bitrate_switch", "error_state_indicator", "is_rx", "dlc", "data", "channel")
_INTS, _FLAGS = ("t_ns", "arbitration_id", "dlc"), FIELDS[2:9]

CAN_FRAME_SCHEMA: dict[str, Any] = {
    "title": CAN_SCHEMA_NAME,
    "description": "One raw CAN / CAN FD frame as python-can received it (bsc recorder).",
    "type": "object",
    "properties": {
        "t_ns": {"type": "integer", "description": "frame timestamp (python-can), ns"},
        "arbitration_id": {"type": "integer"},
        "is_extended_id": {"type": "boolean"},
        "is_remote_frame": {"type": "boolean"},
        "is_error_frame": {"type": "boolean"},
        "is_fd": {"type": "boolean"},
        "bitrate_switch": {"type": "boolean"},
        "error_state_indicator": {"type": "boolean"},
        "is_rx": {"type": "boolean"},
        "dlc": {"type": "integer"},
        "data": {"type": "string", "contentEncoding": "base64",
                 "description": "payload bytes, base64"},
        "channel": {"type": "string",
                    "description": "python-can channel the frame came from, as text (\"\" when none)"},
    },
    "required": ["t_ns", "arbitration_id", "is_extended_id", "is_remote_frame",
                 "is_error_frame", "is_fd", "bitrate_switch", "dlc", "data", "channel"],
}



def can_frame_to_record(msg) -> dict[str, Any]:
    """A python-can ``Message`` as a JSON-ready dict (the ``bsc.CanFrame`` schema).

    ``data`` is base64 and round-trips bit for bit; ``t_ns`` is ``round(timestamp * 1e9)``.
    """
    channel = channel_text(msg.channel)
    return {
        "t_ns": round(msg.timestamp * 1e9),
        "arbitration_id": msg.arbitration_id,
        "is_extended_id": msg.is_extended_id,
        "is_remote_frame": msg.is_remote_frame,
        "is_error_frame": msg.is_error_frame,
        "is_fd": msg.is_fd,
        "bitrate_switch": msg.bitrate_switch,
        "error_state_indicator": msg.error_state_indicator,
        "is_rx": msg.is_rx,
        "dlc": msg.dlc,
        "data": base64.b64encode(bytes(msg.data)).decode("ascii"),
        "channel": channel,
    }


def channel_text(channel) -> str:
    """A frame's python-can channel as recorded: text, ``""`` for none (one JSON type per field,
    as Foxglove's schema loader needs; a log from before this wrote null or an integer, and reads
    back as it was)."""
    return "" if channel is None else channel if isinstance(channel, str) else str(channel)


_JSON_BOOL = {True: "true", False: "false"}


def _text_before(k: int) -> str:
    """The record's literal text between value ``k - 1`` and value ``k`` (``data`` is quoted)."""
    out = ("{" if k == 0 else ",") + f'"{FIELDS[k]}":'
    if k and FIELDS[k - 1] == "data":
        out = '"' + out
    return out + ('"' if FIELDS[k] == "data" else "")


# the record as a %-format (the writer), its literal parts (the compiled reader), a regex (the reader)
_CAN_JSON = "".join(_text_before(k) + ("%d" if n in _INTS else "%s") for k, n in enumerate(FIELDS)) + "}"
KEYS = tuple(_text_before(k).encode() for k in range(len(FIELDS)))
_INT_RE, _BOOL_RE = rb"(-?(?:0|[1-9][0-9]*))", rb"(true|false)"
_VALUE_RE = {"data": rb"([A-Za-z0-9+/=]*)", "channel": rb'(null|-?(?:0|[1-9][0-9]*)|"[ !#-\[\]-~]*")'}
_CAN_RECORD = re.compile(b"".join(re.escape(KEYS[k]) + _VALUE_RE.get(n, _INT_RE if n in _INTS else _BOOL_RE)
                                  for k, n in enumerate(FIELDS)) + rb"\}")
_CHANNEL_JSON: dict = {}


def can_frame_json(msg) -> tuple[int, bytes]:
    """``(t_ns, JSON bytes)`` of :func:`can_frame_to_record`, encoded as the recorder's encoder
    does (same bytes), about 3x faster: the gateway records every frame in its worker thread."""
    try:
        b = _JSON_BOOL
        ch = _CHANNEL_JSON.get(msg.channel)
        if ch is None:
            rec_ch = can_frame_to_record(msg)["channel"]
            ch = _CHANNEL_JSON[msg.channel] = encode_json(rec_ch)
        t = round(msg.timestamp * 1e9)
        return t, (_CAN_JSON % (
            t, msg.arbitration_id, b[msg.is_extended_id], b[msg.is_remote_frame], b[msg.is_error_frame],
            b[msg.is_fd], b[msg.bitrate_switch], b[msg.error_state_indicator], b[msg.is_rx], msg.dlc,
            base64.b64encode(bytes(msg.data)).decode("ascii"), ch)).encode()
    except (KeyError, TypeError):        # a field that is not a plain bool, int or hashable channel
        rec = can_frame_to_record(msg)
        return rec["t_ns"], encode_json(rec).encode()


def can_frame_json_rows(rows, channel=None) -> list[bytes]:
    """:func:`can_frame_json` of frames given as :data:`drivers.kernel.FRAME_DTYPE` rows (read
    straight from a socket): the same bytes python-can's message of the frame would give, with
    ``channel`` (the receiving bus's) and ``is_rx`` true (a received frame)."""
    b = _JSON_BOOL
    channel = channel_text(channel)     # as can_frame_json: a list or an object is not a JSON value
    ch = _CHANNEL_JSON.get(channel)
    if ch is None:
        ch = _CHANNEL_JSON[channel] = encode_json(channel)
    out = []
    b64 = base64.b64encode
    t_ns, ids, flags = rows["t_ns"].tolist(), rows["can_id"].tolist(), rows["flags"].tolist()
    dlcs, lens, data = rows["dlc"].tolist(), rows["length"].tolist(), rows["data"]
    for k in range(len(rows)):
        f = flags[k]
        out.append((_CAN_JSON % (t_ns[k], ids[k], b[bool(f & 1)], b[bool(f & 2)], b[bool(f & 4)], b[bool(f & 8)],
                                 b[bool(f & 16)], b[bool(f & 32)], "true", dlcs[k],
                                 b64(data[k, :lens[k]].tobytes()).decode("ascii"), ch)).encode())
    return out


def can_frame_from_record(record: Mapping[str, Any]):
    """The python-can ``Message`` back from a ``bsc.CanFrame`` dict (inverse of the above)."""
    import can

    return can.Message(
        timestamp=record["t_ns"] / 1e9,
        arbitration_id=record["arbitration_id"],
        is_extended_id=record["is_extended_id"],
        is_remote_frame=record["is_remote_frame"],
        is_error_frame=record["is_error_frame"],
        is_fd=record["is_fd"],
        bitrate_switch=record["bitrate_switch"],
        error_state_indicator=record.get("error_state_indicator", False),
        is_rx=record.get("is_rx", True),
        dlc=record["dlc"],
        data=base64.b64decode(record["data"], validate=True),
        channel=record["channel"] if record["channel"] != "" else None,
    )


def can_topic(bus: str) -> str:
    """The topic of raw frames from logical bus ``bus`` (``ft0`` -> ``/can/ft0``)."""
    if not bus or not all(c.isalnum() or c in "_-." for c in bus):
        raise ValueError(f"bus name {bus!r}: use letters, digits, '_', '-', '.'")
    return CAN_TOPIC_PREFIX + bus


def can_frame_from_json(data: bytes, can_ids: frozenset[int] | set[int] | None = None):
    """The python-can ``Message`` of a ``bsc.CanFrame`` record's JSON bytes (what
    ``can_frame_from_record(json.loads(data))`` gives), or None when its id is not in ``can_ids``.
    The recorder's own form is read with one regex (about 4x faster); any other JSON form
    (another writer, a channel with escapes) through ``json``. A malformed record: ValueError."""
    import can

    g = _CAN_RECORD.fullmatch(data)
    if g is None:
        try:
            rec = json.loads(data)
        except ValueError as exc:
            raise ValueError(f"not JSON ({exc})") from None
        if not isinstance(rec, dict):
            raise ValueError("not a JSON object")
        if can_ids is not None and rec.get("arbitration_id") not in can_ids:
            return None
        try:
            return can_frame_from_record(rec)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"malformed ({exc!r})") from None
    (t_ns, ident, ext, rtr, err, fd, brs, esi, rx, dlc, payload, channel) = g.groups()
    ident = int(ident)
    if can_ids is not None and ident not in can_ids:
        return None
    try:
        raw = base64.b64decode(payload, validate=True)
    except ValueError as exc:
        raise ValueError(f"malformed ({exc!r})") from None
    if channel == b"null" or channel == b'""':          # "" is how a frame without a channel is written
        chan: str | int | None = None
    elif channel[:1] == b'"':
        chan = channel[1:-1].decode("ascii")
    else:
        chan = int(channel)
    true = b"true"
    return can.Message(timestamp=int(t_ns) / 1e9, arbitration_id=ident, is_extended_id=ext == true,
                       is_remote_frame=rtr == true, is_error_frame=err == true, is_fd=fd == true,
                       bitrate_switch=brs == true, error_state_indicator=esi == true, is_rx=rx == true,
                       dlc=int(dlc), data=raw, channel=chan)
