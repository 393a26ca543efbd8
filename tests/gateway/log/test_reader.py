"""The one reader of a session log (gateway/log/reader.py): file order and log-time order give
the same messages, the second sorted by log time; topic, predicate and time window select."""
from __future__ import annotations

import random

import can
import pytest

from gateway.log.errors import McapFileError
from gateway.log.reader import iter_can_frames, iter_messages, read_messages
from gateway.log.recorder import Recorder


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    """Frames on two buses and notes, written out of log-time order, in several chunks."""
    rnd = random.Random(3)
    path = tmp_path_factory.mktemp("reader") / "r.mcap"
    with Recorder(path, chunk_size=2048) as rec:
        for i in range(3000):
            t = 1_000_000 + i * 1000 + rnd.randrange(-5000, 5000)       # jittered: not monotonic
            rec.record_can(("a", "b")[i % 2], can.Message(timestamp=t / 1e9, arbitration_id=0x100 + i % 7,
                                                         data=rnd.randbytes(8)), log_time_ns=t)
            if i % 10 == 0:
                rec.record("/notes", {"i": i}, log_time_ns=t)
    return path


def test_file_and_log_time_order_give_the_same_messages(log):
    files = [(t, s, m.log_time, bytes(m.data)) for t, s, m in iter_messages(log)]
    times = [(t, s, m.log_time, bytes(m.data)) for t, s, m in iter_messages(log, log_time_order=True)]
    assert len(files) == 3300 and sorted(files) == sorted(times)
    assert [x[2] for x in times] == sorted(x[2] for x in times)
    assert [x[2] for x in files] != sorted(x[2] for x in files)          # the file order is not sorted


@pytest.mark.parametrize("log_time_order", [False, True])
def test_topics_predicates_and_windows_select(log, log_time_order):
    every = [(t, m.log_time) for t, _, m in iter_messages(log, log_time_order=log_time_order)]
    notes = [(t, m.log_time) for t, _, m in iter_messages(log, "/notes", log_time_order=log_time_order)]
    assert notes == [x for x in every if x[0] == "/notes"] and len(notes) == 300
    can_only = list(iter_messages(log, want=lambda t, s: s == "bsc.CanFrame", log_time_order=log_time_order))
    assert {t for t, _, _ in can_only} == {"/can/a", "/can/b"} and len(can_only) == 3000
    lo, hi = 1_500_000, 1_700_000
    window = [(t, m.log_time) for t, _, m in iter_messages(log, start_ns=lo, end_ns=hi,
                                                           log_time_order=log_time_order)]
    assert window == [x for x in every if lo <= x[1] < hi] and window


def test_can_frames_in_either_order_and_by_id(log):
    files = list(iter_can_frames(log, buses=["a"]))
    times = list(iter_can_frames(log, buses=["a"], log_time_order=True))
    key = [(b, t, m.arbitration_id, bytes(m.data)) for b, t, m in files]
    assert sorted(key) == sorted((b, t, m.arbitration_id, bytes(m.data)) for b, t, m in times)
    assert [t for _, t, _ in times] == sorted(t for _, t, _ in times) and len(files) == 1500
    assert all(round(m.timestamp * 1e9) == t for _, t, m in files)
    picked = list(iter_can_frames(log, can_ids=[0x101, 0x103], log_time_order=True))
    assert picked and {m.arbitration_id for _, _, m in picked} == {0x101, 0x103}


def test_decoded_messages_and_a_truncated_file(log, tmp_path):
    got = list(read_messages(log, ["/notes"], start_s=0.0, duration_s=0.5))
    assert got and all(m.data == {"i": m.data["i"]} for m in got)
    assert [m.log_time_ns for m in got] == sorted(m.log_time_ns for m in got)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log.read_bytes()[: len(log.read_bytes()) // 2])
    with pytest.raises(McapFileError, match="bsc recover"):
        list(iter_messages(cut, log_time_order=True))
