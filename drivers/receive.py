"""Frames read straight from a bus's socket into :data:`drivers.kernel.FRAME_DTYPE` rows.

python-can builds one ``can.Message`` per frame (4-13 us of Python each: its ``udp_multicast``
unpacks a msgpack map into keyword arguments, its SocketCAN dissects the frame in Python); at
the nominal 13.4 k frames/s that alone is most of a core's budget for the gateway. A
:class:`BusReader` takes over the reading of a bus python-can opened (the bus keeps its
configuration, filters and lifetime): it calls ``recvmsg_into`` on the bus's socket for every
datagram waiting (about a microsecond each) and one compiled kernel turns the batch into rows.

Two wire formats, as python-can writes them:

SocketCAN (``struct can_frame`` / ``struct canfd_frame`` of ``<linux/can.h>``, native endian)::

    offset 0          4        5        6       7             8
           | can_id u32 | len u8 | flags u8 | res | len8_dlc u8 | data[8] (classic) or [64] (FD) |

    can_id: bits 0-28 id, 29 error frame, 30 remote, 31 extended; a 72-byte datagram is CAN FD
    (flags bit 0 bit-rate switch, bit 1 error state indicator); a classic frame with len 8 and
    8 < len8_dlc <= 15 reports that raw DLC (python-can's ``dissect_can_frame``)

python-can ``udp_multicast`` (``can.interfaces.udp_multicast.utils.pack_message``): a msgpack
map of ``timestamp`` (replaced by the receive time, as python-can does), ``arbitration_id``,
``is_extended_id``, ``is_remote_frame``, ``is_error_frame``, ``channel``, ``dlc``, ``data``
(bin), ``is_fd``, ``bitrate_switch``, ``error_state_indicator``, in any order. A datagram that is
not such a map is counted (:attr:`BusReader.rejected`) and left out, never an exception.

Timestamps: the kernel's receive time (``SO_TIMESTAMPNS``, which python-can enables on both
socket kinds), as integer ns: exact, where python-can's float seconds lose ~0.2 us at today's
epoch. Without the ancillary time (a socket without the option), the read time.
"""
from __future__ import annotations

import socket
import struct
import time
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from numba import njit

from drivers.kernel import FLAG_BRS, FLAG_ERROR, FLAG_ESI, FLAG_EXTENDED, FLAG_FD, FLAG_REMOTE, FRAME_DTYPE

if TYPE_CHECKING:
    import can

_jit = njit(cache=True, fastmath=False, error_model="numpy", nogil=True)

Bytes = npt.NDArray[np.uint8]   # datagrams (one per row), a datagram, a key
Ints = npt.NDArray[np.int64]
Int = int | np.int64            # an integer in a kernel: numba makes both an int64

SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_TIMESPEC = struct.Struct("@qq")
_ANC = socket.CMSG_SPACE(_TIMESPEC.size)
SOCKETCAN_SLOT = 72           # CANFD_MTU
UDP_SLOT = 256                # a packed python-can message is ~150-200 bytes
_FD_DLC = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64], dtype=np.int64)


# --- SocketCAN -------------------------------------------------------------------------------------

@_jit
def parse_socketcan(raw: Bytes, lens: Ints, ts: Ints, bus: int, little: bool, fd_dlc: Ints, out: np.ndarray) -> int:
    """``raw`` (N, 72) datagrams of ``lens`` bytes received at ``ts`` ns -> ``out`` rows. Returns
    the number of rows written (datagrams of another size are not frames: skipped)."""
    k = 0
    for i in range(raw.shape[0]):
        n = lens[i]
        if n != 16 and n != 72:
            continue
        d = raw[i]
        if little:
            cid = np.uint32(d[0]) | (np.uint32(d[1]) << 8) | (np.uint32(d[2]) << 16) | (np.uint32(d[3]) << 24)
        else:
            cid = np.uint32(d[3]) | (np.uint32(d[2]) << 8) | (np.uint32(d[1]) << 16) | (np.uint32(d[0]) << 24)
        length = np.int64(d[4])
        fd = n == 72
        ok = False
        for v in fd_dlc:
            if v == length:
                ok = True
        if not ok:                                  # as python-can: the next valid FD length
            for v in fd_dlc:
                if v >= length:
                    length = v
                    break
        dlc = length
        flags = 0
        if fd:
            flags |= FLAG_FD
            if d[5] & 1:
                flags |= FLAG_BRS
            if d[5] & 2:
                flags |= FLAG_ESI
        elif length == 8 and 8 < d[7] <= 15:
            dlc = np.int64(d[7])
        if cid & np.uint32(0x80000000):
            flags |= FLAG_EXTENDED
            aid = cid & np.uint32(0x1FFFFFFF)
        else:
            aid = cid & np.uint32(0x7FF)
        if cid & np.uint32(0x40000000):
            flags |= FLAG_REMOTE
        if cid & np.uint32(0x20000000):
            flags |= FLAG_ERROR
        r = out[k]
        r["t_ns"] = ts[i]
        r["can_id"] = aid
        r["bus"] = bus
        r["flags"] = flags
        r["dlc"] = dlc if dlc <= 255 else 255
        avail = n - 8
        m = length if length <= avail else avail
        if flags & FLAG_REMOTE:                     # python-can's Message drops a remote frame's bytes
            m = 0
        r["length"] = m
        for j in range(64):
            r["data"][j] = d[8 + j] if j < m else 0
        k += 1
    return k


# --- python-can udp_multicast (msgpack) ------------------------------------------------------------

@_jit
def _mp_uint(d: Bytes, p: Int, n: Int) -> np.int64:
    v = np.int64(0)
    for j in range(n):
        v = (v << 8) | np.int64(d[p + j])
    return v


@_jit
def _mp_value(d: Bytes, p: Int, end: Int) -> tuple[int, Int, Int, Int, Int]:
    """(kind, int value, start, length, next position) of the msgpack value at ``p``: kind 0 nil,
    1 bool, 2 int, 3 float (skipped), 4 str, 5 bin, -1 not understood."""
    if p >= end:
        return -1, 0, 0, 0, end
    b = np.int64(d[p])
    if b <= 0x7F:
        return 2, b, 0, 0, p + 1
    if b >= 0xE0:
        return 2, b - 256, 0, 0, p + 1
    if 0xA0 <= b <= 0xBF:
        n = b - 0xA0
        return 4, 0, p + 1, n, p + 1 + n
    if b == 0xC0:
        return 0, 0, 0, 0, p + 1
    if b == 0xC2 or b == 0xC3:
        return 1, b - 0xC2, 0, 0, p + 1
    if b == 0xC4 or b == 0xD9:                     # bin8, str8
        if p + 2 > end:
            return -1, 0, 0, 0, end
        n = np.int64(d[p + 1])
        return (5 if b == 0xC4 else 4), 0, p + 2, n, p + 2 + n
    if b == 0xC5 or b == 0xDA:                     # bin16, str16
        if p + 3 > end:
            return -1, 0, 0, 0, end
        n = _mp_uint(d, p + 1, 2)
        return (5 if b == 0xC5 else 4), 0, p + 3, n, p + 3 + n
    if b == 0xCA:
        return 3, 0, 0, 0, p + 5
    if b == 0xCB:
        return 3, 0, 0, 0, p + 9
    if 0xCC <= b <= 0xCF:                          # uint 8/16/32/64
        n = np.int64(1) << (b - 0xCC)
        if p + 1 + n > end:
            return -1, 0, 0, 0, end
        return 2, _mp_uint(d, p + 1, n), 0, 0, p + 1 + n
    if 0xD0 <= b <= 0xD3:                          # int 8/16/32/64
        n = np.int64(1) << (b - 0xD0)
        if p + 1 + n > end:
            return -1, 0, 0, 0, end
        v = _mp_uint(d, p + 1, n)
        bits = 8 * n
        if bits < 64 and v >= (np.int64(1) << (bits - 1)):
            v -= np.int64(1) << bits
        return 2, v, 0, 0, p + 1 + n
    return -1, 0, 0, 0, end


@_jit
def _key_is(d: Bytes, s: Int, n: Int, key: Bytes) -> bool:
    if n != key.shape[0]:
        return False
    for j in range(n):
        if d[s + j] != key[j]:
            return False
    return True


@_jit
def parse_udp(raw: Bytes, lens: Ints, ts: Ints, bus: int, keys: tuple[Bytes, ...], out: np.ndarray, bad: Ints) -> int:
    """``raw`` (N, slot) msgpack datagrams -> ``out`` rows; returns the rows written and counts
    the datagrams that are not python-can messages in ``bad[0]``. ``keys``: the field names in
    :data:`_UDP_KEYS` order, as byte arrays."""
    k = 0
    for i in range(raw.shape[0]):
        d = raw[i]
        end = lens[i]
        if end < 1 or end > d.shape[0]:
            bad[0] += 1
            continue
        b = np.int64(d[0])
        p: Int                          # (declarations only: no code; numba types both as int64)
        aid: Int
        dlc: Int
        ds: Int
        dn: Int
        if 0x80 <= b <= 0x8F:
            count, p = b - 0x80, 1
        elif b == 0xDE and end >= 3:
            count, p = _mp_uint(d, 1, 2), 3
        else:
            bad[0] += 1
            continue
        aid, flags, dlc, ds, dn, have = np.int64(0), 0, np.int64(0), 0, -1, 0
        good = True
        for _ in range(count):
            kk, _v, ks, kn, p = _mp_value(d, p, end)
            if kk != 4 or p > end:
                good = False
                break
            vk, v, vs, vn, p = _mp_value(d, p, end)
            if vk < 0 or p > end:
                good = False
                break
            if _key_is(d, ks, kn, keys[0]):                      # arbitration_id
                if vk != 2 or v < 0:
                    good = False
                    break
                aid = v
                have |= 1
            elif _key_is(d, ks, kn, keys[1]):                    # dlc
                if vk != 2 or v < 0:
                    good = False
                    break
                dlc = v
                have |= 2
            elif _key_is(d, ks, kn, keys[2]):                    # data
                if vk != 5:
                    good = False
                    break
                ds, dn = vs, vn
                have |= 4
            else:
                for f in range(6):                               # the boolean flags
                    if _key_is(d, ks, kn, keys[3 + f]):
                        if vk != 1:
                            good = False
                        elif v:
                            if f == 0:
                                flags |= FLAG_EXTENDED
                            elif f == 1:
                                flags |= FLAG_REMOTE
                            elif f == 2:
                                flags |= FLAG_ERROR
                            elif f == 3:
                                flags |= FLAG_FD
                            elif f == 4:
                                flags |= FLAG_BRS
                            else:
                                flags |= FLAG_ESI
                        break
                if not good:
                    break
        if not good or have != 7 or dn > 64:
            bad[0] += 1
            continue
        r = out[k]
        r["t_ns"] = ts[i]
        r["can_id"] = aid if aid <= 0xFFFFFFFF else 0xFFFFFFFF
        r["bus"] = bus
        r["flags"] = flags
        if flags & FLAG_REMOTE:                     # python-can's Message drops a remote frame's bytes
            dn = 0
        r["dlc"] = dlc if dlc <= 255 else 255
        r["length"] = dn
        for j in range(64):
            r["data"][j] = d[ds + j] if j < dn else 0
        k += 1
    return k


_UDP_KEYS = ("arbitration_id", "dlc", "data", "is_extended_id", "is_remote_frame", "is_error_frame", "is_fd",
             "bitrate_switch", "error_state_indicator")


# --- the reader ------------------------------------------------------------------------------------

class BusReader:
    """Reads one python-can bus's socket straight into rows (module docstring). Use
    :func:`reader_for`; ``read`` never blocks and raises ``OSError`` as the socket does (a bus
    that went down)."""

    def __init__(self, sock: socket.socket, bus_index: int, kind: str, capacity: int = 64):
        self.sock, self.bus_index, self.kind = sock, bus_index, kind
        self.slot = SOCKETCAN_SLOT if kind == "socketcan" else UDP_SLOT
        self.rejected = 0             # datagrams that were not frames, so far
        self.last_read = 0            # datagrams the last read() took from the socket
        self._bad = np.zeros(1, dtype=np.int64)
        self._keys = tuple(np.frombuffer(k.encode(), dtype=np.uint8).copy() for k in _UDP_KEYS)
        self._little = struct.pack("=I", 1) == struct.pack("<I", 1)
        self._grow(capacity)

    def _grow(self, n: int) -> None:
        self._raw = np.zeros((n, self.slot), dtype=np.uint8)
        self._views = [memoryview(self._raw[i]) for i in range(n)]
        self._lens = np.zeros(n, dtype=np.int64)
        self._ts = np.zeros(n, dtype=np.int64)
        self._rows = np.zeros(n, dtype=FRAME_DTYPE)

    def read(self, max_n: int) -> np.ndarray:
        """Up to ``max_n`` frames waiting in the socket now, as rows (a view of a buffer reused
        by the next call)."""
        if max_n > self._raw.shape[0]:
            self._grow(max_n)
        recv = self.sock.recvmsg_into
        views, lens, ts = self._views, self._lens, self._ts
        flags = socket.MSG_DONTWAIT
        n = 0
        while n < max_n:
            try:
                size, anc, _, _ = recv((views[n],), _ANC, flags)
            except (BlockingIOError, InterruptedError):
                break
            lens[n] = size
            t = 0
            for level, typ, data in anc:
                if level == socket.SOL_SOCKET and typ == SO_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
                    sec, nsec = _TIMESPEC.unpack_from(data)
                    t = sec * 1_000_000_000 + nsec
            ts[n] = t or time.time_ns()
            n += 1
        self.last_read = n
        if n == 0:
            return self._rows[:0]
        if self.kind == "socketcan":
            k = parse_socketcan(self._raw[:n], lens[:n], ts[:n], self.bus_index, self._little, _FD_DLC, self._rows)
            self.rejected += n - k
        else:
            self._bad[0] = 0
            k = parse_udp(self._raw[:n], lens[:n], ts[:n], self.bus_index, self._keys, self._rows, self._bad)
            self.rejected += int(self._bad[0])
        return self._rows[:k]


def reader_for(bus: can.BusABC, bus_index: int) -> BusReader | None:
    """A :class:`BusReader` for a python-can SocketCAN or ``udp_multicast`` bus (they are the
    interfaces with a socket of their own), else None (read it with ``bus.recv``)."""
    socketcan: tuple[type, ...]
    try:
        from can.interfaces.socketcan import SocketcanBus
        socketcan = (SocketcanBus,)
    except ImportError:  # pragma: no cover - python-can always has it
        socketcan = ()
    from can.interfaces.udp_multicast import UdpMulticastBus

    if isinstance(bus, socketcan):
        sock = getattr(bus, "socket", None)
        return BusReader(sock, bus_index, "socketcan") if isinstance(sock, socket.socket) else None
    if isinstance(bus, UdpMulticastBus):
        # python-can keeps its multicast socket in a private attribute: checked here, never
        # assumed (a python-can that moved it reads through bus.recv as before)
        sock = getattr(getattr(bus, "_multicast", None), "_socket", None)
        return BusReader(sock, bus_index, "udp") if isinstance(sock, socket.socket) else None
    return None
