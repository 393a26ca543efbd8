"""The first wave's live estimator, kept as the test oracle of :mod:`gateway.estimator.core`.

Plain Python on Pinocchio and numpy: the sync policy written with lists, dicts and sets, the maths
by the reference functions of :mod:`gateway.estimator.torques` (Pinocchio's ``rnea`` and LAPACK's
least squares) and :class:`gateway.estimator.thrusters.ThrusterFilter`. The product runs the
compiled :class:`gateway.estimator.core.EstimatorCore`; ``tests/gateway/estimator/test_core.py`` feeds both
the same samples and requires the same epochs, flags and commanded values, and efforts within
1e-9 of their scale. Slow on purpose (a few hundred us per epoch): it is written to be read.

Synchronisation policy (docs/estimator.md, "Live"):

- An *epoch* is one F/T sampling instant (1 kHz). Its required members are the F/T sample of
  every arm, the joint state of every joint and the valve command (no interpolation: every
  device samples at the epoch). A sample belongs to the epoch of its slot on a grid of
  one-period slots centred on the bursts of frames: the grid's phase is placed in the widest
  quiet gap between the first 64 members' arrival phases, then follows the bursts' middles
  (a step's frames arrive spread over most of a period on a loaded bus).
- An epoch is computed as soon as it is complete. When a later epoch completes first, the
  earlier one is computed with what it has (its missing inputs were lost: each bus is FIFO) and
  flagged; so is the oldest epoch when more than ``max_open`` are waiting (a silent bus).
- Slower streams are applied to the first epoch that is at least half a period later than
  their timestamp: IMU samples (they update the thruster filter and the base rate), torque and
  thruster commands (the "commanded" fields). Their maximum age: ``imu_max_age_periods`` of their own
  period; older means ``stale:<device>``. What arrived by the time an epoch is computed is
  applied right after its efforts are out, the rest when the next epoch is computed.
- A missing joint state holds the previous one (``stale:<arm>/<joint>``, that arm's efforts not
  good); a missing F/T sample or valve command makes all the epoch's efforts not good
  (``missing:<device>``: the base motion needs every arm's reaction). Saturated or
  faulty inputs flag ``saturated:<device>`` / ``fault:<device>``; until the first IMU sample the
  estimates are ``warmup``. ``good`` = no flag.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from drivers import wire
from drivers.samples import ImuSample, JointSample, ThrusterCommand, TorqueCommand, ValveCommand, WrenchSample
from gateway.efforts import JointEfforts, ThrusterEffort
from gateway.estimator.joint_filter import JointFilterSettings
from gateway.estimator.model import EstimatorModel
from gateway.estimator.thrusters import ThrusterFilter, ThrusterFilterSettings
from gateway.estimator.torques import joint_accelerations_from_ft, joint_torques, joint_torques_simplified
from gateway.estimator.wrench import arm_reaction
from robot_description import Robot
from robot_description.thrusters import ThrusterLayout

from reference_joint_filter import SequentialFilter, _fused, _J_w0


@dataclass(frozen=True)
class LiveSettings:
    max_open: int = 20                 # epochs waiting for members before the oldest is forced out
    imu_max_age_periods: int = 3       # the IMU sample an epoch uses may be this many IMU periods old
    thrusters: ThrusterFilterSettings = field(default_factory=ThrusterFilterSettings)
    joints: JointFilterSettings = field(default_factory=JointFilterSettings)


class _Epoch:
    __slots__ = ("t_ns", "ft", "joints", "valves", "open", "first", "last")

    def __init__(self, t_ns: int, open_: bool = True):
        self.t_ns = t_ns                   # the epoch's time on the grid (LiveEstimator._grid)
        self.first = self.last = None      # earliest and latest own timestamp of its members
        self.ft: dict = {}                 # arm -> WrenchSample
        self.joints: dict = {}             # "<arm>/<joint>" -> JointSample
        self.valves: ValveCommand | None = None
        self.open = open_                  # False: a throw-away epoch for a sample too late to use


Output = Callable[[object], None]

_MEMBER = {WrenchSample: 0, JointSample: 1, ValveCommand: 2}
PHASE_LEARN_SAMPLES = 64     # members held at start to find where the sensor bursts sit in a period
PHASE_TRACK = 64             # the grid follows the bursts' middle with this time constant (epochs)
_SLOW = (ImuSample, TorqueCommand, ThrusterCommand)


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
        self._center: int | None = None         # a time at the centre of a burst: the grid's phase
        self._learning: list | None = []         # samples held until the phase is known
        self._learn_members = 0
        self._faults: set[str] = set()
        self.epochs = 0
        self.good = 0
        self.late = 0
        self._n_arms, self._n_joints = len(self.arms), len(self.joint_names)
        self._joint_arm = [name.split("/", 1)[0] for name in self.joint_names]
        self._arm_spans = []                     # (arm, joint names tuple, names list, col, n)
        col = 0
        for a in self.arms:
            names = self.arm_joints[a]
            self._arm_spans.append((a, tuple(names), names, col, len(names)))
            col += len(names)
        self._valves_cache: dict[int, np.ndarray] = {}
        self._no_valves = np.zeros(self.layout.n)
        self._no_valves.setflags(write=False)
        self._stale_imu_ns = self.settings.imu_max_age_periods * self.imu_period_ns
        # the joint filter per arm (numpy, the kernel's order) and the last epoch's time
        self._jf = [SequentialFilter(len(a.columns), s.joints, dtype=np.float64) for a in self.model.arms]
        self._filter_t: int | None = None

    # -- input -------------------------------------------------------------------------------
    def add(self, sample) -> None:
        if self._learning is not None:
            self._learning.append(sample)
            if isinstance(sample, (WrenchSample, JointSample, ValveCommand)):
                self._learn_members += 1
                if self._learn_members >= PHASE_LEARN_SAMPLES:
                    self._lock_phase()
            return
        kind = _MEMBER.get(sample.__class__)
        if kind is None:
            if isinstance(sample, WrenchSample):
                kind = 0
            elif isinstance(sample, JointSample):
                kind = 1
            elif isinstance(sample, ValveCommand):
                kind = 2
            elif isinstance(sample, _SLOW):
                self._pending.append(sample)
                return
            else:
                return
        t = sample.t_ns
        e = self._member(self._grid(t))
        if e.first is None or t < e.first:
            e.first = t
        if e.last is None or t > e.last:
            e.last = t
        if kind == 0:
            e.ft[sample.device] = sample
        elif kind == 1:
            e.joints[sample.device] = sample
        else:
            e.valves = sample
        self._advance(e)

    def _lock_phase(self) -> None:
        """Place the epoch grid: a boundary in the middle of the widest quiet gap between the held
        members' arrival phases (between one step's burst of frames and the next), then process
        the held samples. Depends only on the set of timestamps, not on their order."""
        held, self._learning = self._learning, None
        ts = [x.t_ns for x in held if isinstance(x, (WrenchSample, JointSample, ValveCommand))]
        ts = ts or [x.t_ns for x in held] or [0]
        t0, p = min(ts), self.period_ns
        ph = sorted({(t - t0) % p for t in ts})
        gaps = [(ph[0] + p - ph[-1], ph[-1])] + [(b - a, a) for a, b in zip(ph, ph[1:])]
        width, start = max(gaps)
        self._center = t0 + start + width // 2 + self.half      # half a period from the boundary
        for x in held:
            self.add(x)

    def _grid(self, t: int) -> int:
        """The grid time of the epoch a sample stamped ``t`` belongs to (within half a period)."""
        c, p = self._center, self.period_ns
        return c + ((t - c + self.half) // p) * p

    def _member(self, t: int) -> _Epoch:
        half = self.half
        opened = self._open
        for e in opened:
            if abs(e.t_ns - t) < half:
                return e
        if t <= self._last_closed + half:
            self.late += 1
            return _Epoch(t, False)                # a throw-away epoch: too late to be used
        e = _Epoch(t)
        if not opened or opened[-1].t_ns < t:      # (kept sorted by time)
            opened.append(e)
        else:
            k = 0
            while opened[k].t_ns <= t:
                k += 1
            opened.insert(k, e)
        return e

    def _complete(self, e: _Epoch) -> bool:
        return (e.valves is not None and len(e.ft) == self._n_arms
                and len(e.joints) == self._n_joints)

    def _advance(self, touched: _Epoch) -> None:
        # Every open epoch but ``touched`` was incomplete after its last change (complete ones are
        # computed at once), so the last complete one, if any, is ``touched``.
        opened = self._open
        last = opened.index(touched) if touched.open and self._complete(touched) else -1
        max_open = self.settings.max_open
        if len(opened) - (last + 1) > max_open:
            last = len(opened) - max_open - 1
        if last < 0:
            return
        ready, self._open = opened[:last + 1], opened[last + 1:]
        for e in ready:
            e.open = False
            self._compute(e)

    def flush(self) -> None:
        """Compute every waiting epoch with what it has (end of a log or of a run)."""
        if self._learning is not None:
            self._lock_phase()
        ready, self._open = self._open, []
        for e in ready:
            e.open = False
            self._compute(e)

    # -- one epoch ---------------------------------------------------------------------------
    def _apply_pending(self, lim: int) -> None:
        """Apply the slower-stream samples whose grid time is at most ``lim``, in arrival order."""
        keep = []
        grid = self._grid
        for s in self._pending:
            g = grid(s.t_ns)
            if g > lim:
                keep.append(s)
            elif isinstance(s, ImuSample):             # it ends the filter steps of its grid epoch
                self.kf.imu(g, np.asarray(s.accel_m_s2), np.asarray(s.rate_rad_s))
                self._gyro_t = g
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

    def _valves(self, e: _Epoch) -> np.ndarray:
        if e.valves is None:
            return self._no_valves
        mask = e.valves.valves
        v = self._valves_cache.get(mask)
        if v is None:
            v = ((mask >> self._shifts) & 1).astype(float)
            v.setflags(write=False)
            if len(self._valves_cache) < 4096:
                self._valves_cache[mask] = v
        return v

    def _compute(self, e: _Epoch) -> None:
        t = e.t_ns
        if t > self._last_closed:
            self._last_closed = t
        if e.first is not None and self._complete(e):      # the grid follows the bursts (drift)
            self._center += ((e.first + e.last) // 2 - t) // PHASE_TRACK
        self.epochs += 1
        if self._pending:
            self._apply_pending(t - self.half)
        common: set[str] = self._faults          # noted by the slower streams applied since the last epoch
        self._faults = set()
        if self._gyro_t is None:
            common.add("warmup")
        elif t - self._gyro_t > self._stale_imu_ns:
            common.add("stale:imu")
        if e.valves is None:
            common.add("missing:valves")
        arm_flags: dict[str, set] | None = None
        row: list[float] = []
        efts = e.ft
        ft_trusted = True                 # every F/T sample present, none saturated or faulty
        ft_ok = [False] * self._n_arms    # per arm: its sample may be applied (joint filter)
        for ai, a in enumerate(self.arms):
            w = efts.get(a)
            if w is None:
                arm_flags = arm_flags or {x: set() for x in self.arms}
                arm_flags[a].add(f"missing:{a}")
                row += (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
                ft_trusted = False
                continue
            row += w.force_n
            row += w.torque_nm
            ft_ok[ai] = not w.saturated and not (w.status & wire.FT_FAULT)
            if w.saturated:
                arm_flags = arm_flags or {x: set() for x in self.arms}
                arm_flags[a].add(f"saturated:{a}")
                ft_trusted = False
            if w.status & wire.FT_FAULT:
                arm_flags = arm_flags or {x: set() for x in self.arms}
                arm_flags[a].add(f"fault:{a}")
                ft_trusted = False
        ft = np.array(row, dtype=float).reshape(self._n_arms, 6)
        ejs = e.joints
        q, dq = self._q, self._dq
        rate_ok = np.zeros(self._n_joints, dtype=bool)
        for i, name in enumerate(self.joint_names):
            js = ejs.get(name)
            if js is None:
                arm_flags = arm_flags or {x: set() for x in self.arms}
                arm_flags[self._joint_arm[i]].add(f"stale:{name}" if self._have_joint[i] else f"missing:{name}")
                continue
            q[i] = js.angle_rad
            dq[i] = js.rate_rad_s
            self._have_joint[i] = True
            rate_ok[i] = not js.saturated and not (js.status & wire.DRIVE_FAULT)
            if js.saturated:
                arm_flags = arm_flags or {x: set() for x in self.arms}
                arm_flags[self._joint_arm[i]].add(f"saturated:{name}")
            if js.status & wire.DRIVE_FAULT:
                arm_flags = arm_flags or {x: set() for x in self.arms}
                arm_flags[self._joint_arm[i]].add(f"fault:{name}")

        # the joint filter: F/T rows only with the arm's joints fresh and the base motion trusted
        base_ok = ft_trusted and not common
        for arm in self.model.arms:
            if not base_ok or not rate_ok[list(arm.columns)].all():
                ft_ok[arm.index] = False
        valves = self._valves(e)
        arm_w = arm_reaction(self.model, ft)
        kf = self.kf
        thr = kf.wrench(valves)
        # the filter learns only from whole, trusted steps: a step without every arm's F/T
        # sample or without the valve command (or with a saturated or faulty F/T sample) is left
        # out, and the IMU samples whose interval it falls in are not applied (kf.imu)
        if ft_trusted and e.valves is not None:
            kf.push_epoch(t, arm_w, valves)
        # base motion: the spacecraft is pushed by the thrusters and the arms, nothing else
        m = self.model
        w_s = kf.w
        sj = self.settings.joints
        # whole periods since the filter's last epoch (the grid's drift tracking is not motion)
        dt = ((t - self._filter_t + self.half) // self.period_ns) * self.period_ns * 1e-9 \
            if self._filter_t is not None else 0.0
        if sj.enabled and not 0.0 < dt <= sj.max_gap_s:
            for f in self._jf:
                f.started = False
        base_w = arm_w                    # less the F/T biases the joint filter has learnt so far
        if sj.enabled and self._filter_t is not None:
            dt = ((t - self._filter_t + self.half) // self.period_ns) * self.period_ns * 1e-9
            if 0.0 < dt <= sj.max_gap_s:
                seen = np.array([f.x[2 * f.n:].astype(float) if f.started else np.zeros(6) for f in self._jf])
                base_w = arm_w - arm_reaction(m, seen)
        a_s = (thr[:3] + base_w[:3]) / m.mass_s
        dw_s = np.linalg.solve(m.inertia_s, (thr[3:] + base_w[3:]) - np.cross(w_s, m.inertia_s @ w_s))
        data = self.data
        simp = joint_torques_simplified(m, data, q, ft)
        ddq = joint_accelerations_from_ft(m, data, q, dq, ft, a_s, w_s, dw_s)
        full = joint_torques(m, data, q, dq, ddq, ft, a_s, w_s, dw_s)
        bias: list[tuple[float, ...]] = [()] * self._n_arms
        if sj.enabled:
            # the joint filter (gateway/estimator/joint_filter.py), in the kernel's order
            self._filter_t = t
            Js, w0 = _J_w0(m, data, q, dq, a_s, w_s, dw_s)
            fddq = ddq.copy()
            fused_arms = []
            for arm in m.arms:
                f, cols, n = self._jf[arm.index], list(arm.columns), len(arm.columns)
                if f.started:
                    f.step(Js[arm.index], ft[arm.index] - w0[arm.index], ft_ok[arm.index], dq[cols],
                           rate_ok[cols], dt)
                elif ft_ok[arm.index]:
                    f.start(dq[cols], ddq[cols])
                if f.started:
                    fddq[cols] = f.x[n:2 * n]
                    bias[arm.index] = tuple(float(v) for v in f.x[2 * n:])
                    fused_arms.append(arm)
            if fused_arms:
                covs = [f.P for f in self._jf]
                seen = [f.x[2 * f.n:].astype(float) if f.started else np.zeros(6) for f in self._jf]
                fused = _fused(m, data, sj, covs, q, dq, fddq, ft, a_s, w_s, dw_s, Js, seen)
                for arm in fused_arms:
                    full[list(arm.columns)] = fused[list(arm.columns)]

        # a missing or bad F/T sample corrupts the base motion, so every arm's full estimate
        if arm_flags is not None:
            common |= {f for f in set().union(*arm_flags.values()) if "/" not in f}
        full_l, simp_l, dq_l, thr_l = full.tolist(), simp.tolist(), dq.tolist(), thr.tolist()
        cmd = self._cmd
        for a, names_t, names, col, n in self._arm_spans:
            flags = tuple(sorted(common | (arm_flags[a] if arm_flags is not None else set())))
            cmds = [cmd.get(j) for j in names]
            have = None not in cmds
            self.out(JointEfforts(
                arm=a, t_ns=t, joints=names_t, full_nm=tuple(full_l[col:col + n]),
                simplified_nm=tuple(simp_l[col:col + n]),
                commanded_nm=tuple(float(c[0]) for c in cmds) if have else (),
                commanded_t_ns=min(c[1] for c in cmds) if have else 0,
                rate_rad_s=tuple(dq_l[col:col + n]), good=not flags, flags=flags,
                ft_bias=bias[self.arms.index(a)]))
        flags = tuple(sorted(common))
        tc = self._thr_cmd
        self.good += not flags
        self.out(ThrusterEffort(
            t_ns=t, force_n=tuple(thr_l[:3]), moment_nm=tuple(thr_l[3:]),
            commanded_force_n=tc.force_n if tc else (0.0, 0.0, 0.0),
            commanded_moment_nm=tc.moment_nm if tc else (0.0, 0.0, 0.0),
            commanded_t_ns=tc.t_ns if tc else 0, valves=tc.valves if tc else 0,
            good=not flags, flags=flags))
        if self._pending:                 # off the latency path: what the next epoch applies first
            self._apply_pending(t + self.half)
