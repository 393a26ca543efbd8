"""How many messages per second the MCAP recorder sustains, beside the raw mcap writer.

Run: ``python -m benchmarks.bench_recorder [--n N]``. Three figures, measured in one run on the
same machine, with the recorder's default chunking (128 KiB, zstd):

- anchor: ``mcap.Writer.add_message`` of pre-encoded bytes (the library's floor: no JSON, no
  queue, no thread), same chunk size and compression;
- raw CAN frames: ``Recorder.record_can`` of python-can Messages (8-byte payloads);
- typed samples: ``Recorder.record`` of ``WrenchSample`` dataclasses.

For the recorder, "calls/s" is the rate the producer can hand messages over (encode + enqueue)
and "sustained/s" is messages over the time until the file is finished (queue drained, summary
written), i.e. what it can keep up with indefinitely. The queue is sized to N so nothing is
dropped; the drop count is printed to prove it.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path


def bench_anchor(path: Path, payloads: list[bytes]) -> float:
    from mcap.writer import Writer

    t0 = time.perf_counter()
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=128 * 1024)
        w.start()
        sid = w.register_schema("bsc.CanFrame", "jsonschema", b"{}")
        cid = w.register_channel("/can/ft0", "json", sid)
        for i, data in enumerate(payloads):
            w.add_message(cid, i, data, i)
        w.finish()
    return len(payloads) / (time.perf_counter() - t0)


def bench_recorder(path: Path, n: int, feed) -> tuple[float, float, int]:
    from gateway.log.recorder import Recorder

    rec = Recorder(path, queue_size=n + 1)
    t0 = time.perf_counter()
    feed(rec)
    t1 = time.perf_counter()
    rec.close()
    t2 = time.perf_counter()
    stats = rec.stats
    assert stats.flushed == n - stats.dropped, stats
    return n / (t1 - t0), n / (t2 - t0), stats.dropped


def measure(n: int) -> dict:
    """Every figure for ``n`` messages per case (files in a temporary directory)."""
    import can

    from drivers.samples import WrenchSample
    from gateway.log.canframe import can_frame_to_record
    from gateway.log.schema import encode_json

    frames = [can.Message(timestamp=1.0 + i * 1e-4, arbitration_id=0x100 + i % 8,
                          data=i.to_bytes(8, "little"), channel="vcan0") for i in range(n)]
    samples = [WrenchSample("arm0", 1_000_000_000 + i * 100_000, i, (0.1 * i, -2.0, 9.81),
                            (0.01, 0.02, 0.03)) for i in range(n)]
    payloads = [encode_json(can_frame_to_record(m)).encode() for m in frames]

    def feed_can(rec):
        record = rec.record_can
        for m in frames:
            record("ft0", m)

    def feed_samples(rec):
        record = rec.record
        for s in samples:
            record("/samples/wrench/arm0", s)

    with tempfile.TemporaryDirectory(prefix="bench_recorder_") as tmp:
        d = Path(tmp)
        anchor = bench_anchor(d / "anchor.mcap", payloads)
        can_calls, can_sust, can_drop = bench_recorder(d / "can.mcap", n, feed_can)
        smp_calls, smp_sust, smp_drop = bench_recorder(d / "samples.mcap", n, feed_samples)
        sizes = {p.name: p.stat().st_size for p in d.iterdir()}
    return {"n": n, "anchor": anchor, "can_calls": can_calls, "can_sust": can_sust,
            "can_drop": can_drop, "smp_calls": smp_calls, "smp_sust": smp_sust,
            "smp_drop": smp_drop, "can_bytes": sizes["can.mcap"] / n,
            "smp_bytes": sizes["samples.mcap"] / n}


def figures(quick: bool = False) -> list[dict]:
    """The suite's rows: sustained recorder rates beside the python-can virtual bus (can the
    recorder keep up with a bus?), and the recorder as a fraction of the bare mcap writer."""
    from benchmarks.anchors import ratio, row

    m = measure(20_000 if quick else 100_000)
    n = m["n"]
    return [
        row("bare mcap Writer.add_message (pre-encoded)", m["anchor"], "msg/s",
            anchor="can_virtual", ratio=ratio(m["anchor"], "can_virtual"),
            note=f"{n} messages, chunk 128 KiB zstd"),
        row("recorder raw CAN frames, sustained", m["can_sust"], "msg/s", anchor="can_virtual",
            ratio=ratio(m["can_sust"], "can_virtual"),
            note=f"{m['can_sust'] / m['anchor']:.2f}x the bare mcap writer; calls "
                 f"{m['can_calls']:,.0f}/s; dropped {m['can_drop']}; {m['can_bytes']:.1f} B/msg"),
        row("recorder typed samples, sustained", m["smp_sust"], "msg/s", anchor="can_virtual",
            ratio=ratio(m["smp_sust"], "can_virtual"),
            note=f"{m['smp_sust'] / m['anchor']:.2f}x the bare mcap writer; calls "
                 f"{m['smp_calls']:,.0f}/s; dropped {m['smp_drop']}; {m['smp_bytes']:.1f} B/msg"),
    ]


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=100_000, help="messages per case")
    args = parser.parse_args(argv)

    m = measure(args.n)
    n, anchor = m["n"], m["anchor"]
    print(f"recorder benchmark, {n} messages per case, chunk 128 KiB zstd")
    print(f"  anchor  mcap Writer.add_message (pre-encoded): {anchor:>10,.0f} msg/s")
    print(f"  raw CAN frames   record_can:  calls {m['can_calls']:>10,.0f} msg/s   "
          f"sustained {m['can_sust']:>10,.0f} msg/s   ({m['can_sust'] / anchor:.2f} x anchor, "
          f"dropped {m['can_drop']}, {m['can_bytes']:.1f} B/msg on disk)")
    print(f"  typed samples    record:      calls {m['smp_calls']:>10,.0f} msg/s   "
          f"sustained {m['smp_sust']:>10,.0f} msg/s   ({m['smp_sust'] / anchor:.2f} x anchor, "
          f"dropped {m['smp_drop']}, {m['smp_bytes']:.1f} B/msg on disk)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
