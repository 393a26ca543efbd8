"""``bsc analyze PATH...``: actuator and sensor degradation from recorded sessions.

One session file or folders of many, taken in time order (``bsc.series`` metadata, else the
recording's start time), analysed in parallel worker processes with a progress bar. Per session:
friction per joint, efficiency per thruster axis, sensor consistency; across sessions: baselines
and CUSUM change detection (thresholds in the rules file, docs/monitoring.md).

    bsc analyze logs/                      # readable summary
    bsc analyze logs/ --json               # alerts as JSON lines on stdout
    bsc analyze logs/ --report report/     # report.md + PNG trend plots
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from gateway.cli import UserError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("paths", nargs="+", metavar="PATH",
                   help="session .mcap files, CAN logs (.log candump, .asc, .blf, .trc, .csv, .gz of them; "
                        "replayed first: needs --robot), or folders of them")
    p.add_argument("--json", action="store_true", help="print alerts as JSON lines (one per alert) on stdout")
    p.add_argument("--report", type=Path, metavar="DIR", help="write report.md and PNG trend plots into DIR")
    p.add_argument("--rules", type=Path, metavar="FILE", help="rules file (default: the shipped default.toml)")
    p.add_argument("--baseline", type=int, metavar="N", help="sessions that define normal (default: rules file, 3)")
    p.add_argument("--workers", type=int, metavar="N", help="worker processes (default: CPU count)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    from gateway.commands.import_log import add_log_arguments

    add_log_arguments(p.add_argument_group("CAN logs"))


def run(args: argparse.Namespace) -> int:
    import json

    from gateway import analysis
    from gateway.analysis.report import summary_text, write_report
    from gateway.monitor.rules import load_rules

    rules = load_rules(args.rules)
    baseline = args.baseline if args.baseline is not None else rules.baseline_sessions
    if baseline < 1:
        raise UserError("--baseline must be at least 1")
    import tempfile

    from gateway.commands.import_log import analyze_logs

    with tempfile.TemporaryDirectory(prefix="bsc-analyze-") as tmp:
        paths, not_replayed = analyze_logs(args.paths, args, Path(tmp))
        result, skipped = analysis.run(paths, detectors=rules.detectors or None, baseline_sessions=baseline,
                                       workers=args.workers, progress=not args.quiet and sys.stderr.isatty())
    skipped = not_replayed + skipped
    for reason in skipped:
        print(f"bsc analyze: skipped {reason}", file=sys.stderr)
    for ses in result.sessions:
        for note in ses.notes:
            print(f"bsc analyze: note: {note}", file=sys.stderr)
    if args.json:
        for f in result.findings:
            print(json.dumps(f.to_json(), allow_nan=False), flush=False)
    else:
        print(summary_text(result, skipped))
    if args.report:
        path = write_report(result, args.report, skipped, rules.path)
        print(f"bsc analyze: wrote {path}", file=sys.stderr)
    return 0
