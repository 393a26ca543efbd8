"""Reading a session log: one reader of messages, in file (recording) order or in log-time
order, and the raw CAN frames on top of it.

- :func:`iter_messages` (shaped like mcap's ``iter_messages``): ``(topic, schema name, message)``
  of the channels asked for, ``message`` with ``log_time`` (ns) and ``data`` (bytes). File order
  walks the records itself (chunks parsed with ``struct``, message indexes skipped unread); log
  time order merges the chunks by the summary's index (the mcap library's reader).
- :func:`iter_can_frames`: ``(bus, t_ns, can.Message)`` of the raw CAN channels, decoded by the
  one CAN-frame codec (:mod:`gateway.log.canframe`).
- :func:`read_messages`: messages decoded from JSON (:class:`LoggedMessage`), in log-time order;
  :func:`to_dataclass` rebuilds a sample.
- :func:`readable`: a complete version of a file (itself, or a recovered copy of a truncated one).

A truncated or corrupt file raises :class:`~gateway.log.errors.McapFileError` naming
``bsc recover``; ``readable`` recovers a truncated one on its own, after one warning line.
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import struct
import tempfile
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any, NamedTuple

from isal.isal_zlib import crc32   # CRC-32 as zlib computes it, about 6x faster (ISA-L)

from gateway.log.canframe import can_frame_from_json, can_frame_from_record
from gateway.log.errors import LogError, McapFileError
from gateway.log.names import CAN_SCHEMA_NAME, CAN_TOPIC_PREFIX, MAGIC
from gateway.log.scan import PARSE_ERRORS, check_footer, recover, scan_header


Warn = Callable[[str], None]


def no_warn(_: str) -> None:
    pass


@contextlib.contextmanager
def readable(path: str | os.PathLike[str], warn: Warn = no_warn) -> Iterator[Path]:
    """A complete version of ``path``: itself, or (truncated: a killed recorder, a full disk) a
    temporary recovered copy, after one warning line. Foreign / empty files raise
    :class:`McapFileError`."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if path.is_dir():
        raise IsADirectoryError(f"{path}: is a directory, not an MCAP file")
    scan_header(path)
    ok, why = check_footer(path)
    if ok:
        yield path
        return
    with tempfile.TemporaryDirectory(prefix="bsc-replay-") as tmp:
        report = recover(path, Path(tmp) / path.name)
        if report.messages == 0:
            raise LogError(f"{path}: truncated ({why}) and no complete message survives")
        warn(f"{path} is truncated ({report.stop_reason or why}); replaying the "
             f"{report.messages} messages recovered from it")
        yield report.output


class _Msg(NamedTuple):
    log_time: int
    data: bytes


_RECORD = struct.Struct("<BQ")


_MESSAGE_HEAD = struct.Struct("<HIQQ")        # channel id, sequence, log time, publish time


_OP_CHANNEL, _OP_MESSAGE = 0x04, 0x05


def _chunk_messages(chunk, chans: Mapping[int, Any]) -> list[tuple[int, int, bytes]] | None:
    """``(channel id, log time, data)`` of every message of a chunk, parsed with ``struct``
    (the library builds a Python record object per message, the slowest part of a replay).
    ``None`` when the chunk needs the library: other compression, or a channel not yet known.
    CRC and decompression errors raise as the library's would."""
    if chunk.compression == "zstd":
        import zstandard

        data = zstandard.ZstdDecompressor().decompress(
            chunk.data, max_output_size=chunk.uncompressed_size)
    elif chunk.compression == "":
        data = chunk.data
    else:
        return None
    if len(data) != chunk.uncompressed_size:
        raise ValueError(f"chunk decompressed to {len(data)} bytes, "
                         f"{chunk.uncompressed_size} announced")
    if chunk.uncompressed_crc and crc32(data) != chunk.uncompressed_crc:
        raise ValueError("chunk CRC mismatch")
    out = []
    append = out.append
    rec_unpack = _RECORD.unpack_from
    head_unpack = _MESSAGE_HEAD.unpack_from
    off, end = 0, len(data)
    while off < end:
        op, length = rec_unpack(data, off)
        body = off + 9
        off = body + length
        if off > end:
            raise ValueError("record runs past the end of its chunk")
        if op == _OP_MESSAGE:
            cid, _, t, _ = head_unpack(data, body)
            if cid not in chans:
                return None
            append((cid, t, data[body + 22:off]))
        elif op == _OP_CHANNEL and _CHANNEL_ID.unpack_from(data, body)[0] not in chans:
            return None
    return out


_CHANNEL_ID = struct.Struct("<H")


class _ChunkHead(NamedTuple):
    """The fields of a Chunk record (``mcap.records.Chunk`` without building one)."""

    message_start_time: int
    message_end_time: int
    uncompressed_size: int
    uncompressed_crc: int
    compression: str
    data: bytes


_CHUNK_FIXED = struct.Struct("<QQQII")        # start, end, uncompressed size, crc, compression length


_U64 = struct.Struct("<Q")


_OP_MESSAGE_INDEX, _OP_CHUNK, _OP_DATA_END, _OP_FOOTER = 0x07, 0x06, 0x0F, 0x02


_RECORD_LIMIT = 4 * 2 ** 30                   # the mcap StreamReader's default record size limit


def _chunk_head(body: bytes) -> _ChunkHead:
    start, end, size, crc, clen = _CHUNK_FIXED.unpack_from(body, 0)
    compression = str(body[32:32 + clen], "utf-8")
    (dlen,) = _U64.unpack_from(body, 32 + clen)
    return _ChunkHead(start, end, size, crc, compression, body[40 + clen:40 + clen + dlen])


def iter_file_order(path: str | os.PathLike[str], want: Callable[[str, str], bool] | None = None,
                    start_ns: int | None = None, end_ns: int | None = None
                    ) -> Iterator[tuple[str, str, Any]]:
    """``(topic, schema_name, message)`` of a complete log in FILE (= recording) order;
    ``message`` has ``log_time`` (ns) and ``data`` (bytes).

    ``want(topic, schema_name)`` selects channels; ``[start_ns, end_ns)`` selects log times
    (chunks wholly outside are skipped without decompressing them).

    Records are walked here rather than by the library's StreamReader: message index records
    (two integers per message, after every chunk) are skipped unread, chunks are parsed with
    ``struct``; every other record (rare) goes through the library's parser.
    """

    from mcap.opcode import Opcode
    from mcap.records import Channel, Chunk, DataEnd, Footer, Message, Schema
    from mcap.stream_reader import StreamReader, breakup_chunk

    path = Path(path)
    schemas: dict[int, str] = {}
    chans: dict[int, tuple[str, str] | None] = {}
    known_ops = {int(op) for op in Opcode}

    def register(rec) -> None:
        if isinstance(rec, Channel):
            name = schemas.get(rec.schema_id, "")
            chans[rec.id] = (rec.topic, name) if want is None or want(rec.topic, name) else None
        elif isinstance(rec, Schema):
            schemas[rec.id] = rec.name

    def corrupt(exc) -> McapFileError:
        return McapFileError(f"{path}: corrupt data ({exc}); `bsc recover {path}` "
                             "copies everything that is intact")

    with open(path, "rb") as f:
        # Channel and schema records live inside chunks (written before first use): take them
        # from the summary, so that a chunk skipped for its time range cannot hide one.
        try:
            from mcap.reader import SeekingReader

            summary = SeekingReader(f).get_summary()
        except PARSE_ERRORS as exc:
            raise McapFileError(f"{path}: corrupt summary ({exc}); `bsc recover {path}` "
                                "rebuilds it") from exc
        if summary is not None:
            for sc in summary.schemas.values():
                register(sc)
            for ch in summary.channels.values():
                register(ch)
        f.seek(0)
        if f.read(len(MAGIC)) != MAGIC:
            raise corrupt("bad magic bytes")
        read, unpack_head = f.read, _RECORD.unpack
        while True:
            head = read(9)
            if len(head) < 9:
                raise corrupt("end of file before the data end record")
            op, length = unpack_head(head)
            if length > _RECORD_LIMIT:
                raise corrupt(f"record of {length} bytes")
            if op == _OP_MESSAGE_INDEX:
                f.seek(length, 1)
                continue
            body = read(length)
            if len(body) < length:
                raise corrupt("end of file inside a record")
            if op == _OP_DATA_END or op == _OP_FOOTER:
                return
            try:
                if op == _OP_CHUNK:
                    rec = _chunk_head(body)
                    if ((end_ns is not None and rec.message_start_time >= end_ns)
                            or (start_ns is not None and rec.message_end_time < start_ns)):
                        continue
                    fast = _chunk_messages(rec, chans)
                    if fast is not None:
                        for cid, t, data in fast:
                            ch = chans[cid]
                            if (ch is not None and (start_ns is None or t >= start_ns)
                                    and (end_ns is None or t < end_ns)):
                                yield ch[0], ch[1], _Msg(t, data)
                        continue
                    inner = breakup_chunk(Chunk(**rec._asdict()), validate_crc=True)
                elif op not in known_ops:
                    continue                        # unknown record types are skipped
                else:
                    one = StreamReader(io.BytesIO(head + body), skip_magic=True, emit_chunks=True,
                                       record_size_limit=None).records
                    inner = (next(one),)
            except PARSE_ERRORS as exc:
                raise corrupt(exc) from exc
            for r in inner:
                if isinstance(r, Message):
                    ch = chans.get(r.channel_id)
                    t = r.log_time
                    if (ch is not None and (start_ns is None or t >= start_ns)
                            and (end_ns is None or t < end_ns)):
                        yield ch[0], ch[1], r
                elif isinstance(r, (DataEnd, Footer)):
                    return
                else:
                    register(r)


class _LoggedRecord(NamedTuple):
    log_time: int
    data: bytes
    publish_time: int
    sequence: int


def iter_messages(path: str | os.PathLike[str], topics: Iterable[str] | str | None = None, *,
                  want: Callable[[str, str], bool] | None = None, start_ns: int | None = None,
                  end_ns: int | None = None, log_time_order: bool = False
                  ) -> Iterator[tuple[str, str, Any]]:
    """``(topic, schema name, message)`` of a complete log, ``message`` with ``log_time`` (ns)
    and ``data`` (bytes): the channels of ``topics`` (all when None) that ``want(topic, schema)``
    takes, with log times in ``[start_ns, end_ns)``; in file (= recording) order, or with
    ``log_time_order`` in log-time order (ties in file order). A truncated file raises
    :class:`McapFileError` (``readable`` recovers one first); corrupt data too, naming
    ``bsc recover``."""
    names = None if topics is None else {topics} if isinstance(topics, str) else set(topics)

    def pick(topic: str, schema: str) -> bool:
        return (names is None or topic in names) and (want is None or want(topic, schema))

    if not log_time_order:
        yield from iter_file_order(path, pick, start_ns, end_ns)
        return
    from mcap.reader import SeekingReader

    path = Path(path)
    scan_header(path)
    ok, why = check_footer(path)
    if not ok:
        raise McapFileError(f"{path}: file is truncated ({why}); run `bsc recover {path}` first")
    if start_ns is not None and end_ns is not None and end_ns <= start_ns:
        return
    with open(path, "rb") as f:
        try:
            reader = SeekingReader(f, validate_crcs=True)
            summary = reader.get_summary()
            chosen = None
            if summary is not None:
                chosen = [c.topic for c in summary.channels.values()
                          if pick(c.topic, summary.schemas[c.schema_id].name if c.schema_id in summary.schemas
                                  else "")]
                if not chosen:
                    return
            items = reader.iter_messages(topics=chosen, log_time_order=True, starting_at=start_ns,
                                         ending_before=end_ns)
            while True:
                item = next(items, None)
                if item is None:
                    return
                schema, channel, msg = item
                name = schema.name if schema else ""
                if chosen is None and not pick(channel.topic, name):
                    continue
                yield channel.topic, name, _LoggedRecord(msg.log_time, msg.data, msg.publish_time, msg.sequence)
        except PARSE_ERRORS as exc:          # CRC mismatch, bad zstd frame
            raise McapFileError(f"{path}: corrupt data ({exc}); `bsc recover {path}` "
                                "copies everything that is intact") from exc


def json_record(path: Path, topic: str, data: bytes) -> dict[str, Any]:
    try:
        obj = json.loads(data)
    except ValueError as exc:
        raise McapFileError(f"{path}: {topic}: a message is not JSON ({exc})") from None
    if not isinstance(obj, dict):
        raise McapFileError(f"{path}: {topic}: a message is not a JSON object")
    return obj


def iter_can_frames(path: str | os.PathLike[str], *, buses: Iterable[str] | None = None,
                    can_ids: Iterable[int] | None = None, start_ns: int | None = None,
                    end_ns: int | None = None, log_time_order: bool = False) -> Iterator[tuple[str, int, Any]]:
    """``(bus, t_ns, can.Message)`` of the raw CAN channels (``/can/<bus>``, of ``buses``: all when
    None; of ``can_ids``: all when None), in recording order or with ``log_time_order`` in
    log-time order (:func:`iter_messages`).

    ``t_ns`` is the log time (the frame's own timestamp); ``msg.timestamp`` is ``t_ns / 1e9``,
    which rounds back to exactly ``t_ns``.
    """
    bus_set = None if buses is None else {CAN_TOPIC_PREFIX + b for b in buses}
    id_set = None if can_ids is None else frozenset(can_ids)

    def want(topic: str, schema: str) -> bool:
        return (schema == CAN_SCHEMA_NAME and topic.startswith(CAN_TOPIC_PREFIX)
                and (bus_set is None or topic in bus_set))

    cut = len(CAN_TOPIC_PREFIX)
    buses_of: dict[str, str] = {}
    for topic, _, m in iter_messages(path, want=want, start_ns=start_ns, end_ns=end_ns,
                                     log_time_order=log_time_order):
        bus = buses_of.get(topic)
        if bus is None:
            bus = buses_of[topic] = topic[cut:]
        try:
            msg = can_frame_from_json(m.data, id_set)
        except ValueError as exc:
            raise McapFileError(f"{path}: {topic}: a frame record is {exc}") from None
        if msg is not None:
            yield bus, m.log_time, msg


@dataclasses.dataclass(frozen=True, slots=True)
class LoggedMessage:
    """One message read back: ``data`` is the decoded JSON record."""

    topic: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    schema_name: str
    data: dict[str, Any]

    def can_message(self):
        """The python-can ``Message`` of a raw CAN record (``bsc.CanFrame`` schema)."""
        if self.schema_name != CAN_SCHEMA_NAME:
            raise TypeError(f"{self.topic}: schema {self.schema_name} is not {CAN_SCHEMA_NAME}")
        return can_frame_from_record(self.data)


def read_messages(path: str | os.PathLike[str], topics: Iterable[str] | str | None = None, *,
                  start_s: float | None = None, duration_s: float | None = None,
                  start_ns: int | None = None, end_ns: int | None = None) -> Iterator[LoggedMessage]:
    """Messages of ``topics`` (all when None) in log-time order, JSON-decoded
    (:func:`iter_messages` with ``log_time_order``).

    Time window: absolute ``[start_ns, end_ns)`` in the log time base, or ``start_s`` seconds
    after the file's first message (of any topic) and ``duration_s`` long.
    """
    path = Path(path)
    if start_s is not None or duration_s is not None:
        from gateway.log.context import read_summary

        summary = read_summary(path)
        first = summary.start_ns if summary is not None and summary.start_ns is not None else 0
        base = (first if start_ns is None else start_ns) + (round(start_s * 1e9) if start_s is not None else 0)
        start_ns = base
        if duration_s is not None:
            end_ns = base + round(duration_s * 1e9)
    for topic, schema, m in iter_messages(path, topics, start_ns=start_ns, end_ns=end_ns, log_time_order=True):
        try:
            data = json.loads(m.data)
        except ValueError as exc:
            raise McapFileError(f"{path}: {topic}: a message is not JSON ({exc}); `bsc recover {path}` "
                                "copies everything that is intact") from exc
        yield LoggedMessage(topic, m.log_time, m.publish_time, m.sequence, schema, data)



def to_dataclass(cls: type, record: dict[str, Any]):
    """Rebuild a (frozen) sample dataclass from its decoded record: JSON lists become tuples
    where the field is a tuple, as in :mod:`drivers.samples`."""
    import typing

    from gateway.log.schema import pair_value_type, pairs_from_json

    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in record:
            continue
        value = record[f.name]
        if isinstance(value, list) and pair_value_type(hints.get(f.name)):
            value = pairs_from_json(value)
        elif isinstance(value, list) and typing.get_origin(hints.get(f.name)) is tuple:
            value = tuple(value)
        kwargs[f.name] = value
    return cls(**kwargs)
