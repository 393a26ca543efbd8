"""The simulation loop: physics at 1 kHz, flight software, thrusters, sensors, truth.

``Simulation.step()`` advances one millisecond and returns a :class:`Readings` (what the
sensors and the flight computer put on the buses during that millisecond); ``run()`` steps to
the end and returns the :class:`~simulator.truth.Trace`. The sensor firmware
(``simulator.firmware``) consumes ``Readings``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

import robot_description
from robot_description import Robot

from .controller import Controller, Target, pregrasp_ik
from .dynamics import Dynamics, Friction
from .scenario import Scenario
from .sensors import Encoders, ForceTorqueSensors, Imu, cross3
from .thrusters import PWPFM, Allocator, Layout, ThrusterErrors
from .truth import Trace

DT_S = 1e-3          # physics, F/T and encoder rate: 1 kHz
DT_NS = 1_000_000


@dataclass
class Readings:
    """What the devices report during one step, ``None`` where a device does not sample."""

    t_ns: int
    ft: np.ndarray                         # (p, 6) per arm [f; t], sensor frames
    ft_saturated: np.ndarray               # (p,) bool
    joint_angle: np.ndarray                # (n,) rad, v order
    joint_rate: np.ndarray                 # (n,) rad/s
    imu: tuple | None = None               # (quat_wxyz, rate, accel, saturated) at the IMU rate
    torque_cmd: np.ndarray | None = None   # (n,) N m, at the controller rate
    thruster_cmd: np.ndarray | None = None  # (6,) body wrench about C, at the base rate
    valves: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))


def friction_from(robot: Robot, cfg, enabled: bool = True) -> Friction:
    n = robot.n_joints
    if not enabled:
        return Friction.none(n)
    frac = np.full(n, float(cfg.coulomb_fraction))
    per = getattr(cfg, "per_joint", None)
    if per:
        names = robot.joint_names
        for name, value in vars(per).items():
            if name not in names:
                raise ValueError(f"friction.per_joint: no joint {name!r} (joints: {', '.join(names)})")
            frac[names.index(name)] = float(value)
    coulomb = frac * robot.effort_limit
    return Friction(coulomb, coulomb * float(cfg.static_ratio), np.full(n, float(cfg.viscous_nms_rad)))


class Simulation:
    def __init__(self, scenario: Scenario, robot: Robot | None = None, friction: bool = True):
        self.scenario = sc = scenario
        cfg = sc.cfg
        self.robot = robot or robot_description.load(sc.robot)
        r = self.robot
        self.n_steps = int(round(sc.duration_s / DT_S))
        seeds = np.random.SeedSequence(sc.seed).spawn(6)
        rng = [np.random.default_rng(s) for s in seeds]

        self.friction_enabled = friction
        self.dyn = Dynamics(r.model, friction_from(r, cfg.friction, friction), DT_S)
        self._base_coulomb = self.dyn.friction.coulomb_nm.copy()
        q = r.neutral()
        init = cfg.controller.initial_q_deg
        for k, arm in enumerate(r.arms):
            angles = init[k] if k < len(init) else init[-1]
            q[list(arm.iq)] = np.radians(np.resize(np.array(angles, dtype=float), arm.n))
        self.target = Target(cfg.target, len(r.arms))
        g, _ = self.target.grasp_points(0.0)
        outward = g - self.target.center
        outward /= np.linalg.norm(outward, axis=1, keepdims=True)
        q = pregrasp_ik(r, q, g + cfg.controller.standoff_m * outward)
        self.dyn.q = q

        self.ctrl = Controller(r, cfg.controller, self.target)
        self.ctrl.start(q)
        self.ctrl_every = max(1, round(1.0 / (cfg.controller.rate_hz * DT_S)))
        self.base_every = max(1, round(1.0 / (cfg.controller.base_rate_hz * DT_S)))

        self.layout = Layout.from_config(cfg.thrusters)
        self.alloc = Allocator(self.layout, cfg.thrusters.keepout_deg)
        pw = cfg.thrusters.pwpfm
        self.pwpfm = PWPFM(self.layout.n, DT_S, pw.km, pw.tau_s, pw.u_on, pw.u_off, pw.min_on_s)
        self.thr_err = ThrusterErrors(self.layout, cfg.thrusters, rng[0], DT_S)

        scale = float(cfg.noise.scale)
        self.ft = ForceTorqueSensors(cfg.noise.ft, scale, len(r.arms), rng[1])
        self.imu = Imu(cfg.noise.imu, scale, rng[3], r.R_imu, r.r_imu)
        self.imu_every = max(1, round(1.0 / (cfg.noise.imu.rate_hz * DT_S)))
        self.enc = Encoders(cfg.noise.encoder, scale, r.n_joints, rng[4])

        # sensor frame <- first joint frame, for the F/T truth from RNEA's joint forces
        self._sensor_M = [r.model.frames[a.sensor_frame].placement for a in r.arms]
        self._rdata = r.model.createData()
        self._degrade = list(sc.data.get("degrade", []))
        self._check_degrade()

        self.k = 0
        self.tau_cmd = np.zeros(r.n_joints)
        self.demand = np.zeros(6)
        self.u_cmd = np.zeros(self.layout.n)
        self.wrench_cmd = np.zeros(6)
        self.ee = self.ee_des = np.zeros((len(r.arms), 3))   # end effector and its reference, inertial
        self.trace = Trace.allocate(self)

    # ------------------------------------------------------------------------------------------
    def _check_degrade(self) -> None:
        names = self.robot.joint_names
        arms = [a.name for a in self.robot.arms]
        for d in self._degrade:
            if d["kind"] == "friction_growth" and d["joint"] not in names:
                raise ValueError(f"degrade: no joint {d['joint']!r} (joints: {', '.join(names)})")
            if d["kind"].startswith("thruster") and not 0 <= d["thruster"] < self.layout.n:
                raise ValueError(f"degrade: thruster index {d['thruster']} outside 0..{self.layout.n - 1}")
            if d["kind"] == "ft_bias_drift" and d["arm"] not in arms:
                raise ValueError(f"degrade: no arm {d['arm']!r} (arms: {', '.join(arms)})")
            if d["kind"] == "thruster_stuck" and d["state"] not in ("open", "closed"):
                raise ValueError("degrade: thruster_stuck state must be 'open' or 'closed'")

    def _apply_degradations(self, t: float) -> None:
        fr = self.dyn.friction
        ratio = float(self.scenario.cfg.friction.static_ratio)
        for d in self._degrade:
            if t < d["onset_s"]:
                continue
            kind = d["kind"]
            if kind == "friction_growth" and self.friction_enabled:
                j = self.robot.joint_names.index(d["joint"])
                frac0 = self._base_coulomb[j] / self.robot.effort_limit[j]
                s = min(1.0, (t - d["onset_s"]) / max(d["ramp_s"], 1e-9))
                fr.coulomb_nm[j] = (frac0 + s * (d["to_fraction"] - frac0)) * self.robot.effort_limit[j]
                fr.static_nm[j] = fr.coulomb_nm[j] * ratio
            elif kind == "thruster_loss":
                self.thr_err.degrade[d["thruster"]] = d["factor"]
            elif kind == "thruster_stuck":
                self.thr_err.stuck[d["thruster"]] = 1 if d["state"] == "open" else -1
            elif kind == "ft_bias_drift":
                k = [a.name for a in self.robot.arms].index(d["arm"])
                dt = t - d["onset_s"]
                self.ft.drift[k] = dt * np.concatenate([d["force_n_per_s"], d["torque_nm_per_s"]]).astype(float)

    # ------------------------------------------------------------------------------------------
    def step(self) -> Readings:
        """Advance one millisecond; the readings are those sampled at the start of the step."""
        k, r, dyn = self.k, self.robot, self.dyn
        t = k * DT_S
        if self._degrade:
            self._apply_degradations(t)
        q, v = dyn.q, dyn.v
        jq, jv = q[7:], v[6:]
        angle, rate = self.enc.read(jq, jv)

        torque_cmd = thruster_cmd = None
        if k % self.ctrl_every == 0:
            # the flight computer sees the encoders and the navigation solution of the base
            qm = q.copy()
            qm[7:] = angle
            vm = v.copy()
            vm[6:] = rate
            self.tau_cmd, self.ee, self.ee_des = self.ctrl.joint_torques(t, qm, vm)
            torque_cmd = self.tau_cmd
        if k % self.base_every == 0:
            M = pin.XYZQUATToSE3(q[:7])
            self.demand = self.ctrl.base_wrench(q, v)
            allowed = self.alloc.allowed(M.rotation, M.translation, self.target.center, self.target.radius)
            self.u_cmd = self.alloc.allocate(self.demand, allowed)
            self.wrench_cmd = self.alloc.B @ self.u_cmd
            thruster_cmd = self.wrench_cmd
        valves = self.thr_err.valves(self.pwpfm.step(self.u_cmd / self.layout.max_n))
        thrust = self.thr_err.thrust(valves)
        wrench_act = self.thr_err.B_actual @ thrust

        a = dyn.step(wrench_act, self.tau_cmd)

        # truth at the start of the step: transmitted wrenches from RNEA with the actual motion
        data = self._rdata
        pin.rnea(r.model, data, q, v, a)
        ft_true = np.empty((len(r.arms), 6))
        for i, arm in enumerate(r.arms):
            f = self._sensor_M[i].actInv(data.liMi[arm.joints[0]].act(data.f[arm.joints[0]]))
            ft_true[i, :3] = f.linear
            ft_true[i, 3:] = f.angular
        ft_meas, ft_sat = self.ft.read(ft_true)

        w, dw = v[3:6], a[3:6]
        a_c = a[:3] + cross3(w, v[:3])          # classical acceleration of C, body frame
        self.imu.accumulate(a_c, w, dw)
        imu = None
        if (k + 1) % self.imu_every == 0:         # output at the end of its averaging interval
            quat, g, acc, g_true, acc_true, sat = self.imu.read(pin.XYZQUATToSE3(dyn.q[:7]).rotation)
            imu = (quat, g, acc, sat)
            self.trace.record_imu(self, quat, g, acc, g_true, acc_true)

        self.trace.record(self, q, v, a, a_c, ft_true, ft_meas, angle, rate, valves, thrust, wrench_act)
        self.k += 1
        return Readings(t_ns=k * DT_NS, ft=ft_meas, ft_saturated=ft_sat, joint_angle=angle,
                        joint_rate=rate, imu=imu, torque_cmd=torque_cmd, thruster_cmd=thruster_cmd,
                        valves=valves)

    def run(self, progress: bool = False) -> Trace:
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(total=self.n_steps, unit="ms", unit_scale=True, desc=f"sim {self.scenario.name}",
                       mininterval=0.5, leave=False)
        while self.k < self.n_steps:
            self.step()
            if bar is not None and self.k % 250 == 0:
                bar.update(250)
        if bar is not None:
            bar.close()
        return self.trace
