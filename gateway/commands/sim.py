"""``bsc sim``: run the simulated space robot in lockstep and write its truth trace and plots.

    bsc sim --scenario capture --duration 8 --out sim-out

Writes ``truth.npz`` (docs/truth-trace.md), ``summary.json`` and PNG figures like the paper's:
trajectories, end-effector error with and without friction, commanded vs actual joint torques
and thruster wrench.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


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


def run(args: argparse.Namespace) -> int:
    from simulator import plots, scenario
    from simulator.engine import Simulation

    overrides = {}
    if args.duration is not None:
        if args.duration <= 0:
            raise ValueError("--duration must be positive")
        overrides["duration_s"] = float(args.duration)
    if args.seed is not None:
        overrides["seed"] = args.seed
    if args.robot:
        overrides["robot"] = args.robot
    sc = scenario.load(args.scenario, overrides)
    args.out.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    sim = Simulation(sc)
    trace = sim.run(progress=not args.quiet)
    wall = time.perf_counter() - t0
    trace.save(args.out / "truth.npz")
    summary = {"scenario": sc.name, "robot": sim.robot.name, "duration_s": sc.duration_s,
               "steps": trace.n, "wall_s": round(wall, 3), "realtime_factor": round(sc.duration_s / wall, 2),
               "files": ["truth.npz"]}
    if not args.no_plots:
        traces = {"with friction": trace}
        if not args.no_compare and sc.cfg.friction.coulomb_fraction > 0:
            traces["without friction"] = Simulation(sc, friction=False).run(progress=not args.quiet)
        for name, fn in (("trajectories.png", lambda p: plots.trajectories(trace, p)),
                         ("ee_error.png", lambda p: plots.ee_error(traces, p)),
                         ("joint_torques.png", lambda p: plots.joint_torques(trace, p)),
                         ("thruster_wrench.png", lambda p: plots.thruster_wrench(trace, p))):
            fn(args.out / name)
            summary["files"].append(name)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"simulated {sc.duration_s:g} s of {sc.name!r} ({sim.robot.name}) in {wall:.1f} s "
          f"({summary['realtime_factor']:g}x real time); wrote {', '.join(summary['files'])} to {args.out}/")
    return 0
