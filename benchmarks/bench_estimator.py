"""Throughput of the estimator the product runs: ``python -m benchmarks.bench_estimator [--robot R]``.

Per epoch (one F/T instant, 1 kHz), three levels of ``gateway/estimator/``, each called once per
epoch or sample (as the live gateway does) and once for a whole batch (as a replay does):

- the chain kernel (``chain_kernel.EpochKernel``): base motion, joint accelerations from the F/T
  sensors, simplified and full joint torques of every arm; ``epoch`` per epoch, ``batch`` for N;
- the thruster filter's IMU update (``thruster_kernel.CompiledThrusterFilter``) with the steps of
  its interval pushed, random valve masks (30 % open): ``push_epoch`` and ``imu`` per call, or
  ``run`` over the whole event stream;
- the whole ``EstimatorCore`` (sync policy, both kernels, flags) on the decoded samples of a
  scenario (capture): every sample in one ``feed``, or one ``feed`` per sample.

The machine is shared, so absolute figures drift: each is printed beside an anchor measured in
the same run (numpy's batched ``(N,6,6) @ (N,6,1)``, ``benchmarks/anchors.py``).
"""
from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

import robot_description  # noqa: E402
from gateway.estimator import EstimatorModel  # noqa: E402
from gateway.estimator import core, thruster_kernel  # noqa: E402
from gateway.estimator.chain_kernel import EpochKernel  # noqa: E402
from robot_description.thrusters import ThrusterLayout  # noqa: E402

# name -> minimum epochs/s: the offline full joint torques, as the batch numpy estimator's target was
TARGETS = {"chain kernel, batch": 200_000}


def _best(fn, repeat: int, setup=lambda: None) -> float:
    """Best wall time of ``repeat`` calls ``fn(setup())``, ``setup`` untimed (a fresh filter or
    core for every run), after one untimed call (numba's first dispatch of a signature loads
    the compiled code)."""
    fn(setup())
    times = []
    for _ in range(repeat):
        state = setup()
        t0 = time.perf_counter()
        fn(state)
        times.append(time.perf_counter() - t0)
    return min(times)


def scenario_rows(name: str, seconds: float):
    """A scenario's robot, thruster layout and sample rows: the drivers' event rows in arrival
    order, what the pipeline feeds the estimator core."""
    from gateway.pipeline import Pipeline
    from simulator import firmware, scenario
    from simulator.engine import Simulation

    sc = scenario.load(name, {"duration_s": seconds})
    sim = Simulation(sc)
    fw = firmware.Firmware(sim.robot)
    got: list = []
    pipe = Pipeline(sim.robot, emit=lambda key, obj: None, estimate=False,
                    on_samples=lambda events, log_ns: got.append(events.copy()))
    while sim.k < sim.n_steps:
        for bus, msg in fw.frames(sim.step()):
            pipe.feed(bus, msg)
    # np.concatenate would drop the dtype's padding, which the compiled core does not accept
    rows = np.zeros(sum(len(g) for g in got), dtype=core.SAMPLE_DTYPE)
    k = 0
    for g in got:
        rows[k:k + len(g)] = g
        k += len(g)
    return sim.robot, ThrusterLayout.from_config(sc.cfg.thrusters), rows


def measure(robot_name: str = "paper_robot", n: int = 100_000, live: int = 5_000, seconds: float = 2.0,
            repeat: int = 3, scenario: str = "capture"):
    """``(robot, rows)``: rows of ``(name, per second, unit, us each, note)``."""
    robot = robot_description.load(robot_name)
    em = EstimatorModel.from_robot(robot)
    rng = np.random.default_rng(0)
    N, nj, p = n, em.n_joints, em.n_arms
    L = min(live, N)
    rows = []

    def bench(name, fn, count, unit, note, setup=lambda: None):
        dt = _best(fn, repeat, setup)
        rows.append((name, count / dt, unit, dt / count * 1e6, note))

    # chain kernel
    kernel = EpochKernel(em)
    q, dq = rng.uniform(-3.0, 3.0, (N, nj)), rng.uniform(-1.0, 1.0, (N, nj))
    ft, thr, w_s = rng.normal(0.0, 50.0, (N, p, 6)), rng.normal(0.0, 30.0, (N, 6)), rng.normal(0.0, 0.05, (N, 3))
    out = kernel.outputs()

    def chain_single(_):
        for k in range(L):
            kernel.epoch(q[k], dq[k], ft[k], thr[k], w_s[k], out=out)

    what = f"{robot.name}, {p} arms, {nj} joints"
    bench("chain kernel, one call per epoch", chain_single, L, "epochs/s", f"{what}; {L} calls from Python")
    bench("chain kernel, batch", lambda _: kernel.batch(q, dq, ft, thr, w_s), N, "epochs/s", f"{what}; N = {N}")

    # thruster filter: every IMU sample ends an interval of imu_steps steps
    layout = ThrusterLayout.named()
    steps = 2
    M = max(L, 1)
    t_imu = 1_000_000_000 + np.arange(1, M + 1, dtype=np.int64) * steps * 1_000_000
    masks = (rng.random((M, steps, layout.n)) < 0.3) @ (1 << np.arange(layout.n, dtype=np.int64))
    arm = rng.normal(0.0, 20.0, (M, steps, 6))
    acc, rate = rng.normal(0.0, 0.05, (M, 3)), rng.normal(0.0, 0.01, (M, 3))
    kind = np.tile(np.array([thruster_kernel.STEP] * steps + [thruster_kernel.IMU]), M)
    back = np.r_[np.arange(steps - 1, -1, -1), 0]         # the steps, then the IMU sample ending them
    t_ev = (t_imu[:, None] - back[None, :] * 1_000_000).reshape(-1)
    arm_ev = np.zeros((M, steps + 1, 6))
    arm_ev[:, :steps] = arm
    mask_ev = np.zeros((M, steps + 1), dtype=np.int64)
    mask_ev[:, :steps] = masks
    acc_ev, rate_ev = np.zeros((M, steps + 1, 3)), np.zeros((M, steps + 1, 3))
    acc_ev[:, steps], rate_ev[:, steps] = acc, rate

    def new_filter():
        return thruster_kernel.CompiledThrusterFilter(em, layout, dt=1e-3, imu_steps=steps)

    t_step = t_ev.reshape(M, steps + 1)

    def kf_single(kf):
        for i in range(M):
            for j in range(steps):
                kf.push_epoch(int(t_step[i, j]), arm[i, j], int(masks[i, j]))
            kf.imu(int(t_imu[i]), acc[i], rate[i])

    def kf_batch(kf):
        kf.run(kind, t_ev, arm_ev.reshape(-1, 6), mask_ev.reshape(-1), acc_ev.reshape(-1, 3), rate_ev.reshape(-1, 3))

    kf_what = f"{layout.n} thrusters, {6 * layout.n + 6} states, {steps} steps pushed per update"
    bench("thruster filter IMU update, one call each", kf_single, M, "updates/s", f"{kf_what}; {M} updates",
          new_filter)
    bench("thruster filter IMU update, batch", kf_batch, M, "updates/s", f"{kf_what}; one run() of {M} updates",
          new_filter)

    # the whole estimator core on real samples
    srobot, slayout, srows = scenario_rows(scenario, seconds)
    probe = core.EstimatorCore(srobot, layout=slayout)
    probe.feed(srows)
    probe.flush()
    epochs = probe.epochs
    per = len(srows) / max(epochs, 1)

    def new_core():
        return core.EstimatorCore(srobot, layout=slayout)

    def core_batch(c):
        c.feed(srows)
        c.flush()

    singles = [srows[k:k + 1] for k in range(len(srows))]       # slicing is the caller's work, not the core's

    def core_single(c):
        for rows in singles:
            c.feed(rows)
        c.flush()

    core_what = (f"{scenario} scenario ({srobot.name}), {seconds:g} s: {len(srows)} samples, {epochs} epochs "
                 f"({per:.1f} samples each)")
    bench("EstimatorCore, all samples in one call", core_batch, epochs, "epochs/s", core_what, new_core)
    bench("EstimatorCore, one call per sample", core_single, epochs, "epochs/s", core_what, new_core)
    return robot, rows


def figures(quick: bool = False) -> list[dict]:
    """The suite's rows (paper_robot), each beside numpy's batched (N,6,6)@(N,6,1) products."""
    from benchmarks.anchors import ratio, row

    robot, rows = measure(n=20_000 if quick else 100_000, live=1_000 if quick else 5_000,
                          seconds=1.0 if quick else 2.0)
    out = []
    for name, rate, unit, us, note in rows:
        lim = TARGETS.get(name)
        out.append(row(name, rate, unit, target=None if lim is None else f">= {lim:,.0f} {unit}",
                       ok=None if lim is None else rate >= lim, anchor="numpy_matmul",
                       ratio=ratio(rate, "numpy_matmul"), note=f"{note}; {us:.2f} us each"))
    return out


def main(argv: list[str] | None = None) -> int:
    from benchmarks.anchors import get

    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_estimator", description=__doc__.splitlines()[0])
    parser.add_argument("--robot", default="paper_robot")
    parser.add_argument("-n", "--epochs", type=int, default=100_000, help="batch size of the chain kernel")
    parser.add_argument("--live", type=int, default=5_000, help="calls of the one-at-a-time forms")
    parser.add_argument("--scenario", default="capture", help="the scenario whose samples EstimatorCore is fed")
    parser.add_argument("--seconds", type=float, default=2.0, help="its length, s")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)

    robot, rows = measure(args.robot, args.epochs, args.live, args.seconds, args.repeat, args.scenario)
    anchor = get("numpy_matmul")
    print(f"robot {robot.name}, best of {args.repeat}; anchor numpy (N,6,6)@(N,6,1): {anchor:,.0f} products/s")
    width = max(len(r[0]) for r in rows)
    for name, rate, unit, us, note in rows:
        print(f"  {name:<{width}}  {rate:>12,.0f} {unit:<10} {us:>9.3f} us each   ({note})")
    ok = all(rate >= TARGETS[name] for name, rate, *_ in rows if name in TARGETS)
    print("target (chain kernel batch >= 200,000 epochs/s):", "met" if ok else "NOT met")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
