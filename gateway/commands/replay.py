"""``bsc replay FILE``: run a recorded session again, offline or live.

- ``--out DIR``: offline. The raw CAN frames go through fresh drivers and estimator as fast as
  possible; ``DIR/replay.mcap`` gets every health report and effort (``--samples``: every decoded
  sample too), ``DIR/report.json`` the counts, rejections and speed. Several logs: each into its
  own folder of DIR, one session per process (``--workers``), and ``DIR/replays.json``.
- ``--interface I --channel PREFIX|BUS=CH``: the raw frames go back onto CAN buses (any
  python-can interface) with their recorded timing.
- ``--zenoh [--connect ...]``: the recorded samples and efforts are republished on their keys
  with their recorded timing.

Options as rosbag2 users expect: ``--rate`` (0 = as fast as possible), ``--loop``,
``--start``/``--duration`` (seconds from the log's start), ``--can-id`` and ``--topic``
filters, a progress bar (``--quiet`` hides it).
"""
from __future__ import annotations

import argparse
import sys

from gateway.cli import UserError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", nargs="+", help="MCAP log written by bsc record / the gateway, or a CAN log (.log "
                        "candump, .asc, .blf, .trc, .csv, .gz of them: needs --robot, and --bus); offline (--out) "
                        "takes any number of MCAP logs: each replays into its own folder of DIR, one per process")
    mode = parser.add_argument_group("mode (exactly one)")
    mode.add_argument("--out", "-o", metavar="DIR",
                      help="offline: replay through drivers + estimator into DIR")
    mode.add_argument("--interface", "-i", default=None,
                      help="live CAN: python-can interface (socketcan, virtual, ...)")
    mode.add_argument("--zenoh", action="store_true",
                      help="live zenoh: republish the recorded samples and efforts")
    from drivers.canbus import add_can_arguments

    add_can_arguments(parser.add_argument_group("CAN"), interface_help=None,
                      channel_help="channel prefix (<prefix>-<bus>), or BUS=CHANNEL per bus to play "
                                   "(repeatable; buses not named are not played)",
                      fd_help="CAN FD buses (default: as the log says)")
    sel = parser.add_argument_group("selection and timing")
    sel.add_argument("--rate", "-r", type=float, default=1.0, metavar="R",
                     help="playback speed factor (default 1; 0 = as fast as possible)")
    sel.add_argument("--loop", "-l", action="store_true", help="play again and again until Ctrl-C")
    sel.add_argument("--start", type=float, default=None, metavar="S",
                     help="begin S seconds after the log's start")
    sel.add_argument("--duration", type=float, default=None, metavar="S",
                     help="play S seconds of the log")
    sel.add_argument("--can-id", action="append", default=[], metavar="ID[,ID...]",
                     help="only these CAN ids (decimal or 0x hex; repeatable)")
    sel.add_argument("--topic", action="append", default=[], metavar="GLOB",
                     help="only topics matching GLOB (e.g. '/can/arm0', 'bsc/*/efforts/**'; "
                          "repeatable)")
    sel.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    from gateway.commands import RT_PRIORITY_HELP

    sel.add_argument("--rt-priority", type=int, default=0, metavar="N",
                     help="live playback (--interface, --zenoh): " + RT_PRIORITY_HELP)
    off = parser.add_argument_group("offline")
    off.add_argument("--robot", default=None, metavar="NAME|FILE",
                     help="robot description (default: the log's robot.urdf attachment; required for a CAN log)")
    from gateway.commands.import_log import BUS_HELP

    off.add_argument("--bus", action="append", default=[], metavar="BUS=CHANNEL", help="a CAN log: " + BUS_HELP)
    off.add_argument("--model", default=None, metavar="NAME|FILE",
                     help="the estimator's robot model, if not the robot's own")
    off.add_argument("--copy-can", action="store_true",
                     help="copy the raw frames into the output (a replayable output)")
    off.add_argument("--samples", action="store_true",
                     help="also record every decoded sample (default: efforts and health only)")
    off.add_argument("--check", action="store_true",
                     help="compare the replayed efforts with the ones the log recorded: exit 3 when any differs "
                          "beyond 1e-9 relative, or differs at all while the log's kernels are these")
    off.add_argument("--workers", type=int, default=None, metavar="N",
                     help="processes for several logs (default: one per CPU)")
    off.add_argument("--force", action="store_true", help="replace DIR/replay.mcap, report.json")
    zen = parser.add_argument_group("zenoh playback")
    zen.add_argument("--wait", type=float, default=0.0, metavar="S",
                     help="wait up to S s for subscribers to match before publishing")
    from gateway.zenoh_config import add_zenoh_arguments

    add_zenoh_arguments(parser)


def _warn(text: str) -> None:
    print(f"bsc replay: warning: {text}", file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    from gateway.log.canlog import is_can_log

    if isinstance(args.file, str):         # run again by replay_can_log on the imported session
        args.file = [args.file]
    if args.bus and not any(is_can_log(f) for f in args.file):
        raise UserError("--bus maps the channels of a CAN log (.log, .asc, .blf, .trc, .csv); an MCAP log has buses")
    from gateway.replay import parse_can_ids

    modes = [m for m, on in (("--out", args.out is not None), ("--interface", args.interface),
                             ("--zenoh", args.zenoh)) if on]
    if len(modes) != 1:
        raise UserError("choose one mode: --out DIR (offline), --interface/--channel (CAN) "
                        "or --zenoh" + (f" (got {' '.join(modes)})" if modes else ""))
    if args.rate < 0:
        raise UserError(f"--rate {args.rate}: must be >= 0 (0 = as fast as possible)")
    if args.interface and not args.channel:
        raise UserError("--interface needs --channel PREFIX or BUS=CHANNEL")
    if args.channel and not args.interface:
        raise UserError("--channel needs --interface")
    from gateway.commands import check_interface

    check_interface(args)
    can_ids = parse_can_ids(args.can_id) if args.can_id else None
    from gateway.commands import check_rt_priority

    check_rt_priority(args.rt_priority)
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers {args.workers}: must be at least 1")
    if any(is_can_log(f) for f in args.file):      # the options checked: import it, then replay that
        if len(args.file) > 1:
            raise UserError("CAN logs replay one at a time (or `bsc import` each into a session, then replay "
                            "the sessions together)")
        from gateway.commands.import_log import replay_can_log

        args.file = args.file[0]
        return replay_can_log(args, run)
    if args.out is not None:
        if args.rt_priority:
            raise UserError("--rt-priority is for live playback (--interface, --zenoh), not --out")
        return _offline(args, can_ids) if len(args.file) == 1 else _offline_many(args, can_ids)
    if len(args.file) > 1:
        raise UserError(f"live playback takes one log, not {len(args.file)} (several logs: --out DIR)")
    args.file = args.file[0]
    if args.loop and args.rate == 0:
        raise UserError("--loop needs --rate > 0 (an unpaced endless loop would flood)")
    if args.interface:
        return _live_can(args, can_ids)
    if can_ids is not None:
        raise UserError("--can-id filters raw CAN frames: use it with --out or --interface")
    return _live_zenoh(args)


def _offline_options(args: argparse.Namespace, can_ids) -> dict:
    return dict(robot=args.robot, model=args.model, fd=True if args.fd else None, start_s=args.start,
                duration_s=args.duration, can_ids=can_ids, topics=args.topic or None, copy_can=args.copy_can,
                overwrite=args.force, samples=args.samples, check=args.check)


def _offline(args: argparse.Namespace, can_ids) -> int:
    from gateway.replay import replay_offline

    r = replay_offline(args.file[0], args.out, progress=not args.quiet, warn=_warn, **_offline_options(args, can_ids))
    print(f"bsc replay: {r.frames_in} frames, {r.log_duration_s:.3f} s of log in "
          f"{r.wall_s:.2f} s ({r.speed_x_realtime:.1f}x real time, {r.frames_per_s:.0f} frames/s)")
    print(f"bsc replay: {r.samples} samples, {r.efforts} efforts ({r.good_efforts} good), "
          f"{r.valve_wrenches} learned valve wrenches, {r.health_reports} health reports, {r.alerts} alerts")
    if r.rejections:
        print("bsc replay: rejected: " + ", ".join(f"{k} {v}" for k, v in r.rejections.items()))
    if r.frames_skipped:
        print("bsc replay: skipped: " + ", ".join(f"{k} {v}" for k, v in r.frames_skipped.items()))
    dropped = r.recorder.get("dropped_queue_full", 0) + r.recorder.get("dropped_write_error", 0)
    if dropped:
        print(f"bsc replay: warning: {dropped} messages not written")
    print(f"bsc replay: wrote {r.output} and {r.output.rsplit('/', 1)[0]}/report.json")
    if r.check is not None:
        print(f"bsc replay: check: {r.check['summary']}")
        if not r.check["ok"]:
            from gateway.cli import EXIT_TARGETS_MISSED

            return EXIT_TARGETS_MISSED
    return 0


def _offline_many(args: argparse.Namespace, can_ids) -> int:
    """Several logs: each into its own folder of DIR, one session per process; a line per log as it
    ends, a total, and DIR/replays.json (each log's output, figures or error)."""
    import json
    import time
    from pathlib import Path

    from gateway.cli import EXIT_TARGETS_MISSED, EXIT_USAGE
    from gateway.parallel import workers_for
    from gateway.replay import replay_many

    out = Path(args.out)
    n = len(args.file)
    workers = workers_for(n, args.workers)

    def done(i, o) -> None:
        for w in o.warnings:
            print(f"bsc replay: {o.source}: warning: {w}", file=sys.stderr)
        if o.error is not None:
            print(f"bsc replay: {o.source}: error: {o.error}", file=sys.stderr)
            return
        r = o.report
        line = (f"bsc replay: {o.source} -> {r.output}: {r.frames_in} frames, {r.log_duration_s:.1f} s of log, "
                f"{r.speed_x_realtime:.1f}x real time, {r.efforts} efforts ({r.good_efforts} good)")
        if r.check is not None:
            line += f"; check: {r.check['summary']}"
        print(line, flush=True)

    t0 = time.perf_counter()
    outcomes = replay_many(args.file, out, workers=workers, progress=not args.quiet and sys.stderr.isatty(),
                           done=done, **_offline_options(args, can_ids))
    wall = time.perf_counter() - t0
    good = [o for o in outcomes if o.error is None]
    log_s = sum(o.report.log_duration_s for o in good)
    print(f"bsc replay: {len(good)} of {n} logs, {log_s:.1f} s of log in {wall:.1f} s "
          f"({log_s / wall if wall > 0 else 0:.1f}x real time on {workers} process{'es' if workers > 1 else ''})")
    index = [{"source": o.source, "output": o.output, "error": o.error, "warnings": o.warnings,
              **({} if o.report is None else {"frames_in": o.report.frames_in, "efforts": o.report.efforts,
                                             "log_duration_s": o.report.log_duration_s,
                                             "speed_x_realtime": o.report.speed_x_realtime,
                                             "check": o.report.check})} for o in outcomes]
    out.mkdir(parents=True, exist_ok=True)
    (out / "replays.json").write_text(json.dumps({"logs": index, "wall_s": wall, "workers": workers}, indent=1) + "\n")
    print(f"bsc replay: wrote {out}/replays.json")
    if len(good) < n:
        return EXIT_USAGE
    if any(o.report.check is not None and not o.report.check["ok"] for o in good):
        return EXIT_TARGETS_MISSED
    return 0


def _live_can(args: argparse.Namespace, can_ids) -> int:
    import contextlib

    from gateway.commands import set_rt_priority, stop_on_sigterm
    from gateway.commands.gateway import channels, open_can
    from gateway.log.context import read_context
    from gateway.log.reader import readable
    from gateway.replay import play_can

    stop, restore = stop_on_sigterm()
    try:
        with readable(args.file, _warn) as src, contextlib.ExitStack() as stack:
            ctx = read_context(src)
            chans = channels(args.channel, list(ctx.buses), every=False)
            from drivers.canbus import BusOptions

            buses = open_can(stack, args.interface, chans, list(ctx.buses), fd=args.fd or ctx.fd,
                             options=BusOptions.from_args(args))
            set_rt_priority(args.rt_priority)
            stats = play_can(src, buses, rate=args.rate, loop=args.loop, start_s=args.start,
                             duration_s=args.duration, can_ids=can_ids,
                             topics=args.topic or None, stop=stop, progress=not args.quiet,
                             warn=_warn)
    finally:
        restore()
    print("bsc replay: " + stats.line("sent frames"))
    return 0


def _live_zenoh(args: argparse.Namespace) -> int:
    import zenoh

    from gateway.commands import set_rt_priority, stop_on_sigterm
    from gateway.replay import play_zenoh
    from gateway.zenoh_config import config_from_args

    stop, restore = stop_on_sigterm()
    try:
        with zenoh.open(config_from_args(args)) as session:
            set_rt_priority(args.rt_priority)
            stats = play_zenoh(args.file, session, rate=args.rate, loop=args.loop,
                               start_s=args.start, duration_s=args.duration,
                               topics=args.topic or None, stop=stop, progress=not args.quiet,
                               wait_s=args.wait, warn=_warn)
    finally:
        restore()
    print("bsc replay: " + stats.line("published samples"))
    return 0
