"""``bsc monitor``: live monitoring of one robot or many over zenoh, with a terminal dashboard.

Subscribes to ``bsc/<robot>/efforts/**``, ``sensors/commands/**`` (commands observed on the
buses) and ``health/**`` (``--robot '*'`` for every robot), tracks residuals, friction,
efficiency, staleness, loss and bus load, applies the alert rules (``--rules FILE``, default
the shipped one) and publishes alert transitions on ``bsc/<robot>/alerts`` (also logged;
``--alert-log FILE`` appends JSON lines).

    bsc monitor --connect tcp/127.0.0.1:7447                      # dashboard until Ctrl-C
    bsc monitor --connect tcp/127.0.0.1:7447 --duration 30 --once # run 30 s, print one final frame
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from gateway.cli import UserError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", default="*", metavar="NAME", help="robot name, or '*' for every robot (default)")
    p.add_argument("--rules", type=Path, metavar="FILE", help="rules file (default: the shipped default.toml)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    p.add_argument("--once", action="store_true", help="no live redraw: print one dashboard frame at the end")
    p.add_argument("--refresh", type=float, default=1.0, metavar="S", help="dashboard refresh period (default 1 s)")
    p.add_argument("--alert-log", type=Path, metavar="FILE", help="append every alert as a JSON line to FILE")
    p.add_argument("--no-publish", action="store_true", help="do not publish alerts on zenoh")
    from gateway.zenoh_config import add_zenoh_arguments

    add_zenoh_arguments(p)


def run(args: argparse.Namespace) -> int:
    import logging
    import time

    import zenoh

    from gateway.monitor.dashboard import CLEAR, render
    from gateway.monitor.rules import load_rules
    from gateway.monitor.service import MonitorService
    from gateway.zenoh_config import config_from_args

    if args.duration is not None and args.duration <= 0:
        raise UserError("--duration must be positive")
    if args.refresh <= 0:
        raise UserError("--refresh must be positive")
    rules = load_rules(args.rules)
    live = not args.once
    tty = sys.stdout.isatty()
    logging.basicConfig(level=logging.WARNING if live and tty else logging.INFO, format="%(message)s",
                        stream=sys.stderr)
    from gateway.commands import stop_on_sigterm

    stop, _ = stop_on_sigterm()           # the process ends with the command
    last = [0.0]

    def frame(svc: MonitorService, force: bool = False) -> None:
        now = time.monotonic()
        if not force and (not live or now - last[0] < args.refresh):
            return
        last[0] = now
        stats = {"received": svc.received, "dropped": svc.dropped, "rejected": svc.rejected}
        text = render(svc.monitor.snapshot(time.time_ns()), svc.alerts, color=tty, stats=stats)
        sys.stdout.write((CLEAR if tty and live else "") + text)
        sys.stdout.flush()

    with zenoh.open(config_from_args(args)) as session:
        with MonitorService(session, args.robot, rules, alert_log=args.alert_log,
                            publish=not args.no_publish, tick_s=min(0.25, args.refresh)) as svc:
            print(f"bsc monitor: watching bsc/{args.robot}/ (rules {rules.path})", file=sys.stderr, flush=True)
            try:
                svc.run(stop, args.duration, on_tick=frame)
            except KeyboardInterrupt:
                pass
            frame(svc, force=True)
            raised = sum(a.state == "raised" for a in svc.alerts)
            print(f"bsc monitor: {svc.received} samples, {raised} alert(s) raised, "
                  f"{len(svc.alerts) - raised} cleared ({svc.others} of them from other services)", file=sys.stderr)
    return 0
