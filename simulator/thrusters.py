"""Reaction-control thrusters: layout, allocation with a keep-out cone, PWPFM valves, errors.

Frames: positions and force directions are in the spacecraft body frame; the wrench of the set
is referred to C (the body origin), force through C and moment about C.

Pipeline each control cycle: demanded body wrench -> allocation (non-negative thrust per
thruster, thrusters whose plume would reach the target disabled) -> "commanded" wrench
``B u``. Each millisecond: PWPFM turns every thruster's demand into valve on/off -> the actual
force of an open valve differs from nominal by gain (scatter, thermal, tank pressure,
degradation), bias and misalignment.
"""
from __future__ import annotations

import math

import numpy as np
import scipy
from scipy.optimize import nnls

from robot_description.thrusters import LAYOUTS, ThrusterLayout, wrench_matrix

# The layout (positions, directions, max thrust; named tables such as "ring18") is robot data,
# shared with the gateway's estimator: robot_description/thrusters.py.
Layout = ThrusterLayout
__all__ = ["LAYOUTS", "Layout", "wrench_matrix", "Allocator", "PWPFM", "ThrusterErrors"]

_nnls_routine = None
if scipy.__version__ == "1.17.1":   # the pinned scipy: the compiled routine behind
    # scipy.optimize.nnls, called directly without the wrapper's argument checks (the
    # allocation runs at every base-control step); any other version uses the public function
    from scipy.optimize._slsqplib import nnls as _nnls_routine


class Allocator:
    """Demanded body wrench -> thrust per thruster in [0, max], plumes kept off the target.

    Non-negative least squares on ``[B; eps I] u = [w; 0]`` over the allowed thrusters, then
    scaled down as a whole if any thruster would exceed ``limit`` of its maximum (keeps the
    wrench's direction; ``limit`` < 1 leaves an inner loop thrust to correct with). A thruster
    is disallowed when its exhaust (minus its force direction) points within ``keepout_deg`` +
    the target's angular radius of the line to the target centre.
    """

    def __init__(self, layout: Layout, keepout_deg: float, eps: float = 1e-3, limit: float = 1.0):
        if not (isinstance(limit, (int, float)) and 0 < limit <= 1):
            raise ValueError(f"thrust limit must be a fraction in (0, 1], got {limit!r}")
        self.layout = layout
        self.limit = float(limit)
        self.B = layout.B
        self.keepout = math.radians(keepout_deg)
        self.eps = eps
        self._systems: dict[bytes, tuple] = {}     # allowed set -> (idx, scale, A, zeros)

    def allowed(self, R_world_body: np.ndarray, p_world: np.ndarray,
                target_center: np.ndarray, target_radius: float) -> np.ndarray:
        to_target = (target_center - p_world) - self.layout.pos_m.dot(R_world_body.T)
        dist = np.sqrt((to_target * to_target).sum(axis=1))
        # exhaust direction (minus the force direction) . line to the target
        cosang = -(to_target.dot(R_world_body) * self.layout.dir).sum(axis=1) / dist
        half = self.keepout + np.arcsin(np.minimum(target_radius / dist, 1.0))
        return cosang < np.cos(half)

    def allocate(self, wrench: np.ndarray, allowed: np.ndarray) -> np.ndarray:
        u = np.zeros(self.layout.n)
        key = allowed.tobytes()
        if key not in self._systems:                   # the allowed set rarely changes
            idx = np.flatnonzero(allowed)
            scale = self.layout.max_n[idx]
            A = self.B[:, idx] * scale                 # unknowns: fraction of max thrust
            A = np.vstack([A, self.eps * np.eye(idx.size)])
            self._systems[key] = (idx, scale, A, np.zeros(idx.size))
        idx, scale, A, zeros = self._systems[key]
        if idx.size == 0 or not np.count_nonzero(wrench):
            return u
        b = np.concatenate([wrench, zeros])
        if _nnls_routine is None:
            x, _ = nnls(A, b, maxiter=50 * idx.size)
        else:                                          # A, b: C-contiguous float64, finite
            x, _, info = _nnls_routine(A, b, 50 * idx.size)
            if info == 3:
                raise RuntimeError("Maximum number of iterations reached.")   # as nnls() does
        peak = x.max()
        if peak > self.limit:
            x /= peak / self.limit
        u[idx] = x * scale
        return u


class PWPFM:
    """Pulse-width pulse-frequency modulators, one per thruster, updated every ``dt``.

    A first-order filter (gain ``km``, time constant ``tau_s``) of the error between the demand
    (fraction of max thrust) and the valve state drives a Schmitt trigger (on above ``u_on``,
    off below ``u_off``); a valve once opened stays open at least ``min_on_s`` (the minimum
    impulse bit). Over time the duty cycle follows the demand.
    """

    def __init__(self, n: int, dt: float, km: float, tau_s: float, u_on: float, u_off: float,
                 min_on_s: float):
        self.dt, self.km, self.u_on, self.u_off = dt, km, u_on, u_off
        self.alpha = dt / tau_s
        self.min_on = max(1, round(min_on_s / dt))
        self.f = np.zeros(n)
        self.on = np.zeros(n, dtype=bool)
        self.on_steps = np.zeros(n, dtype=int)

    def step(self, demand_frac: np.ndarray) -> np.ndarray:
        self.f += self.alpha * (self.km * (demand_frac - self.on) - self.f)
        turn_on = ~self.on & (self.f > self.u_on)
        turn_off = self.on & (self.f < self.u_off) & (self.on_steps >= self.min_on)
        self.on = (self.on | turn_on) & ~turn_off
        self.on_steps = np.where(self.on, self.on_steps + 1, 0)
        return self.on

    def run(self, demand_frac: np.ndarray, steps: int) -> np.ndarray:
        """``steps`` calls of :meth:`step` with the same demand, at once: valve states (steps, n).

        Between two valve switches the filter input is constant, so after m updates the filter
        is ``F(m) = c + r^m (f - c)`` (``c = km (demand - on)``, ``r = 1 - dt/tau``), monotonic
        in m: whether a thruster switches within the chunk is decided by ``F`` at the ends of
        the steps where it may switch. For those that do (a few), the closed form is stepped
        through the chunk, segment by segment. The same valve sequence as :meth:`step`; the
        filter state equal to rounding (``r^m`` instead of m repeated updates). In Python
        floats: for some twenty thrusters, cheaper than numpy calls.
        """
        L = steps
        if getattr(self, "_rp_len", 0) != L:
            self._rp = ((1.0 - self.alpha) ** np.arange(L + 1, dtype=float)).tolist()
            self._rp_len = L
        rp, km, u_on, u_off, min_on = self._rp, self.km, self.u_on, self.u_off, self.min_on
        r1, rL = rp[1], rp[L]
        f_new, on_new, cnt_new, switching = [], [], [], []
        for i, (d, o, f0, n_on) in enumerate(zip(demand_frac.tolist(), self.on.tolist(), self.f.tolist(),
                                                 self.on_steps.tolist())):
            c = km * (d - o)
            x = c + rL * (f0 - c)                        # after the last update, if no switch
            if o:                                        # may close once open min_on steps
                lo = max(1, min_on - n_on + 1)
                switches = lo <= L and (x < u_off or c + rp[lo] * (f0 - c) < u_off)
            else:
                switches = x > u_on or c + r1 * (f0 - c) > u_on
            if switches:
                col = []
                m = 0                                    # updates since the segment started
                for _ in range(L):
                    m += 1
                    x = c + rp[m] * (f0 - c)
                    if o:                                # open for n_on + m - 1 steps before this one
                        if x < u_off and n_on + m - 1 >= min_on:
                            o, n_on, f0, m = False, 0, x, 0
                            c = km * (d - o)
                    elif x > u_on:
                        o, n_on, f0, m = True, 1, x, 0
                        c = km * (d - o)
                    col.append(o)
                switching.append((i, col))
                n_on += m
            else:
                n_on += L
            f_new.append(x)
            on_new.append(o)
            cnt_new.append(n_on if o else 0)
        valves = np.empty((L, len(f_new)), dtype=bool)
        valves[:] = self.on
        for i, col in switching:
            valves[:, i] = col
        self.f, self.on, self.on_steps = np.array(f_new), np.array(on_new), np.array(cnt_new)
        return valves


class ThrusterErrors:
    """What an open valve really delivers: per-thruster gain, bias and misalignment.

    gain = (1 + scatter) * pressure factor * (1 + thermal_coeff * (T - T0)) * degradation;
    the chamber warms while firing and cools towards T0.
    """

    def __init__(self, layout: Layout, cfg, rng: np.random.Generator, dt: float):
        n = layout.n
        self.layout, self.dt = layout, dt
        self.scatter = 1.0 + cfg.gain_sigma * rng.standard_normal(n)
        self.bias_n = cfg.bias_sigma_n * rng.standard_normal(n)
        self.pressure = cfg.pressure_factor
        self.thermal = cfg.thermal_coeff_per_k
        self.heating = cfg.heating_k_per_s
        self.cool = dt / cfg.cooling_tau_s
        self.dT = np.zeros(n)
        self.degrade = np.ones(n)          # set by scenario degradations
        self.stuck = np.zeros(n, dtype=int)  # 0 normal, -1 stuck closed, +1 stuck open
        # misalignment: rotate each direction by a small random rotation
        ang = np.radians(cfg.misalign_deg) * rng.standard_normal((n, 3))
        self.dir_actual = np.array([_rotvec(a) @ d for a, d in zip(ang, layout.dir)])
        self.B_actual = wrench_matrix(layout.pos_m, self.dir_actual)

    def run(self, commanded: np.ndarray, degrade: np.ndarray | None = None,
            stuck: np.ndarray | None = None, leak: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """A chunk of L steps at once: (valves (L, n) after stuck valves, thrust (L, n) in N).

        ``commanded``: (L, n) PWPFM valve states; ``degrade``/``stuck``: (L, n) per-step
        degradation factors and stuck states, or None for the current ones; ``leak`` (L, n): the
        fraction of its thrust a closed valve still delivers (a leaking seat), or None. The thermal state
        follows ``dT <- dT + heating dt valve - (dt / cooling_tau) dT`` step by step, evaluated
        in closed form over the chunk (a linear recurrence with a known input).
        """
        L = len(commanded)
        v = commanded.copy()
        if stuck is not None:
            v[stuck < 0] = False
            v[stuck > 0] = True
        elif self.stuck.any():
            v[:, self.stuck < 0] = False
            v[:, self.stuck > 0] = True
        if getattr(self, "_chunk_len", 0) != L:
            r = 1.0 - self.cool
            e = np.arange(L + 1)[:, None] - np.arange(L)[None, :] - 1       # j - 1 - i
            self._Pin = np.where(e >= 0, r ** np.maximum(e, 0), 0.0) * (self.heating * self.dt)
            self._Pfree = (r ** np.arange(L + 1, dtype=float))[:, None]
            self._chunk_len = L
        dT = self._Pfree * self.dT + self._Pin.dot(v)                # (L + 1, n): dT before step j
        gain = self.scatter * self.pressure * (1.0 + self.thermal * dT[:L])
        gain *= self.degrade if degrade is None else degrade
        f = v * (self.layout.max_n * gain + self.bias_n)
        if leak is not None:
            f = f + ~v * leak * (self.layout.max_n * gain)
        self.dT = dT[L]
        return v, f

    def valves(self, commanded: np.ndarray) -> np.ndarray:
        v = commanded.copy()
        v[self.stuck < 0] = False
        v[self.stuck > 0] = True
        return v

    def thrust(self, valves: np.ndarray) -> np.ndarray:
        """Thrust magnitude of each thruster this step (N), and update the thermal state."""
        gain = self.scatter * self.pressure * (1.0 + self.thermal * self.dT) * self.degrade
        f = valves * (self.layout.max_n * gain + self.bias_n)
        self.dT += self.heating * self.dt * valves - self.cool * self.dT
        return f


def tilted(direction: np.ndarray, angle_deg: float) -> np.ndarray:
    """A thruster's unit ``direction`` tilted by ``angle_deg`` towards the body axis most
    perpendicular to it (the first of x, y, z on a tie): the nozzle knocked askew, a
    ``[[degrade]] thruster_misalign``. The tilt's plane is fixed by the direction alone, so a
    scenario states it with one number and a test knows where the thrust went."""
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    e = np.eye(3)[int(np.argmin(np.abs(d)))]
    k = np.cross(d, e)
    return _rotvec(np.radians(angle_deg) * k / np.linalg.norm(k)) @ d


def _rotvec(a: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(a))
    if th < 1e-15:
        return np.eye(3)
    k = a / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K
