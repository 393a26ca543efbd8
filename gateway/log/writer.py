"""The recorder's MCAP writer: chunks that the caller ends, built without an object per message.

The same file as ``mcap.writer.Writer`` (mcap 1.x) writes for the same calls, byte for byte
(``tests/gateway/log/test_mcapwriter.py`` compares them), with two differences of use:

- a chunk ends only when the caller says (:meth:`McapWriter.end_chunk`), so the recorder knows
  exactly which messages are on disk;
- :meth:`McapWriter.add_message` appends one message record to the chunk buffer with one
  ``struct.pack`` (about 2.5x faster than ``Writer.add_message``, which builds a ``Message``
  record and a builder call per field), and :meth:`McapWriter.add_messages` a whole block of
  them (payloads in one buffer) with one compiled pass, no Python step per message; the message
  indexes are written from arrays (the library's ``MessageIndex.write`` makes two builder calls
  per message).

It is built from the library's public records (``mcap.records``: Header, Chunk, MessageIndex,
ChunkIndex, Statistics, Summary offsets, Footer ...) and ``mcap.data_stream.RecordBuilder``,
never from the library writer's private state. Schemas and channels are written inside the
chunk that first uses them (as the library does) and again in the summary.
"""
from __future__ import annotations

import struct
from collections import defaultdict
from typing import IO, Any

from isal.isal_zlib import crc32   # CRC-32 as zlib computes it, about 6x faster (ISA-L)
import numpy as np
from numba import njit
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (Attachment, AttachmentIndex, Channel, Chunk, ChunkIndex, DataEnd, Footer, Header,
                          MessageIndex, Metadata, MetadataIndex, Schema, Statistics, SummaryOffset)
from mcap.writer import MCAP0_MAGIC, CompressionType

_MESSAGE_HEAD = struct.Struct("<BQHIQQ")     # opcode, record length, channel, sequence, log time, publish time
_MESSAGE = int(Opcode.MESSAGE)
# the same head as a packed numpy record (31 bytes), for blocks of messages
_HEAD_DTYPE = np.dtype([("op", "u1"), ("len", "<u8"), ("channel", "<u2"), ("seq", "<u4"), ("log", "<u8"),
                        ("pub", "<u8")])
_INDEX_HEAD = struct.Struct("<BQHI")         # opcode, record length, channel, records' byte length


@njit(cache=True, nogil=True, _nrt=False)
def _interleave(heads, data, offsets, out) -> None:
    """``out`` = head 0, payload 0, head 1, payload 1, ...: ``heads`` (n, 31) bytes, payload k
    ``data[offsets[k] - offsets[0]:offsets[k + 1] - offsets[0]]``."""
    w = 0
    base = offsets[0]
    for k in range(heads.shape[0]):
        for b in range(heads.shape[1]):
            out[w + b] = heads[k, b]
        w += heads.shape[1]
        for b in range(offsets[k] - base, offsets[k + 1] - base):
            out[w] = data[b]
            w += 1


def _index_record(cid: int, times: np.ndarray, offsets: np.ndarray) -> bytes:
    """A MessageIndex record, the bytes ``mcap.records.MessageIndex.write`` gives."""
    body = np.empty((len(times), 2), dtype="<u8")
    body[:, 0] = times
    body[:, 1] = offsets
    n = 16 * len(times)
    return _INDEX_HEAD.pack(int(Opcode.MESSAGE_INDEX), 6 + n, cid, n) + body.tobytes()


ZSTD_LEVEL = 1
"""zstd level of the chunks. On this project's logs (chunks of about 130 KB of JSON records) level
1 compresses faster than the library's default 3 and smaller: a demo log's 56 MB of chunks in
54 against 81 ms, ratio 7.29 against 6.90, and they decompress in 35 against 46 ms (2026-11-26)."""


class McapWriter:
    """An MCAP file on ``stream`` (any binary stream with ``write`` and ``tell``)."""

    def __init__(self, stream: IO[bytes], compression: CompressionType = CompressionType.ZSTD,
                 zstd_level: int = ZSTD_LEVEL):
        if compression == CompressionType.ZSTD:
            import zstandard

            self._compress = zstandard.ZstdCompressor(level=zstd_level).compress
            self._compression = "zstd"
        elif compression == CompressionType.LZ4:
            import lz4.frame

            self._compress = lz4.frame.compress
            self._compression = "lz4"
        else:
            self._compress = None
            self._compression = ""
        self._stream = stream
        self._rb = RecordBuilder()                      # records outside chunks
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._chunk_indexes: list[ChunkIndex] = []
        self._attachment_indexes: list[AttachmentIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._counts: defaultdict[int, int] = defaultdict(int)
        self._stats = dict(message_count=0, message_start_time=0, message_end_time=0, chunk_count=0,
                           attachment_count=0, metadata_count=0)
        # the chunk being built
        self._chunk = bytearray()
        self._index: dict[int, list[tuple[int, int]]] = {}
        self._blocks: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}   # add_messages' (times, offsets)
        self._chunk_messages = 0
        self.messages_in_chunks = 0                     # messages of the chunk records written so far
        self._chunk_start = self._chunk_end = 0

    # --- the file's start and its definitions
    def start(self, profile: str = "", library: str = "") -> None:
        self._stream.write(MCAP0_MAGIC)
        Header(profile=profile, library=library).write(self._rb)
        self._flush_records()

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        sid = len(self._schemas) + 1
        schema = self._schemas[sid] = Schema(id=sid, name=name, encoding=encoding, data=data)
        self._in_chunk(schema)
        return sid

    def register_channel(self, topic: str, message_encoding: str, schema_id: int,
                         metadata: dict[str, str] | None = None) -> int:
        cid = len(self._channels) + 1
        channel = self._channels[cid] = Channel(id=cid, topic=topic, message_encoding=message_encoding,
                                                schema_id=schema_id, metadata=dict(metadata or {}))
        self._in_chunk(channel)
        return cid

    def _in_chunk(self, record: Any) -> None:
        rb = RecordBuilder()
        record.write(rb)
        self._chunk += rb.end()

    # --- messages
    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0) -> None:
        st = self._stats
        if st["message_count"] == 0:
            st["message_start_time"] = st["message_end_time"] = log_time
        elif log_time < st["message_start_time"]:
            st["message_start_time"] = log_time
        elif log_time > st["message_end_time"]:
            st["message_end_time"] = log_time
        st["message_count"] += 1
        self._counts[channel_id] += 1
        if self._chunk_messages == 0:
            self._chunk_start = self._chunk_end = log_time
        elif log_time < self._chunk_start:
            self._chunk_start = log_time
        elif log_time > self._chunk_end:
            self._chunk_end = log_time
        self._chunk_messages += 1
        buf = self._chunk
        index = self._index.get(channel_id)
        if index is None:
            index = self._index[channel_id] = []
        index.append((log_time, len(buf)))
        buf += _MESSAGE_HEAD.pack(_MESSAGE, 22 + len(data), channel_id, sequence, log_time, publish_time)
        buf += data

    def add_messages(self, channel_ids: np.ndarray, log_times: np.ndarray, data, offsets: np.ndarray,
                     publish_time: int, sequences: np.ndarray) -> int:
        """Messages ``k`` = 0..n-1 in order, as many :meth:`add_message` calls would add them (the
        same bytes): channel ``channel_ids[k]``, log time ``log_times[k]``, payload
        ``data[offsets[k] - offsets[0]:offsets[k + 1] - offsets[0]]`` (``data``: bytes or a uint8
        array), ``publish_time`` for all, sequence ``sequences[k]``. Returns the bytes added."""
        n = len(channel_ids)
        if n == 0:
            return 0
        offsets = np.asarray(offsets, dtype=np.int64)
        log_times = np.asarray(log_times, dtype=np.int64)
        sizes = offsets[1:] - offsets[:-1]
        heads = np.empty(n, dtype=_HEAD_DTYPE)
        heads["op"] = _MESSAGE
        heads["len"] = 22 + sizes
        heads["channel"] = channel_ids
        heads["seq"] = sequences
        heads["log"] = log_times
        heads["pub"] = publish_time
        total = 31 * n + int(offsets[-1] - offsets[0])
        out = np.empty(total, dtype=np.uint8)
        payload = np.frombuffer(data, dtype=np.uint8) if isinstance(data, (bytes, bytearray, memoryview)) else data
        _interleave(heads.view(np.uint8).reshape(n, 31), payload, offsets, out)
        start = len(self._chunk)
        at = start + 31 * np.arange(n, dtype=np.int64) + (offsets[:-1] - offsets[0])
        lo, hi = int(log_times.min()), int(log_times.max())
        st = self._stats
        if st["message_count"] == 0:
            st["message_start_time"], st["message_end_time"] = lo, hi
        else:
            st["message_start_time"] = min(st["message_start_time"], lo)
            st["message_end_time"] = max(st["message_end_time"], hi)
        st["message_count"] += n
        if self._chunk_messages == 0:
            self._chunk_start, self._chunk_end = lo, hi
        else:
            self._chunk_start, self._chunk_end = min(self._chunk_start, lo), max(self._chunk_end, hi)
        self._chunk_messages += n
        cids = np.asarray(channel_ids)
        uniq, first = np.unique(cids, return_index=True)
        for cid in uniq[np.argsort(first)].tolist():        # in order of first appearance, as one by one
            sel = cids == cid
            self._counts[cid] += int(np.count_nonzero(sel))
            self._index.setdefault(cid, [])
            self._blocks.setdefault(cid, []).append((log_times[sel], at[sel]))
        self._chunk += out.data
        return total

    @property
    def chunk_messages(self) -> int:
        return self._chunk_messages

    def end_chunk(self) -> None:
        """Write the chunk being built (when it holds a message) and its message indexes."""
        if self._chunk_messages == 0:
            return
        raw = bytes(self._chunk)
        data = self._compress(raw) if self._compress is not None else raw
        chunk = Chunk(compression=self._compression, data=data, message_start_time=self._chunk_start,
                      message_end_time=self._chunk_end, uncompressed_crc=crc32(raw),
                      uncompressed_size=len(raw))
        self._flush_records()
        start = self._stream.tell()
        chunk.write(self._rb)
        length = self._rb.count
        self._flush_records()
        # its messages are in the file now, whatever happens to the index records that follow
        # (a reader without them, or `bsc recover`, still finds them in the chunk)
        self.messages_in_chunks += self._chunk_messages
        index_start = self._stream.tell()
        offsets = {}
        for cid, records in self._index.items():
            offsets[cid] = index_start + self._rb.count
            blocks = self._blocks.get(cid)
            if blocks is None and len(records) < 8:
                MessageIndex(channel_id=cid, records=records).write(self._rb)
                continue
            singles = np.array(records, dtype=np.int64).reshape(-1, 2)
            times = np.concatenate([singles[:, 0], *(b[0] for b in blocks or ())])
            at = np.concatenate([singles[:, 1], *(b[1] for b in blocks or ())])
            order = np.argsort(at, kind="stable")        # file order: offsets grow with it
            self._rb.write(_index_record(cid, times[order], at[order]))
        index_length = self._rb.count
        self._flush_records()
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=self._chunk_start, message_end_time=self._chunk_end, chunk_start_offset=start,
            chunk_length=length, message_index_offsets=offsets, message_index_length=index_length,
            compression=self._compression, compressed_size=len(data), uncompressed_size=len(raw)))
        self._stats["chunk_count"] += 1
        self._chunk = bytearray()
        self._index = {}
        self._blocks = {}
        self._chunk_messages = 0
        self._chunk_start = self._chunk_end = 0

    # --- records outside chunks
    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._flush_records()
        offset = self._stream.tell()
        self._stats["metadata_count"] += 1
        Metadata(name=name, metadata=data).write(self._rb)
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=self._rb.count, name=name))
        self._flush_records()

    def add_attachment(self, create_time: int, log_time: int, name: str, media_type: str, data: bytes) -> None:
        self._flush_records()
        offset = self._stream.tell()
        self._stats["attachment_count"] += 1
        Attachment(create_time=create_time, log_time=log_time, name=name, media_type=media_type,
                   data=data).write(self._rb)
        self._attachment_indexes.append(AttachmentIndex(
            offset=offset, length=self._rb.count, create_time=create_time, log_time=log_time,
            data_size=len(data), name=name, media_type=media_type))
        self._flush_records()

    def _flush_records(self) -> None:
        self._stream.write(self._rb.end())

    # --- the end
    def finish(self) -> None:
        """End the chunk in progress, then the data section, the summary (schemas, channels,
        statistics, chunk, attachment and metadata indexes, their offsets) and the footer.
        The stream stays open."""
        self.end_chunk()
        DataEnd(data_section_crc=0).write(self._rb)
        self._flush_records()
        summary_start = self._stream.tell()
        sb = RecordBuilder()
        offsets: list[SummaryOffset] = []

        def group(opcode: Opcode, records) -> None:
            first = sb.count
            for r in records:
                r.write(sb)
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + first,
                                         group_length=sb.count - first))

        st = self._stats
        stats = Statistics(message_count=st["message_count"], schema_count=len(self._schemas),
                           channel_count=len(self._channels), attachment_count=st["attachment_count"],
                           metadata_count=st["metadata_count"], chunk_count=st["chunk_count"],
                           message_start_time=st["message_start_time"], message_end_time=st["message_end_time"],
                           channel_message_counts=dict(self._counts))
        group(Opcode.SCHEMA, self._schemas.values())
        group(Opcode.CHANNEL, self._channels.values())
        group(Opcode.STATISTICS, [stats])
        group(Opcode.CHUNK_INDEX, self._chunk_indexes)
        group(Opcode.ATTACHMENT_INDEX, self._attachment_indexes)
        group(Opcode.METADATA_INDEX, self._metadata_indexes)
        offset_start = summary_start + sb.count
        for o in offsets:
            o.write(sb)
        summary = sb.end()
        crc = crc32(summary)
        crc = crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start if summary else 0, offset_start), crc)
        self._stream.write(summary)
        Footer(summary_start=summary_start if summary else 0, summary_offset_start=offset_start,
               summary_crc=crc).write(self._rb)
        self._flush_records()
        self._stream.write(MCAP0_MAGIC)
