"""An in-process python-can bus with a real, pollable file descriptor, for the gateway's direct
receive mode (SocketCAN and udp_multicast have one; python-can ``virtual`` has none).

``rx, tx = dgram_pair()``: frames sent on ``tx`` arrive on ``rx`` through a Unix datagram socket
pair. A frame keeps its own ``timestamp`` (the firmware stamps its frames with simulated time;
python-can ``virtual`` with ``preserve_timestamps`` does the same), so the estimator's epochs do
not depend on thread scheduling in the test. ``rx.failing = True``
makes ``recv`` raise (a link down); ``rx.break_socket()`` closes the socket under its user (a bus
that went away).
"""
from __future__ import annotations

import select
import socket
import struct

import can

_HEAD = struct.Struct("<dIBB")     # timestamp, arbitration id, flags (1 extended, 2 FD), length


class DgramBus(can.BusABC):
    def __init__(self, sock: socket.socket, name: str):
        self.sock = sock
        self.failing = False
        self.received = 0
        super().__init__(channel=name)
        self.channel_info = f"dgram {name}"

    def fileno(self) -> int:
        return self.sock.fileno()

    def send(self, msg: can.Message, timeout=None) -> None:
        flags = (1 if msg.is_extended_id else 0) | (2 if msg.is_fd else 0)
        self.sock.send(_HEAD.pack(msg.timestamp, msg.arbitration_id, flags, len(msg.data)) + bytes(msg.data))

    def _recv_internal(self, timeout):
        if self.failing:
            raise can.CanOperationError("link down (injected by the test)")
        if self.sock.fileno() < 0:
            raise can.CanOperationError("socket closed")
        ready, _, _ = select.select([self.sock], [], [], timeout)
        if not ready:
            return None, False
        raw = self.sock.recv(256)
        stamp, arb, flags, n = _HEAD.unpack_from(raw)
        self.received += 1
        return can.Message(timestamp=stamp, arbitration_id=arb, is_extended_id=bool(flags & 1),
                           is_fd=bool(flags & 2), data=raw[_HEAD.size:_HEAD.size + n]), True

    def break_socket(self) -> None:
        self.sock.close()

    def shutdown(self) -> None:
        super().shutdown()
        self.sock.close()


def dgram_pair(name: str) -> tuple[DgramBus, DgramBus]:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    for s in (a, b):
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    return DgramBus(a, f"{name}-rx"), DgramBus(b, f"{name}-tx")
