"""Offline replay speed: simulated seconds of log replayed per wall second (x real time).

Run: ``python -m benchmarks.bench_replay [--seconds S] [--log FILE]``. Target: >= 100x real
time for a recorded default ``bsc demo`` session, with efforts byte-identical to live.

Without ``--log`` a session is made first: the default scenario in the simulator for
``--seconds`` s, its sensor firmware's CAN frames (``simulator.firmware``) recorded the way the
live gateway does it (record the frame, feed it to ``gateway.pipeline.Pipeline``, record every
emit). The kernels are compiled (or loaded from numba's cache) first and that time is reported
on its own. Then, from the same file, what ``bsc replay`` runs:

- read: the chunks read into frame rows (``gateway.log.frames.mcap_frames``);
- read + drivers + estimator: those rows through a session, output discarded;
- full: ``replay_offline`` (read, drivers, estimator, write efforts and health, report), the
  whole call from opening the log to the output closed, the median of three runs; and the same
  with ``samples=True`` (every decoded sample written too).

The replayed efforts are compared byte for byte with the ones recorded live.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def pipeline_class():
    from gateway.pipeline import Pipeline

    return Pipeline


def simulated_steps(seconds: float):
    """``(robot, iterator of per-ms frame lists)`` from the simulator and its firmware."""
    from simulator import scenario as scenarios
    from simulator.engine import Simulation
    from simulator.firmware import Firmware

    sim = Simulation(scenarios.load(None))
    fw = Firmware(sim.robot)
    fw.frames(sim.step())                       # fail here, not half way, if it cannot run
    return sim.robot, (fw.frames(sim.step()) for _ in range(int(round(seconds * 1000)) - 1))


def synthetic_steps(seconds: float):
    """The same wire traffic at the DBC's nominal rates with random values (no physics)."""
    import random

    import robot_description
    from drivers import frames, wire
    from drivers.samples import ImuSample, JointSample, ThrusterCommand, TorqueCommand, WrenchSample

    robot = robot_description.load(None)
    wm = wire.WireMap.from_robot(robot)
    rnd = random.Random(0)

    def step(k: int):
        t = 1_000_000_000 + k * 1_000_000
        out = []
        for arm, spec in wm.buses.items():
            if spec.arm is None:
                continue
            for i, j in enumerate(spec.joints):
                out.append((arm, frames.encode_joint(JointSample(
                    f"{arm}/{j}", t, k, rnd.uniform(-3, 3), rnd.uniform(-1, 1)), i)))
            if k % 2 == 0:
                out += [(arm, m) for m in frames.encode_torque_commands(
                    [TorqueCommand(f"{arm}/{j}", t, k // 2, rnd.uniform(-5, 5))
                     for j in spec.joints])]
            out += [(arm, m) for m in frames.encode_wrench(WrenchSample(
                arm, t, k, tuple(rnd.uniform(-50, 50) for _ in range(3)),
                tuple(rnd.uniform(-10, 10) for _ in range(3))))]
        if k % 2 == 0:
            out += [("spacecraft", m) for m in frames.encode_imu(ImuSample(
                t, k // 2, (1.0, 0.0, 0.0, 0.0), tuple(rnd.uniform(-0.5, 0.5) for _ in range(3)),
                tuple(rnd.uniform(-0.1, 0.1) for _ in range(3))))]
        if k % 10 == 0:
            out += [("spacecraft", m) for m in frames.encode_thruster(ThrusterCommand(
                t, k // 10, (1.0, 0.0, 0.0), (0.0, 0.0, 0.1), 5))]
        return out

    return robot, (step(k) for k in range(int(round(seconds * 1000))))


def make_session(path: Path, seconds: float, pipeline_cls) -> tuple[int, float]:
    """``seconds`` of the default scenario recorded as the live gateway records it."""
    from gateway.log.recorder import Recorder
    from gateway.log.context import session_context

    try:
        robot, steps = simulated_steps(seconds)
        source = "simulator + firmware"
    except Exception as exc:  # noqa: BLE001 - the simulator may be mid-change; say so, go on
        print(f"simulator unavailable ({type(exc).__name__}: {exc}); synthetic frames at the "
              "nominal rates instead")
        robot, steps = synthetic_steps(seconds)
        source = "synthetic frames"
    n = 0
    t0 = time.perf_counter()
    with Recorder(path, queue_size=1 << 22) as rec:
        rec.add_session_context(**session_context(robot, extra={"mode": f"bench ({source})"}))
        pipe = pipeline_cls(robot, emit=lambda k, o: rec.record(k, o))
        for frame_list in steps:
            for bus, msg in frame_list:
                rec.record_can(bus, msg)
                pipe.feed(bus, msg)
                n += 1
        if hasattr(pipe, "flush"):
            pipe.flush()
    if rec.stats.dropped:
        print(f"warning: {rec.stats.dropped} messages dropped while making the session")
    return n, time.perf_counter() - t0


def _efforts(path: Path) -> dict[str, list[bytes]]:
    """Every effort's bytes, key by key in file order: the contract of replay (and of ``bsc replay
    --check``) is the same bytes in the same order on every key; how keys interleave in the file
    depends on how the frames were batched (gateway/pipeline.py: the learned valve wrenches of a
    call come before the call's efforts)."""
    from gateway.log.reader import iter_file_order

    out: dict[str, list[bytes]] = {}
    for t, _, m in iter_file_order(path, lambda t, s: "/efforts/" in t):
        out.setdefault(t, []).append(bytes(m.data))
    return out


def measure(seconds: float = 5.0, log: Path | None = None, say=print, repeats: int = 3) -> dict:
    """Make (or take) a session; compile or load the kernels (timed on their own); then time what
    ``bsc replay`` runs: reading the chunks into frame rows, those rows through a session
    (drivers + estimator, output discarded), and the whole offline replay (median of
    ``repeats``), with and without the decoded samples. Checks that the replayed efforts are
    byte-identical to the ones recorded live."""
    import statistics

    from gateway.engine import Session
    from gateway.log.frames import batched, mcap_frames
    from gateway.engine.warm import warm
    from gateway.log.context import read_context, resolve_robot
    from gateway.replay import OUTPUT_NAME, replay_offline

    out = {"label": "real pipeline", "real": True, "seconds": seconds}
    t0 = time.perf_counter()
    warm()
    out["t_kernels"] = time.perf_counter() - t0
    say(f"kernels compiled or loaded from numba's cache in {out['t_kernels']:.1f} s (not in the figures below)")
    with tempfile.TemporaryDirectory(prefix="bsc-bench-replay-") as tmp:
        tmp = Path(tmp)
        if log is None:
            log = tmp / "session.mcap"
            n, wall = make_session(log, seconds, pipeline_class())
            out.update(made_frames=n, made_wall=wall, made_bytes=log.stat().st_size)
            say(f"session: {seconds:g} s simulated, {n} frames, recorded live in "
                f"{wall:.1f} s ({log.stat().st_size / 1e6:.1f} MB)")
        ctx = read_context(log)
        span = (ctx.end_ns - ctx.start_ns) / 1e9 if ctx.start_ns is not None else 0.0
        robot = resolve_robot(ctx)

        with Session(robot) as probe:
            buses = list(probe.buses)
        t0 = time.perf_counter()
        chunks = list(batched(mcap_frames(log, buses) or iter(())))     # merged, as bsc replay merges them
        t_read = time.perf_counter() - t0
        frames = sum(len(c.frames) for c in chunks)
        if not chunks:
            raise SystemExit(f"bench_replay: {log} has no chunk index; run bsc recover on it first")

        t0 = time.perf_counter()
        with Session(robot, samples=False) as ses:
            for c in chunks:
                ses.feed_frames(c.frames, c.log_ns)
        t_feed = time.perf_counter() - t0

        runs = {}
        for samples in (False, True):
            walls = []
            for k in range(repeats):
                # the whole call, as a user waits for it: opening, the frames, and the output
                # written and closed (the replay's own wall_s stops before its recorder finishes)
                t0 = time.perf_counter()
                report = replay_offline(log, tmp / f"out{k}", samples=samples, overwrite=True)
                walls.append(time.perf_counter() - t0)
            runs[samples] = (statistics.median(walls), report)
        identical = _efforts(tmp / "out0" / OUTPUT_NAME) == _efforts(log)
        t_full, report = runs[False]
        t_samples, report_s = runs[True]
    out.update(span=span, frames=frames, t_read=t_read, t_feed=t_feed, t_full=t_full,
               x_full=span / t_full, t_samples=t_samples, x_samples=span / t_samples,
               samples=report_s.samples, efforts=report.efforts, health=report.health_reports,
               dropped=report.recorder["dropped"] + report_s.recorder["dropped"], identical=identical)
    return out


TARGET_X = 100.0


def figures(quick: bool = False) -> list[dict]:
    """The suite's rows: x real time of the full offline replay (target >= 100x), and frames/s
    of each stage beside cantools' per-frame decode (what one frame's work is measured against)."""
    from benchmarks.anchors import ratio, row

    m = measure(2.0 if quick else 5.0, say=lambda *_: None)
    same = "efforts byte-identical to live" if m["identical"] else "EFFORTS DIFFER FROM LIVE"
    rows = [row("full offline replay (efforts + health)", m["x_full"], "x real time",
                target=">= 100x", ok=m["x_full"] >= TARGET_X and m["identical"],
                note=f"{m['span']:.2f} s log of the default scenario, {m['frames']} frames; {m['efforts']} "
                     f"efforts, dropped {m['dropped']}; {same}; kernels {m['t_kernels']:.1f} s before"),
            row("full offline replay, with --samples", m["x_samples"], "x real time",
                note=f"{m['samples']} samples as well")]
    for name, t in (("replay: read chunks into frame rows", m["t_read"]),
                    ("replay: read + drivers + estimator", m["t_read"] + m["t_feed"]),
                    ("replay: full (efforts + health)", m["t_full"])):
        rate = m["frames"] / t
        rows.append(row(name, rate, "frames/s", anchor="cantools_decode",
                        ratio=ratio(rate, "cantools_decode"),
                        note=f"{m['span'] / t:.1f}x real time"))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="simulated session length")
    ap.add_argument("--log", type=Path, help="replay this recorded session instead")
    args = ap.parse_args(argv)

    m = measure(args.seconds, args.log)
    frames, span = m["frames"], m["span"]
    print(f"log: {span:.2f} s, {frames} frames ({frames / span:.0f} frames/s of log)")
    print(f"{'stage':<36} {'wall s':>8} {'frames/s':>10} {'x real time':>12}")
    for name, t in (("read chunks into frame rows", m["t_read"]),
                    ("read + drivers + estimator", m["t_read"] + m["t_feed"]),
                    ("full replay (efforts + health)", m["t_full"]),
                    ("full replay with --samples", m["t_samples"])):
        print(f"{name:<36} {t:>8.3f} {frames / t:>10.0f} {span / t:>12.1f}")
    print(f"full replay: {m['efforts']} efforts, {m['health']} health ({m['samples']} samples with --samples), "
          f"dropped {m['dropped']}; efforts byte-identical to live: {'yes' if m['identical'] else 'NO'}")
    print(f"target >= 100x real time: {'met' if m['x_full'] >= TARGET_X and m['identical'] else 'MISSED'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
