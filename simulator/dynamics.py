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
  The candidate test needs the diagonal of the inverse mass matrix; a constant upper bound of
  it (:func:`minv_diagonal_bound`) rules most steps out without computing it, with the same
  result.

A state that stops being finite (NaN or infinity, from an unphysical robot or input) raises
:class:`DivergenceError` at the step that produced it, naming what diverged; the state is left
at the start of that step.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from simulator.errors import SimulatorError


class DivergenceError(SimulatorError, ValueError):
    """The simulated state stopped being finite: ``what`` names the quantities (and whether NaN
    or infinite), ``t_s`` the simulated time of the state, when known."""

    def __init__(self, what: str, t_s: float | None = None):
        self.what, self.t_s = what, t_s
        at = "" if t_s is None else f" at t = {t_s:.3f} s"
        super().__init__(f"simulation diverged{at}: {what} (check the robot's inertias and the controller gains)")

    def at(self, t_s: float) -> "DivergenceError":
        """The same error, stamped with the simulated time of the state."""
        return DivergenceError(self.what, t_s)


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
    """Owns the model and scratch data; ``q, v`` are the state, advanced in place by ``step``.

    After a step, ``data_start`` holds Pinocchio's quantities at the state the step started
    from, computed by its first ABA call: in particular ``data_start.f[j]``, the spatial force
    that joint ``j`` transmits to its subtree (local frame of ``j``), equal to what RNEA gives
    for ``(q, v, a)`` with the returned acceleration (the truth of the F/T sensors).
    """

    def __init__(self, model: pin.Model, friction: Friction, dt: float,
                 joint_names: list[str] | None = None):
        self.model, self.data = model, model.createData()
        # names of the actuated joints in v order, for error messages (default: the URDF's)
        self.joint_names = list(joint_names) if joint_names is not None else [
            model.names[j] for j in range(2, model.njoints) if model.joints[j].idx_v >= 6
            for _ in range(model.joints[j].nv)]
        self.data_start = model.createData()
        self.dt = dt
        self._reach = 1.5 * dt          # a joint this close (in time) to stopping may stick
        self._minv_bound = minv_diagonal_bound(model)
        self.friction = friction
        self.nj = model.nv - 6
        self.q = pin.neutral(model)
        self.v = np.zeros(model.nv)
        self.stuck = np.zeros(self.nj, dtype=bool)
        self._any_stuck = False
        self.tau_friction = np.zeros(self.nj)
        self.contacts = None            # simulator.contact.Contacts: forces on the end effectors
        self.steps = 0                  # steps taken (the contacts' clock)
        # step sizes as arrays: array * array is cheaper than scalar * array on tiny arrays, as
        # ndarray.dot is than @ (the same BLAS call, without matmul's dispatch)
        self._h2, self._h = np.full(model.nv, 0.5 * dt), np.full(model.nv, dt)
        # RK4 weights (dt/6) [1 2 2 1] on the stacked stage rates [kq1..kq4, kv1..kv4]
        c1 = dt / 6.0
        self._weights = np.zeros((2, 8))
        self._weights[0, :4] = self._weights[1, 4:] = (c1, 2.0 * c1, 2.0 * c1, c1)

    @property
    def friction(self) -> Friction:
        """The friction levels, as read-only copies: assign a new :class:`Friction` to change them."""
        return self._friction

    @friction.setter
    def friction(self, fr: Friction) -> None:
        levels = []
        for x in (fr.coulomb_nm, fr.static_nm, fr.viscous_nms):
            x = np.array(x, dtype=float)
            x.setflags(write=False)
            levels.append(x)
        self._friction = Friction(*levels)
        # the same levels as Python floats, for the per-step friction law
        self._levels = tuple(x.tolist() for x in levels)
        self._may_stick = any(self._levels[1])
        # joint speeds above which a joint cannot be a candidate to stick whatever the
        # configuration: breakaway x bound of (M^-1)_ii x reach (x 1 + 1e-6, far above rounding)
        self._sure_slip = [0.0 if s == 0.0 else s * u * (1.0 + 1e-6) * self._reach
                           for s, u in zip(self._levels[1], self._minv_bound)]

    # -- the step ---------------------------------------------------------------------------
    def step(self, base_wrench: np.ndarray, tau_motor: np.ndarray) -> np.ndarray:
        """Advance one step; returns the generalized acceleration at the start of the step.

        ``base_wrench``: thruster wrench on the spacecraft (body frame, force through C, moment
        about C). ``tau_motor``: motor torques of the actuated joints, N m.
        """
        model, data, q0, v0 = self.model, self.data, self.q, self.v
        aba, integrate, q_rate = pin.aba, pin.integrate, _q_rate
        h2, h = self._h2, self._h
        tau = np.concatenate((base_wrench, tau_motor))
        fext = self.contacts.fext(self.steps * self.dt, self.data_start, q0) if self.contacts else None
        tau[6:] += self._friction_torques(tau, fext)
        # the external forces (held over the step, in the joints' axes) go with tau into each ABA
        inputs = (tau,) if fext is None else (tau, fext)
        a1 = aba(model, self.data_start, q0, v0, *inputs)
        if fext is not None:
            self._transmitted(fext)
        th = h2 * v0
        v2 = v0 + h2 * a1
        k2q = q_rate(th, v2)
        k2v = aba(model, data, integrate(model, q0, th), v2, *inputs)
        th = h2 * k2q
        v3 = v0 + h2 * k2v
        k3q = q_rate(th, v3)
        k3v = aba(model, data, integrate(model, q0, th), v3, *inputs)
        th = h * k3q
        v4 = v0 + h * k3v
        k4q = q_rate(th, v4)
        k4v = aba(model, data, integrate(model, q0, th), v4, *inputs)
        # (dt/6) (k1 + 2 k2 + 2 k3 + k4) for theta and v at once
        rates = self._weights.dot(np.array((v0, k2q, k3q, k4q, a1, k2v, k3v, k4v)))
        v = v0 + rates[1]
        # every stage feeds v, so a finite v means a finite step; one dot product, not a scan
        if not math.isfinite(v.dot(v)):
            raise self._divergence(tau, v)
        self.q = integrate(model, q0, rates[0])        # (indexing: unpacking a 2-row array costs more)
        self.v = v
        self.steps += 1
        return a1

    def _transmitted(self, fext: list) -> None:
        """``data_start.f`` as RNEA gives it with the external forces: ABA leaves them out of the
        force each joint transmits, the sum over its subtree of inertial minus external forces."""
        model, d = self.model, self.data_start
        for c in range(1, model.njoints):
            fc = fext[c]
            if not fc.vector.any():
                continue
            j = c
            while j > 0:
                d.f[j] -= d.oMi[j].actInv(d.oMi[c].act(fc))
                j = model.parents[j]

    def _divergence(self, tau: np.ndarray, v: np.ndarray) -> DivergenceError:
        """What went non-finite: the inputs if they were (the cause), else the velocities."""
        names = ["the thruster force"] * 3 + ["the thruster moment"] * 3 + [
            f"the motor torque of joint {n}" for n in self.joint_names]
        x = tau
        if all(math.isfinite(e) for e in tau.tolist()):
            names = ["spacecraft linear velocity"] * 3 + ["spacecraft angular velocity"] * 3 + [
                f"joint {n} velocity" for n in self.joint_names]
            x = v
        values = x.tolist()
        bad = [i for i, e in enumerate(values) if not math.isfinite(e)]
        kind = "NaN" if any(math.isnan(values[i]) for i in bad) else "infinite"
        if x is v and len(bad) == len(values):
            what = f"every velocity (spacecraft and joints) is {kind}"
        else:
            items = list(dict.fromkeys(names[i] for i in bad))      # in order, once each
            what = f"{', '.join(items)} {'is' if len(items) == 1 else 'are'} {kind}"
        return DivergenceError(what + "".join(f"; {s}" for s in self._suspect_bodies()))

    def _suspect_bodies(self) -> list[str]:
        """Bodies whose mass or rotational inertia no rigid body has (the usual cause)."""
        out = []
        model = self.model
        for j in range(1, model.njoints):
            Y = model.inertias[j]
            body = "the spacecraft" if j == 1 else f"the body joint {self.joint_names[model.joints[j].idx_v - 6]} moves"
            I = np.array(Y.inertia)
            if not (math.isfinite(Y.mass) and np.isfinite(I).all()):
                out.append(f"{body} has a non-finite mass or inertia")
            elif Y.mass <= 0.0:
                out.append(f"{body} has mass {Y.mass:g} kg")
            elif np.linalg.eigvalsh(I).min() < 0.0:
                out.append(f"{body} has an inertia that is not positive semi-definite")
        return out

    # -- friction ---------------------------------------------------------------------------
    def _friction_torques(self, tau_applied: np.ndarray, fext: list | None = None) -> np.ndarray:
        """Friction torques held over the next step, given all applied generalized forces and the
        external forces ``fext`` (per joint, local frames; None: none).

        Sets ``tau_friction`` and ``stuck``. ``stuck`` is replaced, never written in place, when
        the set of stuck joints changes (the simulation keeps references to it as truth rows).
        Per-joint scalars in Python floats: numpy calls on 2-9 element arrays cost more.
        """
        coulomb, static, viscous = self._levels
        vl = self.v.tolist()[6:]
        # kinetic friction opposing the motion: -coulomb sign(v) - viscous v
        tau_f = [-c * ((v > 0.0) - (v < 0.0)) - d * v for c, d, v in zip(coulomb, viscous, vl)]
        S = near = None
        if self._may_stick:
            for v, w in zip(vl, self._sure_slip):    # (a loop: any() over a generator costs 2x)
                if -w <= v <= w:
                    near = True
                    break
        if near:
            Minv = pin.computeMinverse(self.model, self.data, self.q)   # full symmetric matrix in Pinocchio 4
            # candidates: friction at breakaway can stop the joint within this step
            diag, reach = Minv.diagonal().tolist(), self._reach
            S = [i for i, v in enumerate(vl) if abs(v) <= static[i] * diag[i + 6] * reach and static[i] > 0]
            if S:
                if fext is not None:      # their generalized forces: -rnea(q, 0, 0, fext) in zero gravity
                    z = np.zeros(self.model.nv)
                    tau_applied = tau_applied - pin.rnea(self.model, self.data, self.q, z, z, fext)
                tau_f, S = self._stick(Minv, tau_applied, vl, S)
        if S:
            stuck = np.zeros(self.nj, dtype=bool)
            stuck[S] = True
            self.stuck, self._any_stuck = stuck, True
        elif self._any_stuck:
            self.stuck, self._any_stuck = np.zeros(self.nj, dtype=bool), False
        self.tau_friction = tau_f = np.array(tau_f)
        return tau_f

    def _stick(self, Minv: np.ndarray, tau_applied: np.ndarray, vl: list,
               S: list[int]) -> tuple[list[float], list[int]]:
        """Friction torques and the joints that stay stuck, for the candidate set ``S``."""
        dt = self.dt
        coulomb, static, viscous = self._levels
        nle = pin.nonLinearEffects(self.model, self.data, self.q, self.v)
        Mjj = Minv[6:, 6:]
        a_free = Minv[6:, :].dot(tau_applied - nle)     # joint accelerations without friction
        Ml = Mjj.tolist()
        sgn = [(v > 0.0) - (v < 0.0) for v in vl]        # np.sign
        slip_dir = list(sgn)
        while S:                                  # removes one joint per pass
            tau_o = [-c * s - d * v for c, s, d, v in zip(coulomb, slip_dir, viscous, vl)]
            for i in S:
                tau_o[i] = 0.0
            a = (a_free + Mjj.dot(np.array(tau_o))).tolist()
            # friction on S that makes v_S(t+dt) = 0: v_S + dt (a_S + Minv_SS f_S) = 0
            f_S = [-x for x in _solve_spd(Ml, S, [vl[i] / dt + a[i] for i in S])]
            excess = [abs(f) - static[i] for f, i in zip(f_S, S)]
            worst = max(excess)
            if worst <= 0.0:
                for i, f in zip(S, f_S):
                    tau_o[i] = f
                return tau_o, S
            # the joint with the largest excess breaks away, in the direction it is pushed
            k = excess.index(worst)
            i = S[k]
            slip_dir[i] = sgn[i] if vl[i] != 0 else -((f_S[k] > 0.0) - (f_S[k] < 0.0))
            del S[k]
        return [-c * s - d * v for c, s, d, v in zip(coulomb, slip_dir, viscous, vl)], S

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


def minv_diagonal_bound(model: pin.Model) -> list[float]:
    """Upper bounds, valid in every configuration, of the diagonal of the inverse mass matrix
    over the actuated joints (v order after the base); ``inf`` where there is none.

    For a revolute joint i between bodies A (its parent) and B, with unit axis n:
    ``(M^-1)_ii <= n^T I_A^-1 n + n^T I_B^-1 n``, ``I`` the rotational inertias about the
    bodies' centres of mass. Proof: ``1 / (M^-1)_ii = min x^T M x over x_i = 1`` (twice the
    least kinetic energy with the joint turning at unit rate); the energy is at least that of
    A and B alone, which is at least that of the two as free bodies joined by the joint only:
    ``xi^T (G_A^-1 + G_B^-1)^-1 xi`` (G the spatial inertias at the joint, xi = [0; n] the
    relative twist), and by Cauchy-Schwarz this is at least ``1 / (xi^T G_A^-1 xi + xi^T
    G_B^-1 xi)``, where ``xi^T G^-1 xi = n^T I^-1 n``: a free body's angular acceleration
    under a unit couple about n. Massless bodies and other joint types get no bound.
    """
    axes = {"JointModelRX": (1.0, 0.0, 0.0), "JointModelRY": (0.0, 1.0, 0.0), "JointModelRZ": (0.0, 0.0, 1.0)}
    bound = [float("inf")] * (model.nv - 6)
    for j in range(2, model.njoints):
        jm = model.joints[j]
        name = jm.shortname()
        if jm.nv != 1 or jm.idx_v < 6:
            continue
        if name in axes:
            n = np.array(axes[name])
        elif name == "JointModelRevoluteUnaligned":
            n = np.array(jm.extract().axis, dtype=float)
            n /= np.linalg.norm(n)
        else:
            continue
        total = 0.0
        for I, axis in ((model.inertias[model.parents[j]].inertia, model.jointPlacements[j].rotation @ n),
                        (model.inertias[j].inertia, n)):
            if model.parents[j] == 0 or np.linalg.eigvalsh(I).min() <= 0.0:
                total = float("inf")
                break
            total += float(axis @ np.linalg.solve(I, axis))
        bound[jm.idx_v - 6] = total
    return bound


def _q_rate(th: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rate of the Lie-algebra coordinate theta: dexp^-1(theta) v on the free-flyer block, to
    first order in theta (theta ~ dt v: the next term is ~1e-9 relative at 1 kHz); revolute
    joints are Euclidean. ``v + 0.5 * (theta x v)`` for motions [linear; angular], written out
    in floats (two pin.Motion objects per stage cost more than the rest of the stage)."""
    a0, a1, a2, w0, w1, w2 = th.tolist()[:6]
    out = v.tolist()
    b0, b1, b2, u0, u1, u2 = out[:6]
    out[0] = b0 + 0.5 * ((w1 * b2 - w2 * b1) + (a1 * u2 - a2 * u1))
    out[1] = b1 + 0.5 * ((w2 * b0 - w0 * b2) + (a2 * u0 - a0 * u2))
    out[2] = b2 + 0.5 * ((w0 * b1 - w1 * b0) + (a0 * u1 - a1 * u0))
    out[3] = u0 + 0.5 * (w1 * u2 - w2 * u1)
    out[4] = u1 + 0.5 * (w2 * u0 - w0 * u2)
    out[5] = u2 + 0.5 * (w0 * u1 - w1 * u0)
    return np.array(out)


def _solve_spd(A: list[list[float]], S: list[int], b: list[float]) -> list[float]:
    """x with A[S, S] x = b for a symmetric positive definite A (nested lists), by Gaussian
    elimination without pivoting (stable for SPD) in Python floats: for these few unknowns
    numpy's LAPACK call costs more than the friction step around it."""
    if len(S) == 1:
        return [b[0] / A[S[0]][S[0]]]
    M = [[A[i][j] for j in S] for i in S]
    x = list(b)
    n = len(S)
    for p in range(n):
        for r in range(p + 1, n):
            f = M[r][p] / M[p][p]
            for c in range(p + 1, n):
                M[r][c] -= f * M[p][c]
            x[r] -= f * x[p]
    for p in range(n - 1, -1, -1):
        s = x[p]
        for c in range(p + 1, n):
            s -= M[p][c] * x[c]
        x[p] = s / M[p][p]
    return x
