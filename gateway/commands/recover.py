"""``bsc recover FILE``: salvage a truncated MCAP log (crash, kill, full disk) into a valid one."""
from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", help="MCAP file cut short (or any MCAP file)")
    parser.add_argument("-o", "--output", metavar="OUT",
                        help="output file (default: <stem>.recovered.mcap beside FILE)")
    parser.add_argument("--force", action="store_true", help="replace OUT if it exists")


def run(args: argparse.Namespace) -> int:
    from gateway.log.scan import human_size, recover

    report = recover(args.file, args.output, overwrite=args.force)
    state = ("was already complete" if report.was_complete and not report.damage
             else "" if not report.stop_reason
             else f"was cut at byte {report.stop_offset} ({report.stop_reason}); "
                  f"{human_size(report.bytes_dropped)} of incomplete data dropped")
    if report.damage:
        print(f"{report.source}: {report.damage}")
    if state:
        print(f"{report.source} {state}")
    print(f"wrote {report.output}: {report.messages} messages on {report.channels} channels, "
          f"{report.metadata} metadata, {report.attachments} attachments"
          + (f"; {report.chunks_skipped} corrupt chunks skipped" if report.chunks_skipped else "")
          + (f"; {report.orphan_messages} messages without a channel dropped"
             if report.orphan_messages else ""))
    return 0
