"""The joint loop of the compensator: the outer loop's desired torque in, the drives' command out.

The flight software (the outer loop) commands a desired torque ``d``; the joint delivers
``actual = applied - friction``. The gateway estimates ``actual`` from the base F/T sensors
(:class:`gateway.efforts.JointEfforts` ``full_nm``). Per joint, a PI on the torque error
``e = d - actual_estimated`` gives a correction ``c`` and the drives get ``applied = d + c``::

    c* = kp e + I,      I <- I + ki e dt     (integral clamped to +-max_correction: anti-windup;
                                              no integration into a saturated drive)
    c  = c_prev + clip(c* - c_prev, +-max_rate dt),   then clip(c, +-max_correction)
    applied = clip(d + c, +-torque limit)

With the estimate one step late, ``e = friction - c`` and the integral tracks the friction with
a gain ``ki dt`` per update (0.3 at the defaults; stable below 1 for one step of delay).

Safety, per arm (:class:`JointCompensator`):

- an estimate that is not good (``good`` false, any flag, a non-finite value) opens the loop at
  once: the next command is the desired torque exactly, the integral and the correction are reset;
- no good estimate newer than ``stale_s`` behind the command being corrected: open loop, flag
  ``stale:efforts`` (the gateway stopped, the link dropped);
- going open is never rate-limited (it is always safe); closing again takes ``resume_good`` good
  estimates in a row, then the correction ramps up from zero under the rate limit (flag
  ``limited:rate`` while it does);
- the correction is magnitude-limited (``max_correction`` of the joint's torque limit) and
  rate-limited, so a wrong estimate that passes as good moves the command by a bounded amount at
  a bounded speed (flags ``limited:magnitude``, ``limited:rate``);
- plausibility: the friction an estimate implies (``applied - actual = e + c``) must oppose each
  moving joint's motion (friction dissipates); an estimate implying friction that drives the
  joint, beyond ``plausible_margin`` of its limit in ``plausible_steps`` estimates in a row (an
  F/T bias the gateway did not flag), opens the loop (``estimate:implausible (<joints>)``) for at
  least ``plausible_hold_s`` after the last such trip.

Every transition is recorded in :attr:`JointCompensator.events` (for the service's alerts).
Pure: no I/O, no clock; times are the sensor times the efforts and commands carry.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

from drivers.samples import TorqueCommand
from gateway.control.messages import ControlError, DriveCommand
from gateway.efforts import JointEfforts


@dataclass(frozen=True)
class JointLoopSettings:
    """The joint loop's gains and limits (every one explained in docs/control.md)."""

    kp: float = 0.2                 # proportional gain on the torque error (N m per N m)
    ki_per_s: float = 300.0         # integral gain, 1/s (ki dt = 0.3 per 1 ms estimate)
    max_correction: float = 0.5     # |correction| <= this fraction of the joint's torque limit
    max_rate_per_s: float = 100.0   # |d correction / dt| <= this fraction of the torque limit per s
    stale_s: float = 0.01           # no good estimate this recent behind a command: open loop
    resume_good: int = 5            # good estimates in a row to close the loop again
    # plausibility: the friction an estimate implies must oppose the motion (it dissipates)
    plausible_min_rate: float = 0.02   # rad/s: judged only on joints moving faster than this
    plausible_margin: float = 0.05     # implied friction along the motion beyond this fraction of the limit...
    plausible_steps: int = 10          # ...in this many estimates in a row: open loop,
    plausible_hold_s: float = 1.0      # and it stays open this long after the last implausible trip

    def __post_init__(self):
        for name in ("kp", "ki_per_s", "max_correction", "max_rate_per_s", "stale_s", "plausible_min_rate",
                     "plausible_margin", "plausible_hold_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ControlError(f"joint loop: {name} must be a finite number >= 0, got {v!r}")
        if self.stale_s <= 0 or self.max_rate_per_s <= 0:
            raise ControlError("joint loop: stale_s and max_rate_per_s must be > 0")
        for name in ("resume_good", "plausible_steps"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ControlError(f"joint loop: {name} must be an integer >= 1, got {v!r}")


@dataclass(frozen=True)
class LoopEvent:
    """One transition of an arm's loop: ``state`` ``open`` or ``closed`` at sensor time ``t_ns``."""

    arm: str
    t_ns: int
    state: str
    reason: str


class _Arm:
    """One arm's loop state."""

    def __init__(self, name: str, joints: Sequence[str], limit: np.ndarray):
        self.name, self.joints, self.limit = name, tuple(joints), limit
        n = len(joints)
        self.desired: deque[tuple[int, np.ndarray]] = deque(maxlen=64)   # (t_ns, torques) observed
        self.integral = np.zeros(n)
        self.target = np.zeros(n)          # c* of the last estimate
        self.correction = np.zeros(n)      # c of the last command
        self.last_cmd_ns: int | None = None
        self.last_est_ns: int | None = None     # the last estimate used (good)
        self.good_run = 0                  # good estimates in a row since the last bad one
        self.implausible = np.zeros(len(joints), dtype=int)   # estimates in a row implying driving friction
        self.hold_until_ns = -1            # open at least until then (an implausible estimate)
        self.closed = False
        self.why_open = "no-estimate"
        self.pending: dict[int, dict[str, float]] = {}     # t_ns -> joint -> torque (assembling)

    def desired_at(self, t_ns: int) -> np.ndarray | None:
        """The latest desired torques observed at or before ``t_ns`` (what the actual torque at
        ``t_ns`` should have been: the loop also takes up the command's transport delay)."""
        for t, d in reversed(self.desired):
            if t <= t_ns:
                return d
        return None


class JointCompensator:
    """PI torque compensation of every arm's joints (module docstring).

    ``arms``: ``(arm, joint devices)`` in the robot's order (devices ``<arm>/<joint>``, proximal
    first, as :class:`JointEfforts` lists them); ``limits_nm``: per arm, each joint's torque
    limit (N m). Feed it the observed desired torques (:meth:`observe` a :class:`TorqueCommand`
    sample, or :meth:`desired`) and the gateway's estimates (:meth:`estimate`), and ask for the
    drives' command (:meth:`command`). ``enabled=False``: always open loop (the same path, no
    correction: the open-loop baseline through the same wire).
    """

    def __init__(self, arms: Iterable[tuple[str, Sequence[str]]], limits_nm: Iterable[Sequence[float]],
                 settings: JointLoopSettings | None = None, *, enabled: bool = True):
        self.settings = settings or JointLoopSettings()
        self.enabled = enabled
        self.arms: dict[str, _Arm] = {}
        self._device_arm: dict[str, tuple[str, int]] = {}
        for (name, joints), lim in zip(arms, limits_nm, strict=True):
            lim = np.asarray(lim, dtype=float)
            if lim.shape != (len(joints),) or not np.all(lim > 0):
                raise ControlError(f"joint loop: arm {name}: one positive torque limit per joint expected")
            self.arms[name] = _Arm(name, joints, lim)
            for i, dev in enumerate(joints):
                self._device_arm[dev] = (name, i)
        self.events: list[LoopEvent] = []

    @classmethod
    def for_robot(cls, robot, settings: JointLoopSettings | None = None, **kw) -> "JointCompensator":
        """Arms, joints and torque limits from a :class:`robot_description.Robot`."""
        names = list(robot.joint_names)
        limit = np.asarray(robot.effort_limit, dtype=float)
        arms = [(a.name, [f"{a.name}/{j}" for j in a.joint_names]) for a in robot.arms]
        limits = [[limit[names.index(d)] for d in joints] for _, joints in arms]
        return cls(arms, limits, settings, **kw)

    # -- inputs
    def _arm(self, name: str) -> _Arm:
        try:
            return self.arms[name]
        except KeyError:
            raise ControlError(f"joint loop: no arm {name!r} (arms: {', '.join(self.arms)})") from None

    def desired(self, arm: str, t_ns: int, torques_nm: Sequence[float]) -> None:
        """The outer loop's desired torques of ``arm`` at sensor time ``t_ns``."""
        a = self._arm(arm)
        d = np.asarray(torques_nm, dtype=float)
        if d.shape != (len(a.joints),):
            raise ControlError(f"joint loop: arm {arm}: {len(a.joints)} desired torques expected, got {d.shape}")
        if a.desired and t_ns < a.desired[-1][0]:
            return                                  # an older command arriving late: already superseded
        a.desired.append((int(t_ns), d))

    def observe(self, cmd: TorqueCommand) -> str | None:
        """One joint's observed command (a decoded sample); returns the arm's name when this
        completes the arm's set for its time (then :meth:`command` can correct it), else None."""
        where = self._device_arm.get(cmd.device)
        if where is None:
            return None
        name, _ = where
        a = self.arms[name]
        got = a.pending.setdefault(cmd.t_ns, {})
        got[cmd.device] = cmd.torque_nm
        if len(got) < len(a.joints):
            if len(a.pending) > 8:                  # sets that will never complete (a lost frame)
                for t in sorted(a.pending)[:-8]:
                    del a.pending[t]
            return None
        del a.pending[cmd.t_ns]
        for t in [t for t in a.pending if t < cmd.t_ns]:
            del a.pending[t]
        self.desired(name, cmd.t_ns, [got[d] for d in a.joints])
        return name

    def estimate(self, eff: JointEfforts) -> None:
        """One estimate of the gateway: updates the arm's PI, or opens its loop when not good."""
        a = self.arms.get(eff.arm)
        if a is None:
            return
        full = np.asarray(eff.full_nm, dtype=float)
        ok = (eff.good and not eff.flags and full.shape == (len(a.joints),) and bool(np.all(np.isfinite(full)))
              and tuple(eff.joints) == a.joints)
        if not ok:
            why = "estimate:not-good" + (f" ({','.join(eff.flags)})" if eff.flags else "")
            self._open(a, eff.t_ns, why)
            return
        if a.last_est_ns is not None and eff.t_ns <= a.last_est_ns:
            return                                  # late or repeated: the newer one was used
        d = a.desired_at(eff.t_ns)
        if d is None:
            return                                  # no desired torque known yet: nothing to compare
        s = self.settings
        e = d - full
        # the friction this estimate implies, applied - actual = e + c, must oppose the motion: a
        # sensor fault the gateway did not flag (an F/T bias) shows as friction that drives the joint
        rate = np.asarray(eff.rate_rad_s, dtype=float)
        if rate.shape == e.shape:
            wrong = ((np.abs(rate) > s.plausible_min_rate)
                     & ((e + a.correction) * np.sign(rate) < -s.plausible_margin * a.limit))
            a.implausible = np.where(wrong, a.implausible + 1, 0)
            if np.any(a.implausible >= s.plausible_steps):
                bad = [j for j, n in zip(a.joints, a.implausible) if n >= s.plausible_steps]
                self._open(a, eff.t_ns, f"estimate:implausible ({','.join(bad)})")
                a.hold_until_ns = eff.t_ns + round(s.plausible_hold_s * 1e9)
                a.last_est_ns = eff.t_ns
                return
        dt = 0.0 if a.last_est_ns is None else min((eff.t_ns - a.last_est_ns) * 1e-9, s.stale_s)
        a.last_est_ns = eff.t_ns
        a.good_run += 1
        if not a.closed:
            if a.good_run < s.resume_good or not self.enabled or eff.t_ns < a.hold_until_ns:
                return
            a.closed = True
            a.integral[:] = 0.0
            a.correction[:] = 0.0
            self.events.append(LoopEvent(a.name, eff.t_ns, "closed", "estimates good"))
        cap = s.max_correction * a.limit
        # conditional integration: not further into a drive that is saturated in that direction
        applied = d + a.correction
        push = ~(((applied >= a.limit) & (e > 0)) | ((applied <= -a.limit) & (e < 0)))
        a.integral = np.clip(a.integral + s.ki_per_s * dt * e * push, -cap, cap)
        a.target = s.kp * e + a.integral

    # -- output
    def command(self, arm: str, t_ns: int | None = None) -> DriveCommand:
        """The drives' command of ``arm``: the latest desired torques plus the correction, at
        sensor time ``t_ns`` (default: the latest desired torques' time). Raises when no desired
        torque has been observed yet."""
        a = self._arm(arm)
        if not a.desired:
            raise ControlError(f"joint loop: arm {arm}: no desired torque observed yet")
        t_d, d = a.desired[-1]
        t = t_d if t_ns is None else int(t_ns)
        s = self.settings
        flags: list[str] = []
        if a.closed and (a.last_est_ns is None or t - a.last_est_ns > s.stale_s * 1e9):
            self._open(a, t, "stale:efforts")
        if not a.closed:
            a.correction = np.zeros(len(a.joints))
            a.last_cmd_ns = t
            why = [a.why_open] if self.enabled else ["disabled"]
            return DriveCommand(a.name, t_d, a.joints, tuple(d.tolist()), tuple(d.tolist()),
                                (0.0,) * len(a.joints), False, tuple(why))
        dt = 0.0 if a.last_cmd_ns is None else max(0.0, (t - a.last_cmd_ns) * 1e-9)
        step = s.max_rate_per_s * a.limit * dt
        c = a.correction + np.clip(a.target - a.correction, -step, step)
        if np.any(np.abs(c - a.target) > 1e-9 * a.limit):
            flags.append("limited:rate")
        cap = s.max_correction * a.limit
        if np.any(np.abs(c) > cap):
            flags.append("limited:magnitude")
            c = np.clip(c, -cap, cap)
        applied = np.clip(d + c, -a.limit, a.limit)
        if np.any(applied != d + c):
            flags.append("saturated")
        a.correction, a.last_cmd_ns = c, t
        return DriveCommand(a.name, t_d, a.joints, tuple(applied.tolist()), tuple(d.tolist()),
                            tuple((applied - d).tolist()), True, tuple(sorted(flags)))

    def _open(self, a: _Arm, t_ns: int, why: str) -> None:
        a.good_run = 0
        a.integral[:] = 0.0
        a.target[:] = 0.0
        a.correction[:] = 0.0
        a.why_open = why
        if a.closed:
            a.closed = False
            self.events.append(LoopEvent(a.name, int(t_ns), "open", why))

    def take_events(self) -> list[LoopEvent]:
        """The transitions since the last call (and forgets them)."""
        out, self.events = self.events, []
        return out
