"""The estimator's belief about the robot, built once from a :class:`robot_description.Robot`.

Shaped like Pinocchio's model/data idiom: :class:`EstimatorModel` is immutable and may be
shared between threads; :class:`EstimatorData` is scratch space, one per thread.

Frames (docs/estimator.md, docs/method.md):

- body frame: the spacecraft frame, origin at its centre of mass C;
- sensor frame j: origin S_j, orientation R_j (sensor -> body), both fixed to the spacecraft;
- joint frame i: Pinocchio's frame of joint i. The recursion of :mod:`.chain_kernel` uses an
  "internal" frame per joint, the joint frame turned by a constant rotation Q_i so that the joint
  axis is +z; only the rotation changes, the origin stays on the axis.

Vectors of joint quantities (``q``, ``dq``, ``ddq``, torques) hold the arm joints only, in the
robot's v order (after the six base dofs): ``Robot.joint_names``. Per-arm sensor wrenches are an
array ``(p, 6)`` of ``[f, t]`` in arm order (``Robot.arms``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from gateway.errors import GatewayError
from robot_description import Robot


class EstimatorError(GatewayError):
    """Root of the estimator's errors."""


class EstimatorModelError(EstimatorError, ValueError):
    """The robot cannot be turned into an estimator model (unsupported joint, bad geometry)."""


class EstimatorSettingsError(EstimatorError, ValueError):
    """A setting of the estimator out of its range (a count below 1, a noise figure not > 0)."""


def skew(r: np.ndarray) -> np.ndarray:
    """S(r), the cross-product matrix: ``skew(r) @ f == np.cross(r, f)``."""
    return np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` over the last axis, broadcasting; several times faster than ``np.cross`` on (3,)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), axis=-1)


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, slots=True)
class ChainLink:
    """One joint and the link it moves, for :mod:`.chain_kernel`'s recursion (internal frames, axis +z).

    ``X_motion``/``X_force`` carry a twist/wrench from the previous link's internal frame (the
    body frame at C for the first joint) to this joint's frame at ``q = 0``; the joint rotation
    about +z is applied on top. ``inertia`` is the link's 6x6 spatial inertia about the joint
    origin, ordering (linear, angular) as Pinocchio's.
    """

    joint_id: int
    X_motion: np.ndarray
    X_force: np.ndarray
    inertia: np.ndarray


@dataclass(frozen=True, slots=True)
class ArmModel:
    name: str
    index: int                   # arm index into the (p, 6) wrench array
    joints: tuple[int, ...]      # Pinocchio joint ids, proximal first
    columns: tuple[int, ...]     # indices into the joint-only vectors (q, dq, tau)
    A_s: np.ndarray              # (6, 6) sensor wrench -> wrench on the arm about C, body frame
    sensor_inv: pin.SE3          # body (C) -> sensor placement inverse: maps body quantities to sensor
    axes: np.ndarray             # (n, 3) joint axes in their own joint frames
    unit_twists: tuple[pin.Motion, ...]   # the same as Pinocchio motions (rotation about the axis)
    chain: tuple[ChainLink, ...]
    ee_point: np.ndarray         # (3,) the end effector in the last link's internal frame, m (contact)


@dataclass(frozen=True, slots=True)
class EstimatorModel:
    """Everything the estimator needs, precomputed once. Treat as read-only (its Pinocchio model too)."""

    robot: Robot
    arms: tuple[ArmModel, ...]
    n_joints: int
    joint_arm: np.ndarray        # (n_joints,) arm index of each joint
    mass_s: float                # spacecraft alone, kg
    inertia_s: np.ndarray        # spacecraft alone about C, body frame, kg m^2
    inertia_s_inv: np.ndarray
    A_s_all: np.ndarray          # (6, 6p): [f_s; tau_s] = A_s_all @ ft.ravel() + b(a_s, w_s, dw_s)
    r_imu: np.ndarray            # IMU origin - C, body frame, m
    R_imu: np.ndarray            # IMU frame -> body frame

    @classmethod
    def from_robot(cls, robot: Robot) -> "EstimatorModel":
        model = robot.model
        data = model.createData()
        pin.computeJointJacobians(model, data, pin.neutral(model))
        arms = []
        col = 0
        for k, arm in enumerate(robot.arms):
            R, r = arm.R_sc, arm.r_sc
            A_s = np.zeros((6, 6))
            A_s[:3, :3] = R
            A_s[3:, :3] = skew(r) @ R
            A_s[3:, 3:] = R
            axes, chain = [], []
            Q_parent = np.eye(3)       # the body frame is its own internal frame
            for jid in arm.joints:
                S = pin.getJointJacobian(model, data, jid, pin.LOCAL)[:, model.joints[jid].idx_v]
                if np.linalg.norm(S[:3]) > 1e-12 or abs(np.linalg.norm(S[3:]) - 1.0) > 1e-9:
                    raise EstimatorModelError(
                        f"joint {model.names[jid]!r}: only revolute joints about an axis through "
                        f"the joint origin are supported (motion subspace {S.round(6).tolist()})")
                axis = S[3:] / np.linalg.norm(S[3:])
                axes.append(axis)
                Q = pin.Quaternion.FromTwoVectors(np.array([0.0, 0.0, 1.0]), axis).matrix()
                P = model.jointPlacements[jid]
                C = Q.T @ P.rotation.T @ Q_parent      # parent internal -> this internal, q = 0
                t = Q_parent.T @ P.translation         # joint origin in parent internal coords
                Xm = np.zeros((6, 6))
                Xm[:3, :3] = C
                Xm[:3, 3:] = -C @ skew(t)
                Xm[3:, 3:] = C
                Xf = np.zeros((6, 6))
                Xf[:3, :3] = C
                Xf[3:, :3] = -C @ skew(t)
                Xf[3:, 3:] = C
                Y = model.inertias[jid]
                c = Q.T @ Y.lever
                Ic = Q.T @ Y.inertia @ Q
                Sc = skew(c)
                I6 = np.zeros((6, 6))
                I6[:3, :3] = Y.mass * np.eye(3)
                I6[:3, 3:] = -Y.mass * Sc
                I6[3:, :3] = Y.mass * Sc
                I6[3:, 3:] = Ic - Y.mass * Sc @ Sc
                chain.append(ChainLink(jid, _frozen(Xm), _frozen(Xf), _frozen(I6)))
                Q_parent = Q
            ee = model.frames[arm.ee_frame]
            if int(ee.parentJoint) != arm.joints[-1]:
                raise EstimatorModelError(f"arm {arm.name!r}: the end effector is not on the last joint's link")
            M_sensor = pin.SE3(R, r)
            arms.append(ArmModel(
                name=arm.name, index=k, joints=tuple(arm.joints),
                columns=tuple(range(col, col + arm.n)), A_s=_frozen(A_s),
                sensor_inv=M_sensor.inverse(), axes=_frozen(np.array(axes)),
                unit_twists=tuple(pin.Motion(np.zeros(3), z) for z in axes), chain=tuple(chain),
                ee_point=_frozen(Q_parent.T @ ee.placement.translation)))
            col += arm.n
        if col != robot.n_joints:
            raise EstimatorModelError(f"{robot.name}: {robot.n_joints - col} joint(s) belong to no arm")
        joint_arm = np.concatenate([np.full(a.n, k) for k, a in enumerate(robot.arms)])
        I_s = robot.spacecraft_inertia
        return cls(
            robot=robot, arms=tuple(arms), n_joints=col, joint_arm=_frozen(joint_arm).astype(int),
            mass_s=robot.spacecraft_mass, inertia_s=_frozen(I_s),
            inertia_s_inv=_frozen(np.linalg.inv(I_s)),
            A_s_all=_frozen(np.hstack([a.A_s for a in arms])),
            r_imu=_frozen(robot.r_imu), R_imu=_frozen(robot.R_imu))

    @property
    def n_arms(self) -> int:
        return len(self.arms)

    @property
    def joint_names(self) -> list[str]:
        return self.robot.joint_names

    def data(self) -> "EstimatorData":
        return EstimatorData(self)


@dataclass(slots=True)
class EstimatorData:
    """Scratch space for the per-sample reference forms (:mod:`.torques`). One per thread; never shared."""

    model: EstimatorModel
    pin_data: pin.Data = field(init=False)
    q: np.ndarray = field(init=False)        # full Pinocchio q: base at the origin, identity attitude
    v: np.ndarray = field(init=False)        # base linear velocity kept at zero (see torques.py)
    a: np.ndarray = field(init=False)
    A_tau: np.ndarray = field(init=False)    # (n_joints, 6) last joint_torque_matrix

    def __post_init__(self) -> None:
        pm = self.model.robot.model
        self.pin_data = pm.createData()
        self.q = pin.neutral(pm)
        self.v = np.zeros(pm.nv)
        self.a = np.zeros(pm.nv)
        self.A_tau = np.zeros((self.model.n_joints, 6))


# --- LAPACK without the Python wrappers ----------------------------------------------------------
# ``np.linalg.solve`` spends most of its time on a small system in argument checks (the thruster
# filter's update calls it per IMU sample). This calls the same gufunc with the same arguments,
# so the result is the same bits. numpy's wrapper turns the gufunc's "invalid" floating-point
# signal (singular matrix) into ``LinAlgError``; here it raises ``FloatingPointError`` and the
# numpy function is called again, which then raises exactly as before.
from numpy.linalg import _umath_linalg as _ul  # noqa: E402


def _errstate() -> np.errstate:
    return np.errstate(invalid="raise", over="ignore", divide="ignore", under="ignore")


def solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.linalg.solve(a, b)`` for float64 arrays, ``a`` (m, m), ``b`` (m,) or (m, k)."""
    try:
        with _errstate():
            x: np.ndarray = (_ul.solve1 if b.ndim == 1 else _ul.solve)(a, b, signature="dd->d")
            return x
    except FloatingPointError:
        return np.linalg.solve(a, b)
