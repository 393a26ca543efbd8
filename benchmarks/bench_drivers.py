"""Driver throughput: ``python -m benchmarks.bench_drivers`` (prints figures; not a test).

1. live decode + validation: a realistic arm-bus frame mix fed through the BusMonitor and the
   drivers' ``on_message_received`` in one process (no bus, so the figure is the drivers' own);
2. the same for the spacecraft bus;
3. batch decode (numpy) vs cantools' per-frame ``decode_message`` on the same frames.

``figures()`` gives the same figures as rows for ``python -m benchmarks`` (anchor: cantools
``decode_message`` per frame, benchmarks/anchors.py).
"""
from __future__ import annotations

import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


from drivers import batch, devices, frames, wire  # noqa: E402
from drivers.samples import ImuSample, JointSample, ThrusterCommand, TorqueCommand, WrenchSample  # noqa: E402


def arm_frames(n_cycles: int):
    msgs = []
    for c in range(n_cycles):
        t = c * 1_000_000
        msgs += frames.encode_wrench(WrenchSample("arm0", t, c, (1.0 + c % 7, -2.0, 3.0), (0.1, 0.2, 0.3)))
        msgs.append(frames.encode_joint(JointSample("arm0/j1", t, c, 0.001 * c, 0.1), 0))
        msgs.append(frames.encode_joint(JointSample("arm0/j2", t, c, -0.001 * c, -0.1), 1))
        if c % 2 == 0:
            msgs += frames.encode_torque_commands([TorqueCommand("arm0/j1", t, c // 2, 10.0),
                                                   TorqueCommand("arm0/j2", t, c // 2, -5.0)])
    return msgs


def sc_frames(n_cycles: int):
    msgs = []
    for c in range(n_cycles):
        msgs += frames.encode_imu(ImuSample(c * 2_000_000, c, (1.0, 0.0, 0.0, 0.0), (0.01, 0.02, 0.03),
                                            (0.1, 0.0, 0.0)))
        if c % 5 == 0:
            msgs += frames.encode_thruster(ThrusterCommand(c, c // 5, (1.0, 2.0, 3.0), (0.0, 0.0, 1.0), 5))
    return msgs


def live(spec, msgs, repeat=3):
    best = float("inf")
    n_samples = 0
    for _ in range(repeat):
        out = []
        monitor, drivers = devices.listeners_for(spec, out.append)
        listeners = [monitor, *drivers]
        t0 = time.perf_counter()
        for m in msgs:
            for lst in listeners:
                lst.on_message_received(m)
        best = min(best, time.perf_counter() - t0)
        n_samples = len(out)
    return len(msgs) / best, n_samples


ARM = wire.BusSpec(name="arm0", kind="arm", arm="arm0", joints=("j1", "j2"), ids=wire.arm_ids(2))
SPACECRAFT = wire.BusSpec(name="spacecraft", kind="spacecraft", ids=wire.SPACECRAFT_IDS)
LIVE_TARGET = 50_000        # frames/s, live decode + validation per bus
BATCH_TARGET = 10.0         # batch decode / cantools per-frame decode


def batch_rate(msgs, repeat=5) -> float:
    """Best frames/s of :func:`drivers.batch.decode_batch` over ``msgs`` (arm bus)."""
    ids, data, lengths, t = batch.arrays_from_messages(msgs)
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = batch.decode_batch("arm", ids, data, lengths, t)
        best = min(best, time.perf_counter() - t0)
    n = sum(m.rows.size for m in res.messages.values())
    assert n == len(msgs), (n, len(msgs))
    return len(msgs) / best


def figures(quick: bool = False) -> list[dict]:
    """The suite's rows: live decode per bus and batch decode, beside cantools' per-frame decode."""
    from benchmarks.anchors import ratio, row

    am = arm_frames(4_000 if quick else 10_000)
    sm = sc_frames(2_000 if quick else 5_000)
    rate, ns = live(ARM, am)
    rate_sc, ns_sc = live(SPACECRAFT, sm)
    brate = batch_rate(am)
    rb = ratio(brate, "cantools_decode")
    return [
        row("live decode + validation, arm bus", rate, "frames/s", target=">= 50k frames/s",
            ok=rate >= LIVE_TARGET, anchor="cantools_decode", ratio=ratio(rate, "cantools_decode"),
            note=f"{len(am)} frames -> {ns} samples, best of 3"),
        row("live decode + validation, spacecraft bus", rate_sc, "frames/s", target=">= 50k frames/s",
            ok=rate_sc >= LIVE_TARGET, anchor="cantools_decode",
            ratio=ratio(rate_sc, "cantools_decode"), note=f"{len(sm)} frames -> {ns_sc} samples"),
        row("batch decode (numpy, from the DBC)", brate, "frames/s", target=">= 10x cantools_decode",
            ok=None if rb is None else rb >= BATCH_TARGET, anchor="cantools_decode", ratio=rb,
            note=f"{len(am)} arm frames, best of 5"),
    ]


def main() -> None:
    am = arm_frames(10_000)
    rate, ns = live(ARM, am)
    print(f"live decode + validation, arm bus:        {rate:10,.0f} frames/s  ({len(am)} frames -> {ns} samples)")
    sm = sc_frames(5_000)
    rate_sc, ns = live(SPACECRAFT, sm)
    print(f"live decode + validation, spacecraft bus: {rate_sc:10,.0f} frames/s  ({len(sm)} frames -> {ns} samples)")

    db = wire.database("arm")
    payloads = [bytes(m.data) for m in am]
    t0 = time.perf_counter()
    for m, p in zip(am, payloads):
        db.decode_message(m.arbitration_id, p)
    t_ct = time.perf_counter() - t0
    brate = batch_rate(am)
    print(f"cantools decode_message, per frame:       {len(am) / t_ct:10,.0f} frames/s")
    print(f"batch decode (numpy, from the DBC):       {brate:10,.0f} frames/s")
    print(f"batch / cantools ratio:                   {brate * t_ct / len(am):10.1f} x")
    ok = rate >= LIVE_TARGET and rate_sc >= LIVE_TARGET and brate * t_ct / len(am) >= BATCH_TARGET
    print("targets (live >= 50k frames/s, batch >= 10x cantools):", "met" if ok else "NOT met")


if __name__ == "__main__":
    main()
