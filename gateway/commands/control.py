"""``bsc control``: close the inner loop: the joint drives' commands corrected from the gateway's
estimates, and the thrusters' valves allocated and timed on the per-valve wrenches the gateway
learns (docs/control.md).

    bsc control --robot paper_robot --connect tcp/127.0.0.1:7447
    bsc control --robot paper_robot --zenoh-config deploy/zenoh/controller.json5 --duration 60

Subscribes to ``bsc/<robot>/efforts/joints/**`` and the desired torques the gateway observes on
the arm buses (``bsc/<robot>/sensors/commands/torque/**``), and to the learned per-valve wrenches
(``bsc/<robot>/efforts/valves``), the commanded wrench the gateway observes on the spacecraft bus
(``bsc/<robot>/sensors/commands/thrusters``) and the gateway's alerts (its thruster faults), with
``--thruster-loop``;
publishes each arm's corrected drive command on ``bsc/<robot>/commands/drives/<arm>``, the valves
on ``bsc/<robot>/commands/thrusters`` and the loops' transitions on ``bsc/<robot>/commands/status``.
In a deployment it runs as the ``controller`` role, the only one allowed to publish there.
The thruster loop runs with ``--thruster-loop`` only (docs/control.md), and commands valves only
while the commanded wrench carries the flight software's keep-out mask (``THRUSTER_CMD_ALLOWED``:
which thrusters may fire without their plume reaching the target); without it, none (the robot's
valves keep the flight software's), raised as ``compensation-keepout-unknown``. ``--open-loop`` passes the
desired torques through unchanged (the same path, no correction) and commands no valve.
"""
from __future__ import annotations

import argparse
import sys

from gateway.cli import UserError


def add_arguments(p: argparse.ArgumentParser) -> None:
    from gateway.control.joints import JointLoopSettings
    from gateway.zenoh_config import add_zenoh_arguments

    d = JointLoopSettings()
    p.add_argument("--robot", default="paper_robot", metavar="NAME|FILE",
                   help="robot description: arms, joints, torque limits (default paper_robot)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    p.add_argument("--open-loop", action="store_true",
                   help="publish the desired torques unchanged (no correction) and no valve command")
    g = p.add_argument_group("thruster loop (docs/control.md)")
    g.add_argument("--thruster-loop", action="store_true",
                   help="also command the valves (bsc/<robot>/commands/thrusters), only while the commanded "
                        "wrench carries the flight software's keep-out mask (THRUSTER_CMD_ALLOWED); off by "
                        "default (docs/control.md)")
    g.add_argument("--thrusters", default=None, metavar="NAME|FILE",
                   help="the thruster layout, as bsc gateway takes it (default: the gateway's default layout)")
    g.add_argument("--valve-min-on", type=float, default=0.004, metavar="S",
                   help="the valves' minimum on-time, their minimum impulse bit (default 0.004 s)")
    g = p.add_argument_group("joint loop (docs/control.md)")
    g.add_argument("--kp", type=float, default=d.kp, help=f"proportional gain on the torque error (default {d.kp:g})")
    g.add_argument("--ki", type=float, default=d.ki_per_s, metavar="PER_S",
                   help=f"integral gain, 1/s (default {d.ki_per_s:g})")
    g.add_argument("--max-correction", type=float, default=d.max_correction, metavar="FRACTION",
                   help=f"largest correction, fraction of each joint's torque limit (default {d.max_correction:g})")
    g.add_argument("--max-rate", type=float, default=d.max_rate_per_s, metavar="PER_S",
                   help=f"fastest change of the correction, torque limits per second (default {d.max_rate_per_s:g})")
    g.add_argument("--stale", type=float, default=d.stale_s, metavar="S",
                   help=f"open the loop when no good estimate is this recent (default {d.stale_s:g} s)")
    g.add_argument("--resume-good", type=int, default=d.resume_good, metavar="N",
                   help=f"good estimates in a row to close the loop again (default {d.resume_good})")
    add_zenoh_arguments(p)


def settings_from_args(args: argparse.Namespace):
    from gateway.control.joints import JointLoopSettings

    if args.duration is not None and args.duration <= 0:
        raise UserError("--duration must be positive")
    if not args.valve_min_on > 0:
        raise UserError("--valve-min-on must be positive")
    # the settings' own checks name their fields; say them as the flags the user typed
    flags = {"kp": "--kp", "ki_per_s": "--ki", "max_correction": "--max-correction", "max_rate_per_s": "--max-rate",
             "stale_s": "--stale", "resume_good": "--resume-good"}
    from gateway.control.messages import ControlError

    try:
        return JointLoopSettings(kp=args.kp, ki_per_s=args.ki, max_correction=args.max_correction,
                                 max_rate_per_s=args.max_rate, stale_s=args.stale, resume_good=args.resume_good)
    except ControlError as exc:
        text = str(exc)
        for field, flag in flags.items():
            text = text.replace(f" {field} ", f" {flag} ")
        raise UserError(text.replace("joint loop: ", "")) from None


def run(args: argparse.Namespace) -> int:
    import logging

    import zenoh

    import robot_description
    from gateway.commands import stop_on_sigterm
    from gateway import keys
    from gateway.control.service import ControlService
    from gateway.zenoh_config import config_from_args

    from robot_description.thrusters import ThrusterLayout

    settings = settings_from_args(args)
    robot = robot_description.load(args.robot)
    layout = ThrusterLayout.load(args.thrusters) if args.thruster_loop else None
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    stop, restore = stop_on_sigterm()
    try:
        with zenoh.open(config_from_args(args)) as session, \
                ControlService(session, robot, settings, enabled=not args.open_loop, layout=layout,
                               valve_min_on_s=args.valve_min_on) as ctl:
            mode = "open loop (pass-through)" if args.open_loop else "closed loop"
            out = [keys.drive_commands(robot.name)] + ([keys.thruster_valves(robot.name)] if ctl.thrusters else [])
            print(f"bsc control: robot {robot.name}, {mode}, publishing on {', '.join(out)}",
                  file=sys.stderr, flush=True)
            try:
                ctl.run(stop, args.duration)
            except KeyboardInterrupt:
                pass
            valves = (f"; valve commands out: {ctl.valves_published['closed']} on learned wrenches, "
                      f"{ctl.valves_published['open']} on nominal ones" if ctl.thrusters else "")
            print(f"bsc control: {ctl.received} samples in ({ctl.rejected} rejected), drive commands out: "
                  f"{ctl.published['closed']} closed loop, {ctl.published['open']} open loop{valves}; "
                  f"{sum(a.state == 'raised' and a.rule == 'compensation-open-loop' for a in ctl.alerts)} "
                  "fallback(s)", file=sys.stderr)
    finally:
        restore()
    return 0
