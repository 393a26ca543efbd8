"""``bsc export SESSION.mcap -o FILE``: a session's raw CAN frames as a CAN log for other tools.

The format is the one FILE's name says: ``.log`` (candump -L), ``.asc`` (Vector ASC), ``.blf``
(Vector BLF), ``.trc`` (PEAK TRC), ``.csv`` (python-can CSV), each also ``.gz``. Frames keep the
session's recording order (the order the gateway fed them) and their times, to the microsecond.
Channels are the bus names (candump), or 1, 2, ... in the robot's bus order (ASC, BLF, TRC),
unless ``--bus BUS=CHANNEL`` names them (then only those buses are exported). ``bsc import`` and
``bsc replay`` read the file back.
"""
from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", help="session MCAP (bsc record, the gateway, bsc import)")
    parser.add_argument("--output", "-o", required=True, metavar="FILE",
                        help="the CAN log to write: .log, .asc, .blf, .trc or .csv (or .gz of them)")
    parser.add_argument("--bus", action="append", default=[], metavar="BUS=CHANNEL",
                        help="write bus BUS as channel CHANNEL (repeatable; only the buses named are "
                             "written; ASC/BLF/TRC channels are numbers from 1; a CSV holds one bus: BUS=-)")
    parser.add_argument("--start", type=float, default=None, metavar="S",
                        help="begin S seconds after the session's start")
    parser.add_argument("--duration", type=float, default=None, metavar="S", help="write S seconds of the session")
    parser.add_argument("--can-id", action="append", default=[], metavar="ID[,ID...]",
                        help="only these CAN ids (decimal or 0x hex; repeatable)")
    parser.add_argument("--force", action="store_true", help="replace the output if it exists")
    parser.add_argument("--quiet", "-q", action="store_true", help="no summary line")


def run(args: argparse.Namespace) -> int:
    import sys

    from gateway.log import canlog
    from gateway.log.context import read_context
    from gateway.log.reader import iter_can_frames, readable
    from gateway.replay import ReplayError, parse_can_ids

    fmt = canlog.format_of_name(args.output)
    if fmt not in canlog.FORMATS:
        raise canlog.CanLogError(f"--output {args.output}: name it .log (candump), .asc, .blf, .trc or .csv "
                                 "(or .gz of them)")

    def warn(text: str) -> None:
        print(f"bsc export: warning: {text}", file=sys.stderr, flush=True)

    with readable(args.file, warn) as src:
        ctx = read_context(src)
        buses = ctx.buses
        if not buses:
            raise ReplayError(f"{args.file}: no raw CAN channels (/can/<bus>) to export"
                              + (" (empty log)" if ctx.message_count == 0 else ""))
        bus_map = canlog.parse_bus_map(args.bus, buses)
        channels = canlog.export_channels(fmt, buses, bus_map)
        start_ns, end_ns = ctx.window(args.start, args.duration)
        frames = iter_can_frames(src, buses=list(channels), start_ns=start_ns, end_ns=end_ns,
                                 can_ids=parse_can_ids(args.can_id) if args.can_id else None)
        stats = canlog.export_log(args.output, frames, channels, overwrite=args.force)

    for reason, n in sorted(stats.skipped.items()):
        warn(f"{n} frames not written: {reason}")
    if not args.quiet:
        total = sum(stats.written.values())
        print(f"bsc export: {total} frames to {args.output} ({canlog.FORMATS[fmt]}): "
              + ", ".join(f"{b} {stats.written[b]} as channel {c}" for b, c in channels.items()))
        print("bsc export: read it back with --bus " + " --bus ".join(f"{b}={c}" for b, c in channels.items()))
    return 0
