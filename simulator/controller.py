"""The robot's flight software, inside the simulator: the paper's capture task, or a thruster
checkout.

- Target: a satellite in a flat spin about the inertial z axis, one grasp point per arm on its
  rim.
- Arms: Jacobian-transpose end-effector tracking. Each end effector blends (quintic) from its
  start onto its moving grasp point over ``approach_s`` and then follows it:
  ``tau = J^T (Kp (x_d - x) + Kd (xdot_d - xdot)) - D qdot``, saturated at the torque limits.
  It reads the joint encoders (angles and drive rates) and the navigation solution of the
  base; J is the end effector's position Jacobian with respect to the arm's own joints.
- Spacecraft: PD on position (inertial) and attitude (SO(3) log), demanded body wrench about
  C, allocated to the thrusters at ``base_rate_hz``.
- Checkout (``task = "checkout"``): the arms hold the positions they start in; probe wrenches
  along and about every body axis, both ways in turn, added to the pose loop's demand, make
  every thruster fire (the way a team checks its thrusters before a manoeuvre). No target is
  near, so no plume keep-out.

"Commanded" efforts are what this module asks for; friction and thruster errors make the
actual efforts differ.
"""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

from robot_description import Robot


class Target:
    """Flat spin about the inertial z axis through ``center``; grasp points on the rim."""

    def __init__(self, cfg, n_arms: int):
        self.center = np.array(cfg.center_m, dtype=float)
        self.radius = float(cfg.radius_m)
        self.omega = float(cfg.spin_rpm) * 2.0 * math.pi / 60.0
        grasp = list(cfg.grasp_deg)
        if len(grasp) < n_arms:
            # arms beyond the listed ones get points spread evenly after the last one
            step = 360.0 / n_arms
            grasp += [grasp[-1] + step * (k + 1) for k in range(n_arms - len(grasp))]
        self.phase = np.radians(grasp[:n_arms])

    def grasp_points(self, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions and velocities (n_arms, 3) of the grasp points, inertial frame; for an
        array of K times, (K, n_arms, 3)."""
        ang = self.phase + self.omega * np.asarray(t, dtype=float)[..., None]
        c, s = self.radius * np.cos(ang), self.radius * np.sin(ang)
        p = np.empty(ang.shape + (3,))
        p[..., 0], p[..., 1], p[..., 2] = c, s, 0.0
        v = np.empty_like(p)
        v[..., 0], v[..., 1], v[..., 2] = -self.omega * s, self.omega * c, 0.0
        return p + self.center, v


def pregrasp_ik(robot: Robot, q: np.ndarray, targets: np.ndarray, iters: int = 200) -> np.ndarray:
    """Joint angles that put each end effector at ``targets`` (p, 3), seeded by ``q``.

    Damped least squares on each arm's own joints (the base stays put); raises if a target is
    out of reach, so a scenario never starts from a silently wrong pose.
    """
    model, data = robot.model, robot.model.createData()
    q = q.copy()
    for _ in range(iters):
        pin.computeJointJacobians(model, data, q)
        pin.updateFramePlacements(model, data)
        worst = 0.0
        for k, arm in enumerate(robot.arms):
            e = targets[k] - data.oMf[arm.ee_frame].translation
            worst = max(worst, float(np.linalg.norm(e)))
            J = pin.getFrameJacobian(model, data, arm.ee_frame, pin.LOCAL_WORLD_ALIGNED)[:3, list(arm.iv)]
            dq = J.T @ np.linalg.solve(J @ J.T + 1e-4 * np.eye(3), e)
            q[list(arm.iq)] += np.clip(dq, -0.2, 0.2)
        if worst < 1e-6:
            return q
    raise ValueError(f"pre-grasp pose out of reach (residual {worst:.3f} m): check target.center_m, "
                     f"target.grasp_deg and controller.standoff_m")


def quintic(t: float, T: float) -> tuple[float, float]:
    """Smooth 0 -> 1 blend and its rate over [0, T]."""
    if t >= T:
        return 1.0, 0.0
    x = t / T
    return x**3 * (10 - 15 * x + 6 * x * x), (30 * x * x - 60 * x**3 + 30 * x**4) / T


class Controller:
    def __init__(self, robot: Robot, cfg, target: Target, limit_fraction: float = 1.0):
        """``limit_fraction``: the commands saturate at this fraction of the joints' torque
        limits (1: at the limits; less leaves the drives headroom for an inner loop)."""
        if not 0.0 < limit_fraction <= 1.0:
            raise ValueError(f"command limit must be a fraction in (0, 1] of the torque limits, got {limit_fraction!r}")
        self.robot, self.cfg, self.target = robot, cfg, target
        self.model, self.data = robot.model, robot.model.createData()
        self.kp, self.kd, self.damp = cfg.kp, cfg.kd, cfg.joint_damping
        self.limit = robot.effort_limit * limit_fraction
        self._neg_limit = -self.limit
        self.x0: np.ndarray | None = None
        self.base_p0: np.ndarray | None = None
        self.base_R0: np.ndarray | None = None
        self.iv = [np.array(a.iv) for a in robot.arms]
        self._nv = robot.model.nv
        self._J = np.zeros((len(robot.arms), 3, self._nv))    # end-effector position Jacobians
        self._x = np.empty((len(robot.arms), 3))
        self._Jf, self._xf = self._J.reshape(-1, self._nv), self._x.reshape(-1)   # flat views of both
        self._Jj = self._Jf[:, 6:]                               # columns of the joints
        self._ee_frames = [a.ee_frame for a in robot.arms]
        p3 = 3 * len(robot.arms)
        self._kp, self._kd = np.full(p3, float(self.kp)), np.full(p3, float(self.kd))
        self._damp = np.full(robot.n_joints, float(self.damp))

    def start(self, q: np.ndarray) -> None:
        """Latch the initial end-effector positions and the base pose to hold."""
        pin.framesForwardKinematics(self.model, self.data, q)
        self.x0 = np.array([self.data.oMf[a.ee_frame].translation for a in self.robot.arms])
        M = pin.XYZQUATToSE3(q[:7])
        self.base_p0, self.base_R0 = M.translation.copy(), M.rotation.copy()

    def desired(self, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """End-effector references and their rates (n_arms, 3), inertial; (K, n_arms, 3) for K times.
        A checkout holds the start positions."""
        if self.cfg.task == "checkout":
            shape = np.shape(t) + self.x0.shape
            return np.broadcast_to(self.x0, shape).copy(), np.zeros(shape)
        g, gd = self.target.grasp_points(t)
        if np.ndim(t) == 0:
            s, sd = quintic(t, self.cfg.approach_s)
        else:
            s, sd = (np.array(c)[:, None, None] for c in zip(*(quintic(x, self.cfg.approach_s) for x in t)))
        return (1 - s) * self.x0 + s * g, sd * (g - self.x0) + s * gd

    def joint_torques(self, t: float, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Motor torque commands (saturated), end-effector positions and their desired values."""
        xd, xdd = self.desired(t)
        tau, x = self.torques(xd, xdd, q, v)
        return tau, x, xd

    def torques(self, xd: np.ndarray, xdd: np.ndarray, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Motor torque commands (saturated) and end-effector positions for references (p, 3).

        All arms at once: each end effector's position Jacobian has zero columns for the other
        arms' joints, so ``J_all^T force_all`` over the stacked arms is each arm's ``J^T force``.
        """
        tau, x = self.torques_flat(np.reshape(xd, -1), np.reshape(xdd, -1), q, v)
        return tau, x.reshape(-1, 3)

    def torques_flat(self, xd: np.ndarray, xdd: np.ndarray, q: np.ndarray,
                     v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`torques` with the references and the returned positions flat, (3 p,)."""
        model, data, J, x = self.model, self.data, self._J, self._x
        pin.computeJointJacobians(model, data, q)      # also runs forward kinematics
        frame_jacobian, placement, lwa = pin.getFrameJacobian, pin.updateFramePlacement, pin.LOCAL_WORLD_ALIGNED
        for k, frame in enumerate(self._ee_frames):
            J[k] = frame_jacobian(model, data, frame, lwa)[:3]
            x[k] = placement(model, data, frame).translation   # oMf as getFrameJacobian computed it
        xf = self._xf
        # gains as arrays and ndarray.dot: the same numbers as scalars and @, fewer dispatch costs
        force = self._kp * (xd - xf) + self._kd * (xdd - self._Jf.dot(v))   # full velocity, base motion included
        tau = force.dot(self._Jj) - self._damp * v[6:]
        return np.minimum(np.maximum(tau, self._neg_limit), self.limit), xf.copy()

    def probe(self, t: float) -> np.ndarray:
        """The probe wrench at time ``t`` (body frame, about C): ``probe_force_n`` along +x, -x, +y,
        -y, +z, -z, then ``probe_moment_nm`` about them, each for ``probe_dwell_s``, cycling; zero
        when both sizes are."""
        w = np.zeros(6)
        force, moment = self.cfg.probe_force_n, self.cfg.probe_moment_nm
        if force or moment:
            k = int(t // self.cfg.probe_dwell_s) % 12
            axis = k // 2
            w[axis] = (1.0 - 2.0 * (k % 2)) * (force if axis < 3 else moment)
        return w

    def base_wrench(self, t: float, q: np.ndarray, v: np.ndarray, M: pin.SE3 | None = None) -> np.ndarray:
        """Demanded thruster wrench (body frame, about C) at time ``t``: holding the initial base
        pose, plus the probe (:meth:`probe`) if any (``M``: the base pose ``q[:7]`` as an SE3, if
        already at hand)."""
        if M is None:
            M = pin.XYZQUATToSE3(q[:7])
        R = M.rotation
        kp_p, kp_r = self.cfg.base_kp
        kd_p, kd_r = self.cfg.base_kd
        v_world = R.dot(v[:3])
        f_world = kp_p * (self.base_p0 - M.translation) - kd_p * v_world
        e_R = pin.log3(self.base_R0.T.dot(R))
        m_body = -kp_r * e_R - kd_r * v[3:6]
        demand = np.concatenate([R.T.dot(f_world), m_body])
        if self.cfg.probe_force_n or self.cfg.probe_moment_nm:
            demand += self.probe(t)
        return demand
