"""``bsc import FILE --robot R --bus BUS=CHANNEL ... -o session.mcap``: a CAN log of another
tool (candump -L .log, Vector .asc/.blf, PEAK .trc, python-can .csv, or .gz of them) as a
session MCAP, which everything else takes: ``bsc info``, ``bsc replay``, ``bsc analyze``,
Foxglove.

The frames keep the file's order and their own times (to the microsecond); the robot's URDF and
DBCs are attached. ``bsc replay`` and ``bsc analyze`` take the same logs directly (they import
into a temporary file first).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

BUS_HELP = ("map the log's channel CHANNEL to the robot's bus BUS (repeatable, e.g. --bus arm0=can0 "
            "--bus arm1=can1 --bus spacecraft=can2; ASC/BLF/TRC channels are numbers from 1, CSV's is -); "
            "default: channels named as the buses")


def add_log_arguments(group, *, robot: bool = True) -> None:
    """``--robot`` (when ``robot``) and ``--bus`` for a command that reads CAN logs."""
    if robot:
        group.add_argument("--robot", default=None, metavar="NAME|FILE.urdf",
                           help="the robot of the log (required: a CAN log names none)")
    group.add_argument("--bus", action="append", default=[], metavar="BUS=CHANNEL", help=BUS_HELP)
    group.add_argument("--fd", action="store_true", help="the buses are CAN FD")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", help="CAN log: .log (candump -L), .asc, .blf, .trc, .csv, or .gz of them")
    parser.add_argument("--output", "-o", required=True, metavar="FILE.mcap", help="the session MCAP to write")
    add_log_arguments(parser)
    parser.add_argument("--force", action="store_true", help="replace the output if it exists")
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress bar")


def warn(command: str):
    def _warn(text: str) -> None:
        print(f"bsc {command}: warning: {text}", file=sys.stderr, flush=True)
    return _warn


def load(file, robot: str | None, buses: list[str]):
    """(robot, bus map) of a CAN log's import, checked."""
    from drivers.wire import WireMap
    from gateway.log import canlog

    rob = canlog.robot_for_log(robot, file)
    return rob, canlog.parse_bus_map(buses, list(WireMap.from_robot(rob).buses))


def summary(stats) -> str:
    return (f"{stats.frames_written} of {stats.frames_read} frames ({stats.format}), {stats.span_s:.3f} s; "
            "channels " + ", ".join(f"{c}->{b}" for c, b in stats.channels.items()))


def run(args: argparse.Namespace) -> int:
    from gateway.log import canlog

    if not canlog.is_can_log(args.file):
        raise canlog.CanLogError(f"{args.file}: not a CAN log by its name (use {', '.join(canlog.FORMATS)}, "
                                 "or .gz of them); an MCAP log needs no import")
    if Path(args.output).suffix.lower() != ".mcap":
        raise canlog.CanLogError(f"--output {args.output}: name it .mcap")
    rob, bus_map = load(args.file, args.robot, args.bus)
    stats = canlog.import_log(args.file, args.output, rob, bus_map=bus_map, fd=args.fd, overwrite=args.force,
                              progress=not args.quiet)
    canlog.warn_lines(stats, warn("import"))
    print(f"bsc import: {summary(stats)}")
    print(f"bsc import: wrote {args.output}")
    return 0


def replay_can_log(args: argparse.Namespace, run) -> int:
    """``bsc replay LOG ...`` of a CAN log: imported into a temporary MCAP, then ``run`` (the
    replay of an MCAP log) on it; ``report.json`` says what the import read and left out."""
    import json
    import os

    from gateway.log import canlog

    if getattr(args, "check", False):
        raise canlog.CanLogError("--check compares with the efforts a bsc recording holds; a CAN log holds none")
    if getattr(args, "zenoh", False):
        raise canlog.CanLogError("--zenoh republishes recorded samples and efforts; a CAN log holds raw frames "
                                 "only: replay it with --out DIR, or onto CAN with --interface")
    rob, bus_map = load(args.file, args.robot, args.bus)
    source = args.file
    with canlog.imported(source, rob, bus_map=bus_map, fd=args.fd, progress=not args.quiet) as (mcap, stats):
        canlog.warn_lines(stats, warn("replay"))
        print(f"bsc replay: imported {summary(stats)}")
        args.file, args.robot, args.bus = str(mcap), None, []
        rc = run(args)
    if args.out is not None:
        report = Path(args.out) / "report.json"
        doc = json.loads(report.read_text())
        doc["source"] = str(source)
        doc["import"] = stats.to_json()
        tmp = report.with_name(f".{report.name}.tmp")
        tmp.write_text(json.dumps(doc, indent=1) + "\n")
        os.replace(tmp, report)
    return rc


def first_time_ns(path) -> int:
    """The log time of a CAN log's first frame (for ordering sessions); -1 when none."""
    from gateway.log import canlog

    try:
        return next((t for _, t, _ in canlog.read_log(path)), -1)
    except (canlog.CanLogError, OSError):
        return -1


def analyze_logs(paths, args: argparse.Namespace, tmp: Path) -> tuple[list[str], list[str]]:
    """``bsc analyze`` of CAN logs: ``paths`` with every CAN log (given, or below a given
    folder) replaced by its offline replay in ``tmp`` (the efforts analyze reads), and the
    logs that could not be replayed, each with why.

    The replays are made in the order of the logs' first frames, which is the order analyze
    then takes them in (by the replay's recording start, then by path)."""
    from gateway.log import canlog
    from gateway.replay import replay_offline

    rest, logs, given = [], [], set()
    for p in map(Path, paths):
        if p.is_dir():
            rest.append(str(p))
            logs += sorted(q for q in p.rglob("*") if q.is_file() and canlog.is_can_log(q))
        elif canlog.is_can_log(p):
            logs.append(p)
            given.add(p)
        else:
            rest.append(str(p))
    if not logs:
        return rest, []
    rob, bus_map = load(logs[0], args.robot, args.bus)
    out, skipped = [], []
    for i, log in enumerate(sorted(dict.fromkeys(logs), key=lambda q: (first_time_ns(q), str(q)))):
        try:
            with canlog.imported(log, rob, bus_map=bus_map, fd=args.fd,
                                 progress=not getattr(args, "quiet", True) and sys.stderr.isatty()) as (mcap, stats):
                for line in stats.warnings():
                    print(f"bsc analyze: {log}: {line}", file=sys.stderr)
                d = tmp / f"{i:05d}"
                replay_offline(mcap, d, robot=None)
        except (ValueError, OSError) as exc:
            if log in given:
                raise
            skipped.append(str(exc) if str(log) in str(exc) else f"{log}: {exc}")
            continue
        named = d / f"{log.name}.mcap"        # the session's name; its folder sorts as its time does
        (d / "replay.mcap").rename(named)
        out.append(str(named))
    return rest + out, skipped


def info_lines(path, *, as_json: bool = False) -> str:
    """``bsc info LOG`` of a CAN log: its format, channels (what ``--bus`` maps) with frame
    counts, times, and what import would count as bad."""
    import json
    from collections import Counter

    from gateway.log import canlog
    from gateway.log.scan import human_size

    stats = canlog.ImportStats(source=str(path), format=canlog.FORMATS[canlog.log_format(path)])
    first: dict[str, int] = {}          # per channel: earliest, latest, previous frame time
    last: dict[str, int] = {}
    prev: dict[str, int] = {}
    for chan, t, msg in canlog.read_log(path, stats):
        stats.read(chan, msg)
        stats.timed(chan, t, prev)
        first[chan] = min(first.get(chan, t), t)
        last[chan] = max(last.get(chan, t), t)
    if as_json:
        doc = {k: v for k, v in stats.to_json().items()
               if k not in ("channels", "frames_written", "unmapped", "first_ns", "last_ns")}
        return json.dumps(doc | {"span_s": stats.span_s}, indent=1)
    size = Path(path).stat().st_size
    out = [f"file:        {path} ({human_size(size)})", f"format:      {stats.format} (a CAN log: "
           "`bsc import` makes a session MCAP of it; replay and analyze take it with --robot and --bus)",
           f"frames:      {stats.frames_read}"]
    if stats.min_ns is not None:
        out.append(f"start:       {stats.min_ns} ns   end: {stats.max_ns} ns   duration: {stats.span_s:.3f} s")
    out.append("channels:    (--bus BUS=CHANNEL)")
    width = max([len(c) for c in stats.by_channel] + [7])
    out.append(f"  {'channel':<{width}}  {'frames':>9}  {'rate_hz':>9}")
    for chan, n in sorted(stats.by_channel.items()):
        span = (last[chan] - first[chan]) / 1e9
        rate = (n - 1) / span if span > 0 else 0.0
        out.append(f"  {chan:<{width}}  {n:>9}  {rate:>9.2f}"
                   + (f"  ({stats.backwards[chan]} back in time)" if stats.backwards[chan] else "")
                   + (f"  ({stats.jumps[chan]} jumps > {canlog.JUMP_NS // 10**9} s)" if stats.jumps[chan] else ""))
    kinds = Counter({"error frames": stats.error_frames, "remote frames": stats.remote_frames,
                     "CAN FD frames": stats.fd_frames,
                     "lines that are no frame": stats.bad_lines})
    out.append("bad input:   " + (", ".join(f"{k} {v}" for k, v in kinds.items() if v) or "none"))
    if stats.ended_early:
        out.append(f"ends early:  {stats.ended_early}")
    return "\n".join(out)
