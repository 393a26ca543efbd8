"""Throughput of the estimator's forms: ``python -m benchmarks.bench_estimator [--robot R] [-n N]``.

Prints samples/s for each batch and live form, and, as an anchor measured in the same run (the
machine is shared, so absolute numbers drift), a plain numpy batched matmul of similar size:
``(N, n_joints, 6) @ (N, 6, 1)``, i.e. applying a precomputed A_tau to one wrench per sample.
Targets for paper_robot: batch simplified >= 1e6 samples/s, batch full >= 2e5 samples/s.
"""
from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

import robot_description  # noqa: E402
from gateway.estimator import (  # noqa: E402
    EstimatorModel, joint_torques, joint_torques_batch, joint_torques_simplified,
    joint_torques_simplified_batch, thruster_wrench, thruster_wrench_batch,
)
from gateway.estimator.filters import RotationalKF, gyro_rate_sigma  # noqa: E402


def _best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def measure(robot_name: str = "paper_robot", n: int = 200_000, live: int = 2_000,
            repeat: int = 3):
    """``(robot, n, live, rows)``: rows of ``(name, samples/s, us/sample)`` for every form."""
    robot = robot_description.load(robot_name)
    em = EstimatorModel.from_robot(robot)
    rng = np.random.default_rng(0)
    N, nj, p = n, em.n_joints, em.n_arms
    q, dq, ddq = rng.uniform(-3, 3, (N, nj)), rng.normal(size=(N, nj)), rng.normal(size=(N, nj))
    ft = rng.normal(size=(N, p, 6)) * 100
    a_s, w_s, dw_s = (rng.normal(size=(N, 3)) for _ in range(3))
    A = rng.normal(size=(N, nj, 6))
    w = rng.normal(size=(N, 6, 1))

    rows = []

    def bench(name, fn, n):
        dt = _best(fn, repeat)
        rows.append((name, n / dt, dt / n * 1e6))

    bench("anchor: numpy matmul (N,nj,6)@(N,6,1)", lambda: np.matmul(A, w), N)
    bench("batch thruster wrench", lambda: thruster_wrench_batch(em, ft, a_s, w_s, dw_s), N)
    bench("batch simplified joint torques", lambda: joint_torques_simplified_batch(em, q, ft), N)
    bench("batch full joint torques", lambda: joint_torques_batch(em, q, dq, ddq, ft, a_s, w_s, dw_s), N)

    data = em.data()
    L = min(live, N)

    def live_simple():
        for k in range(L):
            joint_torques_simplified(em, data, q[k], ft[k])

    def live_full():
        for k in range(L):
            joint_torques(em, data, q[k], dq[k], ddq[k], ft[k], a_s[k], w_s[k], dw_s[k])

    def live_thr():
        for k in range(L):
            thruster_wrench(em, ft[k], a_s[k], w_s[k], dw_s[k])

    kf = RotationalKF(em.inertia_s, 1000.0, gyro_rate_sigma(0.07, 1000.0), 100.0)

    def live_kf():
        for k in range(L):
            kf.step(w_s[k] * 1e-2, dw_s[k])

    bench("live thruster wrench (per sample)", live_thr, L)
    bench("live simplified joint torques (per sample)", live_simple, L)
    bench("live full joint torques (per sample)", live_full, L)
    bench("live rotational KF step (per sample)", live_kf, L)
    return robot, N, L, rows


# name -> minimum samples/s (paper_robot)
TARGETS = {"batch simplified joint torques": 1_000_000, "batch full joint torques": 200_000}


def figures(quick: bool = False) -> list[dict]:
    """The suite's rows (paper_robot), each beside numpy's batched (N,6,6)@(N,6,1) products."""
    from benchmarks.anchors import ratio, row

    robot, N, L, rows = measure(n=50_000 if quick else 200_000, live=500 if quick else 2_000)
    out = []
    for name, rate, _us in rows:
        if name.startswith("anchor:"):
            continue
        lim = TARGETS.get(name)
        out.append(row(name, rate, "samples/s",
                       target=None if lim is None else f">= {lim:,.0f} samples/s",
                       ok=None if lim is None else rate >= lim, anchor="numpy_matmul",
                       ratio=ratio(rate, "numpy_matmul"),
                       note=f"{robot.name}, " + (f"batch N = {N}" if name.startswith("batch")
                                                 else f"{L} samples one at a time")))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_estimator", description=__doc__.splitlines()[0])
    parser.add_argument("--robot", default="paper_robot")
    parser.add_argument("-n", "--samples", type=int, default=200_000, help="batch size")
    parser.add_argument("--live", type=int, default=2_000, help="samples for the per-sample forms")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)

    robot, N, L, rows = measure(args.robot, args.samples, args.live, args.repeat)
    em = EstimatorModel.from_robot(robot)
    print(f"robot {robot.name}: {em.n_arms} arms, {em.n_joints} joints; batch N = {N}, live {L} samples, best of {args.repeat}")
    width = max(len(r[0]) for r in rows)
    for name, rate, us in rows:
        print(f"  {name:<{width}}  {rate:>12,.0f} samples/s  {us:>9.3f} us/sample")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
