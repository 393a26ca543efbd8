"""The reader's compiled path for raw CAN frames: a session log's frames as rows, chunk by chunk.

:func:`mcap_frames` (what ``bsc replay`` feeds the session engine) gives the raw CAN frames of a
bsc log (channels ``/can/<bus>``, schema ``bsc.CanFrame``) as :data:`drivers.kernel.FRAME_DTYPE`
rows with their log times, in FILE order (the order the live gateway recorded, and fed, them),
one chunk at a time: the chunk is read at
its offset from the summary's chunk index, decompressed (zstd or none) and CRC-checked, and one
compiled pass walks its records and parses the recorder's own frame JSON (``Recorder.record_can``:
one exact form) straight into rows. A record in any other form (another writer, another key
order) is parsed by ``json`` instead, in its place; bad data raises
:class:`gateway.log.errors.McapFileError` naming the log and ``bsc recover``. The frames are the
ones :func:`gateway.log.reader.iter_can_frames` gives, in the same order (tests hold them equal).

A log without a valid summary (a killed recorder) is read by the record-by-record reader
(:func:`gateway.log.reader.iter_can_frames`); ``bsc replay`` recovers a truncated log first.
"""
from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Iterator, NamedTuple

from isal.isal_zlib import crc32   # CRC-32 as zlib computes it, about 6x faster (ISA-L)
import numpy as np
from numba import njit

from gateway.log.canframe import KEYS
from gateway.log.context import read_summary
from drivers.kernel import FLAG_BRS, FLAG_ERROR, FLAG_ESI, FLAG_EXTENDED, FLAG_FD, FLAG_REMOTE, FRAME_DTYPE

# without reference counting (numba's _nrt option): the walk writes into arrays its caller owns and
# allocates nothing (gateway/estimator/jitopts.py says why it pays)
_jit = njit(cache=True, fastmath=False, error_model="numpy", nogil=True, _nrt=False)

_OP_MESSAGE, _OP_CHUNK = 0x05, 0x06
_CHUNK_FIXED = struct.Struct("<QQQII")          # start, end, uncompressed size, crc, compression length
_KEYS = KEYS                                  # the record's literal parts (gateway.log.canframe)
_B64 = np.full(256, 255, dtype=np.uint8)
for _i, _c in enumerate(b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/"):
    _B64[_c] = _i


class FrameChunk(NamedTuple):
    frames: np.ndarray        # FRAME_DTYPE rows, bus = index into the buses asked for
    log_ns: np.ndarray        # int64, each frame's log time


@_jit
def _match(d, p, end, key):
    n = key.shape[0]
    if p + n > end:
        return -1
    for k in range(n):
        if d[p + k] != key[k]:
            return -1
    return p + n


@_jit
def _uint(d, p, end):
    """(value, next) of decimal digits at ``p`` (no sign), or (-1, -1)."""
    if p >= end or not (48 <= d[p] <= 57):
        return -1, -1
    if d[p] == 48 and p + 1 < end and 48 <= d[p + 1] <= 57:
        return -1, -1                         # a leading zero: not the recorder's form
    v = np.int64(0)
    n = 0
    while p < end and 48 <= d[p] <= 57:
        v = v * 10 + (d[p] - 48)
        p += 1
        n += 1
        if n > 18:
            return -1, -1
    return v, p


@_jit
def _bool(d, p, end):
    """(0/1, next) for ``true``/``false`` at ``p``, or (-1, -1)."""
    if p + 4 <= end and d[p] == 116 and d[p + 1] == 114 and d[p + 2] == 117 and d[p + 3] == 101:
        return 1, p + 4
    if p + 5 <= end and d[p] == 102 and d[p + 1] == 97 and d[p + 2] == 108 and d[p + 3] == 115 and d[p + 4] == 101:
        return 0, p + 5
    return -1, -1


@_jit
def _frame(d, p, end, keys, b64, row):
    """The recorder's frame JSON in ``d[p:end]`` into ``row``; False when it is in another form."""
    p = _match(d, p, end, keys[0])
    if p < 0:
        return False
    t, p = _uint(d, p, end)
    if p < 0:
        return False
    p = _match(d, p, end, keys[1])
    if p < 0:
        return False
    aid, p = _uint(d, p, end)
    if p < 0 or aid > 0xFFFFFFFF:
        return False
    flags = 0
    bits = (FLAG_EXTENDED, FLAG_REMOTE, FLAG_ERROR, FLAG_FD, FLAG_BRS, FLAG_ESI, 0)
    for k in range(7):                        # the six flags, then is_rx (not kept)
        p = _match(d, p, end, keys[2 + k])
        if p < 0:
            return False
        v, p = _bool(d, p, end)
        if p < 0:
            return False
        if v:
            flags |= bits[k]
    p = _match(d, p, end, keys[9])
    if p < 0:
        return False
    dlc, p = _uint(d, p, end)
    if p < 0:
        return False
    p = _match(d, p, end, keys[10])
    if p < 0:
        return False
    q = p                                     # base64 up to the closing quote
    while q < end and d[q] != 34:
        q += 1
    n64 = q - p
    if q >= end or n64 % 4 != 0 or n64 > 88:
        return False
    pad = 0
    if n64 and d[q - 1] == 61:
        pad = 2 if d[q - 2] == 61 else 1
    length = n64 // 4 * 3 - pad
    o = 0
    for g in range(0, n64, 4):
        acc = 0
        for k in range(4):
            c = d[p + g + k]
            if c == 61:
                v = 0
                if g + k < n64 - pad:
                    return False
            else:
                v = b64[c]
                if v == 255:
                    return False
            acc = (acc << 6) | v
        for k in range(3):
            if o < length:
                row["data"][o] = (acc >> (16 - 8 * k)) & 0xFF
                o += 1
    for k in range(length, 64):
        row["data"][k] = 0
    p = _match(d, q, end, keys[11])
    if p < 0:
        return False
    # channel: null, an integer or a plain string; then the closing brace
    if p < end and d[p] == 34:
        p += 1
        while p < end and d[p] != 34:
            if d[p] == 92:                    # an escape: not the recorder's plain form
                return False
            p += 1
        p += 1
    elif p + 4 <= end and d[p] == 110 and d[p + 1] == 117 and d[p + 2] == 108 and d[p + 3] == 108:
        p += 4
    else:
        if p < end and d[p] == 45:
            p += 1
        v, p = _uint(d, p, end)
        if p < 0:
            return False
    if p + 1 != end or d[p] != 125:
        return False
    row["t_ns"] = t
    row["can_id"] = aid
    row["flags"] = flags
    row["dlc"] = dlc if dlc <= 255 else 255
    row["length"] = length
    return True


@_jit
def _walk(d, bus_of, start_ns, end_ns, keys, b64, rows, log_ns, slow_at, slow_off, slow_len):
    """Every message record of the wanted channels (``bus_of[channel] >= 0``) in the chunk bytes
    ``d`` whose log time is in ``[start_ns, end_ns)``: a row each, or a slow-path slot (records in
    another form). Returns (rows written, slow records, error): error 1 = a record runs past the
    chunk."""
    n = 0
    ns = 0
    p = 0
    end = d.shape[0]
    while p < end:
        if p + 9 > end:
            return n, ns, 1
        op = d[p]
        length = np.int64(0)
        for k in range(8):
            length |= np.int64(d[p + 1 + k]) << (8 * k)
        body = p + 9
        p = body + length
        if length < 0 or p > end:
            return n, ns, 1
        if op != _OP_MESSAGE or length < 22:
            continue
        ch = np.int64(d[body]) | (np.int64(d[body + 1]) << 8)
        if ch >= bus_of.shape[0] or bus_of[ch] < 0:
            continue
        t = np.int64(0)
        for k in range(8):
            t |= np.int64(d[body + 6 + k]) << (8 * k)
        if t < start_ns or t >= end_ns:
            continue
        if n + ns >= rows.shape[0]:
            return n, ns, 2                   # the caller's buffers are too small (never: sized by the chunk)
        r = rows[n + ns]
        if _frame(d, body + 22, p, keys, b64, r):
            r["bus"] = bus_of[ch]
            log_ns[n + ns] = t
            n += 1
        else:
            slow_at[ns] = n + ns              # its place in the output
            slow_off[ns] = body + 22
            slow_len[ns] = p - body - 22
            log_ns[n + ns] = t
            rows[n + ns]["bus"] = bus_of[ch]
            ns += 1
    return n, ns, 0


def mcap_frames(path, buses: list[str], *, start_ns: int | None = None, end_ns: int | None = None,
                can_ids=None) -> Iterator[FrameChunk] | None:
    """The raw frames of ``buses`` (``bus`` = index into it), chunk by chunk in file order; None
    when the log has no usable summary (read it with :func:`gateway.log.reader.iter_can_frames`)."""
    from gateway.log.errors import McapFileError
    from gateway.log.canframe import can_frame_from_record
    from gateway.log.names import CAN_SCHEMA_NAME, CAN_TOPIC_PREFIX

    path = Path(path)
    try:
        summary = read_summary(path)
    except (OSError, struct.error, ValueError):
        return None
    if summary is None or not summary.chunks:
        return None
    schemas, channels, chunks = summary.schemas, summary.channels, summary.chunks
    want = {CAN_TOPIC_PREFIX + b: i for i, b in enumerate(buses)}
    bus_of = np.full(max([0, *channels]) + 1, -1, dtype=np.int64)
    for cid, (topic, sid) in channels.items():
        if topic in want and schemas.get(sid) == CAN_SCHEMA_NAME:
            bus_of[cid] = want[topic]
    ids = None if can_ids is None else np.array(sorted(set(can_ids)), dtype=np.int64)
    lo = -(1 << 63) if start_ns is None else start_ns
    hi = (1 << 63) - 1 if end_ns is None else end_ns
    keys = tuple(np.frombuffer(k, dtype=np.uint8).copy() for k in _KEYS)
    chunks = sorted(chunks, key=lambda c: c.offset)

    def corrupt(why) -> McapFileError:
        return McapFileError(f"{path}: corrupt data ({why}); `bsc recover {path}` copies everything that is intact")

    def gen():
        import zstandard

        dec = zstandard.ZstdDecompressor()
        with open(path, "rb") as f:
            cap = 0
            for ci in chunks:
                if ci.end_ns < lo or ci.start_ns >= hi:
                    continue
                if not any(bus_of[c] >= 0 for c in ci.channels if c < len(bus_of)):
                    continue
                f.seek(ci.offset)
                head = f.read(9)
                if len(head) < 9 or head[0] != _OP_CHUNK:
                    raise corrupt(f"no chunk record at offset {ci.offset}")
                body = f.read(struct.unpack_from("<Q", head, 1)[0])
                _, _, size, crc, clen = _CHUNK_FIXED.unpack_from(body, 0)
                comp = body[32:32 + clen].decode("ascii", "replace")
                (dlen,) = struct.unpack_from("<Q", body, 32 + clen)
                raw = body[40 + clen:40 + clen + dlen]
                try:
                    data = dec.decompress(raw, max_output_size=size) if comp == "zstd" else (
                        raw if comp == "" else None)
                except zstandard.ZstdError as exc:
                    raise corrupt(exc) from None
                if data is None:
                    raise corrupt(f"chunk compression {comp!r} is not supported")
                if len(data) != size or (crc and crc32(data) != crc):
                    raise corrupt("chunk CRC or size mismatch")
                d = np.frombuffer(data, dtype=np.uint8)
                if size // 31 + 1 > cap:                      # at most one message per 31 bytes
                    cap = size // 31 + 1
                    buf_rows = np.zeros(cap, dtype=FRAME_DTYPE)
                    buf_log = np.zeros(cap, dtype=np.int64)
                    slow_at = np.zeros(cap, dtype=np.int64)
                    slow_off = np.zeros(cap, dtype=np.int64)
                    slow_len = np.zeros(cap, dtype=np.int64)
                rows, log = buf_rows, buf_log
                n, ns, err = _walk(d, bus_of, lo, hi, keys, _B64, rows, log, slow_at, slow_off, slow_len)
                if err:
                    raise corrupt("a record runs past the end of its chunk")
                total = n + ns
                for k in range(ns):                           # another writer's form: json, in place
                    at, o, ln = int(slow_at[k]), int(slow_off[k]), int(slow_len[k])
                    try:
                        rec = json.loads(data[o:o + ln])
                        msg = can_frame_from_record(rec)
                    except (ValueError, KeyError, TypeError) as exc:
                        raise McapFileError(f"{path}: {CAN_TOPIC_PREFIX}{buses[rows[at]['bus']]}: a frame record "
                                            f"is malformed ({exc!r})") from None
                    from drivers.kernel import columns_from_messages

                    one = columns_from_messages([(int(rows[at]["bus"]), msg)])[0]
                    one["t_ns"] = rec["t_ns"]
                    rows[at] = one
                rows, log = rows[:total].copy(), log[:total].copy()
                if ids is not None and total:
                    keep = np.isin(rows["can_id"].astype(np.int64), ids)
                    rows, log = rows[keep], log[keep]
                if len(rows):
                    yield FrameChunk(rows, log)

    return gen()


BATCH_FRAMES = 4096
"""Frames per batch of :func:`batched`: a recorder's chunk holds about 250 frames, and every call
into the drivers and the estimator, and every batch of output, has a fixed cost; merged to this
size an offline replay ran 20 % faster (2026-11-26)."""


def batched(chunks: Iterator[FrameChunk], min_frames: int = BATCH_FRAMES) -> Iterator[FrameChunk]:
    """``chunks`` merged, in order, into batches of at least ``min_frames`` frames (the last one
    may be smaller): the same frames with the same log times. The estimator gives the same bits
    whatever the batch (its kernels run frame by frame), so this changes only how often Python
    calls it."""
    def merge(held: list[FrameChunk]) -> FrameChunk:
        return held[0] if len(held) == 1 else FrameChunk(np.concatenate([h.frames for h in held]),
                                                         np.concatenate([h.log_ns for h in held]))

    held: list[FrameChunk] = []
    n = 0
    try:
        for c in chunks:
            held.append(c)
            n += len(c.frames)
            if n >= min_frames:
                yield merge(held)
                held, n = [], 0
        if held:
            yield merge(held)
    finally:
        close = getattr(chunks, "close", None)
        if close is not None:
            close()


def read_ahead(chunks: Iterator[FrameChunk], depth: int = 8) -> Iterator[FrameChunk]:
    """``chunks`` read by a thread of their own, up to ``depth`` ahead of the consumer: reading
    (zstd, the chunk walk) releases the GIL, and so do the drivers' and estimator's kernels, so on
    two cores the next chunks are read while this one is estimated. Same chunks, same order; an
    error in the reader is raised here, where the consumer would have met it."""
    import queue
    import threading

    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    end = object()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def run() -> None:
        try:
            for c in chunks:
                if not put(c):
                    return
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, raised there
            put(exc)
            return
        put(end)

    t = threading.Thread(target=run, name="bsc-read-ahead", daemon=True)
    t.start()
    try:
        while True:
            item = q.get()
            if item is end:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        t.join(5.0)
        close = getattr(chunks, "close", None)
        if close is not None and not t.is_alive():
            close()

