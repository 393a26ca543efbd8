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

from gateway.config import RECEIVE_MODES, GatewayConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path, default=None, metavar="FILE.toml",
                        help="the gateway's configuration (every key and its default: deploy/gateway.toml, "
                             "docs/configuration.md); the flags below override it")
    parser.add_argument("--print-config", action="store_true",
                        help="print the configuration this run would use (file + flags + defaults) as TOML, "
                             "and exit")
    from drivers.canbus import add_can_arguments

    can_g = parser.add_argument_group("CAN ([can] and [drivers])")
    add_can_arguments(can_g, interface_help="python-can interface: socketcan, udp_multicast, pcan, kvaser, vector, "
                                            "virtual, ... (here or in --config)")
    can_g.add_argument("--receive", choices=RECEIVE_MODES, default=None,
                       help="how frames reach the worker: direct (it polls the buses' sockets; the auto choice "
                            "when every bus has one: socketcan, udp_multicast) or threads (one python-can "
                            "notifier thread per bus); see docs/latency.md")
    can_g.add_argument("--source-rate", type=source_rate, default=None, metavar="RATE|lockstep",
                       help="device seconds per second of the frame timestamps: 1 (default) for real devices "
                            "and simulators in real time, 2 for a log played at --rate 2, 'lockstep' for a "
                            "simulation paced by its computation (a silence is then counted as a lower bound "
                            "unless the device stamps its samples; docs/faults.md)")
    rob = parser.add_argument_group("robot ([robot])")
    rob.add_argument("--robot", default=None, metavar="NAME|FILE", help="robot description (default paper_robot)")
    rob.add_argument("--model", default=None, metavar="FILE.urdf",
                     help="the gateway's model of the robot when it differs from --robot (default: --robot)")
    rob.add_argument("--thrusters", default=None, metavar="NAME|FILE",
                     help="nominal thruster layout: a name (default ring18, 100 N), a [[thruster]] file or a "
                          "scenario .toml with a [thrusters] table (robot_description/thrusters.py)")
    svc = parser.add_argument_group("service ([service], [recording])")
    svc.add_argument("--record", type=Path, default=None, metavar="FILE.mcap", help="record the session")
    svc.add_argument("--health-period", type=float, default=None, metavar="S",
                     help="health publication period (default 0.5 s)")
    svc.add_argument("--no-samples", action="store_true",
                     help="publish efforts and health only, not every decoded sample (about 15 %% less "
                          "CPU at nominal rates; --record still records everything)")
    svc.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    from gateway.zenoh_config import add_zenoh_arguments

    add_zenoh_arguments(parser)


def configuration(args: argparse.Namespace) -> GatewayConfig:
    """The configuration of this run: ``--config`` (or the defaults), then every flag given over it."""
    config = GatewayConfig.load(args.config) if args.config is not None else GatewayConfig()
    can: dict = {}
    if args.interface is not None:
        can["interface"] = args.interface
    if args.channel:
        can["channels"] = tuple(args.channel)
    if args.fd:
        can["fd"] = True
    if args.bitrate is not None:
        can["bitrate"] = args.bitrate
    if args.data_bitrate is not None:
        can["data_bitrate"] = args.data_bitrate
    if args.bus_kwarg:
        can["bus_kwargs"] = tuple({**dict(config.can.bus_kwargs), **dict(args.bus_kwarg)}.items())
    if args.receive is not None:
        can["receive"] = args.receive
    zen: dict = {}
    if args.zenoh_config is not None:
        zen["config_file"] = args.zenoh_config
    if args.mode is not None:
        zen["mode"] = args.mode
    if args.connect:
        zen["connect"] = tuple(args.connect)
    if args.listen:
        zen["listen"] = tuple(args.listen)
    if args.multicast_scouting:
        zen["multicast_scouting"] = True
    robot = {k: v for k, v in (("description", args.robot), ("model", args.model), ("thrusters", args.thrusters))
             if v is not None}
    service: dict = {}
    if args.health_period is not None:
        service["health_period_s"] = args.health_period
    if args.no_samples:
        service["publish_samples"] = False
    if args.duration is not None:
        service["duration_s"] = args.duration
    drivers = {} if args.source_rate is None else {"source_rate": None if args.source_rate == "lockstep"
                                                   else args.source_rate}
    recording = {} if args.record is None else {"path": args.record}
    return config.updated(can=can, zenoh=zen, robot=robot, service=service, drivers=drivers, recording=recording)


def source_rate(text: str) -> float | str:
    """``--source-rate`` value: a positive number, or ``lockstep`` (the rate is unknown)."""
    if text.strip().lower() == "lockstep":
        return "lockstep"
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
    from drivers.canbus import BusOptions, describe
    from drivers.wire import WireMap
    from gateway.bridge import GatewayService
    from gateway.cli import UserError
    from gateway.commands import stop_on_sigterm
    from gateway.zenoh_config import make_config
    from robot_description.thrusters import ThrusterLayout

    config = configuration(args)
    if args.print_config:
        print(config.to_toml(), end="")
        return 0
    cc = config.can
    if cc.interface is None or not cc.channels:
        raise UserError("the CAN buses: give --interface and --channel, or [can] interface and channels in --config")
    robot = robot_description.load(config.robot.description)
    model = robot_description.load(config.robot.model) if config.robot.model else None
    layout = ThrusterLayout.load(config.robot.thrusters)
    wm = WireMap.from_robot(robot)
    chans = channels(list(cc.channels), list(wm.buses))
    options = BusOptions(cc.bitrate, cc.data_bitrate, cc.bus_kwargs)
    stop, _ = stop_on_sigterm()           # the process ends with the command
    with contextlib.ExitStack() as stack:
        buses = open_can(stack, cc.interface, chans, list(wm.buses), fd=cc.fd, options=options)
        rates = describe(options, cc.interface, chans.values(), fd=cc.fd)
        z = config.zenoh
        session = stack.enter_context(zenoh.open(make_config(connect=z.connect, listen=z.listen,
                                                             config_file=z.config_file, mode=z.mode,
                                                             multicast_scouting=z.multicast_scouting)))
        rec = None
        if config.recording.path is not None:
            from gateway.log.recorder import Recorder
            from gateway.log.context import session_context

            rec = stack.enter_context(Recorder(config.recording.path))
            # the layout the filter starts from, so that a replay of this log starts from it too
            rec.add_session_context(**session_context(robot, fd=cc.fd,
                                                      scenario_text=ThrusterLayout.scenario_text(
                                                          config.robot.thrusters),
                                                      extra={"bus_rates": rates,
                                                             "gateway_config": config.to_toml(docs=False)}))
        gw = stack.enter_context(GatewayService(robot, buses, session, config, model_robot=model, layout=layout,
                                                record=rec))
        freeze_heap()
        print(f"bsc gateway: robot {wm.robot}, buses " + ", ".join(f"{b}={c}" for b, c in chans.items())
              + f" (receive: {gw.receive})" + (f"; {rates}" if rates else ""), flush=True)
        try:
            gw.run(stop, config.service.duration_s)
        except KeyboardInterrupt:
            pass
        st = gw.stats
        print(f"bsc gateway: received {st['received']} frames, dropped {st['dropped']} (backlog full; peak "
              f"{st['peak_backlog']} of {st['max_backlog']}), receive errors "
              f"{sum(b['rx_errors'] for b in st['buses'].values())}; published {gw.published} messages; "
              + ", ".join(f"{k} {v}" for k, v in gw.engine.stats.items()), flush=True)
    return 0
