"""Synthetic effort streams with known friction, efficiency and F/T bias (shared by the tests).

A joint residual ``commanded - estimated`` is ``Fc sign(dq) + Fv dq + bias(q) + noise``; an F/T
bias adds a pose-dependent term to EVERY joint of its arm and a constant wrench to the thruster
estimate; a thruster loss scales the estimated wrench.
"""
from __future__ import annotations

import numpy as np

from gateway import keys
from gateway.efforts import JointEfforts, ThrusterEffort
from gateway.log.recorder import Recorder
from harness.series import EPOCH_NS, SERIES_METADATA, SESSION_SPACING_NS

ROBOT = "synthbot"
ARMS = {"arm0": ("arm0/j1", "arm0/j2"), "arm1": ("arm1/j1", "arm1/j2")}


def joint_stream(rng, n, coulomb, viscous=5.0, ft_bias=0.0, noise=2.0, rate_hz=200.0):
    """Per arm: (t_ns, q, dq, cmd, est) arrays; ``coulomb``: {joint: Nm}; ``ft_bias``: {arm: N m scale}."""
    t = np.arange(n) * int(1e9 / rate_hz)
    out = {}
    for k, (arm, joints) in enumerate(ARMS.items()):
        phase = rng.uniform(0, 2 * np.pi, len(joints))
        s = t / 1e9
        dq = np.stack([0.3 * np.sin(2 * np.pi * 0.25 * s + p) for p in phase], axis=1)
        q = np.stack([0.3 / (2 * np.pi * 0.25) * (1 - np.cos(2 * np.pi * 0.25 * s + p)) for p in phase], axis=1)
        cmd = rng.normal(0, 200, (n, len(joints)))
        b = (ft_bias or {}).get(arm, 0.0)
        res = np.empty_like(cmd)
        for i, j in enumerate(joints):
            res[:, i] = (coulomb[j] * np.sign(dq[:, i]) + viscous * dq[:, i]
                         + b * (1.0 + 0.5 * i * np.cos(q[:, 0]))     # A_tau(q) b: every joint, pose dependent
                         + rng.normal(0, noise, n))
        out[arm] = (t, q, dq, cmd, cmd - res)
    return out


def _touch(contact: dict, arm: str, i: int) -> tuple:
    if arm in contact and contact[arm][0] <= i < contact[arm][1]:
        return tuple(contact[arm][2])
    return ()


def write_session(path, k, *, coulomb=None, efficiency=0.9, ft_bias=None, thr_offset=0.0, seed=0, n=4000,
                  series="synth", contact=None):
    """One synthetic session log with ``bsc.series`` metadata (session index ``k``); ``contact``:
    arm -> ``(i0, i1, wrench)``, the arm's efforts from message i0 to i1 (excluded) carry it."""
    contact = contact or {}
    rng = np.random.default_rng(seed)
    coulomb = coulomb or {j: 90.0 for js in ARMS.values() for j in js}
    base = EPOCH_NS + k * SESSION_SPACING_NS
    meta = {"series": series, "session_index": str(k), "start_ns": str(base)}
    joints = joint_stream(rng, n, coulomb, ft_bias=ft_bias)
    t = joints["arm0"][0]
    cmd_w = rng.normal(0, 60, (n, 6)) * np.array([1, 1, 0.02, 0.02, 0.02, 5])
    valves = (np.abs(cmd_w[:, 0]) > 30).astype(int)
    quiet = (np.arange(n) // 200) % 5 == 0       # every 5th second nothing fires
    cmd_w[quiet] = 0.0
    valves[quiet] = 0
    est_w = efficiency * cmd_w + thr_offset + rng.normal(0, 2.0, (n, 6))
    with Recorder(path, overwrite=True, metadata={SERIES_METADATA: meta}) as rec:
        for i in range(n):
            for arm, (tt, q, dq, cmd, est) in joints.items():
                rec.record(keys.joint_efforts(ROBOT, arm), JointEfforts(
                    arm=arm, t_ns=int(tt[i]), joints=ARMS[arm], full_nm=tuple(est[i]), simplified_nm=tuple(est[i]),
                    commanded_nm=tuple(cmd[i]), commanded_t_ns=int(tt[i]), rate_rad_s=tuple(dq[i]), good=True,
                    contact=_touch(contact, arm, i)),
                    base + int(tt[i]))
            rec.record(keys.thruster_effort(ROBOT), ThrusterEffort(
                t_ns=int(t[i]), force_n=tuple(est_w[i, :3]), moment_nm=tuple(est_w[i, 3:]),
                commanded_force_n=tuple(cmd_w[i, :3]), commanded_moment_nm=tuple(cmd_w[i, 3:]),
                commanded_t_ns=int(t[i]), valves=int(valves[i]), good=True), base + int(t[i]))
    return path
