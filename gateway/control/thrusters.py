"""The thruster loop of the compensator: the outer loop's commanded wrench in, valve commands out.

The flight software (the outer loop) commands a body wrench ``w`` each base period (the
``THRUSTER_CMD`` frames of the spacecraft bus: force through C, moment about C). The valves deliver
``sum_i valve_i(t) W_i``, where ``W_i`` is what valve ``i`` really exerts while open: its nominal
wrench (the layout: thrust along the nominal direction at the nominal position) off by gain
(scatter, pressure, heating), misalignment and bias. The gateway's thruster filter learns every
``W_i`` live (:mod:`gateway.estimator.thrusters`). This loop uses them for the two things the
flight software does with the nominal ones:

- **allocation**: duty cycles ``u`` in [0, 1] with ``sum_i u_i W_i = w`` (non-negative least
  squares on ``[W^T; eps I] u = [w; 0]`` over the usable valves, scaled down as a whole when a duty
  would exceed 1, the least squares bounded to [0, 1] instead: the smallest error in ``w``, flag
  ``saturated``; the nominal allocation scales down as the flight software does, keeping the
  direction). A valve that the allocation on the nominal wrenches would not fire either and that
  would run below ``min_duty`` is left closed: with the minimum on-time, such a valve pulses far
  slower than the band the spacecraft responds to (4 ms pulses at 2 % duty: 5 Hz), and its
  sparse 100 N pulses add more error there than the newton or two of misalignment they would
  correct (measured, docs/control.md);
- **valve timing**: per valve a first-order sigma-delta modulator on its duty, with the minimum
  on-time of the valves (the minimum impulse bit): the accumulated impulse of each valve stays
  within one minimum pulse of ``u_i W_i`` integrated, so the delivered wrench follows ``w`` in
  the band the spacecraft responds to.

Safety (:class:`ThrusterCompensator`):

- **fallback to the nominal allocation**: no learned wrenches yet, an estimate that is not good
  (``good`` false, a flag, a non-finite value) or none newer than ``stale_s`` behind the step being
  commanded: the same allocation and timing on the NOMINAL wrenches, from the next valve command
  on (``closed`` false, the reason in ``flags``); closing again takes ``resume_good`` good
  estimates in a row, the wrenches then ramp from nominal to learned under the rate limit;
- **magnitude and rate limits**: the wrench used for a valve differs from its nominal one by at
  most ``max_deviation`` of its nominal thrust (force) and of nominal thrust times the layout's
  largest lever arm (moment), and moves at most ``max_rate_per_s`` of that scale per second
  (flags ``limited:magnitude``, ``limited:rate``); a valve the filter has not learned (force
  uncertainty above ``learned_sigma`` of its thrust) keeps its nominal wrench;
- **faults are never amplified**: a thruster the gateway's fault detector names (an alert of rule
  ``thruster-fault``) is never commanded open, closed loop or not, until the detector clears it
  (flag ``fault:thruster<i>``); the gateway's ``fault:thrusters`` flag with no thruster named
  opens the loop; thrusters outside the flight software's keep-out mask are never used.

Every transition is recorded in :attr:`ThrusterCompensator.events` (for the service's alerts), as
:class:`gateway.control.joints.LoopEvent` with ``arm`` = ``thrusters``. Pure: no I/O, no clock;
times are the sensor times of the estimates and commands.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import lsq_linear, nnls

from drivers.samples import ThrusterCommand
from gateway.control.joints import LoopEvent
from gateway.control.messages import ControlError, ThrusterValves, ValveWrenches
from gateway.efforts import Alert

LOOP = "thrusters"                    # the loop's name in events and alerts
FAULT_RULE = "thruster-fault"         # gateway.estimator.fdi.RULE: the fault detector's alerts
FAULT_CLEARED = 4.0                   # its evidence "type" of a clearing (fdi.TYPES.index("cleared"))
KNOWN_FAULT_FLAG = "fault:thrusters"  # the efforts' flag while a thruster fault is active


@dataclass(frozen=True)
class ThrusterLoopSettings:
    """The thruster loop's limits (every one explained in docs/control.md)."""

    max_deviation: float = 0.25     # |used - nominal| <= this of the valve's thrust (force), x lever arm (moment)
    max_rate_per_s: float = 1.0     # the used wrench moves at most this of that scale per second
    learned_sigma: float = 0.10     # a valve's force uncertainty above this of its thrust: nominal wrench
    stale_s: float = 0.02           # no good estimate this recent behind a valve command: nominal allocation
    resume_good: int = 5            # good estimates in a row to close the loop again
    eps: float = 1e-3               # the allocation's regularisation (as the flight software's)
    min_duty: float = 0.02          # closed loop: a valve the nominal allocation also leaves below this: not fired

    def __post_init__(self):
        if not (isinstance(self.min_duty, (int, float)) and not isinstance(self.min_duty, bool)
                and 0 <= self.min_duty < 1):
            raise ControlError(f"thruster loop: min_duty must be a fraction in [0, 1), got {self.min_duty!r}")
        for name in ("max_deviation", "max_rate_per_s", "learned_sigma", "stale_s", "eps"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
                raise ControlError(f"thruster loop: {name} must be a finite number > 0, got {v!r}")
        v = self.resume_good
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise ControlError(f"thruster loop: resume_good must be an integer >= 1, got {v!r}")


class SigmaDelta:
    """Valve timing: per valve a first-order sigma-delta modulator on its duty, with a minimum
    on-time of ``min_on`` steps. ``acc_i`` is the impulse valve ``i`` owes (steps of full
    opening): each step it gains ``u_i`` and loses 1 while open. A closed valve opens when it owes
    half a minimum pulse; an open one stays open ``min_on`` steps, then while it owes half a step.
    The debt stays within about one minimum pulse, so over any window the valve delivers its
    duty's impulse to within one pulse."""

    def __init__(self, n: int, min_on: int = 1):
        if n < 1 or min_on < 1:
            raise ControlError("valve timing: at least one valve and a minimum on-time of one step")
        self.n, self.min_on = n, int(min_on)
        self.acc = np.zeros(n)
        self.on = np.zeros(n, dtype=bool)
        self.on_steps = np.zeros(n, dtype=int)

    def step(self, duty: np.ndarray, usable: np.ndarray) -> np.ndarray:
        """The valves (n,) bool of one step for duties ``duty`` (n,) in [0, 1]; a valve not
        ``usable`` closes at once (minimum on-time or not) and owes nothing."""
        acc = self.acc + duty
        keep = self.on & (self.on_steps < self.min_on)
        opens = ~self.on & (acc >= 0.5 * self.min_on)
        stays = self.on & ~keep & (acc >= 0.5)
        on = (keep | opens | stays) & usable & (duty > 0)
        acc = np.where(on, acc - 1.0, acc)
        # a valve with nothing to deliver owes nothing (no pulse left over from an older demand);
        # the debt is bounded either way (a duty of 1 on a valve held closed)
        acc = np.where(usable & (duty > 0), np.clip(acc, -self.min_on, self.min_on), np.minimum(acc, 0.0))
        self.acc = acc
        self.on_steps = np.where(on, self.on_steps + 1, 0)
        self.on = on
        return on.copy()


def mask_bits(mask: int, n: int) -> np.ndarray | None:
    """A bit mask (bit i = thruster i) -> (n,) bool; a negative one (none) -> None."""
    if mask < 0:
        return None
    return ((int(mask) >> np.arange(n)) & 1).astype(bool)


class ThrusterCompensator:
    """Allocation and valve timing on the gateway's learned per-valve wrenches (module docstring).

    ``nominal`` (n, 6): each valve's nominal wrench at full thrust (``ThrusterLayout.nominal_wrenches``),
    ``max_n`` (n,) its nominal thrust (N), ``lever_m`` the layout's largest lever arm (m),
    ``min_on`` the valves' minimum on-time in steps. Feed it the outer loop's commanded wrench
    (:meth:`observe` a :class:`ThrusterCommand`, or :meth:`demand`), the learned wrenches
    (:meth:`estimate` a :class:`ValveWrenches`) and the fault detector's alerts (:meth:`alert`),
    and ask each step for the valves (:meth:`valves`). ``enabled=False``: always the nominal
    allocation (the same path; the baseline of the compensation).
    """

    def __init__(self, nominal, max_n, *, lever_m: float, min_on: int = 1,
                 settings: ThrusterLoopSettings | None = None, enabled: bool = True):
        self.settings = settings or ThrusterLoopSettings()
        self.enabled = enabled
        W0 = np.asarray(nominal, dtype=float)
        fmax = np.asarray(max_n, dtype=float)
        if W0.ndim != 2 or W0.shape[1] != 6 or fmax.shape != (len(W0),) or not np.all(fmax > 0):
            raise ControlError("thruster loop: nominal wrenches (n, 6) and one positive thrust per valve expected")
        if not (math.isfinite(lever_m) and lever_m > 0) or not np.all(np.isfinite(W0)):
            raise ControlError("thruster loop: finite nominal wrenches and a positive lever arm expected")
        self.n = n = len(W0)
        self.nominal, self.max_n = W0, fmax
        # per valve the scale of its force and moment (the limits are fractions of these)
        self.scale = np.column_stack([np.repeat(fmax[:, None], 3, 1), np.repeat((fmax * lever_m)[:, None], 3, 1)])
        self.used = W0.copy()            # the wrenches the allocation uses now
        self.target = W0.copy()          # what the latest good estimate asks for (limited in magnitude)
        self.mod = SigmaDelta(n, min_on)
        self.closed = False
        self.why_open = "no-estimate"
        self.good_run = 0
        self.last_est_ns: int | None = None      # the last good estimate used
        self.last_cmd_ns: int | None = None
        self.faulty: set[int] = set()
        self._demand: tuple[int, np.ndarray, np.ndarray] | None = None   # (t_ns, wrench, allowed)
        self._demands = 0                        # commanded wrenches taken so far
        self._duty = np.zeros(n)
        self._usable = np.ones(n, dtype=bool)
        self._u0_key: tuple | None = None
        self._u0 = np.zeros(n)
        self._alloc_key: tuple | None = None
        self._saturated = False
        self._limited: set[str] = set()
        self.events: list[LoopEvent] = []

    @classmethod
    def for_layout(cls, layout, *, min_on: int = 1, **kw) -> "ThrusterCompensator":
        """From a :class:`robot_description.thrusters.ThrusterLayout`."""
        lever = float(np.max(np.linalg.norm(layout.pos_m, axis=1)))
        return cls(layout.nominal_wrenches, layout.max_n, lever_m=max(lever, 1e-3), min_on=min_on, **kw)

    # -- inputs
    def demand(self, t_ns: int, wrench, allowed=None) -> None:
        """The outer loop's commanded body wrench ``[force N; moment N m]`` (6,) at sensor time
        ``t_ns``; ``allowed`` (n,) bool: the thrusters the flight software may fire (its keep-out
        mask; default all). An older command arriving late is ignored."""
        w = np.asarray(wrench, dtype=float)
        if w.shape != (6,) or not np.all(np.isfinite(w)):
            raise ControlError(f"thruster loop: a commanded wrench is 6 finite numbers, got {w.shape}")
        ok = np.ones(self.n, dtype=bool) if allowed is None else np.asarray(allowed, dtype=bool)
        if ok.shape != (self.n,):
            raise ControlError(f"thruster loop: allowed must be {self.n} booleans")
        if self._demand is not None and t_ns < self._demand[0]:
            return
        self._demand = (int(t_ns), w, ok.copy())
        self._demands += 1

    def observe(self, cmd: ThrusterCommand) -> None:
        """The commanded wrench as the gateway observed it on the spacecraft bus, with the flight
        software's keep-out mask it carries (``cmd.allowed``; -1, not on the wire: every
        thruster, which is why :class:`~gateway.control.service.ControlService` then commands no
        valve at all)."""
        self.demand(cmd.t_ns, (*cmd.force_n, *cmd.moment_nm), mask_bits(cmd.allowed, self.n))

    def alert(self, a: Alert) -> None:
        """An alert of the gateway: a thruster fault (rule ``thruster-fault``) takes that thruster
        out of the allocation until its clearing; others are ignored."""
        if a.rule != FAULT_RULE:
            return
        ev = dict(a.evidence)
        j = ev.get("thruster")
        if j is None or not 0 <= int(j) < self.n:
            return
        j = int(j)
        if ev.get("type") == FAULT_CLEARED:
            self.faulty.discard(j)
        elif j not in self.faulty:
            self.faulty.add(j)
            self.events.append(LoopEvent(LOOP, int(a.t_ns), "fault", f"thruster{j} excluded ({a.message})"))

    def estimate(self, est: ValveWrenches) -> None:
        """The gateway's learned per-valve wrenches: the loop's target, or the nominal allocation
        when not good."""
        s = self.settings
        W = np.asarray(est.wrench, dtype=float)
        sig = np.asarray(est.force_sigma_n, dtype=float)
        flags = tuple(est.flags)
        known = bool(self.faulty) and all(f == KNOWN_FAULT_FLAG for f in flags)   # a fault it already excludes
        ok = ((est.good or known) and (not flags or known) and W.size == 6 * self.n and sig.shape == (self.n,)
              and bool(np.all(np.isfinite(W))) and bool(np.all(np.isfinite(sig))))
        if not ok:
            why = "estimate:not-good" + (f" ({','.join(flags)})" if flags else "")
            self._open(est.t_ns, why)
            return
        if self.last_est_ns is not None and est.t_ns <= self.last_est_ns:
            return                                  # late or repeated
        W = W.reshape(self.n, 6)
        learned = sig <= s.learned_sigma * self.max_n
        target = np.where(learned[:, None], W, self.nominal)
        dev = target - self.nominal
        cap = s.max_deviation * self.scale
        limited = np.abs(dev) > cap
        self._limited = {"limited:magnitude"} if limited.any() else set()
        self.target = self.nominal + np.clip(dev, -cap, cap)
        dt = 0.0 if self.last_est_ns is None else min((est.t_ns - self.last_est_ns) * 1e-9, s.stale_s)
        self.last_est_ns = est.t_ns
        self.good_run += 1
        if not self.closed:
            if self.good_run < s.resume_good or not self.enabled:
                return
            self.closed = True
            self.used = self.nominal.copy()         # ramps from nominal under the rate limit
            self.events.append(LoopEvent(LOOP, int(est.t_ns), "closed", "estimates good"))
            return
        step = s.max_rate_per_s * self.scale * dt
        self.used = self.used + np.clip(self.target - self.used, -step, step)
        if np.any(np.abs(self.used - self.target) > 1e-9 * self.scale):
            self._limited.add("limited:rate")

    # -- output
    def valves(self, t_ns: int) -> ThrusterValves:
        """The valves for the step at sensor time ``t_ns``. Raises when no commanded wrench has
        been observed yet."""
        if self._demand is None:
            raise ControlError("thruster loop: no commanded wrench observed yet")
        s = self.settings
        t = int(t_ns)
        if self.closed and (self.last_est_ns is None or t - self.last_est_ns > s.stale_s * 1e9):
            self._open(t, "stale:efforts")
        W = self.used if self.closed else self.nominal
        _, w, allowed = self._demand
        usable = allowed.copy()
        for j in self.faulty:
            usable[j] = False
        key = (self._demands, self.closed, usable.tobytes(), W.tobytes())
        if key != self._alloc_key:
            self._duty, self._saturated = allocate(W, w, usable, s.eps, bounded=self.closed)
            if self.closed:
                # a valve the nominal allocation would not fire either, at a duty so low that its
                # pulses come slower than the band the spacecraft responds to, stays closed: its
                # sparse pulses would add more error there than the small wrench they correct
                key0 = (self._demands, usable.tobytes())
                if key0 != self._u0_key:            # the nominal allocation changes with the demand only
                    self._u0, _ = allocate(self.nominal, w, usable, s.eps)
                    self._u0_key = key0
                self._duty[(self._duty < s.min_duty) & (self._u0 < s.min_duty)] = 0.0
            self._alloc_key = key
        self._usable = usable
        on = self.mod.step(self._duty, usable)
        flags = [f"fault:thruster{j}" for j in sorted(self.faulty)]
        if self._saturated:
            flags.append("saturated")
        if self.closed:
            flags += sorted(self._limited)
        else:
            flags.append(self.why_open if self.enabled else "disabled")
        self.last_cmd_ns = t
        return ThrusterValves(t, self._mask(on), tuple(self._duty.tolist()), self.closed, tuple(sorted(flags)))

    def schedule(self, t_ns: int, steps: int, step_ns: int, lookahead: int = 0) -> ThrusterValves:
        """The valves of ``steps`` consecutive steps from sensor time ``t_ns``, ``step_ns`` apart,
        at once (``bsc control`` sends those up to the next commanded wrench in one message):
        the loop's state (closed, stale, the allocation) as of the first step, the valve timing
        step by step (the first step's mask in ``valves``, the others in ``following``).
        ``lookahead`` more steps follow them, timed on but not kept by the modulator: the next
        schedule starts again from the state after ``steps`` and replaces them; until it arrives
        they are what the valves do (a schedule that comes a few steps late leaves no gap)."""
        if steps < 1 or step_ns < 1 or lookahead < 0:
            raise ControlError("thruster loop: a schedule is at least one step of a positive length")
        first = self.valves(t_ns)
        following = tuple(self._mask(self.mod.step(self._duty, self._usable)) for _ in range(steps - 1))
        if lookahead:
            mod = self.mod
            kept = (mod.acc.copy(), mod.on.copy(), mod.on_steps.copy())
            following += tuple(self._mask(mod.step(self._duty, self._usable)) for _ in range(lookahead))
            mod.acc, mod.on, mod.on_steps = kept
        self.last_cmd_ns = int(t_ns) + (steps - 1) * step_ns
        return ThrusterValves(first.t_ns, first.valves, first.duty, first.closed, first.flags, following,
                              int(step_ns) if following else 0)

    def _mask(self, on: np.ndarray) -> int:
        return int(np.dot(on.astype(np.int64), 1 << np.arange(self.n, dtype=np.int64)))

    def _open(self, t_ns: int, why: str) -> None:
        self.good_run = 0
        self.used = self.nominal.copy()
        self.why_open = why
        if self.closed:
            self.closed = False
            self.events.append(LoopEvent(LOOP, int(t_ns), "open", why))

    def take_events(self) -> list[LoopEvent]:
        """The transitions since the last call (and forgets them)."""
        out, self.events = self.events, []
        return out


def allocate(W: np.ndarray, wrench: np.ndarray, usable: np.ndarray, eps: float = 1e-3,
             bounded: bool = False) -> tuple[np.ndarray, bool]:
    """Duty cycles (n,) in [0, 1] of valves with wrenches ``W`` (n, 6) (full opening) for the body
    wrench ``wrench`` (6,): non-negative least squares on ``[W^T; eps I] u = [wrench; 0]`` over the
    ``usable`` valves; when a duty would exceed 1 (the wrench is beyond the valves), scaled down as
    a whole (the flight software's way: the wrench's direction kept) or, ``bounded``, the least
    squares bounded to [0, 1] (the smallest error in the wrench). Returns (duties, saturated)."""
    u = np.zeros(len(W))
    idx = np.flatnonzero(usable)
    if idx.size == 0 or not np.any(wrench):
        return u, False
    A = np.vstack([W[idx].T, eps * np.eye(idx.size)])
    b = np.concatenate([wrench, np.zeros(idx.size)])
    x, _ = nnls(A, b, maxiter=50 * idx.size)
    peak = float(x.max())
    if peak > 1.0:
        if bounded:
            x = lsq_linear(A, b, bounds=(0.0, 1.0), method="bvls").x
        else:
            x /= peak
    u[idx] = x
    return u, peak > 1.0

