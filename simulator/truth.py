"""The truth trace: everything that really happened, every millisecond, to judge estimates by.

Saved as one ``.npz`` (numpy arrays, no pickled objects) with a JSON ``meta`` string; the
arrays and their units and frames are listed in ``FIELDS`` (and docs/truth-trace.md).
``N`` = steps, ``p`` = arms, ``n`` = actuated joints, ``m`` = thrusters, ``M`` = IMU samples.

The simulation writes the arrays in place (``simulator.engine``); ``n`` and ``n_imu`` count the
complete rows, and indexing a trace by name returns only those.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FIELDS = {
    "t_s": "(N,) time of the step start, s",
    "q": "(N, nq) configuration: base [x y z qx qy qz qw] (inertial), joint angles rad",
    "v": "(N, nv) base twist (body frame: linear of C, angular) and joint rates",
    "a": "(N, nv) Pinocchio acceleration (base: spatial, body frame) and joint accelerations",
    "base_acc": "(N, 6) classical acceleration of C and angular acceleration, body frame",
    "tau_cmd": "(N, n) commanded motor torque, N m",
    "tau_friction": "(N, n) joint friction torque acting on the joint (opposes motion), N m",
    "tau_act": "(N, n) actual joint torque = motor torque + friction torque, N m",
    "stuck": "(N, n) joint held by static friction during the step",
    "thr_demand": "(N, 6) wrench the base controller demanded, body frame about C, N / N m",
    "thr_cmd": "(N, 6) commanded thruster wrench = allocation B u, body frame about C",
    "thr_act": "(N, 6) actual thruster wrench (PWPFM valves, thrust errors), body frame about C",
    "valves": "(N, m) valve open during the step",
    "thrust": "(N, m) actual thrust of each thruster, N",
    "ft_true": "(N, p, 6) true wrench spacecraft -> arm at the sensor origin, sensor frame",
    "ft_meas": "(N, p, 6) F/T reading (noise, bias, quantization, clamp)",
    "enc_angle": "(N, n) encoder angle, rad",
    "enc_rate": "(N, n) drive rate estimate, rad/s",
    "ee": "(N, p, 3) end-effector position, inertial, m (at the controller rate, held)",
    "ee_des": "(N, p, 3) desired end-effector position, inertial, m",
    "imu_t_s": "(M,) time at the end of each IMU averaging interval, s",
    "imu_quat": "(M, 4) attitude IMU -> inertial, wxyz",
    "imu_rate": "(M, 3) gyro output, IMU frame, rad/s",
    "imu_acc": "(M, 3) accelerometer output (specific force), IMU frame, m/s^2",
    "imu_rate_true": "(M, 3) true mean angular rate over the interval, IMU frame",
    "imu_acc_true": "(M, 3) true mean specific force over the interval, IMU frame",
}


@dataclass
class Trace:
    arrays: dict[str, np.ndarray]
    meta: dict
    n: int = 0                      # steps recorded
    n_imu: int = 0

    @classmethod
    def allocate(cls, sim) -> "Trace":
        r, N = sim.robot, sim.n_steps
        p, nj, m = len(r.arms), r.n_joints, sim.layout.n
        M = N // sim.imu_every + 1
        shapes = {
            "t_s": (N,), "q": (N, r.nq), "v": (N, r.nv), "a": (N, r.nv), "base_acc": (N, 6),
            "tau_cmd": (N, nj), "tau_friction": (N, nj), "tau_act": (N, nj), "stuck": (N, nj),
            "thr_demand": (N, 6), "thr_cmd": (N, 6), "thr_act": (N, 6), "valves": (N, m),
            "thrust": (N, m), "ft_true": (N, p, 6), "ft_meas": (N, p, 6), "enc_angle": (N, nj),
            "enc_rate": (N, nj), "ee": (N, p, 3), "ee_des": (N, p, 3),
            "imu_t_s": (M,), "imu_quat": (M, 4), "imu_rate": (M, 3), "imu_acc": (M, 3),
            "imu_rate_true": (M, 3), "imu_acc_true": (M, 3),
        }
        bools = {"stuck", "valves"}
        arrays = {k: np.zeros(s, dtype=bool if k in bools else float) for k, s in shapes.items()}
        meta = {
            "scenario": sim.scenario.name, "scenario_toml": sim.scenario.text, "seed": sim.scenario.seed,
            "robot": r.name, "urdf": r.urdf, "arms": [a.name for a in r.arms],
            "joints": r.joint_names, "dt_s": 1e-3, "friction": sim.friction_enabled,
            "imu_rate_hz": sim.scenario.cfg.noise.imu.rate_hz,
            "thruster_pos_m": sim.layout.pos_m.tolist(), "thruster_dir": sim.layout.dir.tolist(),
            "thruster_max_n": sim.layout.max_n.tolist(), "fields": FIELDS,
        }
        if sim.scenario.cfg.controller.task == "capture":      # a checkout has no target near
            meta.update(target_center_m=sim.target.center.tolist(), target_radius_m=sim.target.radius)
        return cls(arrays, meta)

    def __getitem__(self, name: str) -> np.ndarray:
        a = self.arrays[name]
        return a[: self.n_imu] if name.startswith("imu_") else a[: self.n]

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        out = {k: self[k] for k in self.arrays}
        np.savez_compressed(path, meta=np.array(json.dumps(self.meta)), **out)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "Trace":
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            arrays = {k: z[k] for k in z.files if k != "meta"}
        return cls(arrays, meta, n=len(arrays["t_s"]), n_imu=len(arrays["imu_t_s"]))
