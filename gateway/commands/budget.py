"""``bsc budget``: worst-case (bit-stuffed) load of every CAN bus of a robot at nominal rates.

Rates are the DBC's ``GenMsgCycleTime`` (F/T and encoders 1 kHz, joint torque commands 500 Hz,
IMU 500 Hz, thruster commands 100 Hz, heartbeats 10 Hz). A bus above 60 % is flagged, with the
documented remedies (docs/wire.md): CAN FD (same frames, 5 Mbit/s data phase: ``--fd``), or a
lower rate.
"""
from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--robot", default=None, metavar="NAME|FILE",
                        help="built-in robot name or URDF file (default: paper_robot)")
    parser.add_argument("--fd", action="store_true", help="CAN FD: 1 Mbit/s arbitration, 5 Mbit/s data phase")
    parser.add_argument("--command-hz", type=float, default=None, metavar="HZ",
                        help="joint torque command rate (default: the DBC's 500 Hz)")
    parser.add_argument("--detail", action="store_true", help="one line per message")


def run(args: argparse.Namespace) -> int:
    import robot_description
    from drivers import wire

    robot = robot_description.load(args.robot)
    wm = wire.WireMap.from_robot(robot)
    mode = "CAN FD 1M/5M (BRS), conservative frame time" if args.fd else "classic CAN 1 Mbit/s, worst-case stuffing"
    print(f"robot {robot.name}: {len(robot.arms)} arm(s), {mode}, limit {wire.LOAD_LIMIT:.0%}")
    rows = wire.budget(wm, fd=args.fd, command_hz=args.command_hz)
    over = []
    for name, bus_rows in rows.items():
        spec = wm.buses[name]
        load = sum(r.load for r in bus_rows)
        frames = sum(r.rate_hz for r in bus_rows)
        what = f"arm, {len(spec.joints)} joint(s)" if spec.kind == "arm" else "spacecraft"
        flag = "OK" if load <= wire.LOAD_LIMIT else "OVER"
        print(f"  bus {name:<12} ({what:<18}) {frames:7.0f} frames/s  load {load:6.1%}  {flag}")
        if args.detail:
            for r in bus_rows:
                print(f"      0x{r.frame_id:03X} {r.message:<22} DLC {r.dlc}  {r.rate_hz:6.0f} Hz "
                      f"x {r.time_per_frame_us:6.1f} us = {r.load:6.2%}")
        if load > wire.LOAD_LIMIT:
            over.append((name, spec, load))
    if over:
        print(f"{len(over)} bus(es) above {wire.LOAD_LIMIT:.0%} at nominal rates. Remedies (docs/wire.md, 'Budget'):")
        fd = wire.budget(wm, fd=True, command_hz=args.command_hz)
        for name, spec, load in over:
            print(f"  {name}: CAN FD with bit-rate switch, same frames (bsc budget --fd): "
                  f"{sum(r.load for r in fd[name]):.1%}")
            if spec.kind == "arm":
                # encoders at half rate keep F/T at 1 kHz
                slow = sum(r.load * (0.5 if r.message.startswith("JOINT_STATE") else 1.0) for r in rows[name])
                print(f"  {name}: or joint state at 500 Hz (F/T stays 1 kHz): {slow:.1%}")
    return 0
