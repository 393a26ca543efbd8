"""Frames read from a log chunk by chunk into rows: exactly the frames (and log times) the
record-by-record reader gives, in file order, with every filter; another writer's records in
place; a corrupt chunk named; no summary -> the caller's slow path."""
from __future__ import annotations

import json
import random

import can
import numpy as np
import pytest

import robot_description
from drivers.kernel import columns_from_messages
from gateway.log import context, reader
from gateway.log.frames import mcap_frames
from gateway.log.errors import McapFileError
from gateway.log.canframe import can_frame_to_record
from gateway.log.recorder import Recorder


def _messages(n: int, seed: int):
    rnd = random.Random(seed)
    out = []
    for k in range(n):
        fd = rnd.random() < 0.2
        length = rnd.choice([0, 3, 8, 12, 64]) if fd else rnd.randint(0, 8)
        bus = rnd.choice(["arm0", "arm1", "spacecraft"])
        out.append((bus, can.Message(
            timestamp=1_767_000_000.123 + k * 7.3e-5 + rnd.random() * 1e-6, arbitration_id=rnd.randrange(2048),
            is_extended_id=rnd.random() < 0.1, is_remote_frame=not fd and rnd.random() < 0.05,
            is_error_frame=rnd.random() < 0.02, is_fd=fd, bitrate_switch=fd and rnd.random() < 0.5,
            error_state_indicator=fd and rnd.random() < 0.1, dlc=length,
            data=bytes(rnd.randrange(256) for _ in range(length)),
            channel=rnd.choice([None, "vcan0", 3]), check=False)))
    return out


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    path = tmp_path_factory.mktemp("src") / "s.mcap"
    pairs = _messages(20_000, 1)
    robot = robot_description.load("paper_robot")
    with Recorder(path, queue_size=1 << 20, chunk_size=64 * 1024) as rec:
        rec.add_session_context(**context.session_context(robot))
        for k, (bus, msg) in enumerate(pairs):
            if k % 997 == 5:               # another writer: keys in another order
                rec.record(f"/can/{bus}", dict(reversed(list(can_frame_to_record(msg).items()))),
                           log_time_ns=round(msg.timestamp * 1e9))
            else:
                rec.record_can(bus, msg)
            if k % 50 == 0:
                rec.record("bsc/x/other", {"k": k})
    return path


def _want(path, buses, **kw):
    got = list(reader.iter_can_frames(path, buses=buses, **kw))
    rows = columns_from_messages([(buses.index(b), m) for b, _, m in got])
    rows["t_ns"] = [round(m.timestamp * 1e9) for _, _, m in got]
    return rows, np.array([t for _, t, _ in got], dtype=np.int64)


@pytest.mark.parametrize("filters", [{}, {"start_ns": 1_767_000_000_400_000_000, "end_ns": 1_767_000_001_100_000_000},
                                     {"can_ids": [5, 100, 2000]}])
def test_the_frames_the_record_reader_gives(log, filters):
    buses = ["arm0", "spacecraft"]
    want_rows, want_log = _want(log, buses, **filters)
    chunks = list(mcap_frames(log, buses, **filters))
    assert len(chunks) > 1 or filters
    rows = np.concatenate([c.frames for c in chunks]) if chunks else np.zeros(0, want_rows.dtype)
    log_ns = np.concatenate([c.log_ns for c in chunks]) if chunks else np.zeros(0, np.int64)
    assert len(rows) == len(want_rows) > 0
    assert rows.tobytes() == want_rows.tobytes() and np.array_equal(log_ns, want_log)


def test_a_corrupt_chunk_is_named(log, tmp_path):
    from mcap.reader import make_reader

    with open(log, "rb") as f:
        ci = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)[3]
    bad = tmp_path / "bad.mcap"
    data = bytearray(log.read_bytes())
    mid = ci.chunk_start_offset + ci.chunk_length // 2          # inside the chunk's compressed data
    data[mid:mid + 64] = bytes(64)
    bad.write_bytes(data)
    with pytest.raises(McapFileError, match="bsc recover"):
        for _ in mcap_frames(bad, ["arm0", "arm1", "spacecraft"]):
            pass


def test_no_summary_means_the_slow_reader(log, tmp_path):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log.read_bytes()[:len(log.read_bytes()) // 2])
    assert mcap_frames(cut, ["arm0"]) is None
    assert json                                # (the slow path parses with json)


def test_read_ahead_gives_the_same_chunks_and_the_reader_errors(log, tmp_path):
    import threading

    from gateway.log.frames import read_ahead

    buses = ["arm0", "arm1", "spacecraft"]
    want = list(mcap_frames(log, buses))
    got = list(read_ahead(mcap_frames(log, buses), depth=2))
    assert len(got) == len(want) > 3
    assert all(a.frames.tobytes() == b.frames.tobytes() and np.array_equal(a.log_ns, b.log_ns)
               for a, b in zip(got, want))

    def failing():
        yield want[0]
        raise McapFileError("broken chunk")

    it = read_ahead(failing())
    assert next(it) is want[0]
    with pytest.raises(McapFileError, match="broken chunk"):
        next(it)

    it = read_ahead(iter(want), depth=1)                 # the consumer stops after one chunk
    next(it)
    it.close()                                           # joins the reader thread
    assert not any(t.name == "bsc-read-ahead" for t in threading.enumerate())


def test_batched_merges_chunks_in_order_and_closes_its_source():
    import numpy as np

    from drivers.kernel import FRAME_DTYPE
    from gateway.log.frames import FrameChunk, batched

    closed = []

    def source():
        try:
            for k in range(10):
                rows = np.zeros(300 + k, dtype=FRAME_DTYPE)
                rows["t_ns"] = np.arange(len(rows)) + 1000 * k
                yield FrameChunk(rows, rows["t_ns"] + 7)
        finally:
            closed.append(True)

    whole = list(source())
    got = list(batched(source(), 1000))
    assert [len(c.frames) for c in got] == [1206, 1222, 617]       # >= 1000 but the last
    assert np.array_equal(np.concatenate([c.frames for c in got]), np.concatenate([c.frames for c in whole]))
    assert np.array_equal(np.concatenate([c.log_ns for c in got]), np.concatenate([c.log_ns for c in whole]))
    it = batched(source(), 1000)
    next(it)
    it.close()                                                      # a consumer that stops early
    assert closed == [True, True, True]
