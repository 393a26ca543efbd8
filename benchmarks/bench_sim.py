"""Simulator speed: simulated seconds per wall second at 1 kHz for the paper's robot.

    python -m benchmarks.bench_sim [--seconds 4]

Prints the real-time factor of the whole loop (physics, controller, thrusters, sensors, truth)
and, as anchors measured in the same run, the cost of the physics step alone and of one
Pinocchio ABA call, so the figure can be read as a ratio on a shared, noisy machine.

``Simulation.run()`` is timed as users run it: every step runs the closed loop (encoders and
joint controller at their rate, base controller and thruster chain per base period, the RK4
physics step with friction) and records the raw truth; the sensor models and derived truth are
evaluated over blocks of recorded steps inside the same call (see simulator/engine.py), and are
included in the time.
"""
from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import pinocchio as pin  # noqa: E402


def measure(seconds: float = 4.0, repeat: int = 3) -> dict:
    """Best wall time of ``Simulation.run()`` of the capture scenario, and the anchors' costs."""
    from simulator import scenario
    from simulator.dynamics import Dynamics, Friction
    from simulator.engine import Simulation

    sc = scenario.load("capture", {"duration_s": seconds})
    best = float("inf")
    for _ in range(repeat):
        sim = Simulation(sc)
        t0 = time.perf_counter()
        sim.run()
        best = min(best, time.perf_counter() - t0)
    steps = sim.n_steps

    dyn = Dynamics(sim.robot.model, Friction.none(sim.robot.n_joints), 1e-3)
    dyn.q = sim.robot.neutral()
    t0 = time.perf_counter()
    for _ in range(steps):
        dyn.step(np.zeros(6), np.ones(sim.robot.n_joints))
    t_phys = time.perf_counter() - t0

    m, d = sim.robot.model, sim.robot.model.createData()
    q, v, tau = sim.robot.neutral(), np.zeros(m.nv), np.ones(m.nv)
    t0 = time.perf_counter()
    for _ in range(steps):
        pin.aba(m, d, q, v, tau)
    t_aba = time.perf_counter() - t0
    return {"seconds": seconds, "repeat": repeat, "steps": steps, "rtf": seconds / best,
            "loop_us": best / steps * 1e6, "phys_us": t_phys / steps * 1e6,
            "aba_us": t_aba / steps * 1e6}


TARGET_RTF = 20.0


def figures(quick: bool = False) -> list[dict]:
    """The suite's rows: real-time factor (anchor: numpy batched products, a machine-speed
    normaliser) and the per-step costs beside one Pinocchio ABA call of the same run."""
    from benchmarks.anchors import ratio, row

    m = measure(2.0 if quick else 4.0, 2 if quick else 3)
    aba = "pin.aba call (this run)"
    return [
        row("simulator, simulated s per wall s", m["rtf"], "x real time", target=">= 20x",
            ok=m["rtf"] >= TARGET_RTF, anchor="numpy_matmul", ratio=ratio(m["rtf"], "numpy_matmul"),
            note=f"capture scenario, paper robot, 1 kHz, {m['seconds']:g} s simulated, "
                 f"best of {m['repeat']}"),
        row("simulator whole loop per step", m["loop_us"], "us", anchor=aba,
            ratio=m["loop_us"] / m["aba_us"], note="ratio = loop cost in ABA calls"),
        row("RK4 physics step alone", m["phys_us"], "us", anchor=aba,
            ratio=m["phys_us"] / m["aba_us"]),
        row("one pin.aba call", m["aba_us"], "us",
            note="the local anchor of the two rows above"),
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=4.0, help="simulated seconds per run")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)

    m = measure(args.seconds, args.repeat)
    per_step, phys, aba = m["loop_us"], m["phys_us"], m["aba_us"]
    print(f"{'figure':44s} {'value':>12s}")
    print(f"{'simulated s per wall s (whole loop, 1 kHz)':44s} {m['rtf']:12.2f}   (target >= 20)")
    print(f"{'whole loop, us per step':44s} {per_step:12.1f}")
    print(f"{'anchor: RK4 physics step alone, us':44s} {phys:12.1f}   ({per_step / phys:.1f}x inside the loop)")
    print(f"{'anchor: one pin.aba call, us':44s} {aba:12.2f}   (loop = {per_step / aba:.0f} ABA calls)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
