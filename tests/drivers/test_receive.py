"""Reading a bus's socket straight into frame rows: the same rows python-can's own reading gives
(through ``columns_from_messages``), for SocketCAN frames and python-can's udp_multicast
datagrams, and bad datagrams counted, never raised."""
from __future__ import annotations

import random
import socket
import struct

import can
import numpy as np
import pytest
from can.interfaces.socketcan.socketcan import build_can_frame, dissect_can_frame
from can.interfaces.udp_multicast.utils import pack_message, unpack_message

from drivers import receive
from drivers.kernel import FRAME_DTYPE, columns_from_messages


def _messages(n: int, seed: int = 0) -> list[can.Message]:
    rnd = random.Random(seed)
    out = []
    for _ in range(n):
        fd = rnd.random() < 0.3
        ext = rnd.random() < 0.2
        length = rnd.choice([0, 1, 5, 8, 12, 64]) if fd else rnd.randint(0, 8)
        out.append(can.Message(
            arbitration_id=rnd.randrange(1 << 29) if ext else rnd.randrange(1 << 11), is_extended_id=ext,
            is_remote_frame=not fd and rnd.random() < 0.05, is_error_frame=rnd.random() < 0.02, is_fd=fd,
            bitrate_switch=fd and rnd.random() < 0.5, error_state_indicator=fd and rnd.random() < 0.1,
            data=bytes(rnd.randrange(256) for _ in range(length)), dlc=length, check=False))
    return out


def _slots(datagrams: list[bytes], slot: int):
    raw = np.zeros((len(datagrams), slot), dtype=np.uint8)
    lens = np.zeros(len(datagrams), dtype=np.int64)
    for i, d in enumerate(datagrams):
        raw[i, :len(d)] = np.frombuffer(d, dtype=np.uint8)
        lens[i] = len(d)
    return raw, lens


def test_socketcan_frames_give_python_cans_rows():
    msgs = _messages(3000)
    frames = [build_can_frame(m) for m in msgs]
    ts = np.arange(len(frames), dtype=np.int64) * 1_000_003 + 1_700_000_000_123_456_789
    want = []
    for f, t in zip(frames, ts.tolist()):           # python-can's own reading of each datagram
        can_id, dlc, flags, data = dissect_can_frame(f)
        m = can.Message(timestamp=t / 1e9, arbitration_id=can_id & (0x1FFFFFFF if can_id & 0x80000000 else 0x7FF),
                        is_extended_id=bool(can_id & 0x80000000), is_remote_frame=bool(can_id & 0x40000000),
                        is_error_frame=bool(can_id & 0x20000000), is_fd=len(f) == 72,
                        bitrate_switch=bool(flags & 1), error_state_indicator=bool(flags & 2), dlc=dlc, data=data,
                        check=False)
        want.append((2, m))
    want_rows = columns_from_messages(want)
    want_rows["t_ns"] = ts                          # exact ns here; python-can's floats round
    raw, lens = _slots(frames, receive.SOCKETCAN_SLOT)
    out = np.zeros(len(frames), dtype=FRAME_DTYPE)
    little = struct.pack("=I", 1) == struct.pack("<I", 1)
    k = receive.parse_socketcan(raw, lens, ts, 2, little, receive._FD_DLC, out)
    assert k == len(frames)
    assert out.tobytes() == want_rows.tobytes()


def test_udp_multicast_datagrams_give_python_cans_rows():
    msgs = _messages(3000, seed=1)
    grams = [pack_message(m) for m in msgs]
    ts = np.arange(len(grams), dtype=np.int64) * 997 + 1_700_000_000_000_000_000
    want = columns_from_messages([(1, unpack_message(g, replace={"timestamp": t / 1e9}))
                                  for g, t in zip(grams, ts.tolist())])
    want["t_ns"] = ts
    raw, lens = _slots(grams, receive.UDP_SLOT)
    out = np.zeros(len(grams), dtype=FRAME_DTYPE)
    bad = np.zeros(1, dtype=np.int64)
    keys = tuple(np.frombuffer(k.encode(), dtype=np.uint8).copy() for k in receive._UDP_KEYS)
    assert receive.parse_udp(raw, lens, ts, 1, keys, out, bad) == len(grams) and bad[0] == 0
    assert out.tobytes() == want.tobytes()


@pytest.mark.parametrize("gram", [b"", b"\x00", b"\x93\x01\x02\x03", b"\x81\xa3abc\xc1",
                                  pack_message(can.Message(data=b"12"))[:-3],
                                  b"\x82\xaearbitration_id\x05\xa3dlc\x02"])      # no data field
def test_bad_datagrams_are_counted_not_raised(gram):
    raw, lens = _slots([gram, pack_message(can.Message(arbitration_id=7, data=b"ok", timestamp=0.0))],
                       receive.UDP_SLOT)
    out = np.zeros(2, dtype=FRAME_DTYPE)
    bad = np.zeros(1, dtype=np.int64)
    keys = tuple(np.frombuffer(k.encode(), dtype=np.uint8).copy() for k in receive._UDP_KEYS)
    k = receive.parse_udp(raw, lens, np.array([5, 6], dtype=np.int64), 0, keys, out, bad)
    assert (k, int(bad[0])) == (1, 1)
    assert int(out[0]["can_id"]) == 7 and bytes(out[0]["data"][:2]) == b"ok" and int(out[0]["t_ns"]) == 6


def test_a_reader_drains_its_socket_with_receive_times():
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        rx.bind(("127.0.0.1", 0))
        rx.setsockopt(socket.SOL_SOCKET, receive.SO_TIMESTAMPNS, 1)
        msgs = _messages(200, seed=2)
        for m in msgs:
            tx.sendto(pack_message(m), rx.getsockname())
        reader = receive.BusReader(rx, 3, "udp", capacity=8)
        got = []
        while len(got) < len(msgs):
            rows = reader.read(50)
            got.extend(rows.copy())
        assert reader.read(50).size == 0               # drained: never blocks
        rows = np.array(got, dtype=FRAME_DTYPE)
        want = columns_from_messages([(3, m) for m in msgs])
        for f in ("can_id", "bus", "flags", "dlc", "length", "data"):
            assert np.array_equal(rows[f], want[f]), f
        assert np.all(np.diff(rows["t_ns"]) >= 0) and rows["t_ns"][0] > 1_600_000_000_000_000_000
    finally:
        rx.close()
        tx.close()
