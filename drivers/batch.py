"""Vectorised decoding of many frames at once (logs, replays), derived from the DBC.

The bit positions come from the cantools signal definitions (start bit, length, byte order,
sign, factor), not from the live decoders' Structs, so a test comparing the two checks both
against the DBC. Results are identical to :func:`drivers.frames.decode_fields` on every frame:
integer signals (unsigned, factor 1) as ``int64``, scaled ones as ``raw * factor`` in float64.

Input: arrays of ids ``(N,)``, payload bytes ``(N, 8)`` (shorter payloads zero padded; CAN FD
payloads longer than 8 bytes are not part of this contract), lengths ``(N,)`` and timestamps
``(N,)`` in ns. Frames whose length differs from the DBC are counted as ``dlc``, ids not in the
DBC as ``unknown_id``; neither raises.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable

import can
import numpy as np

from drivers import wire


@dataclass(frozen=True, slots=True)
class _Sig:
    name: str
    shift: int
    mask: int
    bits: int
    signed: bool
    scale: float | None
    sat_limit: int


@dataclass(frozen=True, slots=True)
class _Msg:
    name: str
    frame_id: int
    length: int
    signals: tuple[_Sig, ...]


def _compile(kind: str) -> dict[int, _Msg]:
    out = {}
    for m in wire.database(kind).messages:
        sigs = []
        for s in sorted(m.signals, key=lambda s: s.start):
            if s.byte_order != "big_endian":
                raise wire.WireError(f"{m.name}.{s.name}: batch decoding assumes big-endian signals")
            msb = (s.start // 8) * 8 + (7 - s.start % 8)      # bit index counted from the MSB of byte 0
            lsb = msb + s.length - 1
            integer = s.scale == 1 and not s.is_signed
            sigs.append(_Sig(s.name, 63 - lsb, (1 << s.length) - 1, s.length, s.is_signed,
                             None if integer else float(s.scale), (1 << (s.length - 1)) - 1 if s.is_signed else 0))
        out[m.frame_id] = _Msg(m.name, m.frame_id, m.length, tuple(sigs))
    return out


_COMPILED = {k: _compile(k) for k in wire.DBC_FILES}


@dataclass(slots=True)
class MessageArrays:
    """All frames of one message in a batch: ``rows`` index the input arrays."""

    name: str
    frame_id: int
    rows: np.ndarray
    t_ns: np.ndarray
    fields: dict[str, np.ndarray]
    saturated: np.ndarray


@dataclass(slots=True)
class BatchResult:
    messages: dict[str, MessageArrays] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)

    def __getitem__(self, name: str) -> MessageArrays:
        return self.messages[name]


def decode_batch(kind: str, ids: np.ndarray, data: np.ndarray, lengths: np.ndarray,
                 t_ns: np.ndarray | None = None) -> BatchResult:
    """Decode every frame of a bus kind (``"arm"``/``"spacecraft"``) in one pass per message."""
    ids = np.asarray(ids, dtype=np.int64)
    data = np.asarray(data, dtype=np.uint8)
    lengths = np.asarray(lengths, dtype=np.int64)
    if data.ndim != 2 or data.shape[0] != ids.shape[0] or data.shape[1] > 8:
        raise ValueError(f"data must be (N, <=8) bytes for N ids, got {data.shape}")
    if data.shape[1] < 8:
        data = np.pad(data, ((0, 0), (0, 8 - data.shape[1])))
    t = np.zeros(ids.shape, np.int64) if t_ns is None else np.asarray(t_ns, dtype=np.int64)
    # the payload as one big-endian 64-bit word per frame
    words = np.ascontiguousarray(data).view(">u8").reshape(-1).astype(np.uint64)
    res = BatchResult()
    known = np.zeros(ids.shape, bool)
    bad_len = 0
    for fid, m in _COMPILED[kind].items():
        sel = ids == fid
        if not sel.any():
            continue
        known |= sel
        ok = sel & (lengths == m.length)
        bad_len += int(np.count_nonzero(sel)) - int(np.count_nonzero(ok))
        rows = np.flatnonzero(ok)
        if rows.size == 0:
            continue
        w = words[rows]
        fields: dict[str, np.ndarray] = {}
        sat = np.zeros(rows.shape, bool)
        for s in m.signals:
            raw = ((w >> np.uint64(s.shift)) & np.uint64(s.mask)).astype(np.int64)
            if s.signed:
                raw = np.where(raw > s.sat_limit, raw - (1 << s.bits), raw)
            if s.scale is None:
                fields[s.name] = raw
            else:
                sat |= (raw >= s.sat_limit) | (raw <= -s.sat_limit)
                fields[s.name] = raw.astype(np.float64) * s.scale
        res.messages[m.name] = MessageArrays(m.name, fid, rows, t[rows], fields, sat)
    unknown = int(np.count_nonzero(~known))
    if unknown:
        res.rejected["unknown_id"] = unknown
    if bad_len:
        res.rejected["dlc"] = bad_len
    return res


def arrays_from_messages(msgs: Iterable[can.Message]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(ids, data (N, 8), lengths, t_ns)`` from python-can messages (e.g. a log reader).

    Error, remote and 29-bit frames get id -1 (counted as ``unknown_id``); payloads longer
    than 8 bytes keep their length (counted as ``dlc``) and their first 8 bytes."""
    msgs = list(msgs)
    n = len(msgs)
    ids = np.empty(n, np.int64)
    data = np.zeros((n, 8), np.uint8)
    lengths = np.empty(n, np.int64)
    t = np.empty(n, np.int64)
    for k, m in enumerate(msgs):
        bad = m.is_error_frame or m.is_remote_frame or m.is_extended_id
        ids[k] = -1 if bad else m.arbitration_id
        d = bytes(m.data or b"")
        lengths[k] = len(d)
        data[k, :min(len(d), 8)] = np.frombuffer(d[:8], np.uint8)
        t[k] = int(round(m.timestamp * 1e9))
    return ids, data, lengths, t
