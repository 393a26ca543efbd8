"""Walk a session log record by record: inspect it (``bsc info``) and recover what is intact.

- :func:`scan` walks a file record by record (the mcap library's record-level reader), so it
  works on a file cut short by a crash or a full disk and stops cleanly where it was cut. A
  corrupt region in the middle is passed over: the walk resumes at the next chunk that is whole
  and passes its CRC, and the region is reported (``ScanResult.skipped``). Channels whose
  defining chunk was lost are taken from the summary when the file still has a valid one.
- :func:`inspect` is what ``bsc info`` prints: duration, channels, rates, gaps, metadata,
  attachments, and whether the file is complete (valid footer and summary) or truncated.
- :func:`recover` rewrites every complete record of a truncated file into a valid one.

Reading a complete log is :mod:`gateway.log.reader`'s.

Bad input (empty, foreign, corrupt header) raises :class:`McapFileError`, a ``ValueError`` with
one readable line that names the file.
"""
from __future__ import annotations

import dataclasses
import io
import json
import os
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

from isal.isal_zlib import crc32   # CRC-32 as zlib computes it, about 6x faster (ISA-L)
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import (Attachment, Channel, Chunk, DataEnd, Footer, Header, Message,
                          Metadata, Schema)
from mcap.stream_reader import MAGIC_SIZE, StreamReader, breakup_chunk

from gateway.log.errors import McapFileError

try:
    from zstandard import ZstdError as _ZstdError
except ImportError:  # pragma: no cover - zstandard ships with mcap's recommended extras
    _ZstdError = McapError

from gateway.log.names import MAGIC

_RECORD_HEADER = struct.Struct("<BQ")          # opcode, length
_FOOTER_SIZE = 1 + 8 + 8 + 8 + 4               # opcode, length, summary start/offset, crc
_KNOWN_OPCODES = {int(op) for op in Opcode}
# Anything a damaged record can throw while the library parses it.
PARSE_ERRORS = (McapError, struct.error, ValueError, KeyError, IndexError, OverflowError,
                 MemoryError, _ZstdError)




@dataclasses.dataclass(slots=True)
class ScanResult:
    """What a record-level pass over a file found.

    ``data_complete``: the data section ended with a DataEnd record (the writer finished).
    ``stop_reason``: why the pass stopped early ("" when it did not); ``stop_offset`` is the
    byte offset of the first record not read. ``chunks_skipped``: complete chunks whose content
    was corrupt (CRC or decompression error), so their messages are lost.
    """

    path: Path
    size: int
    header: Header | None = None
    schemas: dict[int, Schema] = dataclasses.field(default_factory=dict)
    channels: dict[int, Channel] = dataclasses.field(default_factory=dict)
    metadata: list[Metadata] = dataclasses.field(default_factory=list)
    attachments: list[Attachment] = dataclasses.field(default_factory=list)
    message_count: int = 0
    orphan_messages: int = 0
    chunks: int = 0
    chunks_skipped: int = 0
    data_complete: bool = False
    stop_reason: str = ""
    stop_offset: int = 0
    # (start, end, why) of every byte range passed over: a corrupt chunk, or unreadable bytes up to
    # the next chunk that is whole and passes its CRC
    skipped: list[tuple[int, int, str]] = dataclasses.field(default_factory=list)
    announced: set = dataclasses.field(default_factory=set)     # ("s"|"c", id) given to on_record

    @property
    def bytes_skipped(self) -> int:
        return sum(b - a for a, b, _ in self.skipped)

    def damage(self, limit: int = 3) -> str:
        """The skipped regions in words ("" when none), the first ``limit`` with their offsets."""
        if not self.skipped:
            return ""
        where = ", ".join(f"bytes {a}-{b} ({why})" for a, b, why in self.skipped[:limit])
        more = f", and {len(self.skipped) - limit} more" if len(self.skipped) > limit else ""
        return (f"{len(self.skipped)} damaged region(s) skipped, {human_size(self.bytes_skipped)} "
                f"({self.chunks_skipped} corrupt chunk(s)): {where}{more}")


def scan(path: str | os.PathLike[str],
         on_message: Callable[[Channel, Message], None] | None = None,
         on_record: Callable[[Any], None] | None = None, *,
         header_only: bool = False) -> ScanResult:
    """Walk the data section of ``path`` in file order, calling ``on_message`` per message.

    ``on_record`` sees every schema, channel, metadata, attachment and message record in file
    order (what :func:`recover` copies). Raises :class:`McapFileError` when the file is not MCAP
    at all (empty, wrong magic, no header); stops cleanly at a truncation.
    """
    path = Path(path)
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        result = ScanResult(path=path, size=size)
        if size == 0:
            raise McapFileError(f"{path}: empty file")
        magic = f.read(MAGIC_SIZE)
        if not MAGIC.startswith(magic):
            raise McapFileError(f"{path}: not an MCAP file (bad magic bytes {magic[:8]!r})")
        if len(magic) < MAGIC_SIZE:
            raise McapFileError(f"{path}: truncated inside the MCAP magic ({size} bytes)")
        offset = MAGIC_SIZE
        if not header_only:
            _preload_summary(result, path)

        # the end of the last record that proved itself (a chunk whose CRC passed): a record after
        # it with a damaged length (no CRC covers it) may have moved the walk into the middle of
        # what followed, so a corrupt record is looked for, and reported, from here
        verified = MAGIC_SIZE

        def bad(why: str) -> bool:
            """Pass over a corrupt record: True to go on from the next good chunk, False to stop."""
            nonlocal offset, verified
            start = min(offset, verified)
            nxt = _resync(f, start + 1, size) if result.header is not None else None
            if nxt is None:
                _stop(result, start, why)
                return False
            result.skipped.append((start, nxt, why))
            offset = verified = nxt
            f.seek(nxt)
            return True

        while True:
            head = f.read(_RECORD_HEADER.size)
            if len(head) < _RECORD_HEADER.size:
                _stop(result, offset, "end of file" if not head else "incomplete record header")
                break
            opcode, length = _RECORD_HEADER.unpack(head)
            if opcode not in _KNOWN_OPCODES and opcode < 0x80:
                if bad(f"invalid record opcode 0x{opcode:02x} (corrupt data)"):
                    continue
                break
            if length > size - offset - _RECORD_HEADER.size:
                name = _opcode_name(opcode)
                if bad(f"incomplete {name} record ({length} bytes announced, "
                       f"{size - offset - _RECORD_HEADER.size} left)"):
                    continue
                break
            body = f.read(length)
            try:
                record = next(iter(StreamReader(io.BytesIO(head + body), skip_magic=True,
                                                emit_chunks=True,
                                                record_size_limit=length).records), None)
            except PARSE_ERRORS as exc:
                if bad(f"corrupt {_opcode_name(opcode)} record ({exc})"):
                    continue
                break
            if result.header is None:
                if not isinstance(record, Header):
                    raise McapFileError(f"{path}: not an MCAP log (no header record)")
                result.header = record
                if header_only:
                    return result
            elif isinstance(record, Chunk):
                result.chunks += 1
                end = offset + _RECORD_HEADER.size + length
                why = ""
                try:
                    inner = breakup_chunk(record, validate_crc=True)
                    look = offset + _RECORD_HEADER.size + _chunk_length(record)   # past its fields
                except PARSE_ERRORS as exc:
                    result.chunks_skipped += 1
                    inner, look, why = [], offset + 1, f"corrupt chunk: {exc}"
                # No CRC covers a chunk's length: damaged, it can reach over whole chunks that
                # follow (a chunk of 16 KiB announced 1.5 MiB and took 560 intact chunks with it).
                # A chunk that fails its CRC, or announces more than its fields use (a writer's
                # later fields, or damage), is searched for the first whole chunk inside what it
                # announces, and the walk goes on from there.
                nxt = _resync(f, look, size, stop=end) if look < end else None
                for rec in inner:
                    _take(result, rec, on_message, on_record)
                if why or nxt is not None:
                    start = min(offset, verified) if why else look    # from the last proven record
                    result.skipped.append((start, end if nxt is None else nxt,
                                           why or f"chunk length {length} reached over whole chunks (damaged)"))
                verified = end if nxt is None else nxt
                if nxt is not None:
                    offset = nxt
                    f.seek(nxt)
                    continue
                f.seek(end)
            elif isinstance(record, DataEnd):
                result.data_complete = True
                offset += _RECORD_HEADER.size + length
                result.stop_offset = offset
                break
            elif isinstance(record, Footer):
                # A footer without DataEnd: still a finished file (DataEnd is optional-ish in
                # old writers); treat the data as complete.
                result.data_complete = True
                result.stop_offset = offset
                break
            elif record is not None:
                _take(result, record, on_message, on_record)
            offset += _RECORD_HEADER.size + length
    if result.header is None:
        if result.stop_reason.startswith("invalid"):
            raise McapFileError(f"{path}: not an MCAP log (no header record)")
        raise McapFileError(f"{path}: truncated before the first record ({size} bytes)")
    return result


def _stop(result: ScanResult, offset: int, reason: str) -> None:
    result.stop_reason = reason
    result.stop_offset = offset


def _take(result: ScanResult, rec: Any, on_message, on_record) -> None:
    if isinstance(rec, Message):
        channel = result.channels.get(rec.channel_id)
        if channel is None:
            result.orphan_messages += 1
            return
        result.message_count += 1
        if ("c", channel.id) not in result.announced:     # known from the summary only: its chunk was lost
            schema = result.schemas.get(channel.schema_id)
            if schema is not None:
                _take(result, schema, None, on_record)
            _take(result, channel, None, on_record)
        if on_message is not None:
            on_message(channel, rec)
    elif isinstance(rec, Schema):
        if ("s", rec.id) in result.announced:
            return
        result.announced.add(("s", rec.id))
        result.schemas[rec.id] = rec
    elif isinstance(rec, Channel):
        if ("c", rec.id) in result.announced:
            return
        result.announced.add(("c", rec.id))
        result.channels[rec.id] = rec
    elif isinstance(rec, Metadata):
        result.metadata.append(rec)
    elif isinstance(rec, Attachment):
        result.attachments.append(rec)
    else:
        return                               # indexes, statistics: rebuilt by any writer
    if on_record is not None:
        on_record(rec)


def _preload_summary(result: ScanResult, path: Path) -> None:
    """Schemas and channels from the summary of a file that still has a valid one: a message
    whose channel's defining chunk was lost in a damaged region keeps its channel."""
    if not check_footer(path)[0]:
        return
    try:
        from mcap.reader import SeekingReader

        with open(path, "rb") as f:
            summary = SeekingReader(f, validate_crcs=True).get_summary()
    except PARSE_ERRORS + (OSError,):
        return
    if summary is not None:
        result.schemas.update(summary.schemas)
        result.channels.update(summary.channels)


def _chunk_length(chunk: Chunk) -> int:
    """The bytes a chunk record's fields take (its record's length without trailing bytes)."""
    return _CHUNK_FIXED.size + len(chunk.compression.encode()) + 8 + len(chunk.data)


_CHUNK_FIXED = struct.Struct("<QQQII")     # message start/end time, uncompressed size, crc, compression length
_RESYNC_BLOCK = 1 << 20


def _resync(f, start: int, size: int, stop: int | None = None) -> int | None:
    """The offset of the first chunk record at or after ``start`` (and before ``stop``) that is
    whole, decompresses and passes its CRC (a chunk written without a CRC cannot be told from
    noise: it is not taken)."""
    stop = size - _RECORD_HEADER.size if stop is None else min(stop, size - _RECORD_HEADER.size)
    pos = start
    while pos < stop:
        f.seek(pos)
        buf = f.read(_RESYNC_BLOCK + 64)
        i = buf.find(b"\x06")
        while 0 <= i < min(_RESYNC_BLOCK, stop - pos):
            if _chunk_at(f, pos + i, size, buf[i:i + 64]):
                return pos + i
            i = buf.find(b"\x06", i + 1)
        pos += _RESYNC_BLOCK
    return None


def _chunk_at(f, p: int, size: int, peek: bytes) -> bool:
    if len(peek) < _RECORD_HEADER.size + _CHUNK_FIXED.size:
        f.seek(p)
        peek = f.read(64)
        if len(peek) < _RECORD_HEADER.size + _CHUNK_FIXED.size:
            return False
    _, length = _RECORD_HEADER.unpack_from(peek)
    if length < _CHUNK_FIXED.size + 8 or p + _RECORD_HEADER.size + length > size:
        return False
    t0, t1, usize, crc, clen = _CHUNK_FIXED.unpack_from(peek, _RECORD_HEADER.size)
    if t0 > t1 or crc == 0 or clen > 8 or usize > 1 << 34:
        return False
    at = _RECORD_HEADER.size + _CHUNK_FIXED.size
    if len(peek) < at + clen + 8 or peek[at:at + clen] not in (b"", b"zstd", b"lz4"):
        return False
    (n,) = struct.unpack_from("<Q", peek, at + clen)
    if _CHUNK_FIXED.size + clen + 8 + n != length:
        return False
    f.seek(p)
    data = f.read(_RECORD_HEADER.size + length)
    try:
        rec = next(iter(StreamReader(io.BytesIO(data), skip_magic=True, emit_chunks=True,
                                     record_size_limit=length).records), None)
        if not isinstance(rec, Chunk):
            return False
        breakup_chunk(rec, validate_crc=True)
    except PARSE_ERRORS:
        return False
    return True


def _opcode_name(opcode: int) -> str:
    try:
        return Opcode(opcode).name.title().replace("_", "")
    except ValueError:
        return f"0x{opcode:02x}"


def check_footer(path: str | os.PathLike[str]) -> tuple[bool, str]:
    """``(True, "")`` when the file ends with a valid footer, summary and magic; else why not."""
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if size < 2 * MAGIC_SIZE + _FOOTER_SIZE:
            return False, "too short to hold a footer"
        f.seek(size - MAGIC_SIZE)
        if f.read(MAGIC_SIZE) != MAGIC:
            return False, "no closing magic (the writer did not finish)"
        footer_at = size - MAGIC_SIZE - _FOOTER_SIZE
        f.seek(footer_at)
        raw = f.read(_FOOTER_SIZE)
        opcode, length, summary_start, offset_start, crc = struct.unpack("<BQQQI", raw)
        if opcode != Opcode.FOOTER or length != _FOOTER_SIZE - 9:
            return False, "no footer record before the closing magic"
        if summary_start == 0:
            return False, "footer without a summary section"
        if not MAGIC_SIZE <= summary_start < footer_at:
            return False, "footer points outside the file"
        if crc:
            f.seek(summary_start)
            covered = f.read(footer_at + _FOOTER_SIZE - 4 - summary_start)
            if crc32(covered) != crc:
                return False, "summary CRC mismatch"
        return True, ""


# ----------------------------------------------------------------------------- info

@dataclasses.dataclass(slots=True)
class ChannelInfo:
    """Per-topic figures; times in ns of the log time base, gaps in seconds."""

    topic: str
    schema_name: str
    message_encoding: str
    count: int = 0
    first_ns: int | None = None
    last_ns: int | None = None
    max_gap_s: float = 0.0
    max_gap_at_ns: int | None = None
    gaps: list[tuple[int, float]] = dataclasses.field(default_factory=list)
    gaps_total: int = 0
    out_of_order: int = 0

    @property
    def duration_s(self) -> float:
        return 0.0 if self.first_ns is None else (self.last_ns - self.first_ns) / 1e9

    @property
    def rate_hz(self) -> float:
        d = self.duration_s
        return (self.count - 1) / d if d > 0 else 0.0


@dataclasses.dataclass(slots=True)
class LogInfo:
    """What ``bsc info`` reports about one file."""

    path: Path
    size: int
    complete: bool
    status: str                    # "complete" or "truncated: <why>"
    library: str
    profile: str
    message_count: int
    start_ns: int | None
    end_ns: int | None
    channels: list[ChannelInfo]
    metadata: dict[str, dict[str, str]]
    attachments: list[dict[str, Any]]
    gap_threshold_s: float
    chunks: int
    chunks_skipped: int
    orphan_messages: int
    stop_reason: str
    stop_offset: int
    skipped: list[tuple[int, int, str]] = dataclasses.field(default_factory=list)   # damaged byte ranges
    bytes_skipped: int = 0

    @property
    def duration_s(self) -> float:
        return 0.0 if self.start_ns is None else (self.end_ns - self.start_ns) / 1e9

    def to_json(self) -> dict[str, Any]:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d["path"] = str(self.path)
        d["duration_s"] = self.duration_s
        d["channels"] = [dict({f.name: getattr(c, f.name) for f in dataclasses.fields(c)},
                              duration_s=c.duration_s, rate_hz=c.rate_hz)
                         for c in self.channels]
        return d


MAX_GAPS_KEPT = 1000


def inspect(path: str | os.PathLike[str], gap_threshold_s: float = 1.0) -> LogInfo:
    """Scan ``path`` once and summarise it (see :class:`LogInfo`).

    Gaps are measured per channel between consecutive messages in file order; a message older
    than its channel's newest so far counts in ``out_of_order`` instead. At most
    ``MAX_GAPS_KEPT`` gaps above the threshold are listed per channel (``gaps_total`` counts all).
    """
    per: dict[int, ChannelInfo] = {}
    threshold_ns = gap_threshold_s * 1e9

    def on_message(channel: Channel, msg: Message) -> None:
        info = per.get(channel.id)
        if info is None:
            schema = result_schemas.get(channel.schema_id)
            info = per[channel.id] = ChannelInfo(channel.topic, schema.name if schema else "",
                                                 channel.message_encoding)
        t = msg.log_time
        info.count += 1
        if info.last_ns is None:
            info.first_ns = info.last_ns = t
            return
        if t < info.last_ns:
            info.out_of_order += 1
            info.first_ns = min(info.first_ns, t)
            return
        gap = t - info.last_ns
        if gap > info.max_gap_s * 1e9:
            info.max_gap_s = gap / 1e9
            info.max_gap_at_ns = info.last_ns
        if gap > threshold_ns:
            info.gaps_total += 1
            if len(info.gaps) < MAX_GAPS_KEPT:
                info.gaps.append((info.last_ns, gap / 1e9))
        info.last_ns = t

    result_schemas: dict[int, Schema] = {}

    def on_record(rec: Any) -> None:
        if isinstance(rec, Schema):
            result_schemas[rec.id] = rec

    result = scan(path, on_message=on_message, on_record=on_record)
    complete, why = (check_footer(path) if result.data_complete
                     else (False, result.stop_reason))
    if result.skipped:
        status = f"damaged: {result.damage()}" + ("" if result.data_complete else f"; then truncated: {why}")
        complete = False
    else:
        status = "complete" if complete else f"truncated: {why}"
    for channel in result.channels.values():     # channels with no messages are listed too
        if channel.id not in per:
            schema = result.schemas.get(channel.schema_id)
            per[channel.id] = ChannelInfo(channel.topic, schema.name if schema else "",
                                          channel.message_encoding)
    channels = sorted(per.values(), key=lambda c: c.topic)
    starts = [c.first_ns for c in channels if c.first_ns is not None]
    ends = [c.last_ns for c in channels if c.last_ns is not None]
    return LogInfo(
        path=result.path, size=result.size, complete=complete,
        status=status,
        library=result.header.library, profile=result.header.profile,
        message_count=result.message_count, start_ns=min(starts) if starts else None,
        end_ns=max(ends) if ends else None, channels=channels,
        metadata={m.name: dict(m.metadata) for m in result.metadata},
        attachments=[{"name": a.name, "media_type": a.media_type, "size": len(a.data),
                      "log_time_ns": a.log_time} for a in result.attachments],
        gap_threshold_s=gap_threshold_s, chunks=result.chunks,
        chunks_skipped=result.chunks_skipped, orphan_messages=result.orphan_messages,
        stop_reason=result.stop_reason, stop_offset=result.stop_offset,
        skipped=list(result.skipped), bytes_skipped=result.bytes_skipped)


# ----------------------------------------------------------------------------- recover

@dataclasses.dataclass(frozen=True, slots=True)
class RecoverReport:
    source: Path
    output: Path
    was_complete: bool
    messages: int
    channels: int
    metadata: int
    attachments: int
    chunks_skipped: int
    orphan_messages: int
    stop_reason: str
    stop_offset: int
    bytes_dropped: int
    damage: str = ""                       # ScanResult.damage(): the regions passed over, in words
    bytes_skipped: int = 0


def recover(source: str | os.PathLike[str], output: str | os.PathLike[str] | None = None,
            overwrite: bool = False) -> RecoverReport:
    """Rewrite every complete record of ``source`` into a valid MCAP file ``output``: up to where
    it was cut, and past every damaged region (:func:`scan` resumes at the next good chunk).

    Schemas, channels, metadata, attachments and messages are copied in file order (message
    times, sequence numbers and bytes unchanged; schema and channel ids may be renumbered).
    A ``bsc.recover`` metadata record notes the source and where it was cut. The output is
    written to a temporary name and renamed, so a failed recovery leaves no half file.
    Default output: ``<stem>.recovered.mcap`` beside the source.
    """
    from mcap.writer import Writer

    source = Path(source)
    output = Path(output) if output is not None else source.with_name(
        source.stem + ".recovered" + (source.suffix or ".mcap"))
    if output.exists() and output.resolve() == source.resolve():
        raise McapFileError(f"{output}: output would overwrite the file being recovered")
    if output.exists() and not overwrite:
        raise FileExistsError(f"{output} exists")
    header = scan_header(source)
    tmp = output.with_name(f".{output.name}.{os.getpid()}.tmp")
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    counts = {"messages": 0, "metadata": 0, "attachments": 0}
    try:
        with open(tmp, "wb") as f:
            writer = Writer(f, chunk_size=1 << 20)
            writer.start(profile=header.profile, library=header.library)

            def on_record(rec: Any) -> None:
                if isinstance(rec, Schema):
                    schema_ids[rec.id] = writer.register_schema(rec.name, rec.encoding, rec.data)
                elif isinstance(rec, Channel):
                    channel_ids[rec.id] = writer.register_channel(
                        rec.topic, rec.message_encoding, schema_ids.get(rec.schema_id, 0),
                        dict(rec.metadata))
                elif isinstance(rec, Message):
                    writer.add_message(channel_ids[rec.channel_id], rec.log_time, rec.data,
                                       rec.publish_time, rec.sequence)
                    counts["messages"] += 1
                elif isinstance(rec, Metadata):
                    writer.add_metadata(rec.name, dict(rec.metadata))
                    counts["metadata"] += 1
                elif isinstance(rec, Attachment):
                    writer.add_attachment(rec.create_time, rec.log_time, rec.name,
                                          rec.media_type, rec.data)
                    counts["attachments"] += 1

            result = scan(source, on_record=on_record)
            was_complete = result.data_complete and check_footer(source)[0]
            writer.add_metadata("bsc.recover", {
                "source": source.name,
                "source_size": str(result.size),
                "source_complete": str(was_complete).lower(),
                "stop_reason": result.stop_reason,
                "stop_offset": str(result.stop_offset),
                "chunks_skipped": str(result.chunks_skipped),
                "bytes_skipped": str(result.bytes_skipped),
                "skipped_regions": json.dumps(result.skipped[:1000]),
                "messages": str(counts["messages"]),
            })
            writer.finish()
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, output)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return RecoverReport(
        source=source, output=output, was_complete=was_complete, messages=counts["messages"],
        channels=len(channel_ids), metadata=counts["metadata"],
        attachments=counts["attachments"], chunks_skipped=result.chunks_skipped,
        orphan_messages=result.orphan_messages, stop_reason=result.stop_reason,
        stop_offset=result.stop_offset,
        bytes_dropped=0 if result.data_complete else result.size - result.stop_offset,
        damage=result.damage(), bytes_skipped=result.bytes_skipped)


def scan_header(path: str | os.PathLike[str]) -> Header:
    """The header record of ``path``; :class:`McapFileError` if it is not an MCAP log."""
    return scan(path, header_only=True).header


# ----------------------------------------------------------------------------- replay


def human_size(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n} B"  # pragma: no cover


__all__ = ["ChannelInfo", "LogInfo", "McapFileError", "PARSE_ERRORS", "RecoverReport", "ScanResult",
           "check_footer", "human_size", "inspect", "recover", "scan", "scan_header"]
