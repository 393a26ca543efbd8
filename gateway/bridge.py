"""The gateway service: CAN buses -> one pipeline (drivers + estimator) -> zenoh (and MCAP).

:class:`GatewayService` is given the buses (one per :class:`drivers.wire.BusSpec`, opened by
the caller) and an open zenoh session; it owns only the notifiers, the worker thread and the
publishers it creates. Lifecycle::

    # robot: robot_description.Robot; start(): notifiers + worker running
    with GatewayService(robot, buses, session) as gw:
        gw.run(stop_event)                                  # health every health_period_s
    # close(): notifiers stopped, worker drained, publishers undeclared (harmless twice)

Threads. ONE worker thread takes the frames, in arrival order per bus, through
:class:`gateway.engine.Session` (drivers, then the estimator) and publishes what comes out:
efforts and health at once; decoded samples once the step's efforts are out or no frame is
waiting (so a step's efforts never wait behind its samples' publishing; without the estimator,
at once). The recorder (``record=``) gets the raw frames in exactly the order the pipeline saw
them, so ``bsc replay`` reproduces the efforts byte for byte. How frames reach the worker
(``receive=``):

- ``"direct"`` (the default when every bus has a pollable ``fileno()``: SocketCAN,
  ``udp_multicast``): the worker itself waits on all the buses' sockets with ``poll`` and drains
  each ready one with ``recv(0)`` into its own backlog, one FIFO per bus, which it takes in
  timestamp order across buses (:class:`_RowBacklog`). One Python thread per frame path: no
  hand-off between threads and no wait for the GIL (docs/latency.md).
- ``"threads"`` (the default otherwise, e.g. python-can ``virtual``): python-can runs one notifier
  thread per bus; each only tags the frame with its bus and puts it on one FIFO queue that the
  worker reads.

The backlog is bounded either way: at most ``max_backlog`` frames (default
:data:`gateway.config.DEFAULT_MAX_BACKLOG` = 10 000, 0.75 s of the paper robot's nominal 13 400 frames/s; ~180
bytes per waiting frame). Receiving never blocks on it: when the backlog reaches ``max_backlog``
the service sheds load, dropping every arriving frame until the backlog is back to
``resume_backlog`` (90 % of it), so what gets through comes in contiguous runs that still make
complete estimator epochs. In ``direct`` mode the worker drains the sockets between every
:data:`DIRECT_BATCH` frames it processes, so the kernel's socket buffers do not fill first while
the worker runs. Each bus socket also gets an 8 MB kernel receive buffer
(:func:`deepen_receive_buffer`) against the times it does not run. Every
frame is counted per bus: ``received = processed + dropped + in the backlog`` (exactly; after
:meth:`drain` nothing is in the backlog). Drops show in :attr:`stats` and in each bus's health as
the rejection reason ``overflow``; the drivers see them as lost samples.

A bus whose ``recv`` raises (an adapter unplugged, a SocketCAN link down, a bus shut down under
the gateway) does not stop the others: the error is logged once per outage and counted
(``rx_error`` in the bus's health, :attr:`stats`), the bus is retried with a backoff (10 ms
doubling to ``retry_s``), and it is up again at its next frame. If ``reopen(bus_name) ->
can.BusABC`` is given, a bus still failing after ``retry_s`` is replaced by a new one from
``reopen`` (retried every ``retry_s`` until it succeeds); :meth:`replace_bus` does the same on
request. The service shuts down the buses it got from ``reopen``, never the caller's.

Publish time travels as the zenoh attachment ``publish_ns`` (decimal ASCII), so that payloads of
a replay are identical to the live ones.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import queue
import select
import threading
import time
from typing import Callable, Mapping

import can
import numpy as np
from numba import njit

from gateway.errors import GatewayError  # noqa: F401 - the service's errors' root
from drivers import wire
from drivers.kernel import FRAME_DTYPE, columns_from_messages
from drivers.receive import reader_for
from drivers.samples import BusHealth
from gateway import codec
from gateway.engine import Session, Sink
from gateway.config import GatewayConfig
from gateway.engine.sinks import RecorderSink

log = logging.getLogger(__name__)
_STOP = object()
RESUME_FRACTION = 0.9                # after an overflow, accept frames again below this fill
FIRST_BACKOFF_S = 0.01               # first wait after a failed recv; doubles up to retry_s
OVERFLOW_LOG_EVERY_S = 10.0
DIRECT_BATCH = 32                    # direct mode: frames processed between two drains of the sockets
DRAIN_MAX = 16                       # direct mode: frames taken from one socket before the next one's turn
                                     # (a few steps: the buses stay interleaved close to arrival order)
IDLE_POLL_S = 0.1                    # direct mode: longest wait in poll (stop, retries, requests)
QUIET_S = 0.001                      # direct mode: no frame for this long -> publish the held samples
                                     # (poll's resolution: 1 ms)
SAMPLES_HELD_MAX = 512               # decoded samples held for publishing while frames are waiting
SOCKET_RCVBUF = 8 << 20              # bytes asked for each bus socket's kernel receive buffer
SO_RCVBUFFORCE = 33                  # Linux; beyond net.core.rmem_max (needs CAP_NET_ADMIN)


def deepen_receive_buffer(bus, size: int = SOCKET_RCVBUF) -> int | None:
    """Ask for a ``size``-byte kernel receive buffer on ``bus``'s socket (SocketCAN,
    udp_multicast), past ``net.core.rmem_max`` where allowed; returns the size the kernel
    granted (it counts its own overhead, ~1 KB per frame), None for a bus without a socket.

    The default (~200 KB, about 200 frames or 45 ms of one arm bus) overflows silently, in the
    kernel, whenever the gateway is held off the CPU for longer; these frames then show up only
    as lost samples. 8 MB rides out about 1.5 s."""
    import socket

    if not pollable(bus):
        return None
    try:
        with socket.socket(fileno=os.dup(bus.fileno())) as s:    # a duplicate: the same socket
            for opt in (SO_RCVBUFFORCE, socket.SO_RCVBUF):
                try:
                    s.setsockopt(socket.SOL_SOCKET, opt, size)
                    break
                except OSError:
                    continue
            return s.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
    except OSError as exc:
        log.debug("receive buffer of %s: %r", getattr(bus, "channel_info", bus), exc)
        return None


def pollable(bus) -> bool:
    """Whether ``bus`` has a file descriptor that ``poll`` can wait on (SocketCAN, udp_multicast)."""
    try:
        return int(bus.fileno()) >= 0
    except Exception:  # noqa: BLE001 - NotImplementedError, a closed socket, ...
        return False


@njit(cache=True, nogil=True)
def _merge_heads(t, start, end, blocked, max_n, order):
    """The direct backlog's merge: buses' FIFO segments ``[start[b], end[b])`` of the times ``t``,
    taken head by head, earliest first (a tie: the lower bus index), until ``max_n`` or until a
    ``blocked`` bus (its queue empty, its socket possibly holding earlier frames) must be read.
    Writes the indices into ``order``; returns how many, and leaves ``start`` past what was taken."""
    n = 0
    nb = start.shape[0]
    while n < max_n:
        best = -1
        for b in range(nb):
            if start[b] < end[b]:
                if best < 0 or t[start[b]] < t[start[best]]:
                    best = b
            elif blocked[b]:
                return n
        if best < 0:
            return n
        order[n] = start[best]
        start[best] += 1
        n += 1
    return n


class _RowBacklog:
    """The direct mode's backlog: one FIFO of frame rows per bus, taken out in timestamp order
    across buses (:func:`_merge_heads`).

    Buses carry different frame rates, so taking the same number of frames from each in turn
    lets a backlog drift apart by bus (the busier bus falls behind, by tens of steps after a
    second of backlog, and the estimator then forces its epochs out). :meth:`take` gives the
    earliest heads, and stops while a bus whose queue is empty may still hold frames in its
    socket (``unread``): those could be earlier. Within a bus the order is arrival order."""

    def __init__(self, names):
        self.names = list(names)
        self.index = {n: i for i, n in enumerate(self.names)}
        self.unread = dict.fromkeys(self.names, False)
        self._q = [np.zeros(256, dtype=FRAME_DTYPE) for _ in self.names]
        self._head = np.zeros(len(self.names), dtype=np.int64)
        self._tail = np.zeros(len(self.names), dtype=np.int64)
        self.n = 0

    def __len__(self) -> int:
        return self.n

    def waiting(self, name: str) -> int:
        i = self.index[name]
        return int(self._tail[i] - self._head[i])

    def append(self, name: str, rows: np.ndarray) -> None:
        i = self.index[name]
        q, h, t = self._q[i], int(self._head[i]), int(self._tail[i])
        k = len(rows)
        if t + k > len(q):                     # compact, then grow if still short
            live = t - h
            if live + k > len(q):
                grown = np.zeros(max(2 * len(q), live + k), dtype=FRAME_DTYPE)
                grown[:live] = q[h:t]
                q = self._q[i] = grown
            else:
                q[:live] = q[h:t]
            h, t = 0, live
            self._head[i] = 0
        q[t:t + k] = rows
        self._tail[i] = t + k
        self.n += k

    def take(self, max_n: int, *, all_read: bool = False) -> np.ndarray:
        """Up to ``max_n`` waiting frames, earliest first (a copy)."""
        if not self.n:
            return np.zeros(0, dtype=FRAME_DTYPE)
        sizes = [int(t - h) for h, t in zip(self._head, self._tail)]
        flat = np.concatenate([q[h:t] for q, h, t in zip(self._q, self._head.tolist(), self._tail.tolist())])
        starts = np.cumsum([0] + sizes[:-1]).astype(np.int64)
        start, end = starts.copy(), starts + np.array(sizes, dtype=np.int64)
        blocked = np.array([self.unread[n] and not all_read for n in self.names], dtype=np.bool_)
        order = np.empty(min(max_n, self.n), dtype=np.int64)
        # a contiguous copy: a field view types as 'A' in numba, but as 'C' when it has one row
        # (numpy), and each is a compilation of its own
        k = _merge_heads(np.ascontiguousarray(flat["t_ns"]), start, end, blocked, len(order), order)
        self._head += start - starts
        self.n -= k
        return flat[order[:k]]




class BusState:
    """What the service knows of one bus: frame accounting and failures (plain ints, written by
    the bus's notifier thread or the worker, read from anywhere)."""

    __slots__ = ("name", "received", "dropped", "processed", "rx_errors", "reopened", "reopen_failures",
                 "down_since", "last_error", "backoff_s", "last_attempt", "outages", "rcvbuf",
                 "rejected_datagrams")

    def __init__(self, name: str):
        self.name = name
        self.received = self.dropped = self.processed = 0
        self.rx_errors = self.reopened = self.reopen_failures = self.outages = 0
        self.down_since: float | None = None      # time.monotonic() of the first error of an outage
        self.last_error = ""
        self.backoff_s = 0.0
        self.last_attempt = 0.0
        self.rcvbuf: int | None = None            # the socket's kernel receive buffer, bytes
        self.rejected_datagrams = 0               # read directly, not frames (counted by the reader)

    def as_dict(self) -> dict:
        return {"received": self.received, "processed": self.processed, "dropped": self.dropped,
                "rx_errors": self.rx_errors, "outages": self.outages, "down": self.down_since is not None,
                "reopened": self.reopened, "reopen_failures": self.reopen_failures, "last_error": self.last_error,
                "rcvbuf": self.rcvbuf}


class _Tagger(can.Listener):
    """One bus's listener: hands each frame to the service (never blocks) and turns a failing
    ``recv`` into a counted, logged, backed-off retry instead of a dead notifier thread."""

    __slots__ = ("state", "offer", "failed", "wake", "retired")

    def __init__(self, state: BusState, offer, failed):
        self.state, self.offer, self.failed = state, offer, failed
        self.wake = threading.Event()          # set to cut a backoff short (stop, replace)
        self.retired = False

    def on_message_received(self, msg: can.Message) -> None:
        self.offer(self.state, msg)

    def on_error(self, exc: Exception) -> None:
        if self.retired:
            return
        self.wake.wait(self.failed(self.state, exc))

    def stop(self) -> None:
        self.retired = True
        self.wake.set()


class Probe:
    """Timing hooks into a running :class:`GatewayService` (``GatewayService(probe=...)``), for
    benchmarks and diagnostics: what the service does is told, nothing of it is replaced. Each
    method runs on the thread doing the work and must return at once; the default does nothing.
    Stamps are the frames' own (``msg.timestamp`` in ns, a row's ``t_ns``)."""

    def received(self, bus: str, stamps_ns: list[int]) -> None:
        """Frames just taken from ``bus`` by a gateway thread (a notifier: one; the worker: a read)."""

    def feeding(self, stamps_ns: list[int]) -> None:
        """A batch of frames is about to go through the session (drivers, estimator, sinks)."""

    def fed(self, stamps_ns: list[int]) -> None:
        """That batch went through."""

    def ticked(self, start_ns: int, end_ns: int) -> None:
        """One health tick took ``[start_ns, end_ns)`` (``time.time_ns``)."""


class GatewayService:
    def __init__(self, robot, buses: Mapping[str, can.BusABC], session, config: GatewayConfig | None = None, *,
                 model_robot=None, layout=None, record=None, reopen: Callable[[str], can.BusABC] | None = None,
                 log_offset_ns: int = 0, probe: Probe | None = None):
        """``robot``, ``buses`` (opened), the zenoh ``session``: what the service runs on; ``config``:
        how (gateway/config.py; it reads [can] fd and receive, [service], [drivers], [estimator]).
        ``model_robot`` and ``layout``: the loaded model and thruster layout; ``record``: a Recorder;
        ``reopen``: opens a failed bus again by name; ``probe``: timing hooks (:class:`Probe`)."""
        config = config or GatewayConfig()
        svc = config.service
        fd, receive, estimate = config.can.fd, config.can.receive, svc.estimate
        if isinstance(robot, wire.WireMap):                # a wire map names a built-in robot
            import robot_description

            robot = robot_description.load(robot.robot)
        wire_map = wire.WireMap.from_robot(robot)
        missing = set(wire_map.buses) - set(buses)
        if missing:
            raise GatewayError(f"no CAN bus given for {', '.join(sorted(missing))}")
        every_pollable = all(pollable(buses[name]) for name in wire_map.buses)
        if receive == "direct" and not every_pollable:
            raise GatewayError("receive='direct' needs buses with a pollable fileno() (SocketCAN, udp_multicast): "
                               + ", ".join(n for n in wire_map.buses if not pollable(buses[n])) + " have none")
        self.receive = ("direct" if every_pollable else "threads") if receive == "auto" else receive
        self.wire = wire_map
        self.robot = wire_map.robot
        self.buses = dict(buses)
        self.session = session
        self.config = config
        self.probe = probe
        self.fd = fd
        self.health_period_s = svc.health_period_s
        self.recorder = record
        self.publish_samples = svc.publish_samples
        # the session engine: drivers + estimator, log times, raw frames to the recorder
        channels = {name: getattr(buses[name], "channel", None) for name in wire_map.buses}
        sinks = ([RecorderSink(record, channels=channels, rows=True)] if record is not None else []) + [_Publish(self)]
        # log_offset_ns: added to frame times to make log times (frames stamped with simulated time)
        self.engine = Session(robot, sinks, model_robot=model_robot, layout=layout, fd=fd, estimate=estimate,
                              timing=config.drivers.timing(), settings=config.estimator, log_offset_ns=log_offset_ns)
        self.max_backlog = svc.max_backlog
        self.resume_backlog = int(svc.max_backlog * RESUME_FRACTION)
        self.retry_s = float(svc.retry_s)
        self.reopen = reopen
        self.bus_state = {name: BusState(name) for name in self.wire.buses}
        self._bus_list = [self.bus_state[name] for name in self.wire.buses]     # by bus index
        self._queue: queue.SimpleQueue = queue.SimpleQueue()      # threads mode: frames; direct: requests
        self._backlog = _RowBacklog(wire_map.buses)               # direct mode: the worker's own
        self._wake_r = self._wake_w = -1                          # direct mode: wakes the worker's poll
        self._held: list = []                                     # decoded samples waiting to be published
        self._efforts_out = False                                 # published something else since
        self._hold_samples = estimate                             # hold samples behind the efforts
        self._qlock = threading.Lock()           # admission: size check + put + counters, per frame
        self._shedding = False
        self.peak_backlog = 0
        self.overflow_episodes = 0
        self._overflow_logged = -OVERFLOW_LOG_EVERY_S
        self._notifiers: dict[str, tuple[can.Notifier, _Tagger]] = {}
        self._owned: set[int] = set()            # id() of the buses this service opened (reopen)
        self._bus_lock = threading.RLock()       # notifier start/stop/replace
        self._stopping = threading.Event()
        self._worker: threading.Thread | None = None
        self._supervisor: threading.Thread | None = None
        self._publishers: dict[str, object] = {}
        self._schemas = None                     # the queryable that serves the payload schemas
        self._lock = threading.Lock()            # the pipeline is used by the worker and by health ticks
        self._closed = False
        self._publishing = True          # until close() has flushed the estimator's last epochs
        self.published = 0
        self.publish_errors = 0
        self.pipeline_errors = 0

    # --- lifecycle ---------------------------------------------------------------------------

    def start(self) -> "GatewayService":
        if self._closed:
            raise GatewayError("the gateway service is closed")
        if self._worker is None:
            # the schema of every payload, queryable (bsc/<robot>/schemas/<Type>)
            self._schemas = codec.serve_schemas(self.session, self.robot)
            for name in self.wire.buses:
                self.bus_state[name].rcvbuf = deepen_receive_buffer(self.buses[name])
            if self.receive == "direct":
                self._wake_r, self._wake_w = os.pipe()
                os.set_blocking(self._wake_r, False)
                os.set_blocking(self._wake_w, False)
                self._worker = threading.Thread(target=self._work_direct, name="bsc-gateway-worker", daemon=True)
                self._worker.start()
            else:
                self._worker = threading.Thread(target=self._work, name="bsc-gateway-worker", daemon=True)
                self._worker.start()
                with self._bus_lock:
                    for name in self.wire.buses:
                        self._listen(name, self.buses[name])
            if self.reopen is not None:
                self._supervisor = threading.Thread(target=self._supervise, name="bsc-gateway-supervisor",
                                                    daemon=True)
                self._supervisor.start()
        return self

    def thread_ids(self) -> dict[str, list[int]]:
        """Native ids of the service's threads by role (``worker``; ``notifiers``: python-can's
        reader threads, threads mode only), for per-thread CPU accounting."""
        worker = self._worker
        chans = {str(getattr(b, "channel_info", "")) for b in self.buses.values()}
        notifiers = [t.native_id for t in threading.enumerate()
                     if t.native_id is not None and t.name.startswith("Notifier for bus ")
                     and t.name[len("Notifier for bus "):].strip('"') in chans]
        return {"worker": [worker.native_id] if worker is not None and worker.native_id is not None else [],
                "notifiers": notifiers if self.receive == "threads" else []}

    def run(self, stop: threading.Event | None = None, duration_s: float | None = None) -> None:
        """Publish health every ``health_period_s`` until ``stop`` is set or ``duration_s`` passes."""
        self.start()
        stop = stop or threading.Event()
        end = None if duration_s is None else time.monotonic() + duration_s
        while True:
            wait = self.health_period_s if end is None else min(self.health_period_s, end - time.monotonic())
            if wait <= 0 or stop.wait(wait):
                break
            if self.probe is None:
                self.on_tick()
            else:
                t = time.time_ns()
                self.on_tick()
                self.probe.ticked(t, time.time_ns())
        self.publish_health()

    def drain(self, timeout: float = 30.0) -> bool:
        """Wait until every frame received so far went through the pipeline."""
        done = threading.Event()
        self._request(done)
        return done.wait(timeout)

    def _request(self, item) -> None:
        """Hand ``item`` to the worker: a frame-queue marker (threads mode) or a request read
        between two batches of frames (direct mode)."""
        self._queue.put(item)
        if self.receive == "direct":
            self._wake()

    def _wake(self) -> None:
        with contextlib.suppress(OSError):       # full pipe: a wake is pending anyway; closed: stopped
            os.write(self._wake_w, b"w")

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._stopping.set()
        with self._bus_lock:
            for notifier, tagger in self._notifiers.values():
                tagger.stop()
                notifier.stop()
            self._notifiers.clear()
        if self._supervisor is not None:
            self._supervisor.join(30.0)
        if self._worker is not None:
            self._request(_STOP)
            self._worker.join(30.0)
        for fd in (self._wake_r, self._wake_w):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._wake_r = self._wake_w = -1
        with self._bus_lock:
            for bus in self.buses.values():
                if id(bus) in self._owned:
                    self._shutdown(bus)
            self._owned.clear()
        with self._lock:
            self._publishing = False     # the worker's final flush above was still published
            pubs, self._publishers = list(self._publishers.values()), {}
        if self._schemas is not None:
            pubs.append(self._schemas)
            self._schemas = None
        for p in pubs:
            try:
                p.undeclare()
            except Exception as exc:  # noqa: BLE001 - a session closed first must not mask close()
                log.debug("undeclare: %r", exc)

    def __enter__(self) -> "GatewayService":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # --- buses: admission, failures, replacement --------------------------------------------

    def _listen(self, name: str, bus: can.BusABC) -> None:
        tagger = _Tagger(self.bus_state[name], self._offer, self._failed)
        self._notifiers[name] = (can.Notifier(bus, [tagger], timeout=0.1), tagger)

    def _offer(self, st: BusState, msg: can.Message) -> None:
        """A notifier thread's frame: into the queue, or dropped and counted. Never blocks."""
        if self.probe is not None:
            self.probe.received(st.name, [round(msg.timestamp * 1e9)])
        with self._qlock:
            if self._admit(st, self._queue.qsize()):
                self._queue.put((st, msg))
        if st.down_since is not None:
            self._back_up(st)

    def _admit(self, st: BusState, n: int) -> bool:
        """Count a frame received on ``st`` while ``n`` frames wait; False: dropped (counted)."""
        st.received += 1
        if self._shedding:
            if n > self.resume_backlog:
                st.dropped += 1
                return False
            self._shedding = False
        elif n >= self.max_backlog:
            self._shedding = True
            self.overflow_episodes += 1
            st.dropped += 1
            self._log_overflow()
            return False
        if n >= self.peak_backlog:
            self.peak_backlog = n + 1
        return True

    def _log_overflow(self) -> None:
        now = time.monotonic()
        if now - self._overflow_logged >= OVERFLOW_LOG_EVERY_S:
            self._overflow_logged = now
            log.warning("gateway backlog full (%d frames): dropping frames until it is down to %d "
                        "(dropped so far: %s)", self.max_backlog, self.resume_backlog,
                        ", ".join(f"{s.name} {s.dropped}" for s in self.bus_state.values()))

    def _failed(self, st: BusState, exc: Exception) -> float:
        """A notifier thread's ``recv`` raised: count, log once per outage, return the backoff."""
        st.rx_errors += 1
        if st.down_since is None:
            st.down_since = time.monotonic()
            st.outages += 1
            st.last_error = repr(exc)
            st.backoff_s = FIRST_BACKOFF_S
            log.warning("CAN bus %s: receive failed (%r); the other buses continue, retrying%s",
                        st.name, exc, " and reopening" if self.reopen is not None else "")
        else:
            st.backoff_s = min(2 * st.backoff_s, self.retry_s)
        return st.backoff_s

    def _back_up(self, st: BusState) -> None:
        since = st.down_since
        if since is None:
            return
        st.down_since = None
        log.warning("CAN bus %s: receiving again after %.2f s (%d receive errors so far)",
                    st.name, time.monotonic() - since, st.rx_errors)

    def _supervise(self) -> None:
        """Replace buses that keep failing (only with ``reopen``)."""
        while not self._stopping.wait(min(self.retry_s / 4, 0.1)):
            now = time.monotonic()
            for st in self.bus_state.values():
                since = st.down_since
                if since is None or now - since < self.retry_s or now - st.last_attempt < self.retry_s:
                    continue
                st.last_attempt = now
                try:
                    bus = self.reopen(st.name)
                except Exception as exc:  # noqa: BLE001 - the bus is still away: try again later
                    st.reopen_failures += 1
                    log.debug("reopen %s: %r", st.name, exc)
                    continue
                if self.receive == "direct" and not pollable(bus):
                    st.reopen_failures += 1
                    log.warning("reopen %s: the new bus has no pollable fileno(); not used", st.name)
                    self._shutdown(bus)
                    continue
                try:
                    self.replace_bus(st.name, bus, _owned=True)
                except GatewayError:
                    self._shutdown(bus)             # closing: the new bus is not wanted any more
                    return

    def replace_bus(self, name: str, bus: can.BusABC, *, _owned: bool = False) -> None:
        """Listen on ``bus`` instead of the current bus ``name`` (e.g. a bus that went away and
        was opened again). The old bus's notifier is stopped; the old bus is shut down only if
        this service opened it. The bus counts as up again at its first frame."""
        if name not in self.bus_state:
            raise GatewayError(f"no bus {name!r} (buses: {', '.join(self.bus_state)})")
        direct = self.receive == "direct"
        if direct and not pollable(bus):
            raise GatewayError(f"bus {name}: this service receives directly and needs a pollable fileno()")
        with self._bus_lock:
            if self._closed:
                raise GatewayError("the gateway service is closed")
            old = self._notifiers.pop(name, None)
            if old is not None:
                notifier, tagger = old
                tagger.stop()
                notifier.stop()
            prev = self.buses.get(name)
            retired = None
            if prev is not None and id(prev) in self._owned and prev is not bus:
                self._owned.discard(id(prev))
                retired = prev
            self.buses[name] = bus
            if _owned:
                self._owned.add(id(bus))
            st = self.bus_state[name]
            st.rcvbuf = deepen_receive_buffer(bus)
            st.reopened += 1
            st.backoff_s = 0.0
            if direct and self._worker is not None:
                self._request(("swap", name, retired))    # the worker stops polling prev, then shuts it
            else:
                if retired is not None:
                    self._shutdown(retired)
                if self._worker is not None:
                    self._listen(name, bus)
        log.warning("CAN bus %s: listening on a new bus object (%s)", name, getattr(bus, "channel_info", bus))

    @staticmethod
    def _shutdown(bus: can.BusABC) -> None:
        with contextlib.suppress(Exception):
            bus.shutdown()

    # --- the worker --------------------------------------------------------------------------

    def _work(self) -> None:
        """Threads mode: frames from the notifiers' queue, what is waiting taken together."""
        q = self._queue
        get, get_nowait, empty = q.get, q.get_nowait, q.empty
        pending = None
        while True:
            item = pending if pending is not None else get()
            pending = None
            if item is _STOP:
                self._final_flush()
                return
            if isinstance(item, threading.Event):
                self._publish_held()
                item.set()
                continue
            batch = [item]
            while len(batch) < DIRECT_BATCH:
                try:
                    nxt = get_nowait()
                except queue.Empty:
                    break
                if nxt is _STOP or isinstance(nxt, threading.Event):
                    pending = nxt                  # after the frames that came before it
                    break
                batch.append(nxt)
            with self._lock:
                self._process(batch)
            if self._held and empty():
                self._publish_held()

    def _process(self, items: list) -> None:
        """Frames ``(BusState, msg)`` through the session in one pass of its kernels (the caller
        holds ``self._lock``)."""
        for st, _ in items:
            st.processed += 1
        probe = self.probe
        if probe is not None:
            stamps = [round(msg.timestamp * 1e9) for _, msg in items]
            probe.feeding(stamps)
        try:
            self.engine.feed_messages([(st.name, msg) for st, msg in items])
            if probe is not None:
                probe.fed(stamps)
        except Exception:  # noqa: BLE001 - a bug behind a frame must not stop the gateway
            self.pipeline_errors += 1
            if self.pipeline_errors <= 10:
                log.exception("pipeline error on frames of %s (counted; continuing)",
                              ", ".join(sorted({st.name for st, _ in items})))

    def _process_rows(self, rows: np.ndarray) -> None:
        """Frame rows (direct mode, in time order across buses) through the session in one pass
        of its kernels (the caller holds ``self._lock``)."""
        counts = np.bincount(rows["bus"], minlength=len(self._bus_list)).tolist()
        for st, n in zip(self._bus_list, counts):
            st.processed += n
        probe = self.probe
        if probe is not None:
            stamps = rows["t_ns"].tolist()
            probe.feeding(stamps)
        try:
            self.engine.feed_frames(rows)
            if probe is not None:
                probe.fed(stamps)
        except Exception:  # noqa: BLE001 - a bug behind a frame must not stop the gateway
            self.pipeline_errors += 1
            if self.pipeline_errors <= 10:
                log.exception("pipeline error on %d frames (counted; continuing)", len(rows))

    def _admit_rows(self, st: BusState, n: int, waiting: int) -> np.ndarray | None:
        """:meth:`_admit` for ``n`` frames read together while ``waiting`` frames wait: the mask of
        those kept (None: all of them)."""
        keep = None
        for k in range(n):
            if self._admit(st, waiting):
                waiting += 1
            else:
                if keep is None:
                    keep = np.ones(n, dtype=np.bool_)
                keep[k] = False
        return keep

    def _final_flush(self) -> None:
        with self._lock:
            self.engine.close()          # the epochs still waiting, a last health snapshot
        self._publish_held()

    def _work_direct(self) -> None:
        """Direct mode: the worker polls the buses' sockets itself (module docstring)."""
        lock, backlog, requests = self._lock, self._backlog, self._queue
        poller = select.poll()
        poller.register(self._wake_r, select.POLLIN)
        watched: dict[int, tuple[str, can.BusABC, BusState]] = {}     # fd -> the bus polled on it
        fd_of: dict[str, int] = {}
        retry_at: dict[str, float] = {}                                 # failed buses: when to try again
        drains: list[threading.Event] = []
        bad = select.POLLERR | select.POLLHUP | select.POLLNVAL

        def fail(name: str, st: BusState, exc: Exception) -> None:
            unwatch(name)
            retry_at[name] = time.monotonic() + self._failed(st, exc)

        readers: dict[str, object] = {}             # bus -> a BusReader (its socket read directly)
        index = backlog.index

        def receive(name: str, bus: can.BusABC, st: BusState, ev: int) -> int:
            backlog.unread[name] = False
            try:
                reader = readers.get(name)
                if reader is not None:
                    rows = reader.read(DRAIN_MAX)
                    got = reader.last_read
                    st.rejected_datagrams = reader.rejected
                else:
                    msgs = []
                    while len(msgs) < DRAIN_MAX:
                        msg = bus.recv(0)
                        if msg is None:
                            break
                        msgs.append((index[name], msg))
                    got = len(msgs)
                    rows = columns_from_messages(msgs) if msgs else None
                if rows is not None and len(rows):
                    if self.probe is not None:
                        self.probe.received(name, rows["t_ns"].tolist())
                    keep = self._admit_rows(st, len(rows), len(backlog))
                    backlog.append(name, rows if keep is None else rows[keep])
                backlog.unread[name] = got >= DRAIN_MAX         # its socket may hold more
                if not got and ev & bad:
                    raise can.CanOperationError("the bus's socket is closed" if ev & select.POLLNVAL
                                                else "the bus's socket reports an error or hang-up")
            except Exception as exc:  # noqa: BLE001 - any recv failure: counted, backed off, retried
                fail(name, st, exc)
                return 0
            if got and st.down_since is not None:
                self._back_up(st)
            return got

        def watch(name: str) -> None:
            bus, st = self.buses[name], self.bus_state[name]
            try:
                fd = int(bus.fileno())
                if fd < 0:
                    raise can.CanOperationError("the bus has no open socket")
                poller.register(fd, select.POLLIN | select.POLLPRI)
            except Exception as exc:  # noqa: BLE001
                fail(name, st, exc)
                return
            watched[fd], fd_of[name] = (name, bus, st), fd
            reader = reader_for(bus, index[name])
            if reader is None:
                readers.pop(name, None)
            else:
                readers[name] = reader
                reader.rejected = st.rejected_datagrams      # a new bus object: the count goes on
            retry_at.pop(name, None)
            receive(name, bus, st, 0)      # what is waiting, and a failing bus fails again now

        def unwatch(name: str) -> None:
            backlog.unread[name] = False
            fd = fd_of.pop(name, None)
            if fd is not None:
                watched.pop(fd, None)
                with contextlib.suppress(KeyError, ValueError, OSError):
                    poller.unregister(fd)

        for name in self.wire.buses:
            watch(name)
        while True:
            stop = False
            while not requests.empty():
                item = requests.get()
                if item is _STOP:
                    stop = True
                elif isinstance(item, threading.Event):
                    drains.append(item)
                else:                                         # ("swap", name, the old bus to shut down)
                    _, name, retired = item
                    unwatch(name)
                    if retired is not None:
                        self._shutdown(retired)
                    watch(name)
            if stop:
                break
            if retry_at:
                now = time.monotonic()
                for name in [n for n, t in retry_at.items() if t <= now]:
                    watch(name)
            if backlog or drains:
                timeout = 0
            elif self._held:
                timeout = QUIET_S
            else:
                timeout = IDLE_POLL_S
                if retry_at:
                    timeout = max(0.0, min(timeout, min(retry_at.values()) - time.monotonic()))
            got = 0
            for fd, ev in poller.poll(timeout * 1000.0):
                if fd == self._wake_r:
                    with contextlib.suppress(OSError):
                        os.read(fd, 4096)
                    continue
                w = watched.get(fd)
                if w is not None:
                    got += receive(*w, ev)
            if backlog:
                # the poll is a moment old: any bus may have received since, and its frames can be
                # earlier than what was just read from another bus (they were sent before it), so
                # read every bus now (non-blocking) before merging. Reading only the buses with
                # nothing queued left a race: a bus whose queue ran empty in the merge, its next
                # frames already in its socket, let another bus's later frames through first
                # (seen once in a suite run under load, 2026-11-26)
                for name, fd in list(fd_of.items()):
                    if fd in watched:
                        receive(*watched[fd], 0)
                rows = backlog.take(DIRECT_BATCH)             # stops where a bus must be read first
                if len(rows):
                    with lock:
                        self._process_rows(rows)
                for name, more in backlog.unread.items():     # read it now, ready or not
                    if more and not backlog.waiting(name) and name in fd_of:
                        receive(*watched[fd_of[name]], 0)
                if self._efforts_out and not backlog and self._held:    # a step's efforts are out
                    self._publish_held()
            elif not got:                                     # nothing waiting anywhere (quiet)
                if self._held:
                    self._publish_held()
                if drains:
                    for ev_ in drains:
                        ev_.set()
                    drains.clear()
        while backlog:                                        # closing: what was received goes through
            with lock:
                self._process_rows(backlog.take(DIRECT_BATCH, all_read=True))
        self._final_flush()
        for ev_ in drains:
            ev_.set()

    @property
    def backlog(self) -> int:
        """Frames waiting for the worker (at most ``max_backlog``)."""
        return len(self._backlog) if self.receive == "direct" else self._queue.qsize()

    @property
    def stats(self) -> dict:
        """Frame accounting per bus (``received = processed + dropped + in the queue``), bus
        failures, and the backlog: plain data, safe to read from any thread."""
        return {"buses": {name: st.as_dict() for name, st in self.bus_state.items()},
                "received": sum(st.received for st in self.bus_state.values()),
                "processed": sum(st.processed for st in self.bus_state.values()),
                "dropped": sum(st.dropped for st in self.bus_state.values()),
                "backlog": self.backlog, "peak_backlog": self.peak_backlog, "max_backlog": self.max_backlog,
                "overflow_episodes": self.overflow_episodes, "pipeline_errors": self.pipeline_errors,
                "receive": self.receive}

    # --- hooks -------------------------------------------------------------------------------

    def on_tick(self) -> None:
        """Called on the ``run()`` thread every health period: publishes health."""
        self.publish_health()

    # --- publishing --------------------------------------------------------------------------

    def _emit(self, key: str, obj) -> None:
        """An object to publish (efforts and health at once; samples held, see the module
        docstring); ``obj`` may also be its payload, already encoded."""
        if "/sensors/" not in key:
            self.publish(key, obj)
            self._efforts_out = True
        elif self.publish_samples:
            if not self._hold_samples:         # drivers only: the samples are what is published
                self.publish(key, obj)
                return
            self._held.append((key, obj))      # published once the step's efforts are out
            if len(self._held) >= SAMPLES_HELD_MAX:
                self._publish_held()

    def _publish_held(self) -> None:
        self._efforts_out = False
        held, self._held = self._held, []
        for key, obj in held:
            self.publish(key, obj)

    def publish(self, key: str, obj) -> None:
        """Put ``obj`` (an object, or its payload bytes) on ``key``; never raises (counted)."""
        if not self._publishing:
            return
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publishers[key] = codec.declare_publisher(self.session, key)
        try:
            codec.put(pub, obj if obj.__class__ is bytes else codec.encode(obj))
            self.published += 1
        except Exception as exc:  # noqa: BLE001 - a closing session must not kill the worker
            self.publish_errors += 1
            log.debug("put %s: %r", key, exc)

    def health(self, now_ns: int | None = None) -> list:
        """Snapshots of every bus and device (also resets the measured-load window). A bus's
        ``rejected`` also holds the gateway's own counts when non-zero: ``overflow`` (frames
        dropped because the backlog was full), ``rx_error`` (receive calls that raised) and
        ``malformed`` (datagrams read from the bus's socket that were not CAN frames)."""
        now = time.time_ns() if now_ns is None else now_ns
        with self._lock:
            out = self.engine.pipeline.health(now)
        for i, h in enumerate(out):
            st = self.bus_state.get(getattr(h, "bus", None)) if isinstance(h, BusHealth) else None
            if st is not None and (st.dropped or st.rx_errors or st.rejected_datagrams):
                rej = dict(h.rejected)
                if st.dropped:
                    rej["overflow"] = st.dropped
                if st.rx_errors:
                    rej["rx_error"] = st.rx_errors
                if st.rejected_datagrams:
                    rej["malformed"] = st.rejected_datagrams
                out[i] = dataclasses.replace(h, rejected=tuple(sorted(rej.items())))
        return out

    def publish_health(self) -> None:
        if self._closed:
            return
        from gateway import keys

        now = time.time_ns()
        for h in self.health(now):
            with self._lock:
                # log time: the last frame's; before any frame, when the snapshot was taken (a
                # log must not start in 1970 because the gateway waited for its buses)
                last = self.engine.last_log_ns
                self.engine.emit(keys.for_sample(self.robot, h), h, last if last is not None else now)


class _Publish(Sink):
    """The gateway's zenoh side of its session (:meth:`GatewayService._emit`): samples and
    efforts come as rows and go out as payloads written from them (no object per message)."""

    rows = True

    def __init__(self, gw: GatewayService):
        self.gw = gw

    def sample_rows(self, session, events, log_ns) -> None:
        gw = self.gw
        if not gw.publish_samples:
            return
        emit = gw._emit
        for key, _, data, k in session.sample_messages(events):   # encoded once, with the recorder
            # a value that is not finite: codec.encode refuses the object, counted as a put error
            emit(key, data if data is not None else session.pipeline.drivers.to_samples(events[k:k + 1])[0])

    def effort_rows(self, session, rows, log_ns) -> None:
        emit = self.gw._emit
        for i, (key, _, data, _) in enumerate(session.effort_messages(rows)):
            emit(key, data if data is not None else session.encoders().effort_object(rows, i))

    def emit(self, key: str, obj, log_ns: int) -> None:
        self.gw._emit(key, obj)
