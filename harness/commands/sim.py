"""``bsc sim``: run the simulated space robot in lockstep and write its truth trace and plots.

    bsc sim --scenario capture --duration 8 --out sim-out
    bsc sim --interface virtual --channel bsc --realtime --drop-rate 0.01
    bsc sim -i udp_multicast -c arm0=239.74.163.1 -c arm1=239.74.163.2 -c spacecraft=239.74.163.3
    bsc sim --series friction-growth --sessions 12 --out series/fg


Writes ``truth.npz`` (docs/truth-trace.md), ``summary.json`` and PNG figures like the paper's:
trajectories, end-effector error with and without friction, commanded vs actual joint torques
and thruster wrench. With ``--interface`` the robot's sensor firmware also puts every frame on
the robot's CAN buses (any python-can interface; channels as ``bsc gateway`` takes them), in
lockstep or paced to the wall clock (``--realtime``), with optional fault injection
(docs/firmware.md). A scenario's ``[faults]`` table sets the same knobs; flags override it.

With ``--series`` it writes N recorded sessions (MCAP) of the capture task with a known
degradation instead, plus ``series.json`` (onset, per-session truth): the input of
``bsc analyze`` (docs/monitoring.md).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from gateway.cli import UserError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", default="capture", metavar="NAME|FILE",
                   help="built-in scenario name or a TOML file (default: capture)")
    p.add_argument("--robot", metavar="NAME|FILE.urdf", help="override the scenario's robot")
    p.add_argument("--duration", type=float, metavar="S", help="override the scenario duration, s")
    p.add_argument("--seed", type=int, help="override the scenario seed")
    p.add_argument("--out", type=Path, default=Path("sim-out"), metavar="DIR",
                   help="output folder (default: ./sim-out)")
    p.add_argument("--no-plots", action="store_true", help="write the trace only")
    p.add_argument("--no-compare", action="store_true",
                   help="skip the friction-free comparison run (used by the end-effector error plot)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    s_g = p.add_argument_group("degradation series (recorded sessions for bsc analyze)")
    s_g.add_argument("--series", metavar="NAME",
                     help="write a series of recorded sessions: healthy, friction-growth, thruster-loss, "
                          "ft-bias-drift")
    s_g.add_argument("--sessions", type=int, default=12, metavar="N", help="sessions in the series (default 12)")
    s_g.add_argument("--workers", type=int, metavar="N", help="worker processes (default: CPU count)")
    s_g.add_argument("--overwrite", action="store_true", help="replace an existing series in --out")
    can_g = p.add_argument_group("CAN (the sensor firmware; without --interface nothing is sent)")
    from drivers.canbus import CHANNEL_HELP, add_can_arguments

    add_can_arguments(can_g, interface_help="python-can interface: virtual, udp_multicast, socketcan, ...",
                      channel_help=CHANNEL_HELP[:-1] + "; default prefix bsc)",
                      fd_help="send CAN FD frames (same payloads, bit-rate switch)")
    can_g.add_argument("--realtime", action="store_true",
                       help="pace each 1 ms step to the wall clock and stamp frames at send "
                            "(default: lockstep, as fast as possible, simulated-time stamps)")
    from gateway.commands import RT_PRIORITY_HELP

    can_g.add_argument("--rt-priority", type=int, default=0, metavar="N", help="with --realtime: " + RT_PRIORITY_HELP)
    cl_g = p.add_argument_group("closed loop (docs/control.md)")
    cl_g.add_argument("--drives-from", metavar="ENDPOINT",
                      help="with --realtime: the joint drives apply the commands of bsc/<robot>/commands/drives/** "
                           "(bsc control) from the zenoh router at ENDPOINT instead of the flight software's; "
                           "waits until bsc control is connected")
    cl_g.add_argument("--drive-max-age", type=float, default=0.005, metavar="S",
                      help="with --drives-from: a drive command older than this (behind the desired torques it "
                           "corrects) is not applied; that arm's drives take the flight software's command "
                           "(default 0.005 s)")
    cl_g.add_argument("--valves-from", metavar="ENDPOINT",
                      help="with --realtime: the thrusters' valves follow the schedules of "
                           "bsc/<robot>/commands/thrusters (bsc control's thruster loop) from the zenoh router at "
                           "ENDPOINT instead of the flight software's; waits until bsc control is connected")
    cl_g.add_argument("--valve-max-age", type=float, default=0.010, metavar="S",
                      help="with --valves-from: a valve schedule that arrives more than this after its first "
                           "step is not applied (its rows for steps still to come included); those steps keep "
                           "the previous schedule's look-ahead, then the flight software's valves (default "
                           "0.010 s, one commanded-wrench period: docs/control.md)")
    cl_g.add_argument("--thrust-limit", type=float, default=1.0, metavar="FRACTION",
                      help="the flight software allocates at most this fraction of each thruster's thrust "
                           "(default 1; less leaves the valves headroom for an inner loop)")
    cl_g.add_argument("--command-limit", type=float, default=1.0, metavar="FRACTION",
                      help="the flight software saturates its joint commands at this fraction of the torque "
                           "limits (default 1; less leaves the drives headroom for an inner loop)")
    cl_g.add_argument("--compute-lead", type=float, default=0.0003, metavar="S",
                      help="with --drives-from or --valves-from: compute each step this long before it is due "
                           "(default 0.0003 s), "
                           "so that a drive command arriving until then is in it")
    f_g = p.add_argument_group("fault injection (docs/firmware.md; rates are per sample, exclusive)")
    for name, what in (("drop", "a frame is not sent"), ("duplicate", "a frame is sent twice"),
                       ("reorder", "a sample is sent after the device's next one"),
                       ("corrupt", "a measurement byte is flipped"), ("bad-dlc", "a frame is truncated/extended")):
        f_g.add_argument(f"--{name}-rate", type=float, metavar="P", help=f"probability {what}")
    f_g.add_argument("--silent", action="append", default=[], metavar="DEVICE:START_S:DURATION_S",
                     help="the device sends nothing for a while (repeatable); devices: <arm> (its F/T), "
                          "<arm>/<joint>, <arm>/torque_cmd, imu, thrusters, valves")
    f_g.add_argument("--counter-jump", action="append", default=[], metavar="DEVICE:AT_S:N",
                     help="the device's counter skips N values (1..126) at AT_S (repeatable)")
    f_g.add_argument("--fault-seed", type=int, metavar="N", help="seed of the random faults (default 0)")


def _triples(values: list[str], flag: str, kinds) -> tuple:
    out = []
    for v in values:
        parts = v.rsplit(":", 2)
        try:
            if len(parts) != 3 or not parts[0]:
                raise ValueError
            out.append((parts[0], kinds[0](parts[1]), kinds[1](parts[2])))
        except ValueError:
            raise UserError(f"{flag} {v!r}: expected {flag[2:].upper().replace('-', '_')} as "
                             f"DEVICE:{'START_S:DURATION_S' if flag == '--silent' else 'AT_S:N'}") from None
    return tuple(out)


def faults_from(args: argparse.Namespace, table) -> "object":
    """The scenario's ``[faults]`` table with the command-line knobs on top."""
    from simulator.firmware import Faults

    f = Faults.from_table(table)
    changes = {}
    for name in ("drop", "duplicate", "reorder", "corrupt", "bad_dlc"):
        v = getattr(args, f"{name}_rate")
        if v is not None:
            changes[f"{name}_rate"] = v
    if args.silent:
        changes["silent"] = f.silent + _triples(args.silent, "--silent", (float, float))
    if args.counter_jump:
        changes["counter_jumps"] = f.counter_jumps + _triples(args.counter_jump, "--counter-jump", (float, int))
    if args.fault_seed is not None:
        changes["seed"] = args.fault_seed
    return f.replace(**changes) if changes else f


def _uses_can(args: argparse.Namespace) -> bool:
    return bool(args.channel or args.fd or args.realtime or args.silent or args.counter_jump or args.bus_kwarg
                or args.bitrate is not None or args.data_bitrate is not None
                or args.fault_seed is not None
                or any(getattr(args, f"{n}_rate") is not None
                       for n in ("drop", "duplicate", "reorder", "corrupt", "bad_dlc")))


def run(args: argparse.Namespace) -> int:
    if args.series is not None:
        return _run_series(args)
    from harness import demo
    from simulator import plots, scenario
    from simulator.engine import Simulation

    overrides = {}
    if args.duration is not None:
        if args.duration <= 0:
            raise UserError("--duration must be positive")
        overrides["duration_s"] = float(args.duration)
    if args.seed is not None:
        overrides["seed"] = args.seed
    if args.robot:
        overrides["robot"] = args.robot
    if args.interface is None and _uses_can(args):
        raise UserError("--channel, --fd, --realtime, the bus options and the fault options need --interface")
    if args.rt_priority and not args.realtime:
        raise UserError("--rt-priority needs --realtime")
    for flag, given in (("--drives-from", args.drives_from), ("--valves-from", args.valves_from)):
        if given and not args.realtime:
            raise UserError(f"{flag} needs --realtime (and --interface): the loop runs on the wall clock")
    if args.drives_from and args.valves_from and args.drives_from != args.valves_from:
        raise UserError("--drives-from and --valves-from must name the same endpoint (one zenoh session)")
    if not 0.0 < args.thrust_limit <= 1.0:
        raise UserError(f"--thrust-limit must be a fraction in (0, 1], got {args.thrust_limit:g}")
    if not args.valve_max_age > 0:
        raise UserError(f"--valve-max-age must be positive, got {args.valve_max_age:g}")
    if not 0.0 < args.command_limit <= 1.0:
        raise UserError(f"--command-limit must be a fraction in (0, 1], got {args.command_limit:g}")
    if not args.drive_max_age > 0:
        raise UserError(f"--drive-max-age must be positive, got {args.drive_max_age:g}")
    if not 0.0 <= args.compute_lead < 0.001:
        raise UserError(f"--compute-lead must be in [0, 0.001) s, got {args.compute_lead:g}")
    from gateway.commands import check_rt_priority

    check_rt_priority(args.rt_priority)
    sc = scenario.load(args.scenario, overrides)
    args.out.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    sim = Simulation(sc, external_drives=bool(args.drives_from), command_limit=args.command_limit,
                     external_thrusters=bool(args.valves_from), thrust_limit=args.thrust_limit)
    can_summary = None
    if args.interface is None:
        trace = sim.run(progress=not args.quiet)
    else:
        trace, can_summary = _run_on_can(args, sc, sim)
    wall = time.perf_counter() - t0
    trace.save(args.out / "truth.npz")
    summary = {"scenario": sc.name, "robot": sim.robot.name, "duration_s": sc.duration_s,
               "steps": trace.n, "wall_s": round(wall, 3), "realtime_factor": round(sc.duration_s / wall, 2),
               "files": ["truth.npz"]}
    if can_summary is not None:
        summary["can"] = can_summary
    if not args.no_plots:
        traces = {"with friction": trace}
        if not args.no_compare and sc.cfg.friction.coulomb_fraction > 0:
            traces["without friction"] = Simulation(sc, friction=False).run(progress=not args.quiet)
        for name, fn in (("trajectories.png", lambda p: plots.trajectories(trace, p)),
                         ("ee_error.png", lambda p: plots.ee_error(traces, p)),
                         ("joint_torques.png", lambda p: plots.joint_torques(trace, p)),
                         ("thruster_wrench.png", lambda p: plots.thruster_wrench(
                             trace, p, band=(f"{demo.BAND_HZ:g} Hz band", demo.lowpass)))):
            fn(args.out / name)
            summary["files"].append(name)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"simulated {sc.duration_s:g} s of {sc.name!r} ({sim.robot.name}) in {wall:.1f} s "
          f"({summary['realtime_factor']:g}x real time); wrote {', '.join(summary['files'])} to {args.out}/")
    if can_summary is not None:
        sent = ", ".join(f"{b} {n}" for b, n in can_summary["frames_sent"].items())
        injected = {k: v for k, v in can_summary["faults_injected"].items() if v}
        print(f"sent on {args.interface} ({'real time' if args.realtime else 'lockstep'}): frames {sent}"
              + (f"; faults injected {injected}" if injected else ""))
        pc = can_summary.get("pacing")
        if pc:
            print(f"real-time pacing: steps sent p50 {pc['p50_us']:.0f} us, p99 {pc['p99_us']:.0f} us, max "
                  f"{pc['max_us']:.0f} us after their due time; {pc['late_steps']} of {pc['steps']} more than half "
                  "a period late" + (" (a receiver that stamps on arrival puts their frames in the next step's "
                                     "slot; --rt-priority helps: docs/firmware.md)" if pc["late_steps"] else ""))
    return 0


def _run_on_can(args: argparse.Namespace, sc, sim):
    import can

    from gateway.cli import UserError
    from gateway.commands.gateway import channels
    from simulator import firmware

    faults = faults_from(args, sc.data.get("faults"))
    fw = firmware.Firmware(sim.robot, fd=args.fd, faults=faults)
    chans = channels(args.channel or ["bsc"], list(fw.wire.buses))
    try:
        # a FirmwareError (a channel that cannot work) is a ValueError: one line, exit 2
        from drivers.canbus import BusOptions

        options = BusOptions.from_args(args)
        options.check(args.fd)
        buses = firmware.open_buses(sim.robot, args.interface, chans, fd=args.fd, options=options)
    except (can.CanError, ImportError, NotImplementedError, OSError, TypeError) as exc:
        raise UserError(f"cannot open the CAN buses on {args.interface} ({', '.join(chans.values())}): {exc}") from None
    with buses:
        from gateway.commands import set_rt_priority

        set_rt_priority(args.rt_priority)
        inboxes: dict = {}
        if args.drives_from or args.valves_from:
            trace, inboxes = _run_closed_loop(args, sim, buses, fw)
        else:
            trace = firmware.run_on_buses(sim, buses, firmware=fw, realtime=args.realtime, progress=not args.quiet)
    totals = {k: sum(fw.counts[d][k] for d in fw.devices) for k in firmware.COUNT_KEYS if k != "samples"}
    return trace, {"interface": args.interface, "channels": chans, "fd": args.fd, "realtime": args.realtime,
                   "frames_sent": dict(fw.frames_sent), "faults_injected": totals,
                   "pacing": fw.pacing.as_dict() if fw.pacing is not None else None,
                   "faults_per_device": {d: {k: v for k, v in fw.counts[d].items() if v and k != "samples"}
                                         for d in fw.devices
                                         if any(v for k, v in fw.counts[d].items() if k != "samples")},
                   **inboxes}


DRAIN_QUIET_S = 0.5      # after the run: the commands still arriving from a loop that fell behind
DRAIN_MAX_S = 10.0


def _run_closed_loop(args: argparse.Namespace, sim, buses, fw):
    """Real time with the drives and/or the valves on zenoh (harness.closed_loop.DriveInbox,
    ValveInbox): starts once bsc control subscribes to the efforts, computes each step just before
    it is due. Returns (trace, {"drives": ..., "valves": ...} summaries)."""
    import zenoh

    from gateway import codec, keys
    from gateway.zenoh_config import make_config
    from harness.closed_loop import DriveInbox, ValveInbox
    from simulator import firmware

    endpoint = args.drives_from or args.valves_from
    with zenoh.open(make_config(mode="client", connect=[endpoint])) as session:
        inboxes: dict = {}
        try:
            if args.drives_from:
                inboxes["drives"] = DriveInbox(session, sim, max_age_s=args.drive_max_age)
            if args.valves_from:
                inboxes["valves"] = ValveInbox(session, sim, max_age_s=args.valve_max_age)
            need = ([keys.joint_efforts(sim.robot.name, sim.robot.arms[0].name)] if args.drives_from else []) + \
                ([keys.valve_wrenches(sim.robot.name)] if args.valves_from else [])
            for key in need:
                if not codec.wait_for_subscriber(session, key, timeout_s=60.0):
                    raise UserError(f"no bsc control subscribed to {key} at {endpoint} within 60 s")
            applies = [box.apply for box in inboxes.values()]

            def on_step(r) -> None:
                for apply in applies:
                    apply(r)

            trace = firmware.run_on_buses(sim, buses, firmware=fw, realtime=True, progress=not args.quiet,
                                          on_step=on_step, lookahead_steps=1, compute_lead_s=args.compute_lead)
            # a loop that fell behind still answers the steps it saw: count those answers too, until
            # none came for DRAIN_QUIET_S (at most DRAIN_MAX_S)
            for box in inboxes.values():
                box.end()
            t_end = time.monotonic() + DRAIN_MAX_S
            while time.monotonic() < t_end and min(b.quiet_for() for b in inboxes.values()) < DRAIN_QUIET_S:
                time.sleep(0.05)
        finally:
            for box in inboxes.values():
                box.close()
    return trace, {name: box.summary() for name, box in inboxes.items()}


def _run_series(args: argparse.Namespace) -> int:
    from harness.series import DEFAULT_DURATION_S, SERIES, write_series

    if args.series not in SERIES:
        raise UserError(f"--series {args.series!r}: choose one of {', '.join(SERIES)}")
    if args.interface or _uses_can(args) or args.robot or args.seed is not None or args.scenario != "capture":
        raise UserError("--series writes the capture task with its own seeds: it takes --sessions, --duration, "
                         "--workers, --overwrite and --out only")
    if args.duration is not None and args.duration <= 0:
        raise UserError("--duration must be positive")
    t0 = time.perf_counter()
    try:
        paths = write_series(args.series, args.sessions, args.out,
                             duration_s=args.duration or DEFAULT_DURATION_S, progress=not args.quiet,
                             workers=args.workers, overwrite=args.overwrite)
    except FileExistsError as exc:
        raise UserError(f"{exc}; --overwrite replaces it") from None
    truth = json.loads((args.out / "series.json").read_text())
    onset = truth["onset_session"]
    print(f"wrote {len(paths)} sessions of series {args.series!r} to {args.out}/ in "
          f"{time.perf_counter() - t0:.0f} s; "
          + ("no degradation" if onset is None else
             f"{truth['expected_kind']} fault on {truth['expected_target']} from session {onset}")
          + "; truth in series.json")
    return 0
