"""The recorder's MCAP writer (gateway/log/writer.py) writes what mcap's own Writer writes."""
from __future__ import annotations

import io
import random

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from gateway.log import scan
from gateway.log.writer import McapWriter


def _calls(rnd: random.Random):
    """A recording's calls: metadata, attachments, schemas and channels (some registered late),
    messages out of time order, chunks ended at random points, an empty chunk end."""
    calls = [("add_metadata", "bsc.recording", {"a": "1", "b": "x"}),
             ("add_attachment", 5, 5, "robot.urdf", "application/xml", b"<robot/>" * 50),
             ("register_schema", "S1", "jsonschema", b'{"type":"object"}'),
             ("register_channel", "/a", "json", 1, {"k": "v"}),
             ("register_channel", "/b", "json", 1, {})]
    channels = 2
    for k in range(3000):
        r = rnd.random()
        if r < 0.002:
            calls.append(("register_schema", f"S{k}", "jsonschema", b'{"type":"object","title":"%d"}' % k))
        elif r < 0.004:
            calls.append(("register_channel", f"/c{k}", "json", 1, {}))
            channels += 1
        elif r < 0.012:
            calls.append(("flush",))
        elif r < 0.013:
            calls.append(("add_metadata", f"m{k}", {"k": str(k)}))
        else:
            data = bytes(rnd.getrandbits(8) for _ in range(rnd.randint(0, 90)))
            calls.append(("add_message", rnd.randint(1, channels), 1_000_000 + rnd.randint(-5000, 5000) + 1000 * k,
                          data, 7 * k, k & 0xFFFFFFFF))
    calls += [("flush",), ("flush",)]
    return calls


def _play(writer, calls, ours: bool) -> None:
    writer.start(profile="", library="bsc-test")
    for name, *args in calls:
        if name == "flush":
            writer.end_chunk() if ours else writer.flush()
        elif name == "add_message":
            cid, log, data, pub, seq = args
            writer.add_message(cid, log, data, pub, seq)
        else:
            getattr(writer, name)(*args)
    writer.finish()


@pytest.mark.parametrize("compression", [CompressionType.ZSTD, CompressionType.NONE])
@pytest.mark.parametrize("seed", [1, 2])
def test_byte_for_byte_what_the_library_writes(compression, seed):
    calls = _calls(random.Random(seed))
    lib, ours = io.BytesIO(), io.BytesIO()
    _play(Writer(lib, chunk_size=1 << 62, compression=compression), calls, ours=False)
    # the library compresses at zstd's default level (3); ours at ZSTD_LEVEL unless told
    _play(McapWriter(ours, compression=compression, zstd_level=3), calls, ours=True)
    assert ours.getvalue() == lib.getvalue()
    ours.seek(0)
    reader = make_reader(ours)
    summary = reader.get_summary()
    n = sum(1 for c in calls if c[0] == "add_message")
    assert summary.statistics.message_count == n == sum(1 for _ in reader.iter_messages())
    assert summary.statistics.chunk_count == len(summary.chunk_indexes) > 10


def test_a_recorder_file_is_complete_and_reads_back(tmp_path):
    from gateway.log.recorder import Recorder

    path = tmp_path / "s.mcap"
    with Recorder(path, chunk_size=4096) as rec:
        for k in range(5000):
            rec.record("/t", {"t_ns": k, "v": k * 0.25}, log_time_ns=1_000 + k)
    info = scan.inspect(path)
    assert info.complete and rec.stats.written == 5000 and rec.stats.chunks > 10
    with open(path, "rb") as f:
        got = [(m.log_time, m.data) for _, _, m in make_reader(f).iter_messages(topics=["/t"])]
    assert [t for t, _ in got] == list(range(1_000, 6_000))
    assert got[7][1] == b'{"t_ns":7,"v":1.75}'


def _play_blocks(writer, calls, rnd: random.Random) -> None:
    """The same calls, runs of messages handed over as blocks (random lengths; the publish
    times of a block are one, so a block is cut where the next message's differs)."""
    import numpy as np

    writer.start(profile="", library="bsc-test")
    run: list = []

    def put() -> None:
        if run:
            data = b"".join(m[2] for m in run)
            offsets = np.cumsum([0] + [len(m[2]) for m in run]) + 1000       # offsets need not start at 0
            writer.add_messages(np.array([m[0] for m in run]), np.array([m[1] for m in run]), data, offsets,
                                run[0][3], np.array([m[4] for m in run], dtype=np.uint32))
            run.clear()

    for name, *args in calls:
        if name == "add_message":
            if run and (args[3] != run[0][3] or rnd.random() < 0.05):
                put()
            if rnd.random() < 0.1:                                          # some one by one, between blocks
                put()
                writer.add_message(*args)
            else:
                run.append(args)
            continue
        put()
        if name == "flush":
            writer.end_chunk()
        else:
            getattr(writer, name)(*args)
    put()
    writer.finish()


@pytest.mark.parametrize("seed", [1, 2])
def test_blocks_of_messages_write_the_same_bytes(seed):
    calls = _calls(random.Random(seed))
    # a block has one publish time: runs of 40 messages share one
    calls = [("add_message", *c[1:4], c[4] // 40, c[5]) if c[0] == "add_message" else c for c in calls]
    lib, ours = io.BytesIO(), io.BytesIO()
    _play(Writer(lib, chunk_size=1 << 62, compression=CompressionType.ZSTD), calls, ours=False)
    _play_blocks(McapWriter(ours, compression=CompressionType.ZSTD, zstd_level=3), calls, random.Random(seed))
    assert ours.getvalue() == lib.getvalue()


def test_chunks_at_our_zstd_level_read_back_the_same(tmp_path):
    """At :data:`ZSTD_LEVEL` the chunks differ from the library's, their content does not: the same
    records, and the chunks' CRCs (computed with ISA-L) check out in mcap's own reader."""
    from gateway.log.writer import ZSTD_LEVEL

    assert ZSTD_LEVEL != 3                      # else the byte-for-byte test above covers it
    calls = _calls(random.Random(3))
    lib, ours = io.BytesIO(), io.BytesIO()
    _play(Writer(lib, chunk_size=1 << 62, compression=CompressionType.ZSTD), calls, ours=False)
    _play(McapWriter(ours, compression=CompressionType.ZSTD), calls, ours=True)
    assert ours.getvalue() != lib.getvalue()

    def records(buf):
        buf.seek(0)
        return [(c.topic, m.log_time, m.publish_time, m.sequence, bytes(m.data))
                for _, c, m in make_reader(buf, validate_crcs=True).iter_messages(log_time_order=False)]

    assert records(ours) == records(lib)
