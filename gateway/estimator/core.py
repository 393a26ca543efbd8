"""The live estimator compiled: decoded samples in (any order across buses), efforts out.

One implementation for every caller: the live gateway feeds a few samples per call, an offline
replay hundreds of thousands; explicit loops in compiled code give the same bits either way, so a
replay of a session's frames reproduces the efforts the live run published (docs/estimator.md,
"Live").

Synchronisation policy (unchanged from the first wave; docs/estimator.md):

- An *epoch* is one F/T sampling instant (1 kHz). Its required members are the F/T sample of
  every arm, the joint state of every joint and the valve command. A sample belongs to the epoch
  of its slot on a grid of one-period slots centred on the bursts of frames: the grid's phase is
  placed in the widest quiet gap between the first 64 members' arrival phases, then follows the
  bursts' middles.
- An epoch is computed as soon as it is complete. When a later epoch completes first, the earlier
  one is computed with what it has (each bus is FIFO: its missing inputs were lost) and flagged;
  so is the oldest epoch when more than ``max_open`` are waiting (a silent bus).
- Slower streams (IMU, torque and thruster commands) are applied to the first epoch at least half
  a period later than their timestamp; what arrived by the time an epoch is computed is applied
  right after its efforts (the filter's IMU update is off the latency path).
- Flags: a missing joint state holds the previous one (``stale:<arm>/<joint>``); a missing F/T
  sample or valve command makes every estimate of the epoch not good (``missing:<device>``);
  saturated or faulty inputs flag ``saturated:<device>`` / ``fault:<device>``; ``warmup`` until
  the first IMU sample; ``stale:imu`` when it is older than ``imu_max_age_periods`` IMU periods
  (the drivers' ``stale_periods`` is another thing: when a device's health says stale).

Data (all numpy, owned by :class:`EstimatorCore`): sample rows in (:data:`SAMPLE_DTYPE`), per
epoch an output row (:data:`EFFORT_DTYPE`: times, torques, thruster wrench, commanded values and
one flag bit per name of :attr:`EstimatorCore.flag_names`). The maths are
:mod:`.chain_kernel` (base motion and joint torques) and :mod:`.thruster_kernel` (the
valve-aided thruster filter).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import numpy.typing as npt

from drivers import kernel, wire
from robot_description import Robot
from robot_description.thrusters import ThrusterLayout

from . import chain_kernel as ck
from . import joint_filter as jf
from . import fdi as fd
from . import thruster_kernel as tk
from .model import EstimatorModel, EstimatorSettingsError
from .thrusters import ThrusterFilterSettings

if TYPE_CHECKING:
    from drivers.samples import Sample
    from gateway.efforts import JointEfforts, ThrusterEffort, ValveWrenches

from .jitopts import inline as _inl, jit as _jit, jit_alloc as _jit_alloc   # numba's njit, with the kernels' options

# The kernels' arguments: views of one int64 and one float64 buffer (ViewLayout), in groups.
I64 = npt.NDArray[np.int64]
F64 = npt.NDArray[np.float64]
Record = Any                    # a numba record view of a SAMPLE_DTYPE row: numpy's types cannot name its fields
ChainScratch = tuple[F64, F64, F64, F64, F64, F64, F64, F64, F64]     # chain_kernel._scratch
JointFilter = tuple[F64, F64, F64, F64, I64, I64]                   # joint_filter: state, cov, constants, scratch, ok
Chain = tuple[I64, I64, F64, F64, F64, F64, F64, ChainScratch, JointFilter]   # chain_kernel._epoch's arguments
ThrusterArrays = tk.State                                              # CompiledThrusterFilter.state
Scratch = tuple[F64, F64, F64, F64, F64, F64, F64, F64]     # three scratch arrays, then the fault detector's
Views = tuple[I64, I64, I64, I64, I64, F64, F64, F64, F64, F64, Chain, ThrusterArrays, Scratch]

# sample kinds and rows: the compiled drivers' events (drivers/kernel.py EVENT_DTYPE)
WRENCH, JOINT, TORQUE_CMD, IMU, THRUSTER_CMD, VALVES = (kernel.WRENCH, kernel.JOINT, kernel.TORQUE, kernel.IMU,
                                                        kernel.THRUSTER, kernel.VALVE)
SAMPLE_DTYPE = kernel.EVENT_DTYPE
"""One decoded sample (:data:`drivers.kernel.EVENT_DTYPE`). ``values``: WRENCH force (3, N) torque
(3, N m), sensor frame; JOINT angle (rad), rate (rad/s); TORQUE_CMD torque (N m); IMU quaternion
w x y z, rate (3, rad/s), specific force (3, m/s^2), IMU frame; THRUSTER_CMD force (3, N), moment
(3, N m). ``device``: arm index (WRENCH), joint index (JOINT, TORQUE_CMD)."""

PHASE_LEARN_SAMPLES = 64     # members held at start to find where the sensor bursts sit in a period
PHASE_TRACK = 64             # the grid follows the bursts' middle with this time constant (epochs)

# the scalar state (SI array)
_CENTER, _HAVE_CENTER, _LAST_CLOSED, _EPOCHS, _GOOD, _LATE, _N_OPEN, _N_PEND, _N_HELD, _LEARNING, \
    _LEARN_MEMBERS, _GYRO_T, _HAVE_GYRO, _FAULTS, _THR_HAVE, _THR_T, _THR_VALVES, _N_OUT, _PEND_DROPPED, \
    _HELD_DROPPED, _CAUSE, _FILTER_T = range(22)
_N_SI = 22

# the common flags (bits 0..4 of a flag row), then 3 per arm, then 4 per joint
F_WARMUP, F_STALE_IMU, F_MISSING_VALVES, F_SAT_IMU, F_FAULT_IMU = range(5)
_N_COMMON = 5
A_MISSING, A_SATURATED, A_FAULT = range(3)
J_STALE, J_MISSING, J_SATURATED, J_FAULT = range(4)


@dataclass(frozen=True)
class CoreSettings:
    max_open: int = 20                 # epochs waiting for members before the oldest is forced out
    imu_max_age_periods: int = 3       # an epoch's IMU sample may be this many IMU periods old (older: stale:imu)
    thrusters: ThrusterFilterSettings = field(default_factory=ThrusterFilterSettings)
    joints: jf.JointFilterSettings = field(default_factory=jf.JointFilterSettings)
    fdi: fd.FdiSettings | None = field(default_factory=fd.FdiSettings)   # thruster fault detector (None: off)
    pending_capacity: int = 1 << 14    # slower-stream samples waiting for an epoch (oldest dropped beyond)
    held_capacity: int = 1 << 14       # samples held while the grid's phase is learnt

    def __post_init__(self) -> None:
        for name in ("max_open", "imu_max_age_periods", "pending_capacity", "held_capacity"):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise EstimatorSettingsError(f"{name} must be a whole number >= 1, got {value!r}")


def flag_names(robot: Robot) -> list[str]:
    """The flag of each bit of an effort row, in bit order."""
    names = ["warmup", "stale:imu", "missing:valves", "saturated:imu", "fault:imu"]
    for a in robot.arms:
        names += [f"missing:{a.name}", f"saturated:{a.name}", f"fault:{a.name}"]
    for j in robot.joint_names:
        names += [f"stale:{j}", f"missing:{j}", f"saturated:{j}", f"fault:{j}"]
    names.append(THRUSTER_FAULT_FLAG)
    return names


THRUSTER_FAULT_FLAG = "fault:thrusters"
"""The last flag bit: a thruster fault found by the detector (:mod:`.fdi`) and not resolved; it
concerns the thruster effort only."""


def effort_dtype(n_arms: int, n_joints: int, n_flags: int) -> np.dtype:
    return np.dtype([
        ("t_ns", np.int64),                     # the epoch's time on the grid
        ("full_nm", np.float64, (n_joints,)),
        ("simplified_nm", np.float64, (n_joints,)),
        ("rate_rad_s", np.float64, (n_joints,)),
        ("commanded_nm", np.float64, (n_joints,)),
        ("commanded_have", np.int64, (n_joints,)),
        ("commanded_t_ns", np.int64, (n_joints,)),
        ("thruster", np.float64, (6,)),         # force (N), moment about C (N m), body frame
        ("thruster_cmd", np.float64, (6,)),
        ("thruster_cmd_t_ns", np.int64),
        ("thruster_cmd_valves", np.int64),
        ("thruster_cmd_have", np.int64),
        ("ft_bias", np.float64, (max(n_arms, 1), 6)),   # the joint filter's F/T bias per arm, sensor frame
        ("ft_bias_have", np.int64, (max(n_arms, 1),)),
        ("contact", np.float64, (max(n_arms, 1), 6)),   # the contact wrench on each end effector, body axes
        ("contact_have", np.int64, (max(n_arms, 1),)),  # 1: the arm is in contact
        ("flags", np.uint8, (n_flags,)),
        ("cause", np.int64),                    # the input row whose arrival computed it (-1: flush)
    ])


def valve_dtype(n_valves: int, n_flags: int) -> np.dtype:
    """A row of the thruster filter's learned per-valve wrenches as of an epoch (what
    :class:`gateway.efforts.ValveWrenches` publishes; :meth:`EstimatorCore.valve_row`)."""
    return np.dtype([
        ("t_ns", np.int64),                              # the epoch's time on the grid
        ("wrench", np.float64, (6 * n_valves,)),         # W valve by valve: force (N), moment about C (N m)
        ("force_sigma_n", np.float64, (n_valves,)),      # the root of each valve's force covariance's trace
        ("flags", np.uint8, (n_flags,)),                 # the epoch's effort flags (the thruster's published)
    ])


@_jit
def valve_state(x: F64, P: F64, n: int, wrench: F64, sigma: F64, r: int) -> None:
    """Row ``r`` of ``wrench`` (k, 6 n) and ``sigma`` (k, n): the filter's ``W`` (the first 6 n
    states of ``x``) and each valve's force uncertainty, the root of its force covariance's
    trace summed in index order (the bits numpy's ``sum(axis=1)`` of the three gave)."""
    for i in range(n):
        for k in range(6):
            wrench[r, 6 * i + k] = x[6 * i + k]
        v = P[6 * i, 6 * i]
        v += P[6 * i + 1, 6 * i + 1]
        v += P[6 * i + 2, 6 * i + 2]
        sigma[r, i] = np.sqrt(v)


# --- the compiled state machine -------------------------------------------------------------------

@_inl
def _grid(si: I64, period: int, half: int, t: int) -> int:
    c: int = si[_CENTER]
    return c + ((t - c + half) // period) * period


@_inl
def _move_epoch(ep_t: I64, ep_i: I64, ep_ft: F64, ep_j: F64, d: int, s: int) -> None:
    """Open epoch ``s``'s rows copied to ``d`` (element by element: a row assignment wants
    reference counting, which these kernels are compiled without)."""
    for c in range(ep_t.shape[1]):
        ep_t[d, c] = ep_t[s, c]
    for c in range(ep_i.shape[1]):
        ep_i[d, c] = ep_i[s, c]
    for b in range(ep_ft.shape[1]):
        for c in range(ep_ft.shape[2]):
            ep_ft[d, b, c] = ep_ft[s, b, c]
    for b in range(ep_j.shape[1]):
        for c in range(ep_j.shape[2]):
            ep_j[d, b, c] = ep_j[s, b, c]


@_jit_alloc
def _lock_phase(si: I64, cfg: I64, held: np.ndarray) -> None:
    """Place the grid: a boundary in the middle of the widest quiet gap between the held
    members' arrival phases. Depends only on the set of timestamps, not on their order. The
    caller then feeds the held samples again (:func:`_replay_held`)."""
    period, half = cfg[0], cfg[1]
    n = si[_N_HELD]
    si[_LEARNING] = 0
    nm = 0
    for k in range(n):
        kd = held[k]["kind"]
        if kd == WRENCH or kd == JOINT or kd == VALVES:
            nm += 1
    ts = np.empty(max(nm, n, 1), dtype=np.int64)
    m = 0
    if nm > 0:
        for k in range(n):
            kd = held[k]["kind"]
            if kd == WRENCH or kd == JOINT or kd == VALVES:
                ts[m] = held[k]["t_ns"]
                m += 1
    elif n > 0:
        for k in range(n):
            ts[m] = held[k]["t_ns"]
            m += 1
    else:
        ts[0] = 0
        m = 1
    t0 = ts[0]
    for k in range(m):
        if ts[k] < t0:
            t0 = ts[k]
    ph = np.empty(m, dtype=np.int64)
    for k in range(m):
        ph[k] = (ts[k] - t0) % period
    ph = np.unique(ph)                     # sorted, distinct
    # (width, start) of the widest gap; ties go to the later start, as Python's max over tuples
    width = ph[0] + period - ph[ph.shape[0] - 1]
    start = ph[ph.shape[0] - 1]
    for k in range(ph.shape[0] - 1):
        w = ph[k + 1] - ph[k]
        if w > width or (w == width and ph[k] > start):
            width, start = w, ph[k]
    si[_CENTER] = t0 + start + width // 2 + half
    si[_HAVE_CENTER] = 1


@_jit
def _add(si: I64, cfg: I64, held: np.ndarray, s: Record, ep_t: I64, ep_i: I64, ep_ft: F64, ep_j: F64,
         pend: np.ndarray) -> int:
    """Put one sample where it belongs. Returns how many of the first open epochs are ready to be
    computed (:func:`_compute_ready`), or -1 when the grid's phase can now be placed and the held
    samples fed again. (Only the arrays it needs: numba counts references of every array passed
    to a function that is not inlined, and this runs for every sample.)"""
    kind = s["kind"]
    if si[_LEARNING] != 0:
        n = si[_N_HELD]
        if n >= held.shape[0]:
            si[_HELD_DROPPED] += 1
            return 0
        held[n] = s
        si[_N_HELD] = n + 1
        if kind == WRENCH or kind == JOINT or kind == VALVES:
            si[_LEARN_MEMBERS] += 1
            if si[_LEARN_MEMBERS] >= cfg[7]:
                return -1                    # the caller locks the phase and replays the held samples
        return 0
    if kind == IMU or kind == TORQUE_CMD or kind == THRUSTER_CMD:
        n = si[_N_PEND]
        if n >= pend.shape[0]:             # keep the newest: drop the oldest
            for k in range(n - 1):
                pend[k] = pend[k + 1]
            n -= 1
            si[_PEND_DROPPED] += 1
        pend[n] = s
        si[_N_PEND] = n + 1
        return 0
    if kind != WRENCH and kind != JOINT and kind != VALVES:
        return 0
    period, half = cfg[0], cfg[1]
    t = s["t_ns"]
    g = _grid(si, period, half, t)
    # the open epoch within half a period of g (the first, in time order), else a new one
    n_open = si[_N_OPEN]
    e = -1
    for k in range(n_open):
        d = ep_t[k, 0] - g
        if d < 0:
            d = -d
        if d < half:
            e = k
            break
    if e < 0:
        if g <= si[_LAST_CLOSED] + half:
            si[_LATE] += 1                   # too late to be used: only the max_open rule applies
            return _ready(si, cfg, -1, ep_i)
        k = n_open
        if n_open > 0 and ep_t[n_open - 1, 0] >= g:
            k = 0
            while ep_t[k, 0] <= g:
                k += 1
            for r in range(n_open, k, -1):     # make room, keeping time order
                _move_epoch(ep_t, ep_i, ep_ft, ep_j, r, r - 1)
        ep_t[k, 0] = g
        ep_t[k, 1] = 0                       # first, last: own timestamps of its members
        ep_t[k, 2] = 0
        ep_t[k, 3] = 0                       # 1 once first/last are set
        for r in range(ep_i.shape[1]):
            ep_i[k, r] = 0
        si[_N_OPEN] = n_open + 1
        e = k
    if ep_t[e, 3] == 0 or t < ep_t[e, 1]:
        ep_t[e, 1] = t
    if ep_t[e, 3] == 0 or t > ep_t[e, 2]:
        ep_t[e, 2] = t
    ep_t[e, 3] = 1
    p = cfg[2]
    if kind == WRENCH:
        a = s["device"]
        ep_i[e, 3 + 3 * a] = 1
        ep_i[e, 4 + 3 * a] = s["saturated"]
        ep_i[e, 5 + 3 * a] = s["status"]
        for r in range(6):
            ep_ft[e, a, r] = s["values"][r]
    elif kind == JOINT:
        j = s["device"]
        base = 3 + 3 * p + 3 * j
        ep_i[e, base] = 1
        ep_i[e, base + 1] = s["saturated"]
        ep_i[e, base + 2] = s["status"]
        ep_j[e, j, 0] = s["values"][0]
        ep_j[e, j, 1] = s["values"][1]
    else:
        ep_i[e, 0] = 1
        ep_i[e, 1] = s["valves"]
    return _ready(si, cfg, e, ep_i)


@_inl
def _complete(cfg: I64, ep_i: I64, e: int) -> bool:
    p, nj = cfg[2], cfg[3]
    if ep_i[e, 0] == 0:
        return False
    for a in range(p):
        if ep_i[e, 3 + 3 * a] == 0:
            return False
    for j in range(nj):
        if ep_i[e, 3 + 3 * p + 3 * j] == 0:
            return False
    return True


@_inl
def _ready(si: I64, cfg: I64, touched: int, ep_i: I64) -> int:
    # Every open epoch but ``touched`` was incomplete after its last change (complete ones are
    # computed at once), so the last complete one, if any, is ``touched``; beyond max_open the
    # oldest go anyway.
    n_open = si[_N_OPEN]
    last = touched if (touched >= 0 and _complete(cfg, ep_i, touched)) else -1
    max_open = cfg[6]
    if n_open - (last + 1) > max_open:
        last = n_open - max_open - 1
    return last + 1


@_jit
def _compute_ready(si: I64, cfg: I64, nready: int, ep_t: I64, ep_i: I64, ep_ft: F64, ep_j: F64, pend: np.ndarray,
                   out: np.ndarray, jstate: F64, jcmd: F64, jcmd_i: I64, thr_cmd: F64, chain: Chain,
                   tf: ThrusterArrays, scratch: Scratch) -> None:
    """Compute the first ``nready`` open epochs in time order, in place (a computation reads only
    its own epoch's rows), then move the rest down."""
    n_open = si[_N_OPEN]
    for r in range(nready):
        _compute(si, cfg, ep_t[r], ep_i[r], ep_ft[r], ep_j[r], pend, out, jstate, jcmd, jcmd_i, thr_cmd, chain,
                 tf, scratch)
    for r in range(nready, n_open):
        _move_epoch(ep_t, ep_i, ep_ft, ep_j, r - nready, r)
    si[_N_OPEN] = n_open - nready


@_jit
def _apply_pending(si: I64, cfg: I64, lim: int, pend: np.ndarray, jcmd: F64, jcmd_i: I64, thr_cmd: F64,
                   tf: ThrusterArrays, scratch: Scratch) -> None:
    """Apply the slower-stream samples whose grid time is at most ``lim``, in arrival order."""
    period, half = cfg[0], cfg[1]
    n = si[_N_PEND]
    keep = 0
    for k in range(n):
        s = pend[k]
        g = _grid(si, period, half, s["t_ns"])
        if g > lim:
            if keep != k:
                pend[keep] = s
            keep += 1
            continue
        kind = s["kind"]
        if kind == IMU:                       # it ends the filter steps of its grid epoch
            v = s["values"]
            if cfg[13] != 0:                  # the fault detector: the update's innovation, then its verdict
                dst, dcfg, wnom, ha, tap = scratch[3], scratch[4], scratch[5], scratch[6], scratch[7]
                fd.imu_update(tf[0], tf[1], tf[2], tf[3], tf[4], tf[5], tf[6], tf[7], tf[8], tf[9], g, v[7:10],
                              v[4:7], tap, dst, dcfg, wnom, ha)
            else:
                tk.imu(tf[0], tf[1], tf[2], tf[3], tf[4], tf[5], tf[6], tf[7], tf[8], tf[9], g, v[7:10], v[4:7])
            si[_GYRO_T] = g
            si[_HAVE_GYRO] = 1
            if s["saturated"] != 0:
                si[_FAULTS] |= 1 << F_SAT_IMU
            if s["status"] & cfg[10] != 0:
                si[_FAULTS] |= 1 << F_FAULT_IMU
        elif kind == TORQUE_CMD:
            j = s["device"]
            jcmd[j] = s["values"][0]
            jcmd_i[j, 0] = s["t_ns"]
            jcmd_i[j, 1] = 1
        else:
            for r in range(6):
                thr_cmd[r] = s["values"][r]
            si[_THR_HAVE] = 1
            si[_THR_T] = s["t_ns"]
            si[_THR_VALVES] = s["valves"]
    si[_N_PEND] = keep


@_jit
def _compute(si: I64, cfg: I64, et: I64, ei: I64, eft: F64, ej: F64, pend: np.ndarray, out: np.ndarray, jstate: F64,
             jcmd: F64, jcmd_i: I64, thr_cmd: F64, chain: Chain, tf: ThrusterArrays, scratch: Scratch) -> None:
    _period, half, p, nj = cfg[0], cfg[1], cfg[2], cfg[3]
    t = et[0]
    if t > si[_LAST_CLOSED]:
        si[_LAST_CLOSED] = t
    complete = ei[0] != 0
    for a in range(p):
        complete = complete and ei[3 + 3 * a] != 0
    for j in range(nj):
        complete = complete and ei[3 + 3 * p + 3 * j] != 0
    if et[3] != 0 and complete:            # the grid follows the bursts (drift)
        si[_CENTER] += ((et[1] + et[2]) // 2 - t) // cfg[8]
    si[_EPOCHS] += 1
    if si[_N_PEND] > 0:
        _apply_pending(si, cfg, t - half, pend, jcmd, jcmd_i, thr_cmd, tf, scratch)
    o = si[_N_OUT]
    fl = out[o]["flags"]
    for k in range(fl.shape[0]):
        fl[k] = 0
    faults = si[_FAULTS]                   # noted by the slower streams applied since the last epoch
    si[_FAULTS] = 0
    if faults & (1 << F_SAT_IMU):
        fl[F_SAT_IMU] = 1
    if faults & (1 << F_FAULT_IMU):
        fl[F_FAULT_IMU] = 1
    if si[_HAVE_GYRO] == 0:
        fl[F_WARMUP] = 1
    elif t - si[_GYRO_T] > cfg[5]:
        fl[F_STALE_IMU] = 1
    if ei[0] == 0:
        fl[F_MISSING_VALVES] = 1
    ft_trusted = True
    ft = scratch[0]
    jfs = chain[8]
    ft_ok, rate_ok = jfs[4], jfs[5]
    for a in range(p):
        fa = _N_COMMON + 3 * a
        ft_ok[a] = 0
        if ei[3 + 3 * a] == 0:
            fl[fa + A_MISSING] = 1
            for r in range(6):
                ft[a, r] = 0.0
            ft_trusted = False
            continue
        for r in range(6):
            ft[a, r] = eft[a, r]
        ft_ok[a] = 1
        if ei[4 + 3 * a] != 0:
            fl[fa + A_SATURATED] = 1
            ft_trusted = False
            ft_ok[a] = 0
        if ei[5 + 3 * a] & cfg[9] != 0:
            fl[fa + A_FAULT] = 1
            ft_trusted = False
            ft_ok[a] = 0
    for j in range(nj):
        fj = _N_COMMON + 3 * p + 4 * j
        base = 3 + 3 * p + 3 * j
        rate_ok[j] = 0
        if ei[base] == 0:
            if jstate[j, 2] != 0:
                fl[fj + J_STALE] = 1
            else:
                fl[fj + J_MISSING] = 1
            continue
        jstate[j, 0] = ej[j, 0]
        jstate[j, 1] = ej[j, 1]
        jstate[j, 2] = 1.0
        rate_ok[j] = 1
        if ei[base + 1] != 0:
            fl[fj + J_SATURATED] = 1
            rate_ok[j] = 0
        if ei[base + 2] & cfg[11] != 0:
            fl[fj + J_FAULT] = 1
            rate_ok[j] = 0
    # the joint filter applies an arm's F/T rows only when they are the model at this epoch: every
    # joint of the arm fresh (the angles), and the base motion trusted (every F/T sample, the valve
    # command and a fresh, sound IMU sample: no common flag)
    arm_n, arm_col = chain[0], chain[1]
    base_ok = ft_trusted
    for k in range(_N_COMMON):
        if fl[k] != 0:
            base_ok = False
    for a in range(p):
        if not base_ok:
            ft_ok[a] = 0
        for j in range(arm_col[a], arm_col[a] + arm_n[a]):
            if rate_ok[j] == 0:
                ft_ok[a] = 0
    mask = ei[1] if ei[0] != 0 else 0
    # a thruster fault suspected: the base motion is in doubt, and with it every arm's model wrench
    # (the joint filter's contact test holds; docs/estimator.md, 2c)
    hold = 1.0 if cfg[13] != 0 and fd.learning(scratch[3]) == 0.0 else 0.0
    for a in range(p):
        jfs[0][a, jf.S_HOLD] = hold
    if cfg[13] != 0:                       # the faults found so far: stuck valves as they are
        mask = fd.valve_mask(scratch[3], mask)
        if fd.unresolved(scratch[3]):
            fl[cfg[12]] = 1
    row = out[o]
    thr = row["thruster"]
    tk.wrench(tf[0], mask, thr)
    if cfg[13] != 0:                       # and the confirmed leaks (nothing added when none)
        fd.add_leaks(scratch[3], scratch[5], mask, thr)
    q = jstate[:, 0]
    dq = jstate[:, 1]
    w_s = scratch[1][0, :3]
    for k in range(3):                     # the latest gyro rate, body frame (the filter keeps it)
        w_s[k] = tf[9][3 + k]
    a_s = scratch[1][1, :3]
    dw_s = scratch[1][2, :3]
    arm_w = scratch[1][3]
    ddq = scratch[2][0]
    gc, per, U, FU, W, Bt, Vm, cs, vec = chain[7]
    # the joint filter's step: whole periods since its last epoch (the grid's microseconds of
    # drift tracking are not motion); the first epoch: ~1.5e8 s, the filter starts
    dt = ((t - si[_FILTER_T] + half) // _period) * _period * 1e-9
    si[_FILTER_T] = t
    ck._epoch(chain[0], chain[1], chain[2], chain[3], chain[4], chain[5], chain[6][0], q, dq, ft, thr, w_s,
              row["simplified_nm"], ddq, row["full_nm"], a_s, dw_s, arm_w, gc, per, U, FU, W, Bt, Vm, cs, vec,
              dt, ft_ok, rate_ok, jfs[0], jfs[1], jfs[2], jfs[3])
    # the filter learns only from whole, trusted steps (every F/T sample, none saturated or
    # faulty, and the valve command); the IMU samples whose interval a missing step falls in
    # are then not applied (tk.tf_imu)
    if ft_trusted and ei[0] != 0:
        tk.push_epoch(tf[5], tf[6], tf[7], tf[8], t, arm_w, mask)
    row["t_ns"] = t
    row["cause"] = si[_CAUSE]
    fst = jfs[0]
    for a in range(p):
        bo = 2 * chain[0][a]
        have = jfs[2][jf.C_ON] != 0.0 and fst[a, jf.S_STARTED] != 0.0
        row["ft_bias_have"][a] = 1 if have else 0
        touch = have and fst[a, jf.S_MODE] != 0.0
        row["contact_have"][a] = 1 if touch else 0
        for r in range(6):
            row["ft_bias"][a, r] = fst[a, bo + r] if have else 0.0
            row["contact"][a, r] = fst[a, bo + 6 + r] if touch else 0.0
    for j in range(nj):
        row["rate_rad_s"][j] = jstate[j, 1]
        row["commanded_nm"][j] = jcmd[j]
        row["commanded_t_ns"][j] = jcmd_i[j, 0]
        row["commanded_have"][j] = jcmd_i[j, 1]
    for r in range(6):
        row["thruster_cmd"][r] = thr_cmd[r]
    row["thruster_cmd_t_ns"] = si[_THR_T]
    row["thruster_cmd_valves"] = si[_THR_VALVES]
    row["thruster_cmd_have"] = si[_THR_HAVE]
    # good (the thruster effort): no common flag, no arm-level flag of any arm
    good = True
    for k in range(_N_COMMON + 3 * p):
        if fl[k] != 0:
            good = False
    if fl[cfg[12]] != 0:
        good = False
    si[_GOOD] += good
    si[_N_OUT] = o + 1
    if si[_N_PEND] > 0:                    # off the latency path: what the next epoch applies first
        _apply_pending(si, cfg, t + half, pend, jcmd, jcmd_i, thr_cmd, tf, scratch)


# --- the entry points: every array a view of three buffers ------------------------------------------
# A call's cost in the live gateway is mostly numba's dispatch, about 0.06 us per array argument:
# the state lives in one int64 and one float64 buffer, carved into views here (lay: per view
# offset and dims, ViewLayout).

@_jit_alloc
def _i1(I: I64, lay: I64, k: int) -> I64:
    o = lay[k, 0]
    return I[o:o + lay[k, 1]]


@_jit_alloc
def _i2(I: I64, lay: I64, k: int) -> I64:
    o = lay[k, 0]
    return I[o:o + lay[k, 1] * lay[k, 2]].reshape((lay[k, 1], lay[k, 2]))


@_jit_alloc
def _f1(F: F64, lay: I64, k: int) -> F64:
    o = lay[k, 0]
    return F[o:o + lay[k, 1]]


@_jit_alloc
def _f2(F: F64, lay: I64, k: int) -> F64:
    o = lay[k, 0]
    return F[o:o + lay[k, 1] * lay[k, 2]].reshape((lay[k, 1], lay[k, 2]))


@_jit_alloc
def _f3(F: F64, lay: I64, k: int) -> F64:
    o = lay[k, 0]
    return F[o:o + lay[k, 1] * lay[k, 2] * lay[k, 3]].reshape((lay[k, 1], lay[k, 2], lay[k, 3]))


@_jit_alloc
def _views(I: I64, F: F64, lay: I64) -> Views:
    si, cfg = _i1(I, lay, 0), _i1(I, lay, 1)
    ep_t, ep_i, jcmd_i = _i2(I, lay, 2), _i2(I, lay, 3), _i2(I, lay, 4)
    ep_ft, ep_j, jstate = _f3(F, lay, 5), _f3(F, lay, 6), _f2(F, lay, 7)
    jcmd, thr_cmd = _f1(F, lay, 8), _f1(F, lay, 9)
    chain = (_i1(I, lay, 10), _i1(I, lay, 11), _f2(F, lay, 12), _f3(F, lay, 13), _f1(F, lay, 14),
             _f1(F, lay, 15), _f1(F, lay, 16),
             (_f2(F, lay, 17), _f3(F, lay, 18), _f2(F, lay, 19), _f3(F, lay, 20), _f2(F, lay, 21),
              _f2(F, lay, 22), _f2(F, lay, 23), _f2(F, lay, 24), _f2(F, lay, 25)),
             (_f2(F, lay, 44), _f3(F, lay, 45), _f1(F, lay, 46), _f2(F, lay, 47), _i1(I, lay, 48), _i1(I, lay, 49)))
    tf = (_f1(F, lay, 26), _f2(F, lay, 27), _f1(F, lay, 28), _f1(F, lay, 29), _f1(F, lay, 30),
          _i1(I, lay, 31), _f2(F, lay, 32), _i1(I, lay, 33), _i1(I, lay, 34), _f1(F, lay, 35))
    scratch = (_f2(F, lay, 36), _f2(F, lay, 37), _f2(F, lay, 38), _f1(F, lay, 39), _f1(F, lay, 40), _f2(F, lay, 41),
               _f1(F, lay, 42), _f1(F, lay, 43))
    return si, cfg, ep_t, ep_i, jcmd_i, ep_ft, ep_j, jstate, jcmd, thr_cmd, chain, tf, scratch


@_inl
def _feed_one(si: I64, cfg: I64, held: np.ndarray, s: Record, ep_t: I64, ep_i: I64, ep_ft: F64, ep_j: F64,
              pend: np.ndarray, out: np.ndarray, jstate: F64, jcmd: F64, jcmd_i: I64, thr_cmd: F64, chain: Chain,
              tf: ThrusterArrays, scratch: Scratch) -> None:
    nready = _add(si, cfg, held, s, ep_t, ep_i, ep_ft, ep_j, pend)
    if nready > 0:
        _compute_ready(si, cfg, nready, ep_t, ep_i, ep_ft, ep_j, pend, out, jstate, jcmd, jcmd_i, thr_cmd, chain,
                       tf, scratch)
    elif nready < 0:
        _lock_phase(si, cfg, held)
        _replay_held(si, cfg, held, ep_t, ep_i, ep_ft, ep_j, pend, out, jstate, jcmd, jcmd_i, thr_cmd, chain, tf,
                     scratch)


@_jit
def _replay_held(si: I64, cfg: I64, held: np.ndarray, ep_t: I64, ep_i: I64, ep_ft: F64, ep_j: F64, pend: np.ndarray,
                 out: np.ndarray, jstate: F64, jcmd: F64, jcmd_i: I64, thr_cmd: F64, chain: Chain,
                 tf: ThrusterArrays, scratch: Scratch) -> None:
    n = si[_N_HELD]
    si[_N_HELD] = 0
    for k in range(n):                     # learning is over: none of these is held again
        nready = _add(si, cfg, held, held[k], ep_t, ep_i, ep_ft, ep_j, pend)
        if nready > 0:
            _compute_ready(si, cfg, nready, ep_t, ep_i, ep_ft, ep_j, pend, out, jstate, jcmd, jcmd_i, thr_cmd,
                           chain, tf, scratch)


@_jit_alloc
def feed_kernel(I: I64, F: F64, lay: I64, held: np.ndarray, pend: np.ndarray, samples: np.ndarray,
                out: np.ndarray) -> int:
    """Sample rows in arrival order; returns the number of effort rows written to ``out``."""
    si, cfg, ep_t, ep_i, jcmd_i, ep_ft, ep_j, jstate, jcmd, thr_cmd, chain, tf, scratch = _views(I, F, lay)
    return _feed_all(si, cfg, held, samples, ep_t, ep_i, ep_ft, ep_j, pend, out, jstate, jcmd, jcmd_i, thr_cmd,
                     chain, tf, scratch)


@_jit
def _feed_all(si: I64, cfg: I64, held: np.ndarray, samples: np.ndarray, ep_t: I64, ep_i: I64, ep_ft: F64,
              ep_j: F64, pend: np.ndarray, out: np.ndarray, jstate: F64, jcmd: F64, jcmd_i: I64, thr_cmd: F64,
              chain: Chain, tf: ThrusterArrays, scratch: Scratch) -> int:
    """:func:`feed_kernel`'s loop, on the state's views (compiled without reference counting: the
    views are its caller's, nothing here allocates, and counting every array of every call for
    every sample cost more than the arithmetic)."""
    si[_N_OUT] = 0
    for k in range(samples.shape[0]):
        si[_CAUSE] = k
        _feed_one(si, cfg, held, samples[k], ep_t, ep_i, ep_ft, ep_j, pend, out, jstate, jcmd, jcmd_i, thr_cmd,
                  chain, tf, scratch)
    n_out: int = si[_N_OUT]
    return n_out


@_jit_alloc
def feed_cuts_kernel(I: I64, F: F64, lay: I64, held: np.ndarray, pend: np.ndarray, samples: np.ndarray,
                     out: np.ndarray, cuts: I64, n_valves: int, n_at: I64, snap_w: F64, snap_s: F64) -> int:
    """:func:`feed_kernel`, with the thruster filter's learned valve wrenches taken at each cut:
    ``cuts`` ascending (a cut at i: after ``samples[:i]``); at cut c, ``n_at[c]`` the effort rows
    written so far and row c of ``snap_w`` (cuts, 6 n) and ``snap_s`` (cuts, n) the filter's
    wrenches (:func:`valve_state`). The same rows and state as one :func:`feed_kernel` call per
    part (a row's ``cause`` counts from the first sample of all), in one call."""
    si, cfg, ep_t, ep_i, jcmd_i, ep_ft, ep_j, jstate, jcmd, thr_cmd, chain, tf, scratch = _views(I, F, lay)
    return _feed_cuts(si, cfg, held, samples, ep_t, ep_i, ep_ft, ep_j, pend, out, jstate, jcmd, jcmd_i, thr_cmd,
                      chain, tf, scratch, cuts, n_valves, n_at, snap_w, snap_s)


@_jit
def _feed_cuts(si: I64, cfg: I64, held: np.ndarray, samples: np.ndarray, ep_t: I64, ep_i: I64, ep_ft: F64,
               ep_j: F64, pend: np.ndarray, out: np.ndarray, jstate: F64, jcmd: F64, jcmd_i: I64, thr_cmd: F64,
               chain: Chain, tf: ThrusterArrays, scratch: Scratch, cuts: I64, n_valves: int, n_at: I64, snap_w: F64,
               snap_s: F64) -> int:
    """:func:`feed_cuts_kernel`'s loop on the state's views, without reference counting (as
    :func:`_feed_all`)."""
    si[_N_OUT] = 0
    k = 0
    for c in range(cuts.shape[0] + 1):
        stop = cuts[c] if c < cuts.shape[0] else samples.shape[0]
        while k < stop:
            si[_CAUSE] = k
            _feed_one(si, cfg, held, samples[k], ep_t, ep_i, ep_ft, ep_j, pend, out, jstate, jcmd, jcmd_i, thr_cmd,
                      chain, tf, scratch)
            k += 1
        if c < cuts.shape[0]:
            n_at[c] = si[_N_OUT]
            valve_state(tf[0], tf[1], n_valves, snap_w, snap_s, c)
    n_out: int = si[_N_OUT]
    return n_out


@_jit_alloc
def flush_kernel(I: I64, F: F64, lay: I64, held: np.ndarray, pend: np.ndarray, out: np.ndarray) -> int:
    """End of input: every waiting epoch computed with what it has; returns the rows written."""
    si, cfg, ep_t, ep_i, jcmd_i, ep_ft, ep_j, jstate, jcmd, thr_cmd, chain, tf, scratch = _views(I, F, lay)
    si[_N_OUT] = 0
    si[_CAUSE] = -1
    if si[_LEARNING] != 0:
        _lock_phase(si, cfg, held)
        _replay_held(si, cfg, held, ep_t, ep_i, ep_ft, ep_j, pend, out, jstate, jcmd, jcmd_i, thr_cmd, chain, tf,
                     scratch)
    _compute_ready(si, cfg, si[_N_OPEN], ep_t, ep_i, ep_ft, ep_j, pend, out, jstate, jcmd, jcmd_i, thr_cmd, chain,
                   tf, scratch)
    n_out: int = si[_N_OUT]
    return n_out


class ViewLayout:
    """Arrays packed into one int64 and one float64 buffer, in order; ``views[k]`` is array k as
    a view of its buffer (the kernels carve the same views from ``lay``)."""

    def __init__(self, arrays: list[np.ndarray]):
        ni = sum(a.size for a in arrays if a.dtype == np.int64)
        nf = sum(a.size for a in arrays if a.dtype != np.int64)
        self.I = np.zeros(max(ni, 1), dtype=np.int64)
        self.F = np.zeros(max(nf, 1))
        self.lay = np.zeros((len(arrays), 4), dtype=np.int64)
        self.views: list[np.ndarray] = []
        buf: np.ndarray
        oi = of = 0
        for k, a in enumerate(arrays):
            a = np.asarray(a)
            if a.dtype == np.int64:
                buf, o = self.I, oi
                oi += a.size
            else:
                buf, o = self.F, of
                of += a.size
            dims = list(a.shape) + [1] * (3 - a.ndim)
            self.lay[k] = (o, *dims)
            v = buf[o:o + a.size].reshape(a.shape)
            v[...] = a
            self.views.append(v)


# --- the Python side ------------------------------------------------------------------------------

class EstimatorCore:
    """The live estimator of one robot: :meth:`feed` sample rows, get effort rows.

    ``robot`` is the estimator's belief of the robot (its masses, inertias and sensor
    placements); ``layout`` the nominal thruster layout (the filter's prior). Feed
    :data:`SAMPLE_DTYPE` rows in arrival order (:func:`sample_rows` turns driver samples into
    rows); every call returns the effort rows of the epochs it completed, in time order.
    :meth:`efforts` turns rows into the published objects.
    """

    def __init__(self, robot: Robot, *, layout: ThrusterLayout | None = None, settings: CoreSettings | None = None):
        s = self.settings = settings or CoreSettings()
        self.robot = robot
        model = self.model = EstimatorModel.from_robot(robot)
        self.layout = layout or ThrusterLayout.named()
        arm_lay, sc_lay = wire.layouts("arm"), wire.layouts("spacecraft")
        period = arm_lay[wire.FT_A_ID].cycle_ms * 1_000_000
        imu_period = sc_lay[wire.IMU_TIME_ID].cycle_ms * 1_000_000
        self.period_ns = period
        p, nj = model.n_arms, model.n_joints
        self.n_arms, self.n_joints = p, nj
        self.arms = [a.name for a in robot.arms]
        self.arm_joints = [tuple(f"{a.name}/{j}" for j in a.joint_names) for a in robot.arms]
        self.joint_names = [j for names in self.arm_joints for j in names]
        self.joint_index = {j: i for i, j in enumerate(self.joint_names)}
        self.arm_index = {a: i for i, a in enumerate(self.arms)}
        self.flag_names = flag_names(robot)
        self.dtype = effort_dtype(p, nj, len(self.flag_names))
        self.cfg = np.array([period, period // 2, p, nj, imu_period, s.imu_max_age_periods * imu_period, s.max_open,
                             PHASE_LEARN_SAMPLES, PHASE_TRACK, wire.FT_FAULT, wire.IMU_FAULT, wire.DRIVE_FAULT,
                             len(self.flag_names) - 1, int(s.fdi is not None)], dtype=np.int64)
        cap = s.max_open + 8
        si = np.zeros(_N_SI, dtype=np.int64)
        si[_LEARNING] = 1
        si[_LAST_CLOSED] = -(1 << 62)
        si[_FILTER_T] = -(1 << 62)
        nj1 = max(nj, 1)
        arrays = ck.pack(model)
        L = arrays.link.shape[1]
        self.kf = tk.CompiledThrusterFilter(model, self.layout, dt=period * 1e-9,
                                            imu_steps=max(1, imu_period // period), settings=s.thrusters)
        kf = self.kf
        n_thr = self.layout.n
        self.valve_dtype = valve_dtype(kf.n, len(self.flag_names))
        if s.fdi is not None:                 # the fault detector's state and constants (gateway/estimator/fdi.py)
            fdi_arrays = [fd.new_state(n_thr), s.fdi.config(n_thr, imu_period * 1e-9),
                          fd.signatures(self.layout, kf.W),
                          kf.state[3][tk._HA:tk._HA + 18].copy(), np.zeros(tk.tap_size(n_thr))]
        else:
            fdi_arrays = [np.zeros(1), np.zeros(1), np.zeros((1, fd.SIG_COLS)), np.zeros(1), np.zeros(1)]
        packed = ViewLayout([
            si, self.cfg, np.zeros((cap, 4), dtype=np.int64), np.zeros((cap, 3 + 3 * p + 3 * nj), dtype=np.int64),
            np.zeros((nj1, 2), dtype=np.int64),                                       # 0-4
            np.zeros((cap, p, 6)), np.zeros((cap, nj1, 2)), np.zeros((nj1, 3)), np.zeros(nj1), np.zeros(6),  # 5-9
            arrays.arm_n, arrays.arm_col, arrays.sensor, arrays.link, arrays.base,   # 10-14
            np.array(ck.WEIGHTS, dtype=float), np.array([-1.0]),                    # 15-16
            *ck._scratch(p, L),                                                      # 17-25
            *kf.state,                                                               # 26-35
            np.zeros((p, 6)), np.zeros((4, 6)), np.zeros((1, nj1)),                  # 36-38
            *fdi_arrays,                                                             # 39-43
            *jf.new_state(p), s.joints.constants(), np.zeros((jf.SCRATCH_ROWS, jf.MAX_STATE)),   # 44-47
            np.zeros(max(p, 1), dtype=np.int64), np.zeros(nj1, dtype=np.int64),     # 48-49
        ])
        self._I, self._F, self._lay = packed.I, packed.F, packed.lay
        self._si = packed.views[0]
        # the filter object works on the same memory as the kernels (W, efficiency, updates)
        kf.share(packed.views[26:36])
        self._fdi_state = packed.views[39]
        self._fdi_seen = 0
        self._held = np.zeros(s.held_capacity, dtype=SAMPLE_DTYPE)
        self._pend = np.zeros(s.pending_capacity, dtype=SAMPLE_DTYPE)
        self._cap = cap
        self._out = np.zeros(0, dtype=self.dtype)
        # flags -> published tuples: per arm the bits it reports, in the order of their sorted names
        common = list(range(_N_COMMON + 3 * p))
        self._arm_bits: list[I64] = []
        for a, names in enumerate(self.arm_joints):
            bits = common + [_N_COMMON + 3 * p + 4 * self.joint_index[j] + k for j in names for k in range(4)]
            self._arm_bits.append(np.array(sorted(bits, key=lambda b: self.flag_names[b]), dtype=np.int64))
        thr = common + [len(self.flag_names) - 1]             # and the thruster fault flag
        self._thr_bits = np.array(sorted(thr, key=lambda b: self.flag_names[b]), dtype=np.int64)
        self._flag_cache: dict[tuple[int, bytes], tuple[str, ...]] = {}
        # (n_flags, n_arms + 1): 1 where a flag concerns an arm's efforts, then the thrusters'
        self._effort_bits = np.zeros((len(self.flag_names), p + 1), dtype=np.int32)
        for e, concern in enumerate((*self._arm_bits, self._thr_bits)):
            self._effort_bits[concern, e] = 1
        from drivers.frames import builder
        from gateway.efforts import JointEfforts, ThrusterEffort

        self._make_j, self._make_t = builder(JointEfforts), builder(ThrusterEffort)   # built once: ~0.3 ms each

    # -- counters ------------------------------------------------------------------------------
    @property
    def epochs(self) -> int:
        return int(self._si[_EPOCHS])

    def thruster_alarms(self) -> list[dict[str, float | int | str]]:
        """Thruster faults confirmed since the last call (:mod:`.fdi`), in order: ``t_ns`` (when
        confirmed; grid time), ``thruster``, ``fault`` (stuck open, leak, stuck closed, partial
        loss), ``theta`` (its size, fraction of nominal thrust), ``stat``, ``window`` (short,
        long), ``detected_t_ns``. Empty when the detector is off."""
        if self.settings.fdi is None or int(self._fdi_state[fd._S_EVENTS]) == self._fdi_seen:
            return []
        ev = fd.events(self._fdi_state, self.layout.n)
        new = ev[self._fdi_seen:]
        self._fdi_seen = len(ev)
        return [{"t_ns": int(r[0]), "thruster": int(r[1]), "fault": fd.TYPES[int(r[2])], "theta": float(r[3]),
                 "stat": float(r[4]), "window": "short" if r[5] == 0 else "long", "detected_t_ns": int(r[6])}
                for r in new]

    def good_efforts(self, rows: np.ndarray) -> int:
        """How many efforts of the effort ``rows`` are good: per arm and for the thrusters, none of
        the flags that concern it set (as the published ``good``)."""
        hits = rows["flags"] @ self._effort_bits         # flags set that concern each effort (ints: no BLAS)
        return int(np.count_nonzero(hits == 0))

    @property
    def good(self) -> int:
        return int(self._si[_GOOD])

    @property
    def late(self) -> int:
        return int(self._si[_LATE])

    # -- input ---------------------------------------------------------------------------------
    def _reserve(self, n_samples: int) -> None:
        # epochs one call can complete: the open ones plus one per member sample fed, held ones too
        need = self._cap + 2 * n_samples + int(self._si[_N_HELD]) + 1
        if self._out.shape[0] < need:
            self._out = np.zeros(max(need, 2 * self._out.shape[0]), dtype=self.dtype)

    def feed(self, samples: np.ndarray) -> np.ndarray:
        """Sample rows (:data:`SAMPLE_DTYPE`) in arrival order -> the effort rows they completed
        (a view of an internal buffer, valid until the next call)."""
        self._reserve(len(samples))
        n = feed_kernel(self._I, self._F, self._lay, self._held, self._pend, samples, self._out)
        return self._out[:n]

    def feed_cuts(self, samples: np.ndarray, cuts: Sequence[int]) -> tuple[np.ndarray, I64, F64, F64]:
        """:meth:`feed`, taking the learned valve wrenches after ``samples[:i]`` for each ``i`` of
        ``cuts`` (ascending): ``(rows, n_at, wrench, sigma)``, at cut c ``n_at[c]`` rows of
        ``rows`` done and the filter's wrenches ``wrench[c]`` (6 n), ``sigma[c]`` (n), as
        :meth:`valve_row` gives them then. One call where a call per part cost microseconds each."""
        self._reserve(len(samples))
        c = np.asarray(cuts, dtype=np.int64)
        n = self.kf.n
        n_at = np.empty(len(c), dtype=np.int64)
        snap_w, snap_s = np.empty((len(c), 6 * n)), np.empty((len(c), n))
        k = feed_cuts_kernel(self._I, self._F, self._lay, self._held, self._pend, samples, self._out, c, n, n_at,
                             snap_w, snap_s)
        return self._out[:k], n_at, snap_w, snap_s

    def flush(self) -> np.ndarray:
        """End of input: compute every waiting epoch with what it has (rows valid until the next call)."""
        self._reserve(0)
        n = flush_kernel(self._I, self._F, self._lay, self._held, self._pend, self._out)
        return self._out[:n]

    # -- output --------------------------------------------------------------------------------
    def valve_wrenches(self) -> tuple[F64, F64]:
        """The thruster filter's learned per-valve wrenches now (copies; read only): ``W`` (n, 6),
        valve by valve ``[force (N); moment about C (N m)]``, body frame, and each valve's force
        uncertainty (n,), N (1 sigma: the root of its force covariance's trace). Between two
        epochs' computations the filter does not move, so this is its state after the latest."""
        rows = np.zeros(1, dtype=self.valve_dtype)
        self.valve_row(rows, 0)
        n = self.kf.n
        return rows["wrench"][0].reshape(n, 6), rows["force_sigma_n"][0]

    def valve_row(self, rows: np.ndarray, r: int) -> None:
        """Row ``r`` of ``rows`` (:attr:`valve_dtype`): its ``wrench`` and ``force_sigma_n`` the
        filter's now (:meth:`valve_wrenches`); ``t_ns`` and ``flags`` are the caller's."""
        kf = self.kf
        valve_state(kf.x, kf.P, kf.n, rows["wrench"], rows["force_sigma_n"], r)

    def valve_objects(self, rows: np.ndarray) -> list[ValveWrenches]:
        """The published objects of valve rows (:attr:`valve_dtype`)."""
        from gateway.efforts import ValveWrenches

        out = []
        for r in rows:
            flags = self._flags(r["flags"], self._thr_bits, -1)
            out.append(ValveWrenches(int(r["t_ns"]), tuple(r["wrench"].tolist()), tuple(r["force_sigma_n"].tolist()),
                                     not flags, flags))
        return out

    def thruster_flags(self, row_flags: np.ndarray) -> tuple[str, ...]:
        """The flags of the thruster effort of an effort row's ``flags``, as published."""
        return self._flags(row_flags, self._thr_bits, -1)

    def _flags(self, row_flags: np.ndarray, bits: np.ndarray, which: int) -> tuple[str, ...]:
        sel = row_flags[bits]
        key = (which, sel.tobytes())
        out = self._flag_cache.get(key)
        if out is None:
            out = tuple(self.flag_names[b] for b, on in zip(bits.tolist(), sel.tolist()) if on)
            if len(self._flag_cache) < 65536:
                self._flag_cache[key] = out
        return out

    def efforts(self, rows: np.ndarray) -> list[JointEfforts | ThrusterEffort]:
        """The published objects of effort rows: per row one :class:`JointEfforts` per arm, then
        one :class:`ThrusterEffort`."""
        make_j, make_t = self._make_j, self._make_t
        out: list[JointEfforts | ThrusterEffort] = []
        col = 0
        spans: list[tuple[str, tuple[str, ...], int, int, I64, int]] = []
        for a, names in enumerate(self.arm_joints):
            spans.append((self.arms[a], names, col, col + len(names), self._arm_bits[a], a))
            col += len(names)
        for r in rows:
            t = int(r["t_ns"])
            fl = r["flags"]
            full, simp, rate = r["full_nm"].tolist(), r["simplified_nm"].tolist(), r["rate_rad_s"].tolist()
            cmd, cmd_have = r["commanded_nm"].tolist(), r["commanded_have"].tolist()
            cmd_t = r["commanded_t_ns"].tolist()
            bias, bias_have = r["ft_bias"].tolist(), r["ft_bias_have"].tolist()
            touch, touch_have = r["contact"].tolist(), r["contact_have"].tolist()
            for arm, names, lo, hi, bits, a in spans:
                flags = self._flags(fl, bits, a)
                have = all(cmd_have[lo:hi])
                out.append(make_j(arm, t, names, tuple(full[lo:hi]), tuple(simp[lo:hi]),
                                  tuple(cmd[lo:hi]) if have else (), min(cmd_t[lo:hi]) if have else 0,
                                  tuple(rate[lo:hi]), not flags, flags,
                                  tuple(bias[a]) if bias_have[a] else (),
                                  tuple(touch[a]) if touch_have[a] else ()))
            flags = self._flags(fl, self._thr_bits, -1)
            thr = r["thruster"].tolist()
            have = bool(r["thruster_cmd_have"])
            tc = r["thruster_cmd"].tolist()
            out.append(make_t(t, tuple(thr[:3]), tuple(thr[3:]),
                              tuple(tc[:3]) if have else (0.0, 0.0, 0.0), tuple(tc[3:]) if have else (0.0, 0.0, 0.0),
                              int(r["thruster_cmd_t_ns"]) if have else 0, int(r["thruster_cmd_valves"]) if have else 0,
                              not flags, flags))
        return out


def sample_rows(samples: Sequence[Sample], joint_index: dict[str, int], arm_index: dict[str, int]) -> np.ndarray:
    """Driver samples (:mod:`drivers.samples`) -> :data:`SAMPLE_DTYPE` rows, in order. Torque
    commands of joints the model does not have are left out."""
    from drivers.samples import ImuSample, JointSample, ThrusterCommand, TorqueCommand, ValveCommand, WrenchSample

    rows = np.zeros(len(samples), dtype=SAMPLE_DTYPE)
    n = 0
    for s in samples:
        r = rows[n]
        if type(s) is WrenchSample:
            r["kind"], r["device"] = WRENCH, arm_index[s.device]
            r["values"][:6] = (*s.force_n, *s.torque_nm)
            r["saturated"], r["status"] = s.saturated, s.status
        elif type(s) is JointSample:
            r["kind"], r["device"] = JOINT, joint_index[s.device]
            r["values"][:2] = (s.angle_rad, s.rate_rad_s)
            r["saturated"], r["status"] = s.saturated, s.status
        elif type(s) is TorqueCommand:
            j = joint_index.get(s.device)
            if j is None:
                continue
            r["kind"], r["device"] = TORQUE_CMD, j
            r["values"][0] = s.torque_nm
            r["saturated"] = s.saturated
        elif type(s) is ImuSample:
            r["kind"] = IMU
            r["values"][:] = (*s.quat_wxyz, *s.rate_rad_s, *s.accel_m_s2)
            r["saturated"], r["status"] = s.saturated, s.status
        elif type(s) is ThrusterCommand:
            r["kind"] = THRUSTER_CMD
            r["values"][:6] = (*s.force_n, *s.moment_nm)
            r["valves"], r["saturated"] = s.valves, s.saturated
        elif type(s) is ValveCommand:
            r["kind"], r["valves"] = VALVES, s.valves
        else:
            continue
        r["t_ns"] = s.t_ns
        n += 1
    return rows[:n]
