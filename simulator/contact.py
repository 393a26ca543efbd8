"""Contact at an end effector: a force the estimator's model does not know (a grasp, a push, a
collision), from the scenario's ``[[contact]]`` tables.

Each table puts a wrench on one arm's end effector, at the point of its ``<arm>_ee`` frame:

    [[contact]]
    arm = "arm0"            # the arm's name
    onset_s = 3.0           # when it starts
    duration_s = 1.0        # how long it lasts (ramps included)
    force_n = [0, 20, 0]    # the force on the end effector, N
    moment_nm = [0, 0, 0]   # optional: a moment on it too, N m
    frame = "world"         # "world" (inertial axes: a fixed obstacle) or "ee" (the end effector's axes)
    ramp_s = 0.02           # optional: rise and fall time (a linear ramp each way), s

Contacts add up. The world-frame ones are turned into the joint's axes with the orientation at the
start of the step, held over the step like every other input.
The truth of a contact, as a function of time and the state, is :meth:`Contacts.world_wrench`.
"""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

from simulator.errors import SimulatorError

KEYS = {"arm", "onset_s", "duration_s", "force_n"}
OPTIONAL = {"moment_nm": [0.0, 0.0, 0.0], "frame": "world", "ramp_s": 0.02}


class ContactError(SimulatorError, ValueError):
    """A ``[[contact]]`` table the simulator cannot apply."""


class _Contact:
    __slots__ = ("arm", "joint", "X", "onset", "end", "ramp", "force", "moment", "world")

    def profile(self, t: float) -> float:
        """0 outside the contact, 1 in its plateau, linear in between."""
        if t < self.onset or t >= self.end:
            return 0.0
        if self.ramp <= 0.0:
            return 1.0
        return min(1.0, (t - self.onset) / self.ramp, (self.end - t) / self.ramp)


class Contacts:
    """The scenario's contacts on ``robot``; ``items`` the ``[[contact]]`` tables."""

    def __init__(self, robot, items: list[dict]):
        if not isinstance(items, list):
            raise ContactError("'contact' must be an array of tables ([[contact]])")
        self.model = robot.model
        arms = {a.name: a for a in robot.arms}
        self.items: list[_Contact] = []
        for i, d in enumerate(items):
            where = f"contact[{i}]"
            if not isinstance(d, dict):
                raise ContactError(f"{where}: must be a table")
            unknown = set(d) - KEYS - set(OPTIONAL)
            if unknown:
                raise ContactError(f"{where}: unknown key(s) {', '.join(sorted(unknown))} "
                                   f"(keys: {', '.join(sorted(KEYS | set(OPTIONAL)))})")
            missing = KEYS - set(d)
            if missing:
                raise ContactError(f"{where}: missing key(s) {', '.join(sorted(missing))}")
            if d["arm"] not in arms:
                raise ContactError(f"{where}: no arm {d['arm']!r} (arms: {', '.join(arms)})")
            c = _Contact()
            c.arm = list(arms).index(d["arm"])
            frame = self.model.frames[arms[d["arm"]].ee_frame]
            c.joint = int(frame.parentJoint)
            c.X = frame.placement                    # the end effector in its joint's frame
            c.onset = _number(d["onset_s"], f"{where}.onset_s", low=0.0)
            dur = _number(d["duration_s"], f"{where}.duration_s", low=0.0, strict=True)
            c.end = c.onset + dur
            c.ramp = min(_number(d.get("ramp_s", OPTIONAL["ramp_s"]), f"{where}.ramp_s", low=0.0), dur / 2)
            c.force = _vector(d["force_n"], f"{where}.force_n")
            c.moment = _vector(d.get("moment_nm", OPTIONAL["moment_nm"]), f"{where}.moment_nm")
            fr = d.get("frame", OPTIONAL["frame"])
            if fr not in ("world", "ee"):
                raise ContactError(f"{where}.frame must be 'world' or 'ee', got {fr!r}")
            c.world = fr == "world"
            self.items.append(c)
        self._fext = [pin.Force.Zero() for _ in range(self.model.njoints)]

    def __bool__(self) -> bool:
        return bool(self.items)

    def _ee_wrench(self, c: _Contact, s: float, R_ee: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Force and moment on the end effector in its own axes."""
        if c.world:
            return s * R_ee.T.dot(c.force), s * R_ee.T.dot(c.moment)
        return s * c.force, s * c.moment

    def fext(self, t: float, data: pin.Data, q: np.ndarray) -> list | None:
        """The external forces per joint (local frames) at time ``t`` and configuration ``q``, for
        ``pin.aba``; ``data`` takes the placements (only when a contact acts). None when none does."""
        active = [(c, c.profile(t)) for c in self.items]
        active = [(c, s) for c, s in active if s > 0.0]
        if not active:
            return None
        pin.forwardKinematics(self.model, data, q)
        for f in self._fext:
            f.setZero()
        for c, s in active:
            R_ee = data.oMi[c.joint].rotation.dot(c.X.rotation)
            f, m = self._ee_wrench(c, s, R_ee)
            self._fext[c.joint] += c.X.act(pin.Force(f, m))
        return self._fext

    def world_wrench(self, t: float, oMi) -> np.ndarray:
        """The truth: per arm, the contact's force and its moment about the end-effector point,
        inertial axes ``(p, 6)``; ``oMi`` the joints' placements (Pinocchio's ``data.oMi``)."""
        out = np.zeros((1 + max((c.arm for c in self.items), default=0), 6))
        for c in self.items:
            s = c.profile(t)
            if s == 0.0:
                continue
            R_ee = oMi[c.joint].rotation.dot(c.X.rotation)
            f, m = self._ee_wrench(c, s, R_ee)
            out[c.arm, :3] += R_ee.dot(f)
            out[c.arm, 3:] += R_ee.dot(m)
        return out


def _number(x, where: str, low: float, strict: bool = False) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) \
            or x < low or (strict and x == low):
        raise ContactError(f"{where} must be a number {'>' if strict else '>='} {low:g}, got {x!r}")
    return float(x)


def _vector(x, where: str) -> np.ndarray:
    if not isinstance(x, list) or len(x) != 3 or not all(
            isinstance(e, (int, float)) and not isinstance(e, bool) and math.isfinite(e) for e in x):
        raise ContactError(f"{where} must be 3 finite numbers, got {x!r}")
    return np.array(x, dtype=float)
