"""Free-floating multibody dynamics in zero gravity, with stick-slip joint friction.

One call of :meth:`Dynamics.step` advances the state by ``dt`` under inputs held over the step
(zero-order hold, as the flight computer applies them):

- integration: classical RK4 in the Lie algebra at the start configuration (Runge-Kutta
  Munthe-Kaas): stage configurations are ``integrate(q0, theta)`` and the stage rate of
  ``theta`` is ``dexp^-1(theta) v``, so the free-flyer stays on SE(3) and the method keeps its
  accuracy (momentum drift ~1e-14 relative over 10 s without friction, see the tests);
- friction: Coulomb + viscous, with real sticking. A joint whose velocity friction can cancel
  within the step is a candidate to stick; for the candidate set S, the friction torque that
  makes ``v_S`` zero at the end of the step is solved from the inverse mass matrix; a joint
  whose required torque exceeds its breakaway level slips instead, with kinetic friction
  opposing its (would-be) motion. Friction is internal, so it never changes the total
  momentum; the friction torque is held over the step and is part of the joint's actual torque.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin


@dataclass
class Friction:
    """Per-joint friction (arrays over the actuated joints, in v order after the base)."""

    coulomb_nm: np.ndarray       # kinetic level
    static_nm: np.ndarray        # breakaway level (>= coulomb)
    viscous_nms: np.ndarray

    @classmethod
    def none(cls, n: int) -> "Friction":
        z = np.zeros(n)
        return cls(z, z.copy(), z.copy())


class Dynamics:
    """Owns the model and scratch data; ``q, v`` are the state, advanced in place by ``step``."""

    def __init__(self, model: pin.Model, friction: Friction, dt: float):
        self.model, self.data = model, model.createData()
        self.friction = friction
        self.dt = dt
        self.nj = model.nv - 6
        self.q = pin.neutral(model)
        self.v = np.zeros(model.nv)
        self.stuck = np.zeros(self.nj, dtype=bool)
        self.tau_friction = np.zeros(self.nj)

    # -- the step ---------------------------------------------------------------------------
    def step(self, base_wrench: np.ndarray, tau_motor: np.ndarray) -> np.ndarray:
        """Advance one step; returns the generalized acceleration at the start of the step.

        ``base_wrench``: thruster wrench on the spacecraft (body frame, force through C, moment
        about C). ``tau_motor``: motor torques of the actuated joints, N m.
        """
        model, data, q0, v0, dt = self.model, self.data, self.q, self.v, self.dt
        tau = np.empty(model.nv)
        tau[:6] = base_wrench
        tau[6:] = tau_motor
        tau[6:] += self._friction(tau)

        def accel(q, v):
            return pin.aba(model, data, q, v, tau)

        def theta_rate(theta, v):
            # dexp^-1(theta) v on the free-flyer block, to first order in theta (theta ~ dt v:
            # the next term is ~1e-9 relative at 1 kHz); revolute joints are Euclidean.
            out = v.copy()
            out[:6] += 0.5 * pin.Motion(theta[:6]).cross(pin.Motion(v[:6])).vector
            return out

        a1 = accel(q0, v0)
        k1q, k1v = v0, a1
        th = 0.5 * dt * k1q
        v2 = v0 + 0.5 * dt * k1v
        k2q, k2v = theta_rate(th, v2), accel(pin.integrate(model, q0, th), v2)
        th = 0.5 * dt * k2q
        v3 = v0 + 0.5 * dt * k2v
        k3q, k3v = theta_rate(th, v3), accel(pin.integrate(model, q0, th), v3)
        th = dt * k3q
        v4 = v0 + dt * k3v
        k4q, k4v = theta_rate(th, v4), accel(pin.integrate(model, q0, th), v4)
        theta = (dt / 6.0) * (k1q + 2.0 * k2q + 2.0 * k3q + k4q)
        self.q = pin.integrate(model, q0, theta)
        self.v = v0 + (dt / 6.0) * (k1v + 2.0 * k2v + 2.0 * k3v + k4v)
        return a1

    # -- friction ---------------------------------------------------------------------------
    def _friction(self, tau_applied: np.ndarray) -> np.ndarray:
        """Friction torques held over the next step, given all applied generalized forces."""
        fr, nj, dt = self.friction, self.nj, self.dt
        vj = self.v[6:]
        tau_f = -fr.coulomb_nm * np.sign(vj) - fr.viscous_nms * vj
        if not fr.static_nm.any():
            self.tau_friction = tau_f
            self.stuck[:] = False
            return tau_f
        model, data = self.model, self.data
        Minv = pin.computeMinverse(model, data, self.q)    # full symmetric matrix in Pinocchio 4
        diag = Minv.diagonal()[6:]
        # candidates: friction at breakaway can stop the joint within this step
        cand = np.abs(vj) <= fr.static_nm * diag * (1.5 * dt)
        cand &= fr.static_nm > 0
        if not cand.any():
            self.tau_friction = tau_f
            self.stuck[:] = False
            return tau_f
        nle = pin.nonLinearEffects(model, data, self.q, self.v)
        Mj = Minv[6:, :]                          # rows of the actuated joints
        a_free = Mj @ (tau_applied - nle)         # joint accelerations without friction
        S = np.flatnonzero(cand)
        slip_dir = np.sign(vj)
        for _ in range(nj + 1):
            if S.size == 0:
                break
            tau_o = -fr.coulomb_nm * slip_dir - fr.viscous_nms * vj
            tau_o[S] = 0.0
            a = a_free + Mj[:, 6:] @ tau_o
            # friction on S that makes v_S(t+dt) = 0: v_S + dt (a_S + Minv_SS f_S) = 0
            rhs = vj[S] / dt + a[S]
            if S.size == 1:
                f_S = -rhs / Minv[6 + S[0], 6 + S[0]]
            else:
                f_S = -np.linalg.solve(Minv[np.ix_(6 + S, 6 + S)], rhs)
            over = np.abs(f_S) > fr.static_nm[S]
            if not over.any():
                tau_f = tau_o
                tau_f[S] = f_S
                break
            # the joint with the largest excess breaks away, in the direction it is pushed
            k = np.argmax(np.abs(f_S) - fr.static_nm[S])
            i = S[k]
            slip_dir[i] = np.sign(vj[i]) if vj[i] != 0 else -np.sign(f_S[k])
            S = np.delete(S, k)
        else:  # pragma: no cover - the loop removes one joint per pass
            raise RuntimeError("friction solve did not converge")
        if S.size == 0:
            tau_f = -fr.coulomb_nm * slip_dir - fr.viscous_nms * vj
        self.stuck[:] = False
        self.stuck[S] = True
        self.tau_friction = tau_f
        return tau_f

    # -- derived quantities (for truth and tests) -------------------------------------------
    def momentum_world(self) -> np.ndarray:
        """Total linear and angular momentum about the inertial origin, inertial frame."""
        pin.computeCentroidalMomentum(self.model, self.data, self.q, self.v)
        h = self.data.hg                       # about the system CoM, world-aligned axes
        com = self.data.com[0]
        lin = np.array(h.linear)
        ang = np.array(h.angular) + np.cross(com, lin)
        return np.concatenate([lin, ang])

    def kinetic_energy(self) -> float:
        return float(pin.computeKineticEnergy(self.model, self.data, self.q, self.v))

