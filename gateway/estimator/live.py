"""The live estimator: typed samples in (any order across buses), efforts out, with a sync policy.

Synchronisation policy (docs/estimator.md, "Live"):

- An *epoch* is one F/T sampling instant (1 kHz). Its required members are the F/T sample of
  every arm, the joint state of every joint and the valve command, each matched to the epoch
  by timestamp within half an F/T period (no interpolation: every device samples at the epoch).
- An epoch is computed as soon as it is complete. When a later epoch completes first, the
  earlier one is computed with what it has (its missing inputs were lost: each bus is FIFO) and
  flagged; so is the oldest epoch when more than ``max_open`` are waiting (a silent bus).
- Slower streams are applied to the first epoch that is at least half a period later than
  their timestamp: IMU samples (they update the thruster filter and the base rate), torque and
  thruster commands (the "commanded" fields). Their maximum age: ``stale_periods`` of their own
  period; older means ``stale:<device>``.
- A missing joint state holds the previous one (``stale:<arm>/<joint>``, that arm's efforts not
  good); a missing F/T sample or valve command makes all the epoch's efforts not good
  (``missing:<device>``: the base motion needs every arm's reaction). Saturated or
  faulty inputs flag ``saturated:<device>`` / ``fault:<device>``; until the first IMU sample the
  estimates are ``warmup``. ``good`` = no flag.

The result depends only on the samples and their timestamps, never on how the buses' frames
interleave, when nothing is missing: replaying the same frames gives byte-identical efforts.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from drivers import wire
from drivers.samples import ImuSample, JointSample, ThrusterCommand, TorqueCommand, ValveCommand, WrenchSample
from gateway.efforts import JointEfforts, ThrusterEffort
from robot_description import Robot
from robot_description.thrusters import ThrusterLayout

from .model import EstimatorModel, cross
from .thrusters import ThrusterFilter, ThrusterFilterSettings
from .torques import joint_accelerations_from_ft, joint_torques, joint_torques_simplified
from .wrench import arm_reaction


@dataclass(frozen=True)
class LiveSettings:
    max_open: int = 20                 # epochs waiting for members before the oldest is forced out
    stale_periods: int = 3             # a slower stream older than this many of its periods is stale
    thrusters: ThrusterFilterSettings = field(default_factory=ThrusterFilterSettings)


@dataclass
class _Epoch:
    t_ns: int
    ft: dict = field(default_factory=dict)          # arm -> WrenchSample
    joints: dict = field(default_factory=dict)      # "<arm>/<joint>" -> JointSample
    valves: ValveCommand | None = None


Output = Callable[[object], None]


class LiveEstimator:
    """Feed it samples with :meth:`add`; it calls ``out(effort)`` for every computed epoch
    (one :class:`JointEfforts` per arm, then one :class:`ThrusterEffort`)."""

    def __init__(self, robot: Robot, out: Output, *, layout: ThrusterLayout | None = None,
                 settings: LiveSettings | None = None):
        self.settings = s = settings or LiveSettings()
        self.model = EstimatorModel.from_robot(robot)
        self.data = self.model.data()
        self.layout = layout or ThrusterLayout.named()
        self.out = out
        arm_lay, sc_lay = wire.layouts("arm"), wire.layouts("spacecraft")
        self.period_ns = arm_lay[wire.FT_A_ID].cycle_ms * 1_000_000
        self.half = self.period_ns // 2
        self.imu_period_ns = sc_lay[wire.IMU_TIME_ID].cycle_ms * 1_000_000
        self.cmd_period_ns = {"torque": arm_lay[wire.TORQUE_CMD_BASE].cycle_ms * 1_000_000,
                              "thrusters": sc_lay[wire.THRUSTER_FORCE_ID].cycle_ms * 1_000_000}
        self.kf = ThrusterFilter(self.model, self.layout, dt=self.period_ns * 1e-9,
                                 imu_steps=max(1, self.imu_period_ns // self.period_ns), settings=s.thrusters)
        self.arms = [a.name for a in self.model.arms]
        self.arm_joints = {a.name: [f"{a.name}/{n}" for n in a.joint_names] for a in robot.arms}
        self.joint_names = [j for a in self.arms for j in self.arm_joints[a]]
        self._shifts = np.arange(self.layout.n)
        self._open: list[_Epoch] = []
        self._last_closed = -(1 << 62)
        self._pending: list = []                 # slower-stream samples, in arrival order
        self._q = np.zeros(len(self.joint_names))
        self._dq = np.zeros(len(self.joint_names))
        self._have_joint = np.zeros(len(self.joint_names), dtype=bool)
        self._cmd: dict[str, tuple[float, int]] = {}
        self._thr_cmd: ThrusterCommand | None = None
        self._gyro_t: int | None = None
        self._faults: set[str] = set()
        self.epochs = 0
        self.good = 0
        self.late = 0

    # -- input -------------------------------------------------------------------------------
    def add(self, sample) -> None:
        if isinstance(sample, WrenchSample):
            self._member(sample.t_ns).ft[sample.device] = sample
        elif isinstance(sample, JointSample):
            self._member(sample.t_ns).joints[sample.device] = sample
        elif isinstance(sample, ValveCommand):
            self._member(sample.t_ns).valves = sample
        elif isinstance(sample, (ImuSample, TorqueCommand, ThrusterCommand)):
            self._pending.append(sample)
            return
        else:
            return
        self._advance()

    def _member(self, t: int) -> _Epoch:
        for e in self._open:
            if abs(e.t_ns - t) < self.half:
                return e
        if t <= self._last_closed + self.half:
            self.late += 1
            return _Epoch(t)                       # a throw-away epoch: too late to be used
        e = _Epoch(t)
        self._open.append(e)
        self._open.sort(key=lambda x: x.t_ns)
        return e

    def _complete(self, e: _Epoch) -> bool:
        return (e.valves is not None and len(e.ft) == len(self.arms)
                and len(e.joints) == len(self.joint_names))

    def _advance(self) -> None:
        done = [i for i, e in enumerate(self._open) if self._complete(e)]
        last = done[-1] if done else -1
        if len(self._open) - (last + 1) > self.settings.max_open:
            last = len(self._open) - self.settings.max_open - 1
        if last < 0:
            return
        ready, self._open = self._open[:last + 1], self._open[last + 1:]
        for e in ready:
            self._compute(e)

    def flush(self) -> None:
        """Compute every waiting epoch with what it has (end of a log or of a run)."""
        ready, self._open = self._open, []
        for e in ready:
            self._compute(e)

    # -- one epoch ---------------------------------------------------------------------------
    def _apply_pending(self, t: int) -> None:
        keep = []
        for s in self._pending:
            if s.t_ns > t - self.half:
                keep.append(s)
            elif isinstance(s, ImuSample):
                self.kf.imu(s.t_ns, np.asarray(s.accel_m_s2), np.asarray(s.rate_rad_s))
                self._gyro_t = s.t_ns
                self._note(s.saturated, s.status & wire.IMU_FAULT, "imu")
            elif isinstance(s, TorqueCommand):
                self._cmd[s.device] = (s.torque_nm, s.t_ns)
            elif isinstance(s, ThrusterCommand):
                self._thr_cmd = s
        self._pending = keep

    def _note(self, saturated: bool, fault: int, device: str) -> None:
        if saturated:
            self._faults.add(f"saturated:{device}")
        if fault:
            self._faults.add(f"fault:{device}")

    def _compute(self, e: _Epoch) -> None:
        t = e.t_ns
        self._last_closed = max(self._last_closed, t)
        self.epochs += 1
        self._faults = set()
        common: set[str] = set()
        self._apply_pending(t)
        common |= self._faults
        if self._gyro_t is None:
            common.add("warmup")
        elif t - self._gyro_t > self.settings.stale_periods * self.imu_period_ns:
            common.add("stale:imu")
        if e.valves is None:
            common.add("missing:valves")
        arm_flags: dict[str, set] = {a: set() for a in self.arms}
        p = len(self.arms)
        ft = np.zeros((p, 6))
        for k, a in enumerate(self.arms):
            w = e.ft.get(a)
            if w is None:
                arm_flags[a].add(f"missing:{a}")
                continue
            ft[k, :3], ft[k, 3:] = w.force_n, w.torque_nm
            if w.saturated:
                arm_flags[a].add(f"saturated:{a}")
            if w.status & wire.FT_FAULT:
                arm_flags[a].add(f"fault:{a}")
        for i, name in enumerate(self.joint_names):
            js = e.joints.get(name)
            arm = name.split("/", 1)[0]
            if js is None:
                arm_flags[arm].add(f"stale:{name}" if self._have_joint[i] else f"missing:{name}")
                continue
            self._q[i], self._dq[i] = js.angle_rad, js.rate_rad_s
            self._have_joint[i] = True
            if js.saturated:
                arm_flags[arm].add(f"saturated:{name}")
            if js.status & wire.DRIVE_FAULT:
                arm_flags[arm].add(f"fault:{name}")

        valves = np.zeros(self.layout.n) if e.valves is None else ((e.valves.valves >> self._shifts) & 1).astype(float)
        arm_w = arm_reaction(self.model, ft)
        thr = self.kf.wrench(valves)
        self.kf.push_epoch(t, arm_w, valves)
        m, I = self.model, self.model.inertia_s
        w_s = self.kf.w
        a_s = (thr[:3] + arm_w[:3]) / m.mass_s
        dw_s = np.linalg.solve(I, thr[3:] + arm_w[3:] - cross(w_s, I @ w_s))
        q, dq = self._q, self._dq
        simp = joint_torques_simplified(m, self.data, q, ft)
        ddq = joint_accelerations_from_ft(m, self.data, q, dq, ft, a_s, w_s, dw_s)
        full = joint_torques(m, self.data, q, dq, ddq, ft, a_s, w_s, dw_s)

        # a missing or bad F/T sample corrupts the base motion, so every arm's full estimate
        ft_flags = {f for f in set().union(*arm_flags.values()) if "/" not in f}
        common |= ft_flags
        col = 0
        for a in self.arms:
            names = self.arm_joints[a]
            n = len(names)
            flags = tuple(sorted(common | arm_flags[a]))
            cmds = [self._cmd.get(j) for j in names]
            have = all(c is not None for c in cmds)
            self.out(JointEfforts(
                arm=a, t_ns=t, joints=tuple(names),
                full_nm=tuple(float(x) for x in full[col:col + n]),
                simplified_nm=tuple(float(x) for x in simp[col:col + n]),
                commanded_nm=tuple(float(c[0]) for c in cmds) if have else (),
                commanded_t_ns=min(c[1] for c in cmds) if have else 0,
                rate_rad_s=tuple(float(x) for x in dq[col:col + n]),
                good=not flags, flags=flags))
            col += n
        flags = tuple(sorted(common))
        tc = self._thr_cmd
        good = not flags
        self.good += good
        self.out(ThrusterEffort(
            t_ns=t, force_n=tuple(float(x) for x in thr[:3]), moment_nm=tuple(float(x) for x in thr[3:]),
            commanded_force_n=tc.force_n if tc else (0.0, 0.0, 0.0),
            commanded_moment_nm=tc.moment_nm if tc else (0.0, 0.0, 0.0),
            commanded_t_ns=tc.t_ns if tc else 0, valves=tc.valves if tc else 0,
            good=good, flags=flags))
