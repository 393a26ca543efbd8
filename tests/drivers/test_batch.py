"""The vectorised batch decoder equals the live decoder on every frame (and cantools)."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings, strategies as st

from drivers import batch, frames, wire

KINDS = ("arm", "spacecraft")


def frame_strategy(kind):
    ids = sorted(wire.layouts(kind))
    good = st.sampled_from(ids).flatmap(
        lambda i: st.tuples(st.just(i), st.binary(min_size=wire.layouts(kind)[i].length,
                                                  max_size=wire.layouts(kind)[i].length)))
    bad = st.tuples(st.one_of(st.sampled_from(ids), st.integers(0, 0x7FF)), st.binary(max_size=8))
    return st.one_of(good, good, bad)


@settings(max_examples=150, deadline=None)
@given(st.sampled_from(KINDS).flatmap(lambda k: st.tuples(st.just(k), st.lists(frame_strategy(k), max_size=60))))
def test_batch_equals_live_on_every_frame(case):
    kind, fr = case
    n = len(fr)
    ids = np.array([i for i, _ in fr], np.int64)
    data = np.zeros((n, 8), np.uint8)
    for k, (_, d) in enumerate(fr):
        data[k, :len(d)] = np.frombuffer(d, np.uint8)
    lengths = np.array([len(d) for _, d in fr], np.int64)
    res = batch.decode_batch(kind, ids, data, lengths, np.arange(n))
    lays = wire.layouts(kind)
    expect_rows = {}
    for k, (i, d) in enumerate(fr):
        lay = lays.get(i)
        if lay is not None and len(d) == lay.length:
            expect_rows.setdefault(lay.name, []).append(k)
    assert set(res.messages) == set(expect_rows)
    for name, m in res.messages.items():
        assert m.rows.tolist() == expect_rows[name]
        lay = lays[m.frame_id]
        for j, row in enumerate(m.rows):
            values, sat = frames.decode_fields(lay, fr[row][1])
            got = tuple(m.fields[s][j].item() for s in lay.signals)
            assert got == values                      # exact: same float64 arithmetic
            assert bool(m.saturated[j]) == sat
    rejected = sum(res.rejected.values())
    assert rejected == n - sum(len(v) for v in expect_rows.values())


def test_batch_matches_cantools():
    rng = np.random.default_rng(1)
    for kind in KINDS:
        db = wire.database(kind)
        lays = list(wire.layouts(kind).values())
        ids = np.array([lays[k].frame_id for k in rng.integers(0, len(lays), 500)])
        data = rng.integers(0, 256, (500, 8), dtype=np.uint8)
        lengths = np.array([wire.layouts(kind)[i].length for i in ids])
        res = batch.decode_batch(kind, ids, data, lengths)
        for m in res.messages.values():
            for j, row in enumerate(m.rows[:20]):
                ref = db.decode_message(int(ids[row]), bytes(data[row, :lengths[row]]), decode_choices=False)
                for s, v in ref.items():
                    assert abs(m.fields[s][j] - v) <= 1e-9 * max(1.0, abs(v))


def test_batch_from_messages_counts_bad_frames():
    msgs = frames.to_messages(frames.wrench_payloads(
        __import__("drivers.samples", fromlist=["WrenchSample"]).WrenchSample("a", 0, 1, (1.0, 2.0, 3.0),
                                                                            (4.0, 5.0, 6.0))))
    import can
    msgs.append(can.Message(arbitration_id=0x200, is_error_frame=True, is_extended_id=False))
    msgs.append(can.Message(arbitration_id=0x200, data=bytes(64), is_fd=True, is_extended_id=False))
    res = batch.decode_batch("arm", *batch.arrays_from_messages(msgs))
    assert res["FT_SG_A"].fields["force_x"].tolist() == [1.0]
    assert res.rejected == {"unknown_id": 1, "dlc": 1}
