"""``bsc gateway``: drivers and estimator of a robot: samples, efforts and health over zenoh.

Efforts: ``bsc/<robot>/efforts/joints/<arm>`` and ``bsc/<robot>/efforts/thrusters``
(gateway/efforts.py; sync policy in gateway/estimator/core.py). ``--record FILE.mcap`` also
writes the session (raw frames in the order the estimator saw them, samples, efforts, health).

One CAN bus per arm plus the spacecraft bus. ``--channel`` either names every bus
(``--channel arm0=can0 --channel arm1=can1 --channel spacecraft=can2``) or gives one prefix
used as ``<prefix>-<bus>`` (``--channel bsc`` -> ``bsc-arm0``, ``bsc-arm1``, ``bsc-spacecraft``;
the simulator's firmware uses the same rule, ``drivers.wire.channel_name``).
"""
from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    can_g = parser.add_argument_group("CAN")
    can_g.add_argument("--interface", "-i", required=True, help="python-can interface, e.g. socketcan, virtual")
    can_g.add_argument("--channel", "-c", action="append", required=True, metavar="PREFIX|BUS=CHANNEL",
                       help="channel prefix, or BUS=CHANNEL for each bus (repeatable)")
    can_g.add_argument("--fd", action="store_true", help="the buses run CAN FD (same frames, bit-rate switch)")
    from drivers.canbus import add_bus_arguments

    add_bus_arguments(can_g)
    can_g.add_argument("--receive", choices=("auto", "direct", "threads"), default="auto",
                       help="how frames reach the worker: direct (it polls the buses' sockets; the auto choice "
                            "when every bus has one: socketcan, udp_multicast) or threads (one python-can "
                            "notifier thread per bus); see docs/latency.md")
    can_g.add_argument("--source-rate", type=source_rate, default=1.0, metavar="RATE|lockstep",
                       help="device seconds per second of the frame timestamps: 1 (default) for real devices "
                            "and simulators in real time, 2 for a log played at --rate 2, 'lockstep' for a "
                            "simulation paced by its computation (a silence is then counted as a lower bound "
                            "unless the device stamps its samples; docs/faults.md)")
    parser.add_argument("--robot", default=None, metavar="NAME|FILE", help="robot description (default paper_robot)")
    parser.add_argument("--model", default=None, metavar="FILE.urdf",
                        help="the gateway's model of the robot when it differs from --robot (default: --robot)")
    parser.add_argument("--thrusters", default=None, metavar="NAME|FILE",
                        help="nominal thruster layout: a name (default ring18, 100 N), a [[thruster]] file or a "
                             "scenario .toml with a [thrusters] table (robot_description/thrusters.py)")
    parser.add_argument("--record", type=Path, default=None, metavar="FILE.mcap", help="record the session")
    parser.add_argument("--health-period", type=float, default=0.5, metavar="S", help="health publication period")
    parser.add_argument("--no-samples", action="store_true",
                        help="publish efforts and health only, not every decoded sample (about 15 %% less "
                             "CPU at nominal rates; --record still records everything)")
    parser.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    from gateway.zenoh_config import add_zenoh_arguments

    add_zenoh_arguments(parser)


def source_rate(text: str) -> float | None:
    """``--source-rate`` value: a positive number, or ``lockstep`` (unknown: None)."""
    if text.strip().lower() == "lockstep":
        return None
    try:
        rate = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is neither a number nor 'lockstep'") from None
    if not (rate > 0 and rate != float("inf")):
        raise argparse.ArgumentTypeError(f"{text!r}: must be a positive number")
    return rate


def channels(spec: list[str], buses: list[str], *, every: bool = True) -> dict[str, str]:
    """``--channel`` values -> {bus: channel}: one prefix (every bus), or BUS=CHANNEL pairs (for
    every bus, or with ``every=False`` for some: a replay plays only the buses named)."""
    from drivers.wire import channel_name
    from gateway.cli import UserError

    pairs = [c for c in spec if "=" in c]
    if pairs and len(pairs) != len(spec):
        raise UserError("--channel: give either one prefix or BUS=CHANNEL for every bus")
    if not pairs:
        if len(spec) != 1:
            raise UserError("--channel: give one prefix, or BUS=CHANNEL pairs")
        return {b: channel_name(spec[0], b) for b in buses}
    out = dict(c.split("=", 1) for c in pairs)
    unknown, missing = set(out) - set(buses), set(buses) - set(out) if every else set()
    if unknown or missing:
        raise UserError(f"--channel: buses are {', '.join(buses) or 'none'}"
                        + (f"; unknown {', '.join(sorted(unknown))}" if unknown else "")
                        + (f"; missing {', '.join(sorted(missing))}" if missing else ""))
    return out


def open_can(stack, interface: str, chans: dict[str, str], buses: list[str], *, fd: bool = False,
             options=None) -> dict:
    """Open ``chans`` ({bus: channel}) on ``interface`` into the ExitStack ``stack``; a bus that
    cannot open is one UserError line. On ``udp_multicast`` each bus gets the port of its place in
    ``buses`` (the robot's bus order, ``drivers.wire.udp_port``), as the simulator's firmware sends.
    ``options`` (:class:`drivers.canbus.BusOptions`): bit rates and adapter arguments, over
    python-can's configuration, over the DBC's bit rate."""
    import can

    from drivers.wire import udp_port
    from drivers.canbus import BusOptions, open_bus
    from gateway.cli import UserError

    options = options or BusOptions()
    options.check(fd)
    out = {}
    for name, ch in chans.items():
        kw = {"port": udp_port(buses.index(name))} if interface == "udp_multicast" else {}
        try:
            out[name] = stack.enter_context(open_bus(interface, ch, options, fd=fd, **kw))
        except (can.CanError, ImportError, ValueError, TypeError, OSError) as exc:
            raise UserError(f"cannot open CAN bus {name} ({interface} {ch}): {exc}") from None
    return out


def freeze_heap() -> None:
    """Put every object allocated so far (numpy, Pinocchio, zenoh, the models) out of the garbage
    collector's reach (``gc.freeze``): later collections scan only what the running service
    allocates, so no pause grows with the size of the libraries (a full collection of the
    gateway's start-up heap takes about 25 ms, see docs/latency.md)."""
    import gc

    gc.collect()
    gc.freeze()


def run(args: argparse.Namespace) -> int:
    import contextlib

    import zenoh

    import robot_description
    from drivers.health import SourceTiming
    from drivers.wire import WireMap
    from gateway.bridge import GatewayService
    from gateway.zenoh_config import config_from_args

    from robot_description.thrusters import ThrusterLayout

    robot = robot_description.load(args.robot)
    model = robot_description.load(args.model) if args.model else None
    layout = ThrusterLayout.load(args.thrusters)
    wm = WireMap.from_robot(robot)
    chans = channels(args.channel, list(wm.buses))
    from gateway.commands import stop_on_sigterm

    stop, _ = stop_on_sigterm()           # the process ends with the command
    with contextlib.ExitStack() as stack:
        from drivers.canbus import BusOptions

        buses = open_can(stack, args.interface, chans, list(wm.buses), fd=args.fd, options=BusOptions.from_args(args))
        from gateway.commands.record import bus_rates

        rates = bus_rates(args, chans)
        session = stack.enter_context(zenoh.open(config_from_args(args)))
        rec = None
        if args.record is not None:
            from gateway.recorder import Recorder
            from gateway.replay import session_context

            rec = stack.enter_context(Recorder(args.record))
            # the layout the filter starts from, so that a replay of this log starts from it too
            rec.add_session_context(**session_context(robot, fd=args.fd,
                                                      scenario_text=ThrusterLayout.scenario_text(args.thrusters),
                                                      extra={"bus_rates": rates}))
        timing = SourceTiming(rate=args.source_rate)
        gw = stack.enter_context(GatewayService(robot, buses, session, fd=args.fd, health_period_s=args.health_period,
                                                timing=timing,
                                                model_robot=model, layout=layout, record=rec,
                                                publish_samples=not args.no_samples, receive=args.receive))
        freeze_heap()
        print(f"bsc gateway: robot {wm.robot}, buses " + ", ".join(f"{b}={c}" for b, c in chans.items())
              + f" (receive: {gw.receive})" + (f"; {rates}" if rates else ""), flush=True)
        try:
            gw.run(stop, args.duration)
        except KeyboardInterrupt:
            pass
        st = gw.stats
        print(f"bsc gateway: received {st['received']} frames, dropped {st['dropped']} (backlog full; peak "
              f"{st['peak_backlog']} of {st['max_backlog']}), receive errors "
              f"{sum(b['rx_errors'] for b in st['buses'].values())}; published {gw.published} messages; "
              + ", ".join(f"{k} {v}" for k, v in gw.engine.stats.items()), flush=True)
    return 0
