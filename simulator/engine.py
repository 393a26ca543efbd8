"""The simulation loop: physics at 1 kHz, flight software, thrusters, sensors, truth.

``Simulation.step()`` advances one millisecond and returns a :class:`Readings` (what the
sensors and the flight computer put on the buses during that millisecond); ``run()`` steps to
the end and returns the :class:`~simulator.truth.Trace`. The sensor firmware
(``simulator.firmware``) consumes ``Readings``.

Drive commands from outside (an inner loop closed through the buses, docs/control.md):
``Simulation(..., external_drives=True)`` and :meth:`Simulation.command_drives`; the flight
software stays the outer loop (its command is the trace's ``tau_cmd``, the desired torque) and
the drives apply what they were last given. Valve commands likewise:
``Simulation(..., external_thrusters=True)`` and :meth:`Simulation.command_valves`; the flight
software still computes its demanded wrench, allocates and modulates it (the trace's
``thr_demand`` and ``thr_cmd``, what the spacecraft bus carries as the commanded wrench), but
each valve follows the command given for that millisecond, when there is one.

How the loop is organised (for speed; the result does not depend on it):

- each step (``_advance``) runs only what the closed loop needs: the encoders and the joint
  controller on controller steps, the base controller on base steps, the physics step, and
  records the raw truth (state, acceleration, friction, the force each arm's first joint
  transmits, taken from the physics step's first ABA call instead of a separate RNEA); the
  controller outputs are kept as a list and written to the trace (held) by ``_sense``;
- the thruster chain (PWPFM valves, thrust errors, actual wrench) depends only on the
  allocation and on time, so it is computed for a whole base-control period at once;
- the sensor models and the derived truth (F/T wrenches at the sensors, encoder samples, IMU
  samples, classical base acceleration, actual torques) do not feed back, so ``_sense`` runs
  them over blocks of recorded steps: every step inside ``step()`` (which returns that
  step's readings), every ``SENSE_BLOCK`` steps inside ``run()``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

import robot_description
from robot_description import Robot

from .contact import Contacts
from .controller import Controller, Target, pregrasp_ik
from .dynamics import DivergenceError, Dynamics, Friction
from .errors import SimulatorError
from .scenario import Scenario
from .sensors import Encoders, ForceTorqueSensors, Imu, cross_rows
from .thrusters import PWPFM, Allocator, Layout, ThrusterErrors, tilted
from .truth import Trace

DT_S = 1e-3          # physics, F/T and encoder rate: 1 kHz
DT_NS = 1_000_000
# the [[degrade]] kinds of the thrusters
THRUSTER_FAULTS = ("thruster_loss", "thruster_stuck", "thruster_leak", "thruster_misalign")


class DriveCommandError(SimulatorError, ValueError):
    """A drive command the simulated robot cannot take (wrong size, not finite, drives not external)."""


class ValveCommandError(SimulatorError, ValueError):
    """A valve command the simulated robot cannot take (wrong size, not 0/1, a time off the step
    grid, valves not external)."""


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
    thruster_allowed: np.ndarray | None = None  # (n_thrusters,) bool, its keep-out mask, with it
    # commanded (the flight software's PWPFM, or the external command applied), not actual
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


SENSE_BLOCK = 1024      # steps of raw truth run through the sensor models at once by run()


class Simulation:
    def __init__(self, scenario: Scenario, robot: Robot | None = None, friction: bool = True,
                 external_drives: bool = False, command_limit: float = 1.0, external_thrusters: bool = False,
                 thrust_limit: float = 1.0):
        self.scenario = sc = scenario
        cfg = sc.cfg
        self.robot = robot or robot_description.load(sc.robot)
        r = self.robot
        self.n_steps = int(round(sc.duration_s / DT_S))
        seeds = np.random.SeedSequence(sc.seed).spawn(6)
        rng = [np.random.default_rng(s) for s in seeds]

        self.friction_enabled = friction
        self.dyn = Dynamics(r.model, friction_from(r, cfg.friction, friction), DT_S, r.joint_names)
        self.dyn.contacts = Contacts(r, sc.data.get("contact", []))     # forces on the end effectors
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

        self.ctrl = Controller(r, cfg.controller, self.target, limit_fraction=command_limit)
        self.ctrl.start(q)
        self.ctrl_every = max(1, round(1.0 / (cfg.controller.rate_hz * DT_S)))
        self.base_every = max(1, round(1.0 / (cfg.controller.base_rate_hz * DT_S)))

        self.layout = Layout.from_config(cfg.thrusters)
        # thrust_limit < 1: the flight software allocates at most that fraction of each thruster's
        # maximum, leaving an inner loop (external valve commands) thrust to correct with
        self.alloc = Allocator(self.layout, cfg.thrusters.keepout_deg, limit=thrust_limit)
        self._keepout = cfg.controller.task == "capture"
        pw = cfg.thrusters.pwpfm
        self.pwpfm = PWPFM(self.layout.n, DT_S, pw.km, pw.tau_s, pw.u_on, pw.u_off, pw.min_on_s)
        self.thr_err = ThrusterErrors(self.layout, cfg.thrusters, rng[0], DT_S)

        scale = float(cfg.noise.scale)
        self.ft = ForceTorqueSensors(cfg.noise.ft, scale, len(r.arms), rng[1])
        self.imu = Imu(cfg.noise.imu, scale, rng[3], r.R_imu, r.r_imu)
        self.imu_every = max(1, round(1.0 / (cfg.noise.imu.rate_hz * DT_S)))
        self.enc = Encoders(cfg.noise.encoder, scale, r.n_joints, rng[4])

        self._ft_map = [_SensorMap(r.model, arm) for arm in r.arms]
        self._first_joints = [(i, arm.joints[0]) for i, arm in enumerate(r.arms)]
        self._degrade = list(sc.data.get("degrade", []))
        self._check_degrade()
        self._friction_degrade = [d for d in self._degrade if d["kind"] == "friction_growth"]

        self.k = 0
        self.tau_cmd = np.zeros(r.n_joints)
        self.demand = np.zeros(6)
        self.u_cmd = np.zeros(self.layout.n)
        self.wrench_cmd = np.zeros(6)
        # controller outputs (tau_cmd, end-effector positions (3 p,)) of the calls from _ctrl_i0 on,
        # written to the trace (held until the next call) by _sense
        self._ctrl_out: list[tuple[np.ndarray, np.ndarray]] = []
        self._ctrl_i0 = 0
        self._ee = np.zeros(3 * len(r.arms))
        self.trace = Trace.allocate(self)
        self._rows = tuple(self.trace.arrays[name] for name in ("q", "v", "a", "tau_friction", "stuck"))
        # external drive commands (closed loop through the gateway): the joint drives apply the
        # latest command given to command_drives() instead of the flight software's output
        self.external_drives = external_drives
        self._drive_cmd: np.ndarray | None = None
        self._drive_use: np.ndarray | None = None        # joints that take _drive_cmd (None: all)
        self.drive_applied = np.zeros((self.n_steps, r.n_joints)) if external_drives else None
        # raw truth not kept in the trace: force transmitted by each arm's first joint (its frame)
        self._f_joint = np.zeros((self.n_steps, len(r.arms), 6))
        self._sensed = 0                      # rows [0, _sensed) have been through the sensor models
        self._wrench_chunk = np.zeros((self.base_every, 6))
        # the flight software's valve commands (PWPFM) of the base period: what the bus carries; a
        # stuck valve makes the actual valve state (the trace's ``valves``) differ from them
        self._chunk_valves = np.zeros((self.base_every, self.layout.n), dtype=bool)
        # end-effector references at every controller step, computed at once
        self._ref = self.ctrl.desired(np.arange(0, self.n_steps, self.ctrl_every) * DT_S)
        self._ref_flat = tuple(x.reshape(len(x), -1) for x in self._ref)
        self._thr_degrade = any(d["kind"] in THRUSTER_FAULTS for d in self._degrade)
        # external valve commands (thrusters compensated through the gateway): per step, the valves
        # commanded for that millisecond by command_valves(), else the flight software's
        self.external_thrusters = external_thrusters
        self.allowed = np.ones(self.layout.n, dtype=bool)    # the flight software's keep-out mask, this period
        self._valve_cmd: dict[int, np.ndarray] = {}          # step -> commanded valves (n,) bool
        self.valves_late = 0                                 # valve commands for steps already run: not applied
        if external_thrusters:
            self.valves_applied = np.zeros((self.n_steps, self.layout.n), dtype=bool)
            self.valves_external = np.zeros(self.n_steps, dtype=bool)
        else:
            self.valves_applied = self.valves_external = None

    @property
    def ee(self) -> np.ndarray:
        """End-effector positions (p, 3), inertial, at the last controller step."""
        return self._ee.reshape(-1, 3)

    @property
    def ee_des(self) -> np.ndarray:
        """Their references (p, 3) at the last controller step."""
        return self._ref[0][max(0, self.k - 1) // self.ctrl_every]

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
            if d["kind"] == "thruster_stuck" and d["state"] not in ("open", "closed", "free"):
                raise ValueError("degrade: thruster_stuck state must be 'open', 'closed' or 'free'")
            if d["kind"] == "thruster_leak" and not 0.0 <= d["factor"] <= 1.0:
                raise ValueError(f"degrade: thruster_leak factor {d['factor']:g} outside 0..1 (a fraction of the "
                                 "valve's thrust while it is closed)")
            if d["kind"] == "thruster_misalign" and not 0.0 <= d["angle_deg"] <= 90.0:
                raise ValueError(f"degrade: thruster_misalign angle_deg {d['angle_deg']:g} outside 0..90 (the tilt "
                                 "of the thruster's direction, degrees)")

    # Every degradation is a function of time: from its onset on, it sets its value at every step
    # (in list order, so a later entry for the same item wins).
    def _apply_friction_degradations(self, t: float) -> None:
        fr = self.dyn.friction
        coulomb, static = fr.coulomb_nm.copy(), fr.static_nm.copy()
        ratio = float(self.scenario.cfg.friction.static_ratio)
        changed = False
        for d in self._friction_degrade:
            if t < d["onset_s"] or not self.friction_enabled:
                continue
            j = self.robot.joint_names.index(d["joint"])
            frac0 = self._base_coulomb[j] / self.robot.effort_limit[j]
            s = min(1.0, (t - d["onset_s"]) / max(d["ramp_s"], 1e-9))
            coulomb[j] = (frac0 + s * (d["to_fraction"] - frac0)) * self.robot.effort_limit[j]
            static[j] = coulomb[j] * ratio
            changed = True
        if changed:
            self.dyn.friction = Friction(coulomb, static, fr.viscous_nms)

    def _thruster_degradations(self, t: np.ndarray) -> tuple:
        """Per-step (gain factor, stuck state, leak) arrays (len(t), m), each None when no
        degradation sets it."""
        kinds = [d for d in self._degrade if d["kind"] in THRUSTER_FAULTS]
        if not kinds:
            return None, None, None
        m = self.layout.n
        factor, stuck = np.ones((len(t), m)), np.zeros((len(t), m), dtype=int)
        leak = np.zeros((len(t), m)) if any(d["kind"] == "thruster_leak" for d in kinds) else None
        for d in kinds:
            on = t >= d["onset_s"]
            if d["kind"] == "thruster_loss":
                factor[on, d["thruster"]] = d["factor"]
            elif d["kind"] == "thruster_leak":
                leak[on, d["thruster"]] = d["factor"]                          # type: ignore[index]
            elif d["kind"] == "thruster_stuck":
                stuck[on, d["thruster"]] = {"open": 1, "closed": -1, "free": 0}[d["state"]]   # free: as commanded again
        self.thr_err.degrade, self.thr_err.stuck = factor[-1].copy(), stuck[-1].copy()
        return factor, stuck, leak

    def _misalign_wrench(self, t: np.ndarray, thrust: np.ndarray) -> np.ndarray | None:
        """What tilted thrusters add to the steps' wrench (len(t), 6), or None when none is tilted:
        from its onset, a ``thruster_misalign`` thruster's thrust along its actual direction tilted
        by ``angle_deg`` (:func:`.thrusters.tilted`) instead of along its actual direction (a later
        entry for the same thruster wins; 0 degrees ends a tilt)."""
        kinds = [d for d in self._degrade if d["kind"] == "thruster_misalign"]
        if not kinds:
            return None
        err = self.thr_err
        out = np.zeros((len(t), 6))
        col = {}
        for d in kinds:
            j = d["thruster"]
            on = t >= d["onset_s"]
            if j not in col:
                col[j] = np.zeros((len(t), 6))
            new = tilted(err.dir_actual[j], d["angle_deg"])
            pos = self.layout.pos_m[j]
            col[j][on] = np.concatenate([new, np.cross(pos, new)]) - err.B_actual[:, j]
        for j, dcol in col.items():
            out += thrust[:, j:j + 1] * dcol
        return out

    def _ft_drift(self, t: np.ndarray) -> np.ndarray | None:
        """Per-step F/T bias drift (len(t), p, 6), or None when there is none."""
        kinds = [d for d in self._degrade if d["kind"] == "ft_bias_drift"]
        if not kinds:
            return None
        arms = [a.name for a in self.robot.arms]
        drift = np.zeros((len(t), len(arms), 6))
        for d in kinds:
            on = t >= d["onset_s"]
            rate = np.concatenate([d["force_n_per_s"], d["torque_nm_per_s"]]).astype(float)
            drift[on, arms.index(d["arm"])] = (t[on] - d["onset_s"])[:, None] * rate
        return drift

    # ------------------------------------------------------------------------------------------
    def _advance(self) -> None:
        """One step of the closed loop; records the raw truth of row k (see the module docstring)."""
        k, dyn = self.k, self.dyn
        if self._friction_degrade:
            self._apply_friction_degradations(k * DT_S)
        q, v = dyn.q, dyn.v

        if k % self.ctrl_every == 0:
            # the flight computer sees the encoders and the navigation solution of the base
            qm, vm = self.enc.measured_state(q, v, k)
            i = k // self.ctrl_every
            self.tau_cmd, self._ee = self.ctrl.torques_flat(self._ref_flat[0][i], self._ref_flat[1][i], qm, vm)
            self._ctrl_out.append((self.tau_cmd, self._ee))
        j = k % self.base_every
        if j == 0:
            self._base_control(k, q, v)

        tau = self.tau_cmd
        if self.external_drives:
            if self._drive_cmd is not None:
                tau = self._drive_cmd if self._drive_use is None else np.where(self._drive_use, self._drive_cmd, tau)
            self.drive_applied[k] = tau
        wrench = self._wrench_chunk[j] if not self.external_thrusters else self._valves_step(k, j)
        try:
            a = dyn.step(wrench, tau)
        except DivergenceError as exc:
            raise exc.at((k + 1) * DT_S) from None

        Aq, Av, Aa, Atf, Ast = self._rows
        Aq[k] = q
        Av[k] = v
        Aa[k] = a
        Atf[k] = dyn.tau_friction
        Ast[k] = dyn.stuck
        f, F = dyn.data_start.f, self._f_joint[k]
        for i, joint in self._first_joints:
            F[i] = f[joint].vector
        self.k = k + 1

    def _base_control(self, k: int, q: np.ndarray, v: np.ndarray) -> None:
        """Base controller, allocation and the thruster chain of the base period from step k."""
        A, be = self.trace.arrays, self.base_every
        M = pin.XYZQUATToSE3(q[:7])
        self.demand = self.ctrl.base_wrench(k * DT_S, q, v, M)
        if self._keepout:
            allowed = self.alloc.allowed(M.rotation, M.translation, self.target.center, self.target.radius)
        else:                                          # a checkout: no target to keep plumes off
            allowed = self.allowed
        self.u_cmd = self.alloc.allocate(self.demand, allowed)
        self.wrench_cmd = self.alloc.B.dot(self.u_cmd)
        self.allowed = allowed
        # the thruster chain until the next allocation depends on nothing else (unless the valves
        # take external commands: then _valves_step runs it step by step)
        commanded = self.pwpfm.run(self.u_cmd / self.layout.max_n, be)
        hold = slice(k, k + be)
        n = len(A["valves"][hold])
        A["thr_demand"][hold] = self.demand
        A["thr_cmd"][hold] = self.wrench_cmd
        self._chunk_valves = commanded
        if self.external_thrusters:
            return
        factor = stuck = leak = None
        if self._thr_degrade:
            factor, stuck, leak = self._thruster_degradations(np.arange(k, k + be) * DT_S)
        valves, thrust = self.thr_err.run(commanded, factor, stuck, leak)
        self._wrench_chunk = thrust.dot(self.thr_err.B_actual.T)
        if self._thr_degrade and (tilt := self._misalign_wrench(np.arange(k, k + be) * DT_S, thrust)) is not None:
            self._wrench_chunk += tilt
        A["valves"][hold] = valves[:n]
        A["thrust"][hold] = thrust[:n]
        A["thr_act"][hold] = self._wrench_chunk[:n]

    def _valves_step(self, k: int, j: int) -> np.ndarray:
        """External valves: the thruster chain of step k alone (its commanded valves: the external
        command for this millisecond, else the flight software's); returns the actual wrench."""
        ext = self._valve_cmd.pop(k, None)
        commanded = self._chunk_valves[j] if ext is None else ext
        self.valves_applied[k] = commanded
        self.valves_external[k] = ext is not None
        factor = stuck = leak = None
        if self._thr_degrade:
            factor, stuck, leak = self._thruster_degradations(np.array([k * DT_S]))
        valves, thrust = self.thr_err.run(commanded[None, :], factor, stuck, leak)
        wrench = thrust[0].dot(self.thr_err.B_actual.T)
        if self._thr_degrade and (tilt := self._misalign_wrench(np.array([k * DT_S]), thrust)) is not None:
            wrench = wrench + tilt[0]
        A = self.trace.arrays
        A["valves"][k], A["thrust"][k], A["thr_act"][k] = valves[0], thrust[0], wrench
        return wrench

    def _sense(self, k1: int) -> tuple[np.ndarray, np.ndarray]:
        """Sensor models and derived truth for the recorded rows [_sensed, k1).

        Returns the F/T saturation flags of those rows (K, p) and those of the IMU samples
        completed in them (M,).
        """
        k0, A, tr = self._sensed, self.trace.arrays, self.trace
        q, v, a = A["q"][k0:k1], A["v"][k0:k1], A["a"][k0:k1]
        t = np.arange(k0, k1) * DT_S
        # controller outputs, held from each controller step to the next
        ce, i0, out = self.ctrl_every, self._ctrl_i0, self._ctrl_out
        if k1 - k0 <= 2 * ce:                       # a few rows (step()): one by one
            for r in range(k0, k1):
                A["tau_cmd"][r], ee = out[r // ce - i0]
                A["ee"][r] = ee.reshape(-1, 3)
                A["ee_des"][r] = self._ref[0][r // ce]
        else:
            i = np.arange(k0, k1) // ce
            tau_cmd, ee = (np.array(x) for x in zip(*out))
            A["tau_cmd"][k0:k1] = tau_cmd[i - i0]
            A["ee"][k0:k1] = ee[i - i0].reshape(k1 - k0, -1, 3)
            A["ee_des"][k0:k1] = self._ref[0][i]
        keep = k1 // ce                             # the first call still needed (rows from k1 on)
        del out[:keep - i0]
        self._ctrl_i0 = keep
        A["t_s"][k0:k1] = t
        applied = A["tau_cmd"] if self.drive_applied is None else self.drive_applied
        np.add(applied[k0:k1], A["tau_friction"][k0:k1], out=A["tau_act"][k0:k1])
        # classical acceleration of C, body frame: a_lin + w x v_lin
        A["base_acc"][k0:k1, :3] = a[:, :3] + cross_rows(v[:, 3:6], v[:, :3])
        A["base_acc"][k0:k1, 3:] = a[:, 3:6]
        A["enc_angle"][k0:k1], A["enc_rate"][k0:k1] = self.enc.read_block(q[:, 7:], v[:, 6:], k0)
        ft_true = A["ft_true"][k0:k1]
        for i, fm in enumerate(self._ft_map):
            ft_true[:, i] = fm.sensor_wrench(q, self._f_joint[k0:k1, i])
        A["ft_meas"][k0:k1], ft_sat = self.ft.read_block(ft_true, k0, self._ft_drift(t))

        # IMU samples whose averaging interval ends in [k0, k1)
        e, s0 = self.imu_every, tr.n_imu
        s1 = k1 // e
        imu_sat = np.zeros(0, dtype=bool)
        if s1 > s0:
            rows = slice(s0 * e, s1 * e)
            shape = (s1 - s0, e, 3)
            a_c = A["base_acc"][rows, :3].reshape(shape)
            w = A["v"][rows, 3:6].reshape(shape)
            dw = A["a"][rows, 3:6].reshape(shape)
            ends = np.arange(s0 + 1, s1 + 1) * e                # the step after each interval
            quat = np.empty((s1 - s0, 4))
            done = ends < self.k
            quat[done] = A["q"][ends[done], 3:7]
            quat[~done] = self.dyn.q[3:7]                       # the state after the last step
            out = self.imu.read_block(a_c, w, dw, _quat_xyzw_to_rotation(quat), s0)
            A["imu_t_s"][s0:s1] = ends * DT_S
            for name, x in zip(("imu_quat", "imu_rate", "imu_acc", "imu_rate_true", "imu_acc_true"), out):
                A[name][s0:s1] = x
            imu_sat = out[5]
            tr.n_imu = s1
        tr.n = self._sensed = k1
        return ft_sat, imu_sat

    def command_drives(self, tau_nm, use=None) -> None:
        """The joint drives' command from now on, (n,) N m in v order, held until the next one
        (``external_drives=True`` only). The flight software still computes its own command
        (``tau_cmd`` in the trace, what the arm bus carries: the desired torque); the drives
        apply this one instead, saturated at the joints' torque limits as a drive would. ``use``
        (n,) bool: only those joints take it, the others the flight software's command of each
        step (a drive whose external command is late). Until the first call they all apply the
        flight software's command. The trace's ``tau_act`` is the applied command plus friction;
        :attr:`drive_applied` holds the applied command per step."""
        if not self.external_drives:
            raise DriveCommandError("command_drives: this simulation's drives take the flight software's "
                                 "commands (create it with external_drives=True)")
        tau = np.asarray(tau_nm, dtype=float)
        if tau.shape != (self.robot.n_joints,) or not np.all(np.isfinite(tau)):
            raise DriveCommandError(f"command_drives: expected {self.robot.n_joints} finite torques, N m, "
                                 f"got shape {tau.shape}")
        if use is not None:
            use = np.asarray(use, dtype=bool)
            if use.shape != tau.shape:
                raise DriveCommandError(f"command_drives: use must be {self.robot.n_joints} booleans")
        self._drive_cmd = np.clip(tau, -self.robot.effort_limit, self.robot.effort_limit)
        self._drive_use = use

    def command_valves(self, valves, t_ns: int) -> None:
        """The valves' commands for the steps from sensor time ``t_ns`` on (``external_thrusters=True``
        only): ``valves`` (n,) or (L, n) of 0/1 (bool), one row per millisecond, thruster order of the
        layout; each row replaces what an earlier call gave for its step. A row for a step already
        run is not applied (counted in :attr:`valves_late`): a valve command is good for its own
        millisecond only. A step without a command gets the flight software's (PWPFM) valves.
        The flight software still demands, allocates and modulates (``thr_demand``, ``thr_cmd``,
        the commanded wrench on the spacecraft bus); the trace's ``valves``, ``thrust`` and
        ``thr_act`` are what the commanded valves really did (a stuck valve stays stuck), and
        :attr:`valves_applied` / :attr:`valves_external` keep per step the commanded valves and
        whether they were the external ones; :attr:`allowed` is the flight software's keep-out
        mask of the current base period (thrusters whose plume would reach the target: False)."""
        if not self.external_thrusters:
            raise ValveCommandError("command_valves: this simulation's valves take the flight software's "
                                    "commands (create it with external_thrusters=True)")
        v = np.asarray(valves)
        m = self.layout.n
        rows = v[None, :] if v.ndim == 1 else v
        if rows.ndim != 2 or rows.shape[1] != m or rows.shape[0] < 1:
            raise ValveCommandError(f"command_valves: expected {m} valve states per step, (n,) or (L, n), "
                                    f"got shape {v.shape}")
        if rows.dtype != bool:
            if not (np.issubdtype(rows.dtype, np.number) and np.all(np.isin(rows, (0, 1)))):
                raise ValveCommandError("command_valves: valve states must be 0 or 1 (closed, open)")
            rows = rows.astype(bool)
        if isinstance(t_ns, bool) or not isinstance(t_ns, (int, np.integer)) or t_ns < 0 or t_ns % DT_NS:
            raise ValveCommandError(f"command_valves: t_ns must be a step time, a multiple of {DT_NS} ns >= 0, "
                                    f"got {t_ns!r}")
        k0 = int(t_ns) // DT_NS
        for i, row in enumerate(rows):
            if k0 + i < self.k:
                self.valves_late += 1
            elif k0 + i < self.n_steps:
                self._valve_cmd[k0 + i] = row.copy()

    # ------------------------------------------------------------------------------------------
    def step(self) -> Readings:
        """Advance one millisecond; the readings are those sampled at the start of the step."""
        k = self.k
        self._advance()
        ft_sat, imu_sat = self._sense(k + 1)
        A = self.trace.arrays
        imu = None
        if (k + 1) % self.imu_every == 0:         # output at the end of its averaging interval
            s = self.trace.n_imu - 1
            imu = (A["imu_quat"][s].copy(), A["imu_rate"][s].copy(), A["imu_acc"][s].copy(), bool(imu_sat[-1]))
        return Readings(t_ns=k * DT_NS, ft=A["ft_meas"][k].copy(), ft_saturated=ft_sat[-1],
                        joint_angle=A["enc_angle"][k].copy(), joint_rate=A["enc_rate"][k].copy(), imu=imu,
                        torque_cmd=self.tau_cmd if k % self.ctrl_every == 0 else None,
                        thruster_cmd=self.wrench_cmd if k % self.base_every == 0 else None,
                        thruster_allowed=self.allowed.copy() if k % self.base_every == 0 else None,
                        valves=(self._chunk_valves[k % self.base_every] if self.valves_applied is None
                                else self.valves_applied[k]).copy())

    def run(self, progress: bool = False) -> Trace:
        from .progress import SimProgress

        advance = self._advance
        with SimProgress(self.scenario.name, self.n_steps, DT_S, enabled=progress) as bar:
            while self.k < self.n_steps:
                advance()
                if self.k - self._sensed >= SENSE_BLOCK:
                    self._sense(self.k)
                bar.update(self.k)
        if self._sensed < self.k:
            self._sense(self.k)
        return self.trace


class _SensorMap:
    """Force transmitted by an arm's first joint (its local frame) -> wrench at the F/T sensor.

    ``f_S = X (R_joint(q) f)``, X the constant placement of the joint's zero-angle frame in the
    sensor frame: the same as ``sensor.actInv(liMi.act(f))`` in Pinocchio, for many steps at once.
    """

    def __init__(self, model: pin.Model, arm):
        self.model, self.joint = model, arm.joints[0]
        X = model.frames[arm.sensor_frame].placement.actInv(model.jointPlacements[self.joint])
        self.R, self.p = X.rotation.copy(), X.translation.copy()
        self.iq = model.joints[self.joint].idx_q
        jm = model.joints[self.joint]
        axes = {"JointModelRX": (1.0, 0.0, 0.0), "JointModelRY": (0.0, 1.0, 0.0), "JointModelRZ": (0.0, 0.0, 1.0)}
        name = jm.shortname()
        if name in axes:
            self.axis = np.array(axes[name])
        elif name == "JointModelRevoluteUnaligned":
            self.axis = np.array(jm.extract().axis, dtype=float)
        else:                                   # anything else: Pinocchio, one step at a time
            self.axis = None
            self._data = model.createData()
            self._M = model.frames[arm.sensor_frame].placement

    def sensor_wrench(self, q: np.ndarray, f: np.ndarray) -> np.ndarray:
        """(K, 6) [force; moment about S] in the sensor frame for configurations (K, nq) and
        joint forces (K, 6) [linear; angular]."""
        if self.axis is None:
            out = np.empty_like(f)
            for i in range(len(f)):
                pin.forwardKinematics(self.model, self._data, q[i])
                out[i] = self._M.actInv(self._data.liMi[self.joint].act(pin.Force(f[i]))).vector
            return out
        th = q[:, self.iq]
        c, s = np.cos(th), np.sin(th)
        x, y, z = self.axis
        K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
        Rj = (c[:, None, None] * np.eye(3) + s[:, None, None] * K
              + (1.0 - c)[:, None, None] * np.outer(self.axis, self.axis))
        aligned = np.flatnonzero(np.abs(self.axis) == 1.0)
        if aligned.size:
            Rj[:, aligned[0], aligned[0]] = 1.0       # exact, as for Pinocchio's RX/RY/RZ joints
        G = self.R @ Rj
        lin = (G @ f[:, :3, None])[..., 0]
        ang = (G @ f[:, 3:, None])[..., 0] + cross_rows(np.broadcast_to(self.p, lin.shape), lin)
        return np.concatenate([lin, ang], axis=1)


def _quat_xyzw_to_rotation(quat: np.ndarray) -> np.ndarray:
    """(M, 3, 3) rotation matrices of quaternions (M, 4) [x y z w] (Pinocchio's q layout),
    with Eigen's formula (what ``pin.XYZQUATToSE3`` uses)."""
    x, y, z, w = quat[:, 0], quat[:, 1], quat[:, 2], quat[:, 3]
    tx, ty, tz = 2.0 * x, 2.0 * y, 2.0 * z
    twx, twy, twz = tx * w, ty * w, tz * w
    txx, txy, txz = tx * x, ty * x, tz * x
    tyy, tyz, tzz = ty * y, tz * y, tz * z
    R = np.empty((len(quat), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 0, 2] = 1.0 - (tyy + tzz), txy - twz, txz + twy
    R[:, 1, 0], R[:, 1, 1], R[:, 1, 2] = txy + twz, 1.0 - (txx + tzz), tyz - twx
    R[:, 2, 0], R[:, 2, 1], R[:, 2, 2] = txz - twy, tyz + twx, 1.0 - (txx + tyy)
    return R
