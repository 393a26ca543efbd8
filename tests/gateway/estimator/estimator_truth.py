"""Random free-flying states with Pinocchio's inverse dynamics as truth (shared by the estimator tests)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

ROBOTS = ("paper_robot", "three_arm")


@dataclass(frozen=True)
class State:
    """A random free-flying state and Pinocchio's inverse dynamics of it (the truth)."""

    q: np.ndarray            # full Pinocchio q (random base pose)
    v: np.ndarray            # full v, base linear velocity NOT zero
    a: np.ndarray
    tau: np.ndarray          # rnea: [base wrench (thrusters), joint torques]
    ft: np.ndarray           # (p, 6) sensor wrenches, METHOD convention
    a_s: np.ndarray          # classical acceleration of C, body frame
    w_s: np.ndarray
    dw_s: np.ndarray

    @property
    def qj(self):
        return self.q[7:]

    @property
    def dq(self):
        return self.v[6:]

    @property
    def ddq(self):
        return self.a[6:]


def sensor_wrenches(robot, data) -> np.ndarray:
    """Per-arm sensor readings from rnea's data.f (needs forwardKinematics + frame placements)."""
    return np.array([data.oMf[arm.sensor_frame].actInv(data.oMi[arm.joints[0]].act(data.f[arm.joints[0]])).vector
                     for arm in robot.arms])


def random_state(robot, rng: np.random.Generator) -> State:
    m = robot.model
    d = m.createData()
    q = pin.integrate(m, pin.neutral(m), rng.normal(size=m.nv))
    v = rng.normal(size=m.nv) * 0.5
    a = rng.normal(size=m.nv)
    tau = pin.rnea(m, d, q, v, a).copy()
    pin.forwardKinematics(m, d, q)
    pin.updateFramePlacements(m, d)
    ft = sensor_wrenches(robot, d)
    w_s = v[3:6].copy()
    a_s = a[:3] + np.cross(w_s, v[:3])       # classical = spatial + w x v
    return State(q, v, a, tau, ft, a_s, w_s, a[3:6].copy())
