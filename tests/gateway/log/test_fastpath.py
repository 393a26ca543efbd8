"""The recorder's and the replay reader's fast paths against the plain forms: the prebuilt JSON
encoder, the direct MCAP message append, the record walker of ``iter_file_order`` and the
exact-format parser of CAN frame records."""
from __future__ import annotations

import json
import math
import random

import can
import pytest

from drivers.samples import BusHealth, DeviceHealth, ImuSample, JointSample, WrenchSample
from gateway.log import scan
from gateway.log import canframe, schema
from gateway.log.names import CAN_TOPIC_PREFIX
from gateway.log import recorder as rc
from gateway.log import reader
from gateway.efforts import JointEfforts, ThrusterEffort


def _samples(rnd: random.Random, n: int):
    odd = [math.nan, math.inf, -math.inf, -0.0, 1e-310, 1.7976931348623157e308, 0.1, 1 / 3]
    f = lambda: rnd.choice(odd) if rnd.random() < 0.1 else rnd.uniform(-1e3, 1e3)  # noqa: E731
    names = ["arm0", "arm0/j1", "bras-\u00e9", "quote\"d", "back\\slash", "tab\tx", "\u2603"]
    for k in range(n):
        yield rnd.choice([
            WrenchSample(rnd.choice(names), k, k & 0xFF, (f(), f(), f()), (f(), f(), f()), rnd.random() < .5, 3),
            JointSample(rnd.choice(names), k, 7, f(), f()),
            ImuSample(k, 1, (f(), f(), f(), f()), (f(), f(), f()), (f(), f(), f()), True, 0x300),
            JointEfforts(rnd.choice(names), k, ("a/j1", "a/j2"), (f(), f()), (f(), f()), (), 0, (f(), f()),
                         False, ("missing:a", "stale:imu")),
            ThrusterEffort(k, (f(), f(), f()), (f(), f(), f()), (0.0,) * 3, (0.0,) * 3, 0, 5, True),
            DeviceHealth("imu", "spacecraft", k, 1, 2, 3, (("dlc", 1), ("late", 2)), 4, False),
            BusHealth("arm0", k, 9, (), f(), (("ft", 5),)),
        ])


def test_prebuilt_json_encoder_gives_the_same_bytes():
    """The prebuilt per-type encoder gives the generic encoder's bytes (named counts such as a
    health's rejected as [{"name", "value"}] in both)."""
    seen_pairs = False
    for s in _samples(random.Random(1), 3000):
        got = schema.dataclass_json(type(s))(s)
        assert got == schema.encode_json(schema.record_of(s))
        assert got.startswith('{"type":"%s","v":1,' % type(s).__name__)
        seen_pairs |= '"rejected":[{"name":"dlc","value":1}' in got
    assert seen_pairs


def _content(path):
    return [(t, s, m.log_time, bytes(m.data)) for t, s, m in reader.iter_file_order(path)]


def test_record_walker_reads_what_a_full_scan_reads(tmp_path):
    path = tmp_path / "s.mcap"
    rnd = random.Random(3)
    with rc.Recorder(path, chunk_size=8 * 1024) as rec:
        for k, s in enumerate(_samples(rnd, 3000)):
            rec.record(f"/t/{k % 5}", {"t_ns": k, "v": k * 0.5}) if k % 11 == 0 else \
                rec.record(f"/s/{type(s).__name__}", s, log_time_ns=5_000 + k)
    ref = []
    scan.scan(path, lambda ch, m: ref.append((ch.topic, m.log_time, bytes(m.data))))
    assert [(t, lt, d) for t, _, lt, d in _content(path)] == ref
    window = [(t, lt, d) for t, _, m in reader.iter_file_order(path, lambda t, s: t.startswith("/s/"), 6000, 7000)
              for lt, d in [(m.log_time, bytes(m.data))]]
    assert window == [x for x in ref if x[0].startswith("/s/") and 6000 <= x[1] < 7000]


@pytest.mark.parametrize("channel", [None, 0, 7, -1, "can0", "vcan 1", 'q"uote', "\u00e9", "a\\b", "tab\tx"])
def test_can_record_parser_equals_json(tmp_path, channel):
    rnd = random.Random(str(channel))
    msgs = []
    for k in range(300):
        msgs.append(can.Message(
            timestamp=rnd.choice([0.0, 1767000000.123456789, rnd.random() * 1e9]) + k,
            arbitration_id=rnd.randrange(1 << 29), is_extended_id=rnd.random() < .5,
            is_remote_frame=rnd.random() < .2, is_error_frame=rnd.random() < .2, is_fd=rnd.random() < .3,
            bitrate_switch=rnd.random() < .3, error_state_indicator=rnd.random() < .3, is_rx=rnd.random() < .8,
            dlc=rnd.randrange(16), data=bytes(rnd.getrandbits(8) for _ in range(rnd.randrange(65))),
            channel=channel, check=False))
    path = tmp_path / "c.mcap"
    with rc.Recorder(path) as rec:
        for m in msgs:
            rec.record_can("bus0", m)
    got = list(reader.iter_can_frames(path))
    ref = []
    for topic, _, m in reader.iter_file_order(path):
        ref.append((topic[len(CAN_TOPIC_PREFIX):], m.log_time, canframe.can_frame_from_record(json.loads(m.data))))
    assert len(got) == len(ref) == len(msgs)
    for (b1, t1, m1), (b2, t2, m2) in zip(got, ref):
        assert (b1, t1) == (b2, t2)
        for attr in ("timestamp", "arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame", "is_fd",
                     "bitrate_switch", "error_state_indicator", "is_rx", "dlc", "data", "channel"):
            assert getattr(m1, attr) == getattr(m2, attr) and type(getattr(m1, attr)) is type(getattr(m2, attr)), attr


def test_can_record_parser_refuses_what_json_refuses():
    bad = [b'{"t_ns":007,"arbitration_id":1,"is_extended_id":false,"is_remote_frame":false,'
           b'"is_error_frame":false,"is_fd":false,"bitrate_switch":false,"error_state_indicator":false,'
           b'"is_rx":true,"dlc":0,"data":"","channel":null}',
           b'{"t_ns":1,"arbitration_id":1,"is_extended_id":false,"is_remote_frame":false,'
           b'"is_error_frame":false,"is_fd":false,"bitrate_switch":false,"error_state_indicator":false,'
           b'"is_rx":true,"dlc":0,"data":"","channel":"\x01"}']
    for raw in bad:
        assert canframe._CAN_RECORD.fullmatch(raw) is None
        with pytest.raises(ValueError):
            json.loads(raw)


def test_can_frame_json_is_the_encoders_bytes():
    """The recorder's fast CAN-frame encoding gives exactly what encoding the record dict gives,
    for classic and FD frames, remote and error frames, every kind of channel."""
    from gateway.log.canframe import can_frame_json, can_frame_to_record
    from gateway.log.schema import encode_json

    rng = random.Random(7)
    for _ in range(3000):
        fd = rng.random() < 0.3
        n = rng.choice([0, 1, 8, 12, 64]) if fd else rng.randrange(9)
        ext = rng.random() < 0.5
        m = can.Message(timestamp=rng.random() * 2e9, arbitration_id=rng.randrange(1 << (29 if ext else 11)),
                        is_extended_id=ext, is_fd=fd, bitrate_switch=fd and rng.random() < 0.5,
                        error_state_indicator=fd and rng.random() < 0.5, is_rx=rng.random() < 0.5,
                        is_remote_frame=not fd and rng.random() < 0.1, is_error_frame=rng.random() < 0.05,
                        data=bytes(rng.randrange(256) for _ in range(n)),
                        channel=rng.choice([None, "vcan0", "239.74.163.1", 3, 'we"ird\\ch', ("x", 1)]), check=False)
        rec = can_frame_to_record(m)
        assert can_frame_json(m) == (rec["t_ns"], encode_json(rec).encode())
