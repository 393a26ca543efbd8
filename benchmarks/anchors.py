"""Anchors: plain library work, timed in the same run as the benchmarks so figures read as ratios.

The machine this project runs on is shared and noisy: an absolute figure moves by 2x from one
hour to the next. Each benchmark figure is therefore printed beside an anchor measured in the
same run, and judged by the ratio ``value / anchor`` where its target is relative:

- ``cantools_decode``: cantools ``Database.decode_message`` of one frame at a time, on an arm
  bus's frame mix from our DBC (drivers/dbc), frames/s;
- ``zenoh_rtt``: a raw zenoh round trip between two sessions of this process on loopback (a
  router-mode session and a client, ``tcp/127.0.0.1:PORT``, no scouting): put a ping, the other
  session's subscriber puts a pong, the first's subscriber wakes the waiter; median us;
- ``can_virtual``: python-can ``virtual`` bus (in-process), ``send`` on one bus then ``recv`` on
  another of the same channel, one frame at a time, frames/s;
- ``numpy_matmul``: numpy batched small matrix products ``(N,6,6) @ (N,6,1)`` (``np.matmul``),
  products/s.

``get(name)`` measures an anchor once per process and caches it, so a benchmark module can
use its anchor whether it runs alone or inside the suite (which measures all four first).
``python -m benchmarks.anchors`` prints them. An anchor does the same work with or without
``quick`` (each takes well under a second), so ratios compare across quick and full runs.
"""
from __future__ import annotations

import os
import statistics
import threading
import time
from typing import Callable

from gateway.zenoh_config import free_port

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# name -> (unit, what it is)
ANCHORS: dict[str, tuple[str, str]] = {
    "cantools_decode": ("frames/s", "cantools decode_message per frame, arm-bus DBC mix"),
    "zenoh_rtt": ("us", "raw zenoh put->subscriber->put->subscriber round trip, loopback TCP, median"),
    "can_virtual": ("frames/s", "python-can virtual bus send -> recv, one frame at a time"),
    "numpy_matmul": ("products/s", "numpy batched (N,6,6)@(N,6,1) np.matmul"),
}

_cache: dict[str, dict] = {}


def row(name: str, value: float | None, unit: str, *, target: str | None = None,
        ok: bool | None = None, anchor: str | None = None, ratio: float | None = None,
        note: str | None = None) -> dict:
    """One figure in the suite's common shape (``note`` is optional free text)."""
    r = {"name": name, "value": value, "unit": unit, "target": target, "ok": ok,
         "anchor": anchor, "ratio": ratio}
    if note:
        r["note"] = note
    return r


def ratio(value: float | None, anchor: str, quick: bool = False) -> float | None:
    """``value / anchor figure`` (the anchor measured now if this process has not yet)."""
    a = get(anchor, quick)
    if value is None or not a:
        return None
    return value / a


def _best_rate(fn: Callable[[], int], repeat: int) -> float:
    """Best items/s of ``repeat`` calls of ``fn`` (which returns the number of items it did)."""
    best = 0.0
    for _ in range(repeat):
        t0 = time.perf_counter()
        n = fn()
        dt = time.perf_counter() - t0
        best = max(best, n / dt)
    return best


def cantools_decode(quick: bool = False) -> dict:
    from benchmarks.bench_drivers import arm_frames
    from drivers import wire

    msgs = arm_frames(10_000)      # same work quick or not: anchors must compare across runs
    db = wire.database("arm")
    pairs = [(m.arbitration_id, bytes(m.data)) for m in msgs]
    decode = db.decode_message

    def run() -> int:
        for i, d in pairs:
            decode(i, d)
        return len(pairs)

    value = _best_rate(run, 3)
    return row("cantools_decode", value, "frames/s", note=f"{len(pairs)} frames, best of 3")




def zenoh_sessions(port: int | None = None):
    """``(router, client)``: a router-mode session listening on loopback and a client of it."""
    import zenoh

    from gateway.zenoh_config import make_config

    ep = f"tcp/127.0.0.1:{port or free_port()}"
    router = zenoh.open(make_config(listen=[ep], mode="router"))
    try:
        client = zenoh.open(make_config(connect=[ep], mode="client"))
    except Exception:
        router.close()
        raise
    return router, client


def zenoh_rtt(quick: bool = False) -> dict:
    n = 1_000
    router, client = zenoh_sessions()
    pong = threading.Event()
    subs = []
    try:
        echo_pub = router.declare_publisher("bench/anchor/pong")
        subs.append(echo_pub)
        subs.append(router.declare_subscriber("bench/anchor/ping", lambda s: echo_pub.put(s.payload)))
        subs.append(client.declare_subscriber("bench/anchor/pong", lambda s: pong.set()))
        ping = client.declare_publisher("bench/anchor/ping")
        subs.append(ping)
        payload = bytes(64)
        # the route ping -> pong exists once one round trip completes
        deadline = time.monotonic() + 10.0
        while True:
            pong.clear()
            ping.put(payload)
            if pong.wait(0.05):
                break
            if time.monotonic() > deadline:
                raise RuntimeError("zenoh anchor: no round trip within 10 s on loopback")
        for _ in range(20):             # warm up
            pong.clear()
            ping.put(payload)
            pong.wait(1.0)
        rtts = []
        for _ in range(n):
            pong.clear()
            t0 = time.perf_counter()
            ping.put(payload)
            if not pong.wait(1.0):
                raise RuntimeError("zenoh anchor: a round trip took over 1 s")
            rtts.append(time.perf_counter() - t0)
    finally:
        for s in reversed(subs):
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001 - closing the session releases it anyway
                pass
        client.close()
        router.close()
    med = statistics.median(rtts) * 1e6
    p90 = statistics.quantiles(rtts, n=10)[-1] * 1e6
    return row("zenoh_rtt", med, "us", note=f"{n} round trips of 64 B, router + client on "
               f"loopback TCP; p90 {p90:.0f} us")


def can_virtual(quick: bool = False) -> dict:
    import can

    n = 20_000
    channel = f"bsc-bench-anchor-{os.getpid()}"
    tx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    rx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    try:
        msgs = [can.Message(arbitration_id=0x100 + i % 8, data=i.to_bytes(8, "little"),
                            is_extended_id=False) for i in range(n)]
        send, recv = tx.send, rx.recv

        def run() -> int:
            for m in msgs:
                send(m)
                if recv(1.0) is None:
                    raise RuntimeError("can anchor: a frame was lost on the virtual bus")
            return len(msgs)

        value = _best_rate(run, 3)
    finally:
        tx.shutdown()
        rx.shutdown()
    return row("can_virtual", value, "frames/s", note=f"{n} frames, best of 3")


def numpy_matmul(quick: bool = False) -> dict:
    import numpy as np

    n = 200_000
    rng = np.random.default_rng(0)
    a = rng.normal(size=(n, 6, 6))
    b = rng.normal(size=(n, 6, 1))
    out = np.empty((n, 6, 1))

    def run() -> int:
        np.matmul(a, b, out=out)
        return n

    value = _best_rate(run, 5)
    return row("numpy_matmul", value, "products/s", note=f"N = {n}, best of 5")


MEASURE: dict[str, Callable[[bool], dict]] = {
    "cantools_decode": cantools_decode,
    "zenoh_rtt": zenoh_rtt,
    "can_virtual": can_virtual,
    "numpy_matmul": numpy_matmul,
}


def measure(name: str, quick: bool = False) -> dict:
    """Measure anchor ``name`` now (and cache it for :func:`get`)."""
    if name not in MEASURE:
        raise KeyError(f"no anchor {name!r} (anchors: {', '.join(MEASURE)})")
    r = MEASURE[name](quick)
    _cache[name] = r
    return r


def get(name: str, quick: bool = False) -> float | None:
    """The anchor's figure of this run, measured on first use."""
    if name not in _cache:
        measure(name, quick)
    return _cache[name]["value"]


def measured() -> list[dict]:
    """The anchor rows measured so far in this process, in :data:`ANCHORS` order."""
    return [_cache[n] for n in ANCHORS if n in _cache]


def reset() -> None:
    _cache.clear()


def figures(quick: bool = False) -> list[dict]:
    """Measure every anchor (again) and return their rows."""
    return [measure(n, quick) for n in MEASURE]


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m benchmarks.anchors", description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    for r in figures(args.quick):
        print(f"{r['name']:<16} {r['value']:>14,.1f} {r['unit']:<11} {r.get('note', '')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
