"""Record a session to MCAP: raw CAN frames, typed samples, metadata and attachments.

One :class:`Recorder` writes one MCAP file per session (or a numbered series when rotation is
on). Every channel carries a JSON schema (message encoding ``json``, schema encoding
``jsonschema``) so the file opens in Foxglove, and every file holds its own metadata and
attachments, so any single file can be read without the others. File layout, topics and the
crash-safety guarantees are described in ``docs/recording.md``.

Typical use (the lead wires this into ``bsc record`` and the demo)::

    with Recorder("run.mcap", rotate_bytes=512 << 20) as rec:
        rec.add_session_context(urdf_text=urdf, dbc_files={"ft.dbc": dbc}, software="bsc 0.1.0")
        notifier = can.Notifier(bus, [driver, rec.can_listener("ft0")])
        ...
        rec.record("/samples/wrench/arm0", wrench_sample)     # any frozen dataclass or dict
    print(rec.stats)                                          # nothing is ever dropped silently

Threading: ``record*`` may be called from any number of threads (CAN notifier threads, zenoh
callbacks); they encode to JSON in the caller's thread and append to a bounded FIFO. One writer
thread owns the MCAP writer and the file.

Queue semantics: FIFO, because every sample matters to a recording. The queue is bounded
(``queue_size`` messages, default 65 536: about 6 s of a 10 kHz aggregate stream) so a stalled
disk cannot eat the gateway's memory. When it is full the NEW message is refused: ``record*``
returns ``False`` at once (never blocks the caller) and ``stats.dropped_queue_full`` counts it.
Metadata, attachments and channel declarations are control items that bypass the bound, so they
are never dropped.
"""
from __future__ import annotations

import collections
import dataclasses
import json
import os
import socket
import sys
import threading
import time
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from gateway.errors import GatewayError
from gateway.log.canframe import CAN_FRAME_SCHEMA, can_frame_json, can_frame_json_rows, can_topic
from gateway.log.names import (CAN_SCHEMA_NAME, CAN_TOPIC_PREFIX, DBC_ATTACHMENT_PREFIX, JSON_SCHEMA_DIALECT,
                               RECORDING_METADATA, SCENARIO_ATTACHMENT, SESSION_METADATA, URDF_ATTACHMENT,
                               ZENOH_KEYS_METADATA)
from gateway.log.schema import dataclass_json, dict_schema, encode_json, field_names, json_schema_for, qualname

DEFAULT_CHUNK_SIZE = 128 * 1024
DEFAULT_QUEUE_SIZE = 65_536
DEFAULT_FLUSH_INTERVAL_S = 1.0

# Message record = opcode(1) + length(8) + channel(2) + sequence(4) + log/publish time(8+8).
_MESSAGE_OVERHEAD = 31
_POLL_S = 0.01


class RecorderError(GatewayError, OSError):
    """Recording failed (cannot write the file, disk full): data written before stays valid."""


# ----------------------------------------------------------------------------- statistics

@dataclasses.dataclass(frozen=True, slots=True)
class RecorderStats:
    """A snapshot of what the recorder did. Counts are messages unless the name says otherwise.

    ``received``: accepted into the queue. ``written``: handed to the MCAP writer.
    ``flushed``: in chunks written to the file (these survive a SIGKILL of the process; they
    survive a power cut only with ``fsync=True``). ``dropped_*``: refused or lost, by cause.
    """

    received: int
    written: int
    flushed: int
    dropped_queue_full: int
    dropped_write_error: int
    dropped_closed: int
    queue_depth: int
    queue_high_water: int
    chunks: int
    files: int
    bytes_written: int
    error: str | None

    @property
    def dropped(self) -> int:
        return self.dropped_queue_full + self.dropped_write_error + self.dropped_closed


# ----------------------------------------------------------------------------- the recorder

@dataclasses.dataclass(slots=True)
class _Topic:
    key: int
    topic: str
    schema_name: str
    schema: bytes
    channel_metadata: dict[str, str]
    cls: type | None          # the dataclass recorded on this topic, None for dicts / raw


class _Control:
    """A queue item that is not a message: never subject to the queue bound."""

    __slots__ = ("kind", "payload", "done")

    def __init__(self, kind: str, payload: Any = None, done: threading.Event | None = None):
        self.kind = kind
        self.payload = payload
        self.done = done


class _FdStream:
    """Unbuffered file for the MCAP writer: each write goes to the OS at once.

    The writer emits a whole chunk (or metadata record) per ``write``, so nothing the writer has
    finished is ever held in a Python buffer that a SIGKILL would lose.
    """

    def __init__(self, path: Path, overwrite: bool, fsync: bool):
        flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if overwrite else os.O_EXCL)
        self._fd = os.open(path, flags | getattr(os, "O_CLOEXEC", 0), 0o644)
        self._pos = 0
        self._fsync = fsync

    def write(self, data) -> int:
        view = memoryview(data)
        while view:
            n = os.write(self._fd, view)
            view = view[n:]
            self._pos += n
        return len(data)

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        if self._fsync:
            os.fsync(self._fd)

    def close(self, sync: bool = True) -> None:
        if self._fd < 0:
            return
        fd, self._fd = self._fd, -1
        try:
            if sync:
                os.fsync(fd)
        finally:
            os.close(fd)


class _Block:
    """Many encoded messages as one queue item (:meth:`Recorder.record_encoded_block`): topic key,
    log time and payload slice of each, one publish time."""

    __slots__ = ("keys", "log_ns", "data", "offsets", "publish_ns")

    def __init__(self, keys, log_ns, data, offsets, publish_ns: int):
        self.keys, self.log_ns, self.data, self.offsets, self.publish_ns = keys, log_ns, data, offsets, publish_ns


class Recorder:
    """Writes typed records and raw CAN frames to MCAP from any thread; a context manager.

    :param path: the MCAP file. With rotation on, files are ``<stem>_0000<suffix>``,
        ``<stem>_0001<suffix>``, ... next to it (``run.mcap`` -> ``run_0000.mcap``).
    :param chunk_size: uncompressed bytes per chunk (default 128 KiB). A chunk is the unit of
        crash safety: a SIGKILL loses the chunk being filled plus whatever is still queued.
    :param flush_interval_s: a partly filled chunk is written after this long anyway (default
        1 s), so a slow stream is on disk within about a second.
    :param queue_size: bound of the FIFO, in messages (see the module docstring).
    :param rotate_bytes: start a new file once the current one has this many bytes.
    :param rotate_s: start a new file after this many seconds (monotonic clock).
    :param compression: ``"zstd"`` (default) or ``"none"``.
    :param overwrite: replace existing files; by default an existing file is an error, so a
        session never clobbers an earlier log.
    :param fsync: fsync after every chunk (survives power loss; costs disk latency). Files are
        always fsynced when they are finished.
    :param metadata: metadata records ``name -> {key: value}`` for every file.

    Opening the first file happens here, so a bad path (read-only directory, missing folder)
    raises ``OSError`` at once. Later write failures (disk full) stop the recording: messages
    are then counted in ``stats.dropped_write_error``, :attr:`error` is set, and :meth:`close`
    raises :class:`RecorderError`. Files already finished stay valid; the failing file keeps
    every chunk written before the failure (``bsc recover`` makes it valid again).
    """

    def __init__(self, path: str | os.PathLike[str], *, chunk_size: int = DEFAULT_CHUNK_SIZE,
                 flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
                 queue_size: int = DEFAULT_QUEUE_SIZE, rotate_bytes: int | None = None,
                 rotate_s: float | None = None, compression: str = "zstd",
                 overwrite: bool = False, fsync: bool = False,
                 metadata: Mapping[str, Mapping[str, str]] | None = None) -> None:
        from mcap.writer import CompressionType

        if chunk_size < 1024:
            raise ValueError(f"chunk_size {chunk_size}: use at least 1024 bytes")
        if queue_size < 1:
            raise ValueError(f"queue_size {queue_size}: must be positive")
        if rotate_bytes is not None and rotate_bytes < 4 * chunk_size:
            raise ValueError(f"rotate_bytes {rotate_bytes}: use at least 4 chunks")
        if rotate_s is not None and rotate_s <= 0:
            raise ValueError(f"rotate_s {rotate_s}: must be positive")
        try:
            self._compression = {"zstd": CompressionType.ZSTD,
                                 "none": CompressionType.NONE}[compression]
        except KeyError:
            raise ValueError(f"compression {compression!r}: use 'zstd' or 'none'") from None
        self._base = Path(path)
        self._rotating = rotate_bytes is not None or rotate_s is not None
        self._chunk_size = chunk_size
        self._flush_interval_s = flush_interval_s
        self._queue_size = queue_size
        self._rotate_bytes = rotate_bytes
        self._rotate_s = rotate_s
        self._overwrite = overwrite
        self._fsync = fsync
        self._session = uuid.uuid4().hex
        self._start_utc = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())

        self._queue: collections.deque = collections.deque()
        self._wake = threading.Event()
        self._lock = threading.Lock()          # topic registration and caller-side counters
        self._topics: dict[str, _Topic] = {}
        self._topic_list: list[_Topic] = []     # by key; the writer thread reads it by index
        self._metadata: list[tuple[str, dict[str, str]]] = []
        self._attachments: list[tuple[str, str, bytes, int]] = []
        self._closed = False
        self._close_done = False
        self._error: BaseException | None = None

        # Caller side (under _lock): refused messages; messages queued in blocks beyond one per
        # block (the writer thread counts those it popped), so the bound stays in messages.
        self._block_extra_queued = 0
        self._block_extra_popped = 0
        self._dropped_full = 0
        self._dropped_closed = 0
        self._controls_queued = 0
        # Writer-thread side: only the writer thread writes these.
        self._popped = 0
        self._controls_popped = 0
        self._written = 0
        self._flushed = 0
        self._dropped_error = 0
        self._chunks = 0
        self._bytes_done = 0                   # bytes in files already finished
        self._high_water = 0
        self._paths: list[Path] = []

        # Per-file writer state (writer thread only, after the first open here).
        self._writer = None
        self._stream: _FdStream | None = None
        self._channel_ids: list[int] = []
        self._sequences: list[int] = []
        self._pending_bytes = 0
        self._pending_msgs = 0
        self._chunk_started = 0.0
        self._file_started = 0.0

        for name, data in (metadata or {}).items():
            self._metadata.append((name, _str_dict(name, data)))
        try:
            self._open_file()                  # raises OSError here, in the caller's thread
        except BaseException:
            if self._stream is not None:
                self._stream.close(sync=False)
            raise
        self._thread = threading.Thread(target=self._run, name=f"recorder:{self._base.name}",
                                        daemon=True)
        self._thread.start()

    # --------------------------------------------------------------- public API (any thread)

    def record(self, topic: str, sample: Any, log_time_ns: int | None = None) -> bool:
        """Queue one typed record: a dataclass instance (usually from ``drivers.samples``) or a
        JSON-ready mapping. Returns ``False`` when refused (queue full / closed; counted).

        The channel's schema comes from the dataclass's fields on first use (or from the first
        dict, unless :meth:`add_channel` declared it). ``log_time_ns`` defaults to the record's
        ``t_ns`` (the sensor time base, same as the CAN timestamps) or the wall clock if it has
        none. A topic holds one type: recording another type on it raises ``TypeError``.
        """
        info = self._topics.get(topic) or self._declare_for(topic, sample)
        cls = type(sample)
        if info.cls is not None:
            if cls is not info.cls:
                raise TypeError(f"topic {topic}: expected {info.cls.__name__}, "
                                f"got {cls.__name__}")
            data = dataclass_json(cls)(sample)
            t = sample.t_ns if log_time_ns is None and "t_ns" in field_names(cls) else log_time_ns
        elif isinstance(sample, Mapping):
            data = encode_json(sample)
            t = sample.get("t_ns") if log_time_ns is None else log_time_ns
        else:
            raise TypeError(f"topic {topic}: expected a mapping, got {cls.__name__}")
        now = time.time_ns()
        t = now if t is None else int(t)
        if t < 0:
            raise ValueError(f"topic {topic}: log time {t} ns is negative")
        return self._put((info.key, t, now, data.encode()))

    def record_encoded(self, topic: str, cls: type | None, data: bytes, log_time_ns: int) -> bool:
        """Queue one record already encoded as this recorder encodes a ``cls`` dataclass (the
        JSON of its fields, e.g. written from rows by :mod:`gateway.engine.encode`); the channel
        is ``cls``'s, as :meth:`record` declares it. ``cls`` None: a mapping's JSON, on a topic
        :meth:`add_channel` declared with a schema. Returns ``False`` when refused (counted)."""
        info = self._encoded_topic(topic, cls, log_time_ns)
        return self._put((info.key, int(log_time_ns), time.time_ns(), data))

    def record_encoded_many(self, items) -> int:
        """:meth:`record_encoded` for many ``(topic, cls, data, log_time_ns)`` at once, queued in
        their order (one look at the queue's room); returns how many were refused (counted)."""
        now = time.time_ns()
        keys: dict[tuple[str, type], int] = {}     # a batch is a few topics many times: each checked once
        out = []
        for topic, cls, data, t in items:
            key = keys.get((topic, cls))
            if key is None:
                key = keys[topic, cls] = self._encoded_topic(topic, cls, t).key
            elif t < 0:
                raise ValueError(f"topic {topic}: log time {t} ns is negative")
            out.append((key, int(t), now, data))
        take = 0 if self._closed else max(0, min(len(out), self._queue_size - self.queue_depth))
        self._queue.extend(out if take == len(out) else out[:take])
        return self._refused(len(out) - take)

    def record_encoded_block(self, topics, classes, which, data, offsets, log_ns) -> int:
        """:meth:`record_encoded` for a block of messages in one queue item, written by the
        writer thread with no Python step per message (:meth:`McapWriter.add_messages`):
        message k is on ``topics[which[k]]`` (records of ``classes[which[k]]``, as
        :meth:`record_encoded`), at log time ``log_ns[k]``, its payload
        ``data[offsets[k] - offsets[0]:offsets[k + 1] - offsets[0]]`` (``data``: bytes or a uint8
        array, ``offsets`` n + 1 of them). Queued in order; when the queue has room for only
        some, the first ones are queued. Returns how many were refused (counted)."""
        import numpy as np

        log_ns = np.asarray(log_ns, dtype=np.int64)
        n = len(log_ns)
        if n == 0:
            return 0
        if int(log_ns.min()) < 0:
            k = int(np.argmax(log_ns < 0))
            raise ValueError(f"topic {topics[int(which[k])]}: log time {int(log_ns[k])} ns is negative")
        key_of = np.array([self._encoded_topic(t, c, 0).key for t, c in zip(topics, classes)], dtype=np.int64)
        take = 0 if self._closed else max(0, min(n, self._queue_size - self.queue_depth))
        if take:
            with self._lock:
                self._block_extra_queued += take - 1
            self._queue.append(_Block(key_of[np.asarray(which)[:take]], log_ns[:take], data,
                                      np.asarray(offsets, dtype=np.int64)[:take + 1], time.time_ns()))
        return self._refused(n - take)

    def _refused(self, refused: int) -> int:
        """Count ``refused`` messages a call could not queue (closed, or the queue full); returns it."""
        if refused:
            with self._lock:
                if self._closed:
                    self._dropped_closed += refused
                else:
                    self._dropped_full += refused
        return refused

    def _encoded_topic(self, topic: str, cls: type | None, log_time_ns: int) -> _Topic:
        """The topic of ``cls`` records (declared on first use); its type and the time checked."""
        info = self._topics.get(topic)
        if info is None:
            if cls is None:
                raise ValueError(f"topic {topic}: records of mappings need the topic declared (add_channel)")
            with self._lock:
                info = self._topics.get(topic) or self._new_topic(topic, qualname(cls), json_schema_for(cls), cls)
        elif info.cls is not cls:
            raise TypeError(f"topic {topic}: expected {info.cls.__name__ if info.cls else 'records'}, "
                            f"got {cls.__name__ if cls else 'records'}")
        if log_time_ns < 0:
            raise ValueError(f"topic {topic}: log time {log_time_ns} ns is negative")
        return info

    def record_can(self, bus: str, msg, log_time_ns: int | None = None) -> bool:
        """Queue one raw CAN frame (python-can ``Message``) on topic ``/can/<bus>``."""
        info = self._topics.get(CAN_TOPIC_PREFIX + bus) or self._declare_can(bus)
        t_rec, data = can_frame_json(msg)
        t = t_rec if log_time_ns is None else int(log_time_ns)
        if t < 0:
            raise ValueError(f"bus {bus}: log time {t} ns is negative")
        return self._put((info.key, t, time.time_ns(), data))

    def record_can_rows(self, bus: str, rows, log_ns, channel=None) -> int:
        """Queue frames given as rows (:func:`can_frame_json_rows`) on topic ``/can/<bus>``, each
        at its log time in ``log_ns``; returns how many were refused (counted, as
        :meth:`record_can`)."""
        info = self._topics.get(CAN_TOPIC_PREFIX + bus) or self._declare_can(bus)
        now = time.time_ns()
        refused = 0
        for data, t in zip(can_frame_json_rows(rows, channel), log_ns.tolist()):
            if t < 0:
                raise ValueError(f"bus {bus}: log time {t} ns is negative")
            refused += not self._put((info.key, int(t), now, data))
        return refused

    def can_listener(self, bus: str):
        """A python-can ``Listener`` that records every frame of ``bus`` (for a ``Notifier``)."""
        import can

        recorder = self
        self._declare_can(bus)

        class _RecordingListener(can.Listener):
            def on_message_received(self, msg: can.Message) -> None:
                recorder.record_can(bus, msg)

            def stop(self) -> None:
                """The recorder outlives its listeners; close it yourself."""

        return _RecordingListener()

    def add_channel(self, topic: str, schema: Mapping[str, Any] | type,
                    schema_name: str | None = None) -> None:
        """Declare ``topic`` with an explicit JSON schema (a dict) or a dataclass type.

        Optional: topics are declared on first use. Useful to give dict topics a full schema.
        """
        with self._lock:
            if topic in self._topics:
                raise ValueError(f"topic {topic} is already declared")
            if isinstance(schema, type):
                self._new_topic(topic, qualname(schema), json_schema_for(schema), schema)
            else:
                name = schema_name or str(schema.get("title") or topic)
                self._new_topic(topic, name, dict(schema), None)

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Add a metadata record (written to this file and every later rotated file)."""
        entry = (name, _str_dict(name, data))
        with self._lock:
            self._check_open()
            self._metadata.append(entry)
            self._control("metadata", len(self._metadata) - 1)

    def add_attachment(self, name: str, media_type: str, data: bytes,
                       log_time_ns: int | None = None) -> None:
        """Add an attachment (written to this file and every later rotated file)."""
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise TypeError(f"attachment {name}: data must be bytes, got {type(data).__name__}")
        entry = (name, media_type, bytes(data), time.time_ns() if log_time_ns is None
                 else log_time_ns)
        with self._lock:
            self._check_open()
            self._attachments.append(entry)
            self._control("attachment", len(self._attachments) - 1)

    def add_session_context(self, *, urdf_text: str | None = None,
                            dbc_files: Mapping[str, str | bytes] | None = None,
                            scenario_text: str | None = None,
                            zenoh_keys: Mapping[str, str] | None = None,
                            software: str | None = None,
                            extra: Mapping[str, str] | None = None) -> None:
        """Attach what makes a log self-contained, under the documented names.

        ``robot.urdf``, ``dbc/<name>`` and ``scenario.toml`` attachments; ``zenoh.keys``
        metadata (key name -> key expression); ``bsc.session`` metadata (software version, the
        version of the kernels that compute samples and efforts, :data:`gateway.KERNELS`, and
        ``extra``).
        """
        from gateway import KERNELS

        if urdf_text is not None:
            self.add_attachment(URDF_ATTACHMENT, "application/xml", urdf_text.encode())
        for name, text in (dbc_files or {}).items():
            body = text.encode() if isinstance(text, str) else bytes(text)
            self.add_attachment(DBC_ATTACHMENT_PREFIX + Path(name).name, "text/plain", body)
        if scenario_text is not None:
            self.add_attachment(SCENARIO_ATTACHMENT, "application/toml", scenario_text.encode())
        if zenoh_keys:
            self.add_metadata(ZENOH_KEYS_METADATA, dict(zenoh_keys))
        session = {"kernels": KERNELS, **(extra or {})}
        if software is not None:
            session["software"] = software
        self.add_metadata(SESSION_METADATA, session)

    def flush(self, timeout: float | None = None) -> bool:
        """Write everything queued so far into the file (finishing the open chunk); wait.

        Returns ``False`` on timeout. Flushing often makes small chunks: use it at checkpoints,
        not per message.
        """
        if self._closed:
            return True
        done = threading.Event()
        with self._lock:
            self._control("flush", done=done)
        return done.wait(timeout)

    @property
    def stats(self) -> RecorderStats:
        depth = max(0, len(self._queue) - (self._controls_queued - self._controls_popped)
                    + self._block_extra_queued - self._block_extra_popped)
        stream = self._stream
        return RecorderStats(
            received=self._popped + depth, written=self._written, flushed=self._flushed,
            dropped_queue_full=self._dropped_full, dropped_write_error=self._dropped_error,
            dropped_closed=self._dropped_closed, queue_depth=depth,
            queue_high_water=max(self._high_water, depth), chunks=self._chunks,
            files=len(self._paths),
            bytes_written=self._bytes_done + (stream.tell() if stream is not None else 0),
            error=None if self._error is None else _describe(self._error))

    @property
    def queue_depth(self) -> int:
        """Messages waiting for the writer thread now."""
        return len(self._queue) + self._block_extra_queued - self._block_extra_popped

    @property
    def queue_size(self) -> int:
        """The bound of the FIFO, in messages."""
        return self._queue_size

    @property
    def paths(self) -> list[Path]:
        """Files this recorder has opened, oldest first."""
        return list(self._paths)

    @property
    def error(self) -> BaseException | None:
        """The write failure that stopped the recording, if any."""
        return self._error

    def close(self, timeout: float | None = 30.0) -> None:
        """Drain the queue, finish the file (summary + footer) and stop. Closing twice is fine.

        Raises :class:`RecorderError` (once) if the recording failed.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._control("stop")
        self._thread.join(timeout)
        if not self._thread.is_alive():
            # Appended after the stop item (a race with close): never written, so counted.
            late = sum(1 if item.__class__ is tuple else len(item.log_ns) for item in self._queue
                       if item.__class__ is tuple or item.__class__ is _Block)
            self._queue.clear()
            with self._lock:
                self._dropped_closed += late
        else:
            raise RecorderError(f"recorder for {self._base}: writer did not stop within "
                                f"{timeout} s ({len(self._queue)} messages still queued)")
        if self._error is not None and not self._close_done:
            self._close_done = True
            raise RecorderError(f"recording to {self._paths[-1] if self._paths else self._base} "
                                f"failed: {_describe(self._error)}; "
                                f"{self.stats.dropped_write_error} messages not written "
                                f"(complete chunks before the failure are kept: "
                                f"`bsc recover` the last file)") from self._error
        self._close_done = True

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc_info) -> None:
        if exc_info[0] is None:
            self.close()
            return
        try:
            self.close()
        except RecorderError:
            pass        # the exception already propagating matters more; stats keep the count

    # --------------------------------------------------------------- caller-side helpers

    def _put(self, item: tuple) -> bool:
        if self.queue_depth >= self._queue_size or self._closed:
            with self._lock:
                if self._closed:
                    self._dropped_closed += 1
                else:
                    self._dropped_full += 1
            return False
        self._queue.append(item)
        return True

    def _control(self, kind: str, payload: Any = None, done: threading.Event | None = None):
        # Called under _lock, so control items keep their order with declarations.
        self._controls_queued += 1
        self._queue.append(_Control(kind, payload, done))
        self._wake.set()

    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"recorder for {self._base} is closed")

    def _declare_for(self, topic: str, sample: Any) -> _Topic:
        with self._lock:
            if topic in self._topics:
                return self._topics[topic]
            cls = type(sample)
            if dataclasses.is_dataclass(cls):
                return self._new_topic(topic, qualname(cls), json_schema_for(cls), cls)
            if isinstance(sample, Mapping):
                name = "bsc.record" + topic.replace("/", ".").rstrip(".")
                return self._new_topic(topic, name, dict_schema(sample, name), None)
            raise TypeError(f"topic {topic}: cannot record a {cls.__name__} "
                            "(use a dataclass instance or a mapping)")

    def _declare_can(self, bus: str) -> _Topic:
        topic = can_topic(bus)
        with self._lock:
            if topic in self._topics:
                return self._topics[topic]
            return self._new_topic(topic, CAN_SCHEMA_NAME, CAN_FRAME_SCHEMA, None,
                                   {"bus": bus})

    def _new_topic(self, topic: str, schema_name: str, schema: dict, cls: type | None,
                   channel_metadata: dict[str, str] | None = None) -> _Topic:
        self._check_open()
        meta = dict(channel_metadata or {})
        if cls is not None:
            meta["bsc.type"] = qualname(cls)
        info = _Topic(len(self._topic_list), topic, schema_name,
                      json.dumps({"$schema": JSON_SCHEMA_DIALECT, **schema}, indent=1).encode(), meta, cls)
        self._topic_list.append(info)
        self._control("topic", info)
        self._topics[topic] = info         # published last: other threads then see it complete
        return info

    # --------------------------------------------------------------- writer thread

    def _run(self) -> None:
        queue = self._queue
        popleft = queue.popleft
        countdown = 256
        while True:
            try:
                item = popleft()
            except IndexError:
                self._periodic()
                self._wake.wait(_POLL_S)
                self._wake.clear()
                continue
            if item.__class__ is tuple:
                self._popped += 1
                if self._error is None:
                    try:
                        self._write_message(item)
                    except Exception as exc:  # noqa: BLE001 - surfaced by close() and stats
                        self._fail(exc)
                else:
                    self._dropped_error += 1
                countdown -= 1
                if countdown == 0:
                    countdown = 256
                    self._high_water = max(self._high_water, len(queue) + 1)
                    self._periodic()
                continue
            if item.__class__ is _Block:
                n = len(item.log_ns)
                self._popped += n
                self._block_extra_popped += n - 1
                if self._error is None:
                    try:
                        self._write_block(item)
                    except Exception as exc:  # noqa: BLE001 - surfaced by close() and stats
                        self._fail(exc)
                else:
                    self._dropped_error += n
                self._high_water = max(self._high_water, len(queue) + n)
                self._periodic()
                continue
            self._controls_popped += 1
            if item.kind == "stop":
                self._finish(final=True)
                return
            self._handle_control(item)

    def _write_message(self, item: tuple) -> None:
        key, log_time, publish_time, data = item
        seq = self._sequences[key]
        self._sequences[key] = seq + 1
        self._add_message(self._channel_ids[key], log_time, data, publish_time, seq & 0xFFFFFFFF)
        self._written += 1
        if self._pending_msgs == 0:
            self._chunk_started = time.monotonic()
        self._pending_msgs += 1
        self._pending_bytes += _MESSAGE_OVERHEAD + len(data)
        if self._pending_bytes >= self._chunk_size:
            self._flush_chunk()
            if self._rotate_bytes is not None and self._stream.tell() >= self._rotate_bytes:
                self._rotate()

    def _write_block(self, block: _Block) -> None:
        """A block's messages, cut where a chunk fills as :meth:`_write_message` cuts it (after
        the message that reaches the chunk size): the same chunks as one message at a time."""
        import numpy as np

        keys, offsets = block.keys, block.offsets
        n = len(keys)
        cum = np.cumsum(_MESSAGE_OVERHEAD + (offsets[1:] - offsets[:-1]))
        data = np.frombuffer(block.data, dtype=np.uint8) if isinstance(block.data, (bytes, bytearray)) else block.data
        lo = 0
        while lo < n:
            if self._pending_msgs == 0:
                self._chunk_started = time.monotonic()
            before = int(cum[lo - 1]) if lo else 0
            # the first message at which the chunk reaches its size ends this piece
            room = self._chunk_size - self._pending_bytes
            hi = min(n, int(np.searchsorted(cum, before + room, side="left")) + 1)
            # channels and sequences of this file (a rotation between pieces starts them again)
            piece = keys[lo:hi]
            seqs = np.empty(hi - lo, dtype=np.uint32)
            uniq, first = np.unique(piece, return_index=True)
            for key in uniq[np.argsort(first)].tolist():
                sel = np.flatnonzero(piece == key)
                start = self._sequences[key]
                seqs[sel] = (start + np.arange(len(sel), dtype=np.int64)) & 0xFFFFFFFF
                self._sequences[key] = start + len(sel)
            cids = np.asarray(self._channel_ids, dtype=np.int64)[piece]
            base = int(offsets[lo] - offsets[0])
            self._writer.add_messages(cids, block.log_ns[lo:hi], data[base:], offsets[lo:hi + 1],
                                      block.publish_ns, seqs)
            self._written += hi - lo
            self._pending_msgs += hi - lo
            self._pending_bytes += int(cum[hi - 1]) - before
            lo = hi
            if self._pending_bytes >= self._chunk_size:
                self._flush_chunk()
                if self._rotate_bytes is not None and self._stream.tell() >= self._rotate_bytes:
                    self._rotate()

    def _handle_control(self, item: _Control) -> None:
        try:
            if self._error is None:
                if item.kind == "topic":
                    self._register(item.payload)
                elif item.kind == "metadata":
                    # A rotation may already have written it into this file (index < count).
                    if item.payload >= self._metadata_written:
                        self._writer.add_metadata(*self._metadata[item.payload])
                        self._metadata_written = item.payload + 1
                elif item.kind == "attachment":
                    if item.payload >= self._attachments_written:
                        name, media_type, data, log_time = self._attachments[item.payload]
                        self._writer.add_attachment(log_time, log_time, name, media_type, data)
                        self._attachments_written = item.payload + 1
                elif item.kind == "flush":
                    self._flush_chunk()
        except Exception as exc:  # noqa: BLE001 - surfaced by close() and stats
            self._fail(exc)
        finally:
            if item.done is not None:
                item.done.set()

    def _periodic(self) -> None:
        if self._error is not None:
            return
        try:
            now = time.monotonic()
            if self._pending_msgs and now - self._chunk_started >= self._flush_interval_s:
                self._flush_chunk()
            if self._rotate_s is not None and now - self._file_started >= self._rotate_s:
                self._rotate()
        except Exception as exc:  # noqa: BLE001 - surfaced by close() and stats
            self._fail(exc)

    def _flush_chunk(self) -> None:
        if self._pending_msgs == 0:
            return
        self._in_chunks(self._writer.end_chunk)   # writes the chunk and its indexes
        self._stream.flush()
        self._pending_msgs = 0
        self._pending_bytes = 0

    def _in_chunks(self, write) -> None:
        """``write()`` (an end of chunk, the end of the file), counting the messages of the chunks it
        wrote as flushed, also when it fails after a chunk record (on the index records that follow
        it, say at a full disk): those messages are in the file."""
        w = self._writer
        before = w.messages_in_chunks
        try:
            write()
        finally:
            done = w.messages_in_chunks - before
            if done:
                self._flushed += done
                self._pending_msgs -= done       # in the file: not dropped if what follows fails
                self._chunks += 1

    def _rotate(self) -> None:
        self._finish(final=False)
        if self._error is None:
            self._open_file()

    def _finish(self, final: bool) -> None:
        if self._writer is None or self._error is not None:
            return
        try:
            self._in_chunks(self._writer.finish)
            self._pending_msgs = self._pending_bytes = 0
            self._bytes_done += self._stream.tell()
            self._stream.close(sync=True)
            self._writer = None
            self._stream = None
        except Exception as exc:  # noqa: BLE001 - surfaced by close() and stats
            self._fail(exc)

    def _open_file(self) -> None:
        from gateway.log.writer import McapWriter

        path = (self._base.with_name(f"{self._base.stem}_{len(self._paths):04d}"
                                     f"{self._base.suffix}") if self._rotating else self._base)
        stream = _FdStream(path, self._overwrite, self._fsync)
        self._paths.append(path)
        self._stream = stream
        # this class decides when a chunk ends, so it knows exactly which messages are on disk
        # (stats.flushed)
        writer = McapWriter(stream, compression=self._compression)
        self._writer = writer
        self._add_message = writer.add_message
        self._file_started = time.monotonic()
        self._pending_msgs = self._pending_bytes = 0
        writer.start(profile="", library=f"bsc-recorder ({_library_id()})")
        writer.add_metadata(RECORDING_METADATA, self._recording_metadata(path))
        with self._lock:
            metadata = list(self._metadata)
            attachments = list(self._attachments)
            topics = list(self._topic_list)
        for name, data in metadata:
            writer.add_metadata(name, data)
        for name, media_type, data, log_time in attachments:
            writer.add_attachment(log_time, log_time, name, media_type, data)
        self._metadata_written = len(metadata)
        self._attachments_written = len(attachments)
        self._schema_ids: dict[tuple[str, bytes], int] = {}
        self._channel_ids = []
        self._sequences = []
        for info in topics:
            self._register(info)

    def _register(self, info: _Topic) -> None:
        if info.key < len(self._channel_ids):
            return                        # already registered in this file (rotation replay)
        sid = self._schema_ids.get((info.schema_name, info.schema))
        if sid is None:
            sid = self._writer.register_schema(info.schema_name, "jsonschema", info.schema)
            self._schema_ids[(info.schema_name, info.schema)] = sid
        self._channel_ids.append(self._writer.register_channel(
            info.topic, "json", sid, info.channel_metadata))
        self._sequences.append(0)

    def _recording_metadata(self, path: Path) -> dict[str, str]:
        from gateway import __version__

        return {
            "software": f"bsc {__version__}",
            "library": _library_id(),
            "python": sys.version.split()[0],
            "host": socket.gethostname(),
            "session": self._session,
            "session_start_utc": self._start_utc,
            "file_index": str(len(self._paths) - 1),
            "file_name": path.name,
            "file_start_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "chunk_size": str(self._chunk_size),
            "flush_interval_s": str(self._flush_interval_s),
            "queue_size": str(self._queue_size),
            "time_base": "log_time = record t_ns (sensor/CAN clock); "
                         "publish_time = recorder receipt, CLOCK_REALTIME",
        }

    def _fail(self, exc: BaseException) -> None:
        if self._error is None:
            self._error = exc
        self._dropped_error += self._pending_msgs   # handed to the writer, never reached disk
        self._pending_msgs = self._pending_bytes = 0
        if self._stream is not None:
            self._bytes_done += self._stream.tell()  # what the OS took of this file before the failure
            try:
                self._stream.close(sync=False)
            except OSError:
                pass                      # the first error is the one worth reporting
            self._stream = None
        self._writer = None


def _str_dict(name: str, data: Mapping[str, str]) -> dict[str, str]:
    if not all(isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
        raise TypeError(f"metadata {name}: keys and values must be str")
    return dict(data)


def _library_id() -> str:
    from mcap.writer import LIBRARY_IDENTIFIER

    return LIBRARY_IDENTIFIER


def _describe(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        where = f": {exc.filename}" if exc.filename else ""
        return f"[Errno {exc.errno}] {exc.strerror}{where}"
    return f"{type(exc).__name__}: {exc}"
