"""The thruster filter's gyro rows: their noise treated as white (today) against modelled exactly.

    python -m benchmarks.bench_gyro_noise [--scenario capture --scenario three_arm] [--seeds 500,501]
                                          [--workers 2] [--json FILE]

The filter (gateway/estimator/thrusters.py) measures the thrusters' moment through the gyro as the
difference of two consecutive rate samples, ``I (w_k - w_k-1) / T``. Its noise ``I (e_k - e_k-1) / T``
is moving-average (lag-1 correlation -1/2), but the filter takes it as white with twice a sample's
variance (its docstring's "documented simplification"). Consecutive differences then telescope:
over ``N`` samples the rate's noise enters once, not ``N`` times, and a white treatment throws that
away. :class:`ExactGyroFilter` models it exactly: the state gains the gyro noise of the previous
and of the current sample (3 + 3), the gyro rows see ``B (e_k - e_k-1)`` with ``B = I / T`` and no
noise of their own, and after each sample the current noise becomes the previous one (Bryson and
Henrikson's augmentation for coloured measurement noise). Everything else (prior, random walk,
accelerometer rows, history matching) is the reference filter's.

This is a numpy reference form, not yet the compiled kernels the gateway runs
(gateway/estimator/thruster_kernel.py), and not yet tuned with the fault detector (whose
thresholds were set on the white form's innovations). Each healthy session is recorded through the
real path (simulator -> firmware -> CAN frames -> gateway -> MCAP; harness/fdi.py), its thruster
filter inputs read back as ``bsc analyze`` reads them, and three filters run over them: the
compiled kernel (what the gateway publishes, with no fault detector), this module's filter with
the white treatment (it must agree with the kernel: the same filter written again) and with the
exact one. Each is judged as the fault benchmark judges the published wrench (band-limited
20 Hz NRMSE = RMS error / peak, per axis, the whole session, axes of peak >= 10 N or N m).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from gateway.estimator.thrusters import ThrusterFilter  # noqa: E402

AXES = ("fx", "fy", "fz", "mx", "my", "mz")
FORMS = ("kernel", "white", "exact")
DURATION_S = {"capture": 8.0, "three_arm": 4.0}


class ExactGyroFilter(ThrusterFilter):
    """The reference thruster filter with the gyro-difference noise white (``exact=False``: the
    same filter as :class:`ThrusterFilter` up to rounding) or modelled exactly (``exact=True``:
    two more 3-blocks of state, the previous and the current sample's gyro noise). Call
    :meth:`push_epoch` per step and :meth:`update` per IMU sample; :meth:`valve_wrench` is the
    current ``W`` (n, 6)."""

    def __init__(self, *args, exact: bool = False, **kwargs):
        super().__init__(*args, **kwargs)
        self.exact = exact
        self.n0 = n0 = self.ns
        self.sig_g = self.settings.gyro_sigma
        self.B = self.I / (self.imu_steps * self.dt)
        self.last_rate: tuple[int, np.ndarray] | None = None
        if exact:
            x = np.zeros(n0 + 6)
            x[:n0] = self.x
            P = np.zeros((n0 + 6, n0 + 6))
            P[:n0, :n0] = self.P
            P[n0:, n0:] = np.eye(6) * self.sig_g ** 2
            Q = np.zeros(n0 + 6)
            Q[:n0] = self.Q_per_s
            self.x, self.P, self.Q_per_s = x, P, Q

    def valve_wrench(self) -> np.ndarray:
        return self.x[:6 * self.n].reshape(self.n, 6)

    def update(self, t_ns: int, accel_imu: np.ndarray, rate_imu: np.ndarray) -> bool:
        """One IMU sample (IMU frame) ending at ``t_ns``; False when a step of its interval is missing."""
        w = self.R_imu @ np.asarray(rate_imu, float)
        a = self.R_imu @ np.asarray(accel_imu, float)
        prev, self.last_rate = self.last_rate, (t_ns, w)
        nn = self.imu_steps
        cur = self._steps(t_ns, nn)
        if cur is None:
            self._next_noise(fresh=True)
            return False
        n, ns, n0 = self.n, self.x.shape[0], self.n0
        gyr = np.cross(w, self.I @ w)
        rows = np.array([e[1] for e in cur])
        alpha = (rows[:, 3:] - gyr) @ self.I_inv.T
        known = rows[:, :3] / self.m + np.cross(alpha, self.r) + np.cross(w, np.cross(w, self.r))
        H = np.zeros((6, ns))
        y = np.zeros(6)
        R = np.zeros((6, 6))
        y[:3] = a - known.mean(0)
        vbar = np.array([e[2] for e in cur]).mean(0)
        H[:3, :6 * n] = (vbar[None, :, None] * self.Ha[:, None, :]).reshape(3, -1)
        H[:3, 6 * n:6 * n + 6] = self.Ha
        R[:3, :3] = np.eye(3) * self.r_acc
        m = 3
        step_ns = self.dt * 1e9
        fresh = True
        if prev is not None and abs((t_ns - prev[0]) - nn * step_ns) < 0.5 * step_ns:
            span = self._steps(t_ns - step_ns, 2 * nn - 1)
            if span is not None:
                T = nn * self.dt
                arm_m = np.array([e[1][3:] for e in span]) - gyr
                y[3:] = self.I @ (w - prev[1]) / T - self.c @ arm_m
                vt = self.c @ np.array([e[2] for e in span])
                E = np.hstack([np.zeros((3, 3)), np.eye(3)])
                H[3:, :6 * n] = (vt[None, :, None] * E[:, None, :]).reshape(3, -1)
                H[3:, 6 * n + 3:6 * n + 6] = np.eye(3)
                m = 6
                fresh = False
                if self.exact:
                    H[3:, n0:n0 + 3] = -self.B            # the previous sample's noise
                    H[3:, n0 + 3:] = self.B               # this sample's
                else:
                    R[3:, 3:] = 2.0 * self.sig_g ** 2 * self.B @ self.B.T
        if self._last_update_ns is not None:
            self.P[np.diag_indices(ns)] += self.Q_per_s * max(0.0, (t_ns - self._last_update_ns) * 1e-9)
        self._last_update_ns = t_ns
        H, y, R = H[:m], y[:m], R[:m, :m]
        PHt = self.P @ H.T
        S = H @ PHt + R
        K = np.linalg.solve(S, PHt.T).T
        self.x = self.x + K @ (y - H @ self.x)
        IKH = np.eye(ns) - K @ H                           # Joseph form: the gyro rows have R = 0
        P = IKH @ self.P @ IKH.T + K @ R @ K.T
        self.P = 0.5 * (P + P.T)
        self.updates += 1
        self._next_noise(fresh)
        return True

    def _next_noise(self, fresh: bool) -> None:
        """This sample's gyro noise becomes the previous one (``fresh``: none is known, its prior),
        and the next sample's is a new draw."""
        if not self.exact:
            return
        n0, x, P = self.n0, self.x, self.P
        if fresh:
            x[n0:n0 + 3] = 0.0
            P[n0:n0 + 3, :] = 0.0
            P[:, n0:n0 + 3] = 0.0
            P[n0:n0 + 3, n0:n0 + 3] = np.eye(3) * self.sig_g ** 2
        else:
            x[n0:n0 + 3] = x[n0 + 3:]
            P[n0:n0 + 3, :] = P[n0 + 3:, :]
            P[:, n0:n0 + 3] = P[:, n0 + 3:]
            P[n0:n0 + 3, n0:n0 + 3] = P[n0 + 3:, n0 + 3:]
        x[n0 + 3:] = 0.0
        P[n0 + 3:, :] = 0.0
        P[:, n0 + 3:] = 0.0
        P[n0 + 3:, n0 + 3:] = np.eye(3) * self.sig_g ** 2


def stream_of(path: Path):
    """The thruster filter's inputs from a recorded session, as ``bsc analyze`` reads them:
    ``(stream, core, layout)``."""
    from gateway.analysis import fdi as afdi

    ctx, rob, layout = afdi._layout_and_robot(path)
    samples, efforts, core = afdi._decode(path, ctx, rob, layout)
    return afdi.event_stream(samples, efforts, core), core, layout


def step_wrench(stream: dict, core, layout, form: str) -> tuple[np.ndarray, np.ndarray]:
    """Each step's thruster wrench (the estimate before the step's IMU update) by ``form``
    (:data:`FORMS`): ``(t_ns, wrench (N, 6))``."""
    from gateway.estimator import thruster_kernel as tk

    dt = core.period_ns * 1e-9
    imu_steps = max(1, int(core.cfg[4]) // core.period_ns)
    step = stream["kind"] != tk.IMU
    if form == "kernel":
        kf = tk.CompiledThrusterFilter(core.model, layout, dt=dt, imu_steps=imu_steps, settings=core.settings.thrusters)
        wrench, _ = kf.run(stream["kind"], stream["t_ns"], stream["arm"], stream["masks"], stream["accel"],
                           stream["rate"])
        return stream["t_ns"][step], wrench[step]
    f = ExactGyroFilter(core.model, layout, dt=dt, imu_steps=imu_steps, settings=core.settings.thrusters,
                        exact=form == "exact")
    bits = 1 << np.arange(layout.n)
    out = np.zeros((int(step.sum()), 6))
    k = 0
    for kind, t, arm, mask, acc, rate in zip(stream["kind"].tolist(), stream["t_ns"].tolist(), stream["arm"],
                                            stream["masks"].tolist(), stream["accel"], stream["rate"]):
        if kind == tk.IMU:
            f.update(t, acc, rate)
            continue
        v = ((mask & bits) != 0).astype(float)
        out[k] = v @ f.valve_wrench()
        k += 1
        if kind == tk.STEP:
            f.push_epoch(t, arm, v)
    return stream["t_ns"][step], out


def judge(path: Path) -> dict:
    """Per form, per axis: NRMSE (nan: the axis' peak is below 10 N or N m)."""
    from harness.fdi import _nrmse

    truth = np.load(path.with_suffix(".truth.npz"))["thr_act"]
    stream, core, layout = stream_of(path)
    out: dict = {}
    for form in FORMS:
        t0 = time.perf_counter()
        t, w = step_wrench(stream, core, layout, form)
        row = {}
        for c, ax in enumerate(AXES):
            one = np.zeros(6)
            one[c] = 1.0
            row[ax] = _nrmse(t, w * one, truth * one, 0)[0]
        row["wall_s"] = time.perf_counter() - t0
        out[form] = row
    return out


def _job(job) -> dict:
    from harness.fdi import FaultCase, record

    scenario, seed, folder = job
    case = FaultCase(scenario, seed, DURATION_S.get(scenario, 8.0))      # the fault benchmark's healthy sessions
    path = record(case, Path(folder) / f"{case.name}.mcap")
    try:
        return {"session": case.name, **judge(path)}
    finally:
        path.unlink(missing_ok=True)
        path.with_suffix(".truth.npz").unlink(missing_ok=True)


def run(scenarios=("capture", "three_arm"), seeds=(500, 501), workers: int = 2) -> list[dict]:
    from gateway.parallel import map_jobs

    with tempfile.TemporaryDirectory(prefix="bsc-bench-gyro-") as d:
        jobs = [(s, k, d) for s in scenarios for k in seeds]
        return list(map_jobs(_job, jobs, workers=workers))


def figures(quick: bool = False) -> list[dict]:
    """The suite's rows (``bsc bench --only gyro``): per scenario and axis, the worst session's
    NRMSE of the kernel and of the exact model (no target: a measurement for the next kernels)."""
    from benchmarks.anchors import row

    t0 = time.perf_counter()
    seeds = (500,) if quick else (500, 501)
    got = run(("capture", "three_arm"), seeds)
    wall = time.perf_counter() - t0
    rows = []
    for scenario in ("capture", "three_arm"):
        mine = [r for r in got if r["session"].startswith(scenario + "-")]
        for ax in AXES:
            k = [r["kernel"][ax] for r in mine if np.isfinite(r["kernel"][ax])]
            e = [r["exact"][ax] for r in mine if np.isfinite(r["exact"][ax])]
            if not k:
                continue
            rows.append(row(f"{scenario}: thruster {ax}, gyro noise exact (kernel: white)", round(100 * max(e), 2),
                            "% NRMSE", note=f"kernel {100 * max(k):.2f} %; worst of {len(mine)} healthy sessions "
                                            f"(seeds {', '.join(map(str, seeds))}); {wall:.0f} s"))
    return rows


def table(rows: list[dict]) -> str:
    lines = ["| session | form | " + " | ".join(AXES) + " |", "|---|---|" + "---:|" * len(AXES)]
    for r in rows:
        for form in FORMS:
            cells = " | ".join("-" if not np.isfinite(r[form][a]) else f"{100 * r[form][a]:.2f} %" for a in AXES)
            lines.append(f"| {r['session']} | {form} | {cells} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_gyro_noise", description=__doc__.splitlines()[0])
    p.add_argument("--scenario", action="append", help="capture, three_arm (default both)")
    p.add_argument("--seeds", type=lambda t: tuple(int(x) for x in t.split(",")), default=(500, 501))
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--json", metavar="FILE")
    a = p.parse_args(argv)
    rows = run(tuple(a.scenario or ("capture", "three_arm")), a.seeds, a.workers)
    print(table(rows))
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
