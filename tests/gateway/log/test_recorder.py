"""Recorder unit tests: round trips, schemas, metadata, rotation, back-pressure, failures."""
from __future__ import annotations

import json
import threading

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.samples import ImuSample, JointSample, WrenchSample
from gateway.log import errors, reader, scan
from gateway.log.canframe import can_frame_from_record, can_frame_to_record
from gateway.log.names import CAN_SCHEMA_NAME
from gateway.log.recorder import Recorder, RecorderError
from gateway.log.schema import json_schema_for

WRENCH = WrenchSample("arm0", 1_000_000_000, 7, (1.0, -2.5, 3.0), (0.1, 0.2, -0.3), False, 4)


def _frame(i: int, **kw) -> can.Message:
    kw.setdefault("data", i.to_bytes(4, "little") + bytes(4))
    return can.Message(timestamp=1.0 + i * 1e-3, arbitration_id=0x100 + i % 16,
                       is_extended_id=False, channel="vcan0", **kw)


# ----------------------------------------------------------------------------- raw CAN records

can_frames = st.builds(
    lambda fd, ext, remote, err, brs, esi, rx, arb, payload, ts, chan: can.Message(
        timestamp=ts, arbitration_id=arb & (0x1FFFFFFF if ext else 0x7FF), is_extended_id=ext,
        is_remote_frame=remote and not fd, is_error_frame=err, is_fd=fd, bitrate_switch=brs and fd,
        error_state_indicator=esi and fd, is_rx=rx, channel=chan,
        data=b"" if (remote and not fd) else payload[: 64 if fd else 8],
        dlc=None if not (remote and not fd) else len(payload[:8])),
    st.booleans(), st.booleans(), st.booleans(), st.booleans(), st.booleans(), st.booleans(),
    st.booleans(), st.integers(0, 0x1FFFFFFF), st.binary(max_size=64),
    st.floats(0, 4e9, allow_nan=False), st.one_of(st.none(), st.text(max_size=8),
                                                   st.integers(0, 7)))


@given(can_frames)
@settings(max_examples=300, deadline=None)
def test_can_record_round_trips_bit_for_bit(msg):
    rec = json.loads(json.dumps(can_frame_to_record(msg)))      # through JSON, as in the file
    back = can_frame_from_record(rec)
    assert bytes(back.data) == bytes(msg.data)
    for name in ("arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame",
                 "is_fd", "bitrate_switch", "error_state_indicator", "is_rx", "dlc"):
        assert getattr(back, name) == getattr(msg, name), name
    # the channel is recorded as text (one JSON type, as Foxglove needs): "" for none
    assert back.channel == (None if msg.channel in (None, "") else str(msg.channel))
    assert rec["channel"] == ("" if msg.channel is None else str(msg.channel))
    assert abs(back.timestamp - msg.timestamp) < 1e-6           # ns resolution, float seconds


def test_schema_from_dataclass_fields():
    schema = json_schema_for(WrenchSample)
    props = schema["properties"]
    assert schema["title"] == "drivers.samples.WrenchSample"
    assert props["t_ns"] == {"type": "integer"}
    assert props["device"] == {"type": "string"}
    assert props["saturated"] == {"type": "boolean"}
    assert props["force_n"]["type"] == "array" and props["force_n"]["minItems"] == 3
    assert props["force_n"]["items"] == {"type": "number"}
    assert set(schema["required"]) == set(props)
    assert json_schema_for(ImuSample)["properties"]["quat_wxyz"]["maxItems"] == 4


# ----------------------------------------------------------------------------- file contents

def test_records_read_back_in_log_time_order_with_schemas(tmp_path):
    path = tmp_path / "s.mcap"
    with Recorder(path, chunk_size=4096) as rec:
        rec.add_session_context(urdf_text="<robot name='r'/>", dbc_files={"ft.dbc": "VERSION \"\""},
                                scenario_text="[run]\n", zenoh_keys={"wrench": "bsc/ft/*"},
                                software="bsc test")
        rec.add_metadata("custom", {"k": "v"})
        rec.add_attachment("notes.txt", "text/plain", b"hello")
        for i in range(300):
            assert rec.record_can("ft0", _frame(i))
            rec.record("/samples/joint", JointSample("arm0/j1", 1_000_000_000 + i * 2_000_000 + 1,
                                                     i, 0.1 * i, 0.0))
        rec.record("/misc", {"t_ns": 1_000_500_000, "note": "dict record", "x": 1.5})
    assert rec.stats.dropped == 0 and rec.stats.written == rec.stats.flushed == 601
    info = scan.inspect(path)
    assert info.complete and info.message_count == 601
    assert {c.topic: c.count for c in info.channels} == {"/can/ft0": 300, "/samples/joint": 300,
                                                        "/misc": 1}
    assert {"bsc.recording", "bsc.session", "zenoh.keys", "custom"} <= set(info.metadata)
    assert info.metadata["zenoh.keys"] == {"wrench": "bsc/ft/*"}
    assert {a["name"] for a in info.attachments} == {"robot.urdf", "dbc/ft.dbc", "scenario.toml",
                                                     "notes.txt"}
    msgs = list(reader.read_messages(path))
    times = [m.log_time_ns for m in msgs]
    assert times == sorted(times)
    can_msgs = [m for m in msgs if m.topic == "/can/ft0"]
    assert [m.schema_name for m in can_msgs[:1]] == [CAN_SCHEMA_NAME]
    assert [int.from_bytes(m.can_message().data[:4], "little") for m in can_msgs] == list(range(300))
    assert [m.sequence for m in can_msgs] == list(range(300))
    joint = [m for m in msgs if m.topic == "/samples/joint"]
    sample = reader.to_dataclass(JointSample, joint[5].data)
    assert sample == JointSample("arm0/j1", 1_010_000_001, 5, 0.5, 0.0)


def test_typed_sample_round_trip_and_every_channel_has_a_json_schema(tmp_path):
    from mcap.reader import make_reader

    path = tmp_path / "w.mcap"
    with Recorder(path) as rec:
        rec.record("/samples/wrench/arm0", WRENCH)
    with open(path, "rb") as f:
        mcap_reader = make_reader(f)
        summary = mcap_reader.get_summary()
        for ch in summary.channels.values():
            assert ch.message_encoding == "json"
            schema = summary.schemas[ch.schema_id]
            assert schema.encoding == "jsonschema" and json.loads(schema.data)["type"] == "object"
    (m,) = reader.read_messages(path, ["/samples/wrench/arm0"])
    assert m.log_time_ns == WRENCH.t_ns
    assert reader.to_dataclass(WrenchSample, m.data) == WRENCH


def test_time_window_filters(tmp_path):
    path = tmp_path / "t.mcap"
    with Recorder(path) as rec:
        for i in range(100):                        # one frame per 10 ms from t = 1 s
            rec.record_can("b", _frame(0), log_time_ns=1_000_000_000 + i * 10_000_000)
    window = list(reader.read_messages(path, start_s=0.2, duration_s=0.1))
    assert [m.log_time_ns for m in window] == [1_200_000_000 + i * 10_000_000 for i in range(10)]
    absolute = list(reader.iter_can_frames(path, start_ns=1_500_000_000, end_ns=1_520_000_000, log_time_order=True))
    assert [bus for bus, _, _ in absolute] == ["b", "b"]


def test_notifier_listener_records_frames_from_a_virtual_bus(tmp_path):
    path = tmp_path / "bus.mcap"
    with can.Bus(interface="virtual", channel="rec-test", receive_own_messages=False,
                 ignore_config=True) as rx, \
         can.Bus(interface="virtual", channel="rec-test", ignore_config=True) as tx, \
         Recorder(path) as rec:
        got = threading.Event()
        count = [0]

        class Counter(can.Listener):
            def on_message_received(self, msg):
                count[0] += 1
                if count[0] == 20:
                    got.set()

        notifier = can.Notifier(rx, [rec.can_listener("ft0"), Counter()])
        try:
            for i in range(20):
                tx.send(_frame(i))
            assert got.wait(5)
        finally:
            notifier.stop()
    frames = [m for _, _, m in reader.iter_can_frames(path, log_time_order=True)]
    assert [bytes(m.data) for m in frames] == [bytes(_frame(i).data) for i in range(20)]


# ----------------------------------------------------------------------------- lifecycle

def test_close_twice_is_harmless_and_late_records_are_counted(tmp_path):
    rec = Recorder(tmp_path / "c.mcap")
    rec.record("/w", WRENCH)
    rec.close()
    rec.close()
    assert rec.record("/w", WRENCH) is False
    assert rec.stats.dropped_closed == 1 and rec.stats.written == 1
    with pytest.raises(ValueError, match="closed"):
        rec.add_metadata("late", {})


def test_one_type_per_topic_and_bad_inputs_raise(tmp_path):
    with Recorder(tmp_path / "t.mcap") as rec:
        rec.record("/w", WRENCH)
        with pytest.raises(TypeError, match="expected WrenchSample"):
            rec.record("/w", ImuSample(1, 1, (1, 0, 0, 0), (0, 0, 0), (0, 0, 0)))
        with pytest.raises(TypeError):
            rec.record("/o", object())
        with pytest.raises(TypeError, match="str"):
            rec.add_metadata("m", {"k": 1})
        with pytest.raises(ValueError):
            rec.record_can("bad bus/name", _frame(0))


def test_existing_file_is_not_clobbered(tmp_path):
    path = tmp_path / "keep.mcap"
    path.write_bytes(b"precious")
    with pytest.raises(FileExistsError):
        Recorder(path)
    assert path.read_bytes() == b"precious"
    Recorder(path, overwrite=True).close()
    assert scan.inspect(path).complete


def test_queue_full_is_counted_never_silent(tmp_path):
    rec = Recorder(tmp_path / "q.mcap", queue_size=10)
    gate = threading.Event()
    real = rec._write_message

    def stalled_disk(item):                   # the writer thread blocks, as on a stuck disk
        gate.wait(10)
        real(item)

    rec._write_message = stalled_disk
    results = [rec.record_can("b", _frame(i)) for i in range(50)]
    stats = rec.stats
    assert stats.dropped_queue_full == results.count(False) >= 39
    assert stats.received == results.count(True)
    gate.set()
    rec.close()
    final = rec.stats
    assert final.written == final.flushed == results.count(True)
    assert final.received + final.dropped_queue_full == 50
    assert scan.inspect(rec.paths[0]).message_count == final.written


def test_rotation_by_size_each_file_self_contained(tmp_path):
    base = tmp_path / "rot.mcap"
    with Recorder(base, chunk_size=4096, rotate_bytes=16384) as rec:
        rec.add_session_context(urdf_text="<robot/>", zenoh_keys={"a": "b"})
        for i in range(3000):
            rec.record_can("ft0", _frame(i))
            if i == 1500:
                rec.add_metadata("midway", {"i": str(i)})   # joins the current and later files
    paths = rec.paths
    assert len(paths) >= 3
    assert [p.name for p in paths] == [f"rot_{i:04d}.mcap" for i in range(len(paths))]
    total = 0
    for p in paths:
        info = scan.inspect(p)
        assert info.complete
        assert {"bsc.recording", "zenoh.keys"} <= set(info.metadata)
        assert [a["name"] for a in info.attachments] == ["robot.urdf"]
        assert [c.topic for c in info.channels] == ["/can/ft0"]
        total += info.message_count
    assert total == 3000 == rec.stats.flushed
    assert "midway" in scan.inspect(paths[-1]).metadata
    assert "midway" not in scan.inspect(paths[0]).metadata
    indexes = [scan.inspect(p).metadata["bsc.recording"]["file_index"] for p in paths]
    assert indexes == [str(i) for i in range(len(paths))]


def test_rotation_by_duration(tmp_path, monkeypatch):
    import time as real_time
    import types

    import gateway.log.recorder as recorder_module

    clock = [0.0]                              # the recorder's monotonic clock, driven by hand
    fake = types.SimpleNamespace(monotonic=lambda: clock[0], time_ns=real_time.time_ns,
                                 gmtime=real_time.gmtime, strftime=real_time.strftime)
    monkeypatch.setattr(recorder_module, "time", fake)
    with Recorder(tmp_path / "d.mcap", rotate_s=10.0) as rec:
        for i in range(30):
            clock[0] = float(i)                # 30 "seconds" of recording, one frame each
            rec.record_can("b", _frame(i))
            assert rec.flush(5)
    counts = [scan.inspect(p).message_count for p in rec.paths]
    assert len(counts) == 3 and sum(counts) == 30


# ----------------------------------------------------------------------------- failures

def test_read_only_directory_fails_clearly_at_open(read_only_dir):
    with pytest.raises(OSError) as err:
        Recorder(read_only_dir / "x.mcap")
    assert "x.mcap" in str(err.value)


def _record_until_full(rec: Recorder, limit: int, flush_every: int) -> int:
    """Frames into ``rec`` until it fails (or ``limit``), then its close raises the full disk;
    returns the number of frames offered."""
    i = 0
    while rec.error is None and i < limit:
        rec.record_can("ft0", _frame(i, data=i.to_bytes(8, "little")))
        i += 1
        if i % flush_every == 0:
            rec.flush(10)
    with pytest.raises(RecorderError, match="No space left on device"):
        rec.close()
    return i


def test_full_disk_keeps_what_was_written(tiny_fs):
    rec = Recorder(tiny_fs / "full.mcap", chunk_size=4096, rotate_bytes=32768,
                   compression="none")
    rec.add_attachment("robot.urdf", "application/xml", b"<robot/>" * 100)
    i = _record_until_full(rec, 200_000, flush_every=500)
    rec.close()                                # twice: harmless, no second raise
    stats = rec.stats
    assert stats.dropped_write_error > 0 and stats.written + stats.dropped_queue_full <= i
    *finished, last = rec.paths
    assert finished, "expected at least one rotated file before the disk filled"
    recovered = 0
    for p in finished:
        info = scan.inspect(p)
        assert info.complete
        recovered += info.message_count
    if last.stat().st_size > 0:
        out = tiny_fs.parent / "recovered.mcap"
        try:
            report = scan.recover(last, out)
            recovered += report.messages
        except errors.McapFileError:
            pass                               # the disk filled before the header was written
    # Everything counted as flushed is back, and nothing else: the chunk in flight when the disk
    # filled counts as flushed when its chunk record was complete (only its index or the summary
    # failed: recover finds it), as dropped otherwise
    assert stats.flushed == recovered <= stats.written


def test_a_chunk_written_before_its_index_failed_counts_as_in_the_file(tmp_path, monkeypatch):
    """The disk fills on a chunk's message index, right after the chunk record: the chunk's
    messages are in the file (recover finds them), so the recorder counts them flushed, not dropped."""
    import errno

    from gateway.log import recorder as recorder_module

    real_write, indexes = recorder_module._FdStream.write, [0]

    def write(self, data):
        if bytes(data[:1]) == b"\x07":                     # a MessageIndex record (opcode 0x07)
            indexes[0] += 1
            if indexes[0] == 3:
                raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(self, data)

    monkeypatch.setattr(recorder_module._FdStream, "write", write)
    path = tmp_path / "idx.mcap"
    rec = Recorder(path, chunk_size=4096, compression="none")
    _record_until_full(rec, 20_000, flush_every=100)
    stats = rec.stats
    report = scan.recover(path, tmp_path / "fixed.mcap")
    assert stats.flushed == report.messages > 0
    assert stats.chunks == 3                                # the third chunk's index failed
    assert stats.received == stats.flushed + stats.dropped_write_error   # nothing counted twice


def test_many_producer_threads_lose_nothing(tmp_path):
    path = tmp_path / "mt.mcap"
    with Recorder(path, chunk_size=8192) as rec:
        def produce(bus: str):
            for i in range(3000):
                assert rec.record_can(bus, _frame(i))

        threads = [threading.Thread(target=produce, args=(f"b{k}",)) for k in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert rec.stats.flushed == 12000 and rec.stats.dropped == 0
    for k in range(4):
        frames = [int.from_bytes(m.data[:4], "little")
                  for _, _, m in reader.iter_can_frames(path, buses=[f"b{k}"], log_time_order=True)]
        assert frames == list(range(3000))


def test_flushed_data_is_in_the_file_while_recording(tmp_path):
    path = tmp_path / "open.mcap"
    with Recorder(path, flush_interval_s=3600) as rec:
        rec.add_metadata("m", {"a": "b"})
        for i in range(100):
            rec.record_can("ft0", _frame(i))
        assert rec.flush(10)
        assert rec.stats.flushed == 100
        live = scan.inspect(path)              # the file is still open: no footer yet
        assert not live.complete and live.message_count == 100 and "m" in live.metadata
    assert scan.inspect(path).complete


def test_frames_given_as_rows_are_recorded_as_their_messages():
    """A frame read straight from a socket (a row) is recorded with the bytes python-can's
    message of it would give (classic, FD with 64 bytes, remote, error, extended, ESI)."""
    import random

    import can

    from drivers.kernel import columns_from_messages
    from gateway.log.canframe import can_frame_json, can_frame_json_rows

    rnd = random.Random(4)
    msgs = []
    for k in range(500):
        fd = rnd.random() < 0.3
        n = rnd.choice([0, 8, 12, 64]) if fd else rnd.randint(0, 8)
        msgs.append(can.Message(timestamp=1_700_000_000 + k * 1e-4, arbitration_id=rnd.randrange(2048),
                                is_extended_id=rnd.random() < 0.2, is_remote_frame=not fd and rnd.random() < 0.1,
                                is_error_frame=rnd.random() < 0.05, is_fd=fd, bitrate_switch=fd and rnd.random() < 0.5,
                                error_state_indicator=fd and rnd.random() < 0.2, dlc=n,
                                data=bytes(rnd.randrange(256) for _ in range(n)), channel="vcan1", check=False))
    rows = columns_from_messages([(0, m) for m in msgs])
    assert can_frame_json_rows(rows, "vcan1") == [can_frame_json(m)[1] for m in msgs]


@pytest.mark.parametrize("channel", [["a", "list"], {"a": 1}, 3.5, ("t", 1)])
def test_frames_given_as_rows_take_any_channel_a_bus_may_have(channel):
    """A bus's ``channel`` can be any object (python-can ``virtual``: a list of queues); rows are
    recorded with its text, as a message carrying it is, and never raise (the direct gateway's
    recorder sink takes every batch this way: an exception there lost the whole batch)."""
    import can

    from drivers.kernel import columns_from_messages
    from gateway.log.canframe import can_frame_json, can_frame_json_rows

    msg = can.Message(timestamp=1.5, arbitration_id=0x123, data=b"\x01\x02", channel=channel)
    rows = columns_from_messages([(0, msg)])
    assert can_frame_json_rows(rows, channel) == [can_frame_json(msg)[1]]


def test_records_given_together_keep_their_order_and_refusals_are_counted(tmp_path):
    """record_encoded_many (the row sinks' path): a batch that declares new topics half way is
    written in its own order, and what the queue has no room for is refused and counted."""
    from gateway.efforts import Alert, ThrusterEffort
    from gateway.log.schema import dataclass_json
    from gateway.log.reader import iter_file_order

    def alert(k):
        return Alert("r", "sensor", "imu", "x", "info", "raised", k, k, f"n{k}")

    enc = dataclass_json(Alert)
    batch = [(f"/a/{k % 3}", Alert, enc(alert(k)).encode(), 10 + k) for k in range(9)]
    path = tmp_path / "b.mcap"
    with Recorder(path) as rec:
        assert rec.record_encoded_many(batch) == 0
    assert [(t, m.log_time) for t, _, m in iter_file_order(path)] == [(b[0], b[3]) for b in batch]

    with Recorder(tmp_path / "full.mcap", queue_size=4) as rec:
        refused = rec.record_encoded_many(batch)
        assert 5 <= refused <= 9 and rec.stats.dropped_queue_full == refused

    # every record is checked, not only the first of its topic; a wrong type or time refuses the batch
    with Recorder(tmp_path / "bad.mcap") as rec:
        with pytest.raises(ValueError, match="negative"):
            rec.record_encoded_many(batch[:4] + [(batch[4][0], Alert, batch[4][2], -1)])
        with pytest.raises(TypeError):
            rec.record_encoded_many([(batch[0][0], Alert, batch[0][2], 10), (batch[0][0], ThrusterEffort, b"{}", 11)])


def _alerts_block(n: int):
    """``n`` Alert records on three topics as one block: (topics, classes, which, data, offsets, log_ns)."""
    import numpy as np

    from gateway.efforts import Alert
    from gateway.log.schema import dataclass_json

    enc = dataclass_json(Alert)
    payloads = [enc(Alert("r", "sensor", "imu", "x", "info", "raised", k, k, f"n{k}" * (k % 7))).encode()
                for k in range(n)]
    which = np.array([k % 3 for k in range(n)])
    offsets = np.cumsum([0] + [len(p) for p in payloads])
    log_ns = 10 + np.arange(n) * 1000 - 5000 * (np.arange(n) % 2)     # not in time order
    log_ns -= log_ns.min()
    return ["/a/0", "/a/1", "/a/2"], [Alert] * 3, which, b"".join(payloads), offsets, log_ns


def test_a_block_of_records_is_written_as_the_same_records_one_by_one(tmp_path):
    """record_encoded_block (an offline replay's path): the same messages (topics, log times,
    payloads, sequences) in the same chunks as record_encoded_many, across chunk ends and a
    rotation; queue accounting in messages."""
    from mcap.reader import make_reader

    from gateway.efforts import Alert

    topics, classes, which, data, offsets, log_ns = _alerts_block(3000)
    o = offsets.tolist()

    def read(paths):
        out = []
        for p in paths:
            with open(p, "rb") as f:
                reader = make_reader(f)
                chunks = [(c.message_start_time, c.message_end_time, c.uncompressed_size)
                          for c in reader.get_summary().chunk_indexes]
                out.append(([(ch.topic, m.log_time, m.sequence, bytes(m.data)) for _, ch, m in reader.iter_messages(
                    log_time_order=False)], chunks))
        return out

    kw = dict(chunk_size=4096, rotate_bytes=4 * 4096)
    with Recorder(tmp_path / "one.mcap", **kw) as rec:
        batch = [(topics[w], Alert, data[o[k]:o[k + 1]], int(t)) for k, (w, t) in enumerate(zip(which, log_ns))]
        assert rec.record_encoded_many(batch[:1000]) == 0
        assert rec.record_encoded_many(batch[1000:]) == 0
    with Recorder(tmp_path / "block.mcap", **kw) as rec:
        assert rec.record_encoded_block(topics, classes, which[:1000], data, offsets[:1001], log_ns[:1000]) == 0
        assert rec.record_encoded_block(topics, classes, which[1000:], data[o[1000]:], offsets[1000:],
                                        log_ns[1000:]) == 0
    one, block = read(rec_paths(tmp_path, "one")), read(rec_paths(tmp_path, "block"))
    assert len(one) >= 2 and sum(len(m) for m, _ in one) == 3000       # rotated, nothing lost
    assert block == one


def rec_paths(tmp_path, stem):
    return sorted(tmp_path.glob(f"{stem}_*.mcap"))


def test_a_block_is_refused_where_the_queue_has_no_room_and_bad_times_raise(tmp_path):
    topics, classes, which, data, offsets, log_ns = _alerts_block(50)
    rec = Recorder(tmp_path / "q.mcap", queue_size=20)
    gate = threading.Event()
    real = rec._write_block

    def stalled_disk(item):
        gate.wait(10)
        real(item)

    rec._write_block = stalled_disk
    assert rec.record_encoded_block(topics, classes, which[:15], data, offsets[:16], log_ns[:15]) == 0
    assert rec.stats.queue_depth in (0, 15)           # 15 queued, or taken by the (stalled) writer
    refused = rec.record_encoded_block(topics, classes, which[15:], data[int(offsets[15]):], offsets[15:],
                                       log_ns[15:])
    # room for 20 messages less what is queued (15, and the topics' declarations until the writer takes them)
    assert 15 <= refused <= 33 and rec.stats.dropped_queue_full == refused
    gate.set()
    rec.close()
    final = rec.stats
    assert final.written == final.flushed == 50 - refused
    assert final.received + final.dropped_queue_full == 50
    assert rec.record_encoded_block(topics, classes, which, data, offsets, log_ns) == 50   # closed: all refused
    assert rec.stats.dropped_closed == 50
    with Recorder(tmp_path / "bad.mcap") as rec:
        bad = log_ns.copy()
        bad[4] = -1
        with pytest.raises(ValueError, match="negative"):
            rec.record_encoded_block(topics, classes, which, data, offsets, bad)
