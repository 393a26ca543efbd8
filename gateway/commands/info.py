"""``bsc info FILE``: what an MCAP log holds, and whether it is complete or needs recovering."""
from __future__ import annotations

import argparse

from gateway.cli import UserError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", help="MCAP file written by the bsc recorder (or any MCAP file), or a CAN log "
                                     "(.log candump, .asc, .blf, .trc, .csv, .gz of them): its channels and frames")
    parser.add_argument("--gap-s", type=float, default=1.0, metavar="S",
                        help="list inter-message gaps longer than S seconds (default 1.0)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def run(args: argparse.Namespace) -> int:
    import json

    from gateway.log.scan import human_size, inspect

    from gateway.log.canlog import is_can_log

    if is_can_log(args.file):
        from gateway.commands.import_log import info_lines

        print(info_lines(args.file, as_json=args.json))
        return 0
    if not args.gap_s > 0:
        raise UserError(f"--gap-s {args.gap_s}: must be positive")
    info = inspect(args.file, gap_threshold_s=args.gap_s)
    if args.json:
        print(json.dumps(info.to_json(), indent=1, default=str))
        return 0
    out = [f"file:        {info.path} ({human_size(info.size)})"]
    if info.complete:
        out.append("status:      complete (valid summary and footer)")
    elif info.skipped:
        out.append(f"status:      {info.status}; run `bsc recover {info.path}` for a valid copy of the rest")
    else:
        out.append(f"status:      {info.status} at byte {info.stop_offset}; "
                   f"run `bsc recover {info.path}` for a valid copy")
    out.append(f"library:     {info.library}")
    if info.start_ns is None:
        out.append("messages:    0")
    else:
        out.append(f"messages:    {info.message_count} in {info.chunks} chunks"
                   + (f" ({info.chunks_skipped} corrupt, skipped)" if info.chunks_skipped else ""))
        out.append(f"start:       {info.start_ns} ns   end: {info.end_ns} ns   "
                   f"duration: {info.duration_s:.3f} s")
    if info.channels:
        width = max(len(c.topic) for c in info.channels)
        sw = max(len(c.schema_name) for c in info.channels)
        out.append("channels:")
        out.append(f"  {'topic':<{width}}  {'schema':<{sw}}  {'count':>9}  {'rate_hz':>9}  "
                   f"{'max_gap_s':>9}")
        for c in info.channels:
            out.append(f"  {c.topic:<{width}}  {c.schema_name:<{sw}}  {c.count:>9}  "
                       f"{c.rate_hz:>9.2f}  {c.max_gap_s:>9.3f}"
                       + (f"  ({c.out_of_order} out of order)" if c.out_of_order else ""))
    gaps = [(c, t, g) for c in info.channels for t, g in c.gaps]
    if gaps:
        out.append(f"gaps > {info.gap_threshold_s:g} s:")
        for c, t, g in sorted(gaps, key=lambda x: -x[2])[:20]:
            rel = (t - info.start_ns) / 1e9
            out.append(f"  {c.topic}: {g:.3f} s after t0+{rel:.3f} s")
        total = sum(c.gaps_total for c in info.channels)
        if total > 20:
            out.append(f"  ... {total - 20} more (see --json)")
    else:
        out.append(f"gaps > {info.gap_threshold_s:g} s: none")
    out.append("metadata:    " + (", ".join(info.metadata) or "none"))
    out.append("attachments: " + (", ".join(f"{a['name']} ({a['media_type']}, "
                                            f"{human_size(a['size'])})"
                                            for a in info.attachments) or "none"))
    print("\n".join(out))
    return 0
