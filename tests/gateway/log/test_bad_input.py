"""Bad files: every reader entry point and the CLI give one clear line, never a traceback/hang."""
from __future__ import annotations

import base64
import struct
import zlib

import can
import pytest

from gateway.log import errors, reader, scan
from gateway.log.recorder import Recorder

PNG = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + bytes(13) + b"\0\0\0\0"


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    path = tmp_path_factory.mktemp("good") / "good.mcap"
    with Recorder(path, chunk_size=2048, compression="none") as rec:
        rec.add_attachment("robot.urdf", "application/xml", b"<robot/>")
        for i in range(400):
            rec.record_can("ft0", can.Message(timestamp=1 + i * 1e-3, arbitration_id=1,
                                              data=i.to_bytes(8, "little")))
    return path.read_bytes()


def _payload_at(data: bytes, i: int) -> int:
    """Offset of frame ``i``'s base64 payload inside its (uncompressed) chunk."""
    return data.index(base64.b64encode(i.to_bytes(8, "little")))


def _flip(data: bytes, at: int) -> bytes:
    return data[:at] + bytes([data[at] ^ 0xFF]) + data[at + 1:]


# name -> (file bytes from the good file, expected: "error" message part or "recover")
CASES = {
    "empty": (lambda g: b"", "error", "empty file"),
    "text": (lambda g: b"time,value\n1,2\n", "error", "not an MCAP file"),
    "png": (lambda g: PNG, "error", "not an MCAP file"),
    "magic only": (lambda g: g[:8], "error", "truncated before the first record"),
    "half magic": (lambda g: g[:4], "error", "truncated inside the MCAP magic"),
    "half header": (lambda g: g[:20], "error", "truncated before the first record"),
    "zeros": (lambda g: bytes(4096), "error", "not an MCAP file"),
    "magic then garbage": (lambda g: g[:8] + bytes(range(256)) * 4, "error", "no header"),
    "truncated mid-file": (lambda g: g[: len(g) // 2], "recover", None),
    "truncated by one byte": (lambda g: g[:-1], "recover", None),
    "summary cut off": (lambda g: g[: len(g) - 200], "recover", None),
    "flipped byte in a chunk": (lambda g: _flip(g, _payload_at(g, 200)), "recover", None),
    "garbage appended": (lambda g: g[: len(g) // 2] + bytes(range(256)), "recover", None),
}


@pytest.mark.parametrize("name", list(CASES))
def test_bad_file_table(name, good, tmp_path, bsc):
    make, outcome, message = CASES[name]
    path = tmp_path / "bad.mcap"
    path.write_bytes(make(good))
    if outcome == "error":
        for call in (lambda: scan.inspect(path), lambda: scan.recover(path),
                     lambda: list(reader.read_messages(path))):
            with pytest.raises(errors.McapFileError, match=message):
                call()
        for cmd in ("info", "recover"):
            proc = bsc(cmd, path, timeout=30)
            assert proc.returncode == 2, proc.stderr
            assert proc.stdout == ""
            assert proc.stderr.count("\n") == 1 and message in proc.stderr, proc.stderr
            assert proc.stderr.startswith(f"bsc {cmd}: error: ")
        assert not (tmp_path / "bad.recovered.mcap").exists()
        return
    info = scan.inspect(path)
    assert not info.complete
    with pytest.raises(errors.McapFileError, match="bsc recover"):
        list(reader.read_messages(path))
    report = scan.recover(path)
    assert scan.inspect(report.output).complete
    frames = [int.from_bytes(m.data, "little")
              for _, _, m in reader.iter_can_frames(report.output, log_time_order=True)]
    if name == "flipped byte in a chunk":
        assert report.chunks_skipped == 1 and 0 < len(frames) < 400
        assert frames == sorted(frames)
    else:
        assert frames == list(range(len(frames))) and len(frames) > 0
    proc = bsc("info", path)
    assert proc.returncode == 0 and "bsc recover" in proc.stdout


def test_directory_and_missing_file_are_one_line_errors(tmp_path, bsc):
    for target in (tmp_path, tmp_path / "missing.mcap"):
        proc = bsc("info", target)
        assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
        assert "Traceback" not in proc.stderr


def test_recover_refuses_to_overwrite(good, tmp_path, bsc):
    src = tmp_path / "in.mcap"
    src.write_bytes(good[:-100])
    out = tmp_path / "out.mcap"
    out.write_bytes(b"keep")
    proc = bsc("recover", src, "-o", out)
    assert proc.returncode == 2 and "--force" in proc.stderr and out.read_bytes() == b"keep"
    proc = bsc("recover", src, "-o", src)
    assert proc.returncode == 2 and "overwrite the file being recovered" in proc.stderr
    assert bsc("recover", src, "-o", out, "--force").returncode == 0
    assert scan.inspect(out).complete


def test_crc_of_summary_is_checked(good, tmp_path):
    path = tmp_path / "crc.mcap"
    footer_crc_at = len(good) - 8 - 4
    (crc,) = struct.unpack("<I", good[footer_crc_at:footer_crc_at + 4])
    assert crc != 0 and crc == zlib.crc32(good[_summary_start(good):footer_crc_at])
    path.write_bytes(_flip(good, _summary_start(good) + 20))     # inside the summary
    ok, why = scan.check_footer(path)
    assert not ok and "CRC" in why


def _summary_start(data: bytes) -> int:
    return struct.unpack("<Q", data[-8 - 29 + 9:-8 - 29 + 17])[0]


@pytest.fixture(scope="module")
def long_log(tmp_path_factory):
    """About 400 zstd chunks of CAN frames and typed records on three buses."""
    import random

    rnd = random.Random(2)
    path = tmp_path_factory.mktemp("long") / "long.mcap"
    with Recorder(path, chunk_size=16 * 1024, queue_size=1 << 20) as rec:
        rec.add_attachment("robot.urdf", "application/xml", b"<robot/>")
        rec.add_metadata("bsc.session", {"robot": "x"})
        for i in range(60_000):
            rec.record_can(("arm0", "arm1", "spacecraft")[i % 3],
                           can.Message(timestamp=1.0 + i * 1e-4, arbitration_id=rnd.randrange(2048),
                                       data=rnd.randbytes(8)))
            if i % 20 == 0:
                rec.record("bsc/x/note", {"i": i, "v": rnd.random()}, log_time_ns=1_000_000_000 + i * 100_000)
    return path


def _messages(path):
    out = []
    scan.scan(path, on_message=lambda ch, m: out.append((ch.topic, m.log_time, bytes(m.data))))
    return out


@pytest.mark.parametrize("content_damaged", [True, False])
def test_a_chunk_whose_length_is_damaged_does_not_take_the_chunks_after_it(long_log, tmp_path, content_damaged):
    """No CRC covers a chunk record's length. One chunk's length made to reach 100 chunks further
    (with its data damaged too, or intact): recover keeps every message of every other chunk (and
    of that one when its data is intact), and reports the region. Before, the walk trusted the
    length: a chunk of 16 KiB that announced 1.5 MiB took 560 intact chunks with it (a suite run of
    2026-11-28, 1000 flips)."""
    from mcap.reader import make_reader

    data = bytearray(long_log.read_bytes())
    with open(long_log, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    i = len(chunks) // 2
    c, far = chunks[i], chunks[i + 100]
    length = far.chunk_start_offset + far.chunk_length // 2 - c.chunk_start_offset - 9
    struct.pack_into("<Q", data, c.chunk_start_offset + 1, length)
    if content_damaged:
        data[c.chunk_start_offset + c.chunk_length - 100] ^= 0xFF        # inside its compressed records
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data)
    want = _messages(long_log)
    got = _messages(bad)
    assert set(got) <= set(want)
    lost = len(want) - len(got)
    per_chunk = len(want) / len(chunks)
    assert (lost < 2 * per_chunk) if content_damaged else lost == 0, (lost, per_chunk)
    report = scan.recover(bad, tmp_path / "rec.mcap")
    assert len(_messages(tmp_path / "rec.mcap")) == len(got)
    assert report.bytes_skipped < 3 * c.chunk_length, report.damage


def test_recover_keeps_every_intact_chunk_after_damage_in_the_middle(long_log, tmp_path):
    """1000 random bytes flipped in the middle tenth of a session: recover keeps >= 99 % of the
    messages of the chunks the flips did not touch (before: everything after the first damaged
    record was lost), keeps no message that was not in the original, and bsc info names every
    damaged chunk's bytes among its skipped regions."""
    import random

    from mcap.reader import make_reader
    from mcap.stream_reader import breakup_chunk

    data = bytearray(long_log.read_bytes())
    with open(long_log, "rb") as f:
        reader = make_reader(f)
        chunks = sorted(reader.get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) > 300
    rnd = random.Random(7)
    lo, hi = int(len(data) * 0.45), int(len(data) * 0.55)
    flips = sorted(rnd.sample(range(lo, hi), 1000))
    for at in flips:
        data[at] ^= 1 + rnd.randrange(255)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data)

    def hit(c):
        a, b = c.chunk_start_offset, c.chunk_start_offset + c.chunk_length
        return any(a <= x < b for x in flips)

    intact = [c for c in chunks if not hit(c)]
    damaged = [c for c in chunks if hit(c)]
    assert 0 < len(damaged) < 0.2 * len(chunks)
    with open(long_log, "rb") as f:              # the intact chunks' messages, from the original
        f.seek(0)
        raw = f.read()
    from mcap.stream_reader import StreamReader
    import io

    def messages_of(c):
        """(channel id, log time, bytes) of every message of chunk ``c`` in the original file."""
        rec = next(iter(StreamReader(io.BytesIO(raw[c.chunk_start_offset:c.chunk_start_offset + c.chunk_length]),
                                     skip_magic=True, emit_chunks=True).records))
        return [(r.channel_id, r.log_time, bytes(r.data)) for r in breakup_chunk(rec) if type(r).__name__ == "Message"]

    want = sum(len(messages_of(c)) for c in intact)

    report = scan.recover(bad, tmp_path / "rec.mcap")
    kept = _messages(tmp_path / "rec.mcap")
    original = set(_messages(long_log))
    assert all(m in original for m in kept)
    assert len(kept) >= 0.99 * want, (len(kept), want, report.damage)
    assert report.damage and report.bytes_skipped > 0

    info = scan.inspect(bad)
    assert not info.complete and info.status.startswith("damaged: ")
    # truthful: a chunk that lost messages lies in a reported region; one that was not reported
    # kept every message (a flip in its header's time fields, which no CRC covers, harms nothing)
    regions = sorted(info.skipped)
    assert all(a[1] <= b[0] for a, b in zip(regions, regions[1:])), regions     # counted once each
    kept_data = {(t, d) for _, t, d in kept}
    for c in damaged:
        a, b = c.chunk_start_offset, c.chunk_start_offset + c.chunk_length
        if not any(s < b and a < e for s, e, _ in info.skipped):     # no reported region overlaps it
            lost = [m for m in messages_of(c) if (m[1], m[2]) not in kept_data]
            assert not lost, (a, b, len(lost), [x - a for x in flips if a <= x < b], info.skipped[:8])
