"""The main job: a simulated space robot through the whole path, judged against its truth.

``run_live`` is the path a user deploys, in one process with no external server:
simulator -> sensor firmware -> python-can ``virtual`` buses -> :class:`GatewayService`
(drivers + estimator, one worker thread) -> zenoh (a router on loopback) -> a zenoh subscriber
session that collects the efforts. Lockstep, per bus: every ``LOCKSTEP_NS`` of simulated time the
simulator waits until the gateway has taken every frame it sent on EVERY bus up to the previous
such point, so nothing queues without bound and no bus lags the others by more than about two
intervals (beyond ``max_open`` = 20 ms the estimator's sync policy would declare the lagging bus
silent: on a loaded machine one notifier thread can be starved that long).

With nothing late, the live efforts are the ones :func:`run_offline` computes from the same
frames, bit for bit (the sync policy makes the result independent of how buses interleave).

``run_offline`` is the same frames through the same :class:`Pipeline` without buses or zenoh
(deterministic, for the noise sweep); ``run_frames`` feeds recorded frames (the live run's, for
the wrong-model run). ``accuracy`` turns estimates and truth into the figures of ``report.json``.
"""
from __future__ import annotations

import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gateway.efforts import JointEfforts, ThrusterEffort
from gateway.zenoh_config import free_port

AXES = ("fx", "fy", "fz", "mx", "my", "mz")
LOCKSTEP_NS = 5_000_000               # lockstep check every 5 ms of simulated time (see run_live)
QUIET_S = 2.0                         # after the run: no new effort for this long = the rest were lost
JUDGE_FRACTION = 0.05                 # channels below 5 % of the largest peak of their kind: not judged
TARGETS = {"force": 0.01, "moment": 0.02, "simplified_first_joint": 0.02, "full": 0.02}
BAND_HZ = 20.0


@dataclass
class Estimates:
    """Efforts collected per epoch (index = step k = t_ns / 1 ms), NaN where none arrived."""

    thrusters: np.ndarray      # (N, 6)
    full: np.ndarray           # (N, n)
    simplified: np.ndarray     # (N, n)
    good: np.ndarray           # (N,) thruster effort good
    received: int
    contact: np.ndarray | None = None   # (N, p, 6) the published contact wrench per arm, NaN out of contact

    @classmethod
    def empty(cls, n_steps: int, n_joints: int, n_arms: int = 1) -> "Estimates":
        nan = np.full
        return cls(nan((n_steps, 6), np.nan), nan((n_steps, n_joints), np.nan), nan((n_steps, n_joints), np.nan),
                   np.zeros(n_steps, dtype=bool), 0, nan((n_steps, n_arms, 6), np.nan))


class Collector:
    """Puts efforts into :class:`Estimates` arrays (thread-safe enough: one writer per epoch)."""

    def __init__(self, robot, n_steps: int, step_ns: int = 1_000_000):
        self.est = Estimates.empty(n_steps, robot.n_joints, len(robot.arms))
        self.step_ns = step_ns
        self.cols = {}
        self.arm_index = {a.name: i for i, a in enumerate(robot.arms)}
        col = 0
        for a in robot.arms:
            self.cols[a.name] = slice(col, col + a.n)
            col += a.n
        self.n = n_steps
        self.count = 0
        self.done = threading.Event()
        self.expected: int | None = None

    def add(self, obj) -> None:
        k = int(round(obj.t_ns / self.step_ns))
        if not 0 <= k < self.n:
            return
        if isinstance(obj, ThrusterEffort):
            self.est.thrusters[k, :3], self.est.thrusters[k, 3:] = obj.force_n, obj.moment_nm
            self.est.good[k] = obj.good
        elif isinstance(obj, JointEfforts):
            sl = self.cols[obj.arm]
            self.est.full[k, sl] = obj.full_nm
            self.est.simplified[k, sl] = obj.simplified_nm
            if obj.contact and self.est.contact is not None:
                self.est.contact[k, self.arm_index[obj.arm]] = obj.contact
        else:
            return
        self.count += 1
        self.est.received = self.count
        if self.expected is not None and self.count >= self.expected:
            self.done.set()


# --- runs ------------------------------------------------------------------------------------

def _collect(col: Collector):
    """A session sink that puts efforts into ``col``."""
    from gateway.engine import Sink

    class Collect(Sink):
        def emit(self, key, obj, log_ns) -> None:
            col.add(obj)

    return Collect()


def run_offline(scenario, *, model_robot=None, layout=None, settings=None):
    """Simulator -> firmware frames -> a session, in lockstep in this thread. Returns (trace, Estimates, stats).
    ``settings``: the estimator's (:class:`gateway.estimator.core.CoreSettings`; None: the defaults)."""
    from gateway.engine import Session
    from robot_description.thrusters import ThrusterLayout
    from simulator.engine import Simulation
    from simulator.firmware import Firmware

    sim = Simulation(scenario)
    fw = Firmware(sim.robot)
    col = Collector(sim.robot, sim.n_steps)
    ses = Session(sim.robot, [_collect(col)], model_robot=model_robot, samples=False, settings=settings,
                  layout=layout or ThrusterLayout.from_config(scenario.cfg.thrusters))
    feed = ses.feed
    while sim.k < sim.n_steps:
        for bus, msg in fw.frames(sim.step()):
            feed(bus, msg)
    ses.close()
    return sim.trace, col.est, ses.stats


def run_frames(robot, frames, n_steps: int, *, model_robot=None, layout=None):
    """Recorded ``(bus, can.Message)`` frames -> the same session as :func:`run_offline` (e.g. the
    frames of a live run again, with a deliberately wrong model). Returns (Estimates, stats)."""
    from gateway.engine import Session

    col = Collector(robot, n_steps)
    ses = Session(robot, [_collect(col)], model_robot=model_robot, layout=layout, samples=False)
    feed = ses.feed
    for bus, msg in frames:
        feed(bus, msg)
    ses.close()
    return col.est, ses.stats


class _CountingBus:
    """A transmit bus that counts what was sent on it (for the per-bus lockstep) and, when given
    a list, keeps ``(bus, frame)`` in send order."""

    __slots__ = ("bus", "name", "sent", "keep")

    def __init__(self, bus, name: str, keep: list | None):
        self.bus, self.name, self.sent, self.keep = bus, name, 0, keep

    def send(self, msg, timeout=None) -> None:
        self.bus.send(msg, timeout=timeout)
        self.sent += 1
        if self.keep is not None:
            self.keep.append((self.name, msg))


def run_live(scenario, *, record: Path | None = None, progress: bool = False, timeout_s: float = 120.0,
             frames: list | None = None):
    """The deployed path in one process (see the module docstring). Returns (trace, Estimates, info).
    ``frames``: a list that receives every ``(bus, can.Message)`` sent, in order (for
    :func:`run_frames`)."""
    import zenoh

    from gateway import codec, keys
    from gateway.bridge import GatewayService
    from gateway.log.recorder import Recorder
    from gateway.zenoh_config import make_config
    from robot_description.thrusters import ThrusterLayout
    from simulator.engine import Simulation
    from simulator.firmware import Firmware, open_buses, run_on_buses

    sim = Simulation(scenario)
    robot = sim.robot
    fw = Firmware(robot)
    col = Collector(robot, sim.n_steps)
    ep = f"tcp/127.0.0.1:{free_port()}"
    prefix = f"bsc-demo-{uuid.uuid4().hex[:8]}"
    info: dict = {"zenoh_endpoint": ep, "can": f"virtual, channels {prefix}-<bus>"}
    rec = None
    # the firmware stamps frames with simulated time from 0: the log's times are the wall clock of
    # this run (messages, metadata and attachments on one base, as a real robot's session)
    wall0 = time.time_ns()
    if record is not None:
        rec = Recorder(record)
        from gateway.log.context import session_context
        rec.add_session_context(**session_context(robot, scenario_text=scenario.text))
    t0 = time.perf_counter()
    waits = {"lockstep_s": 0.0, "gave_up": 0}
    try:
        with zenoh.open(make_config(mode="router", listen=[ep])) as gw_session, \
                zenoh.open(make_config(mode="client", connect=[ep])) as sub_session, \
                open_buses(robot, "virtual", prefix) as tx, \
                open_buses(robot, "virtual", prefix) as rx:
            # efforts queue up in zenoh (Rust, no GIL) and are decoded here in batches: a Python
            # callback would hold the receiving thread on the GIL, and the gateway's publishers
            # drop (they never block the gateway) when zenoh's queues fill up behind it
            sub = sub_session.declare_subscriber(keys.efforts(robot.name), zenoh.handlers.FifoChannel(1 << 22))
            take = _decoder(col)

            def drain() -> None:
                while (sample := sub.try_recv()) is not None:
                    take(sample)

            if not codec.wait_for_subscriber(gw_session, keys.efforts(robot.name)):
                raise RuntimeError("the demo's zenoh subscription never reached the gateway's session")
            layout = ThrusterLayout.from_config(scenario.cfg.thrusters)
            counting = {name: _CountingBus(bus, name, frames) for name, bus in tx.items()}
            with GatewayService(robot, rx, gw_session, layout=layout, record=rec, log_offset_ns=wall0) as gw:
                states = [(b, gw.bus_state[name]) for name, b in counting.items()]
                marks = {name: 0 for name in counting}

                def catch_up(goals) -> None:
                    """Wait until the gateway took every frame up to ``goals[bus]`` on every bus."""
                    w0 = time.perf_counter()
                    for b, st in states:
                        last_progress, seen = w0, -1
                        while st.processed + st.dropped < goals[st.name]:
                            time.sleep(0.0002)
                            done = st.processed + st.dropped
                            if done != seen:
                                seen, last_progress = done, time.perf_counter()
                            elif time.perf_counter() - last_progress > 5.0:
                                waits["gave_up"] += 1         # a frame the bus never delivered
                                break
                    waits["lockstep_s"] += time.perf_counter() - w0

                def throttle(r):
                    if r.t_ns % LOCKSTEP_NS:
                        return
                    if r.t_ns % 100_000_000 == 0:
                        drain()
                    catch_up(marks)                 # up to the previous check
                    for b, st in states:
                        marks[st.name] = b.sent
                trace = run_on_buses(sim, counting, firmware=fw, progress=progress, on_step=throttle)
                catch_up({st.name: b.sent for b, st in states})
                gw.drain()
                # efforts published so far (the epochs still open are computed when the service
                # closes, after its publishers are gone: they are not on zenoh)
                epochs = gw.engine.stats["epochs"]
            col.expected = epochs * (len(robot.arms) + 1)
            # wait for the last efforts; stop early when none has come for QUIET_S (lost on the way:
            # the gateway's publishers drop rather than block when zenoh's queues are full)
            deadline = time.monotonic() + timeout_s
            last, quiet_since = -1, time.monotonic()
            while True:
                drain()
                now = time.monotonic()
                if col.count >= col.expected or now > deadline or now - quiet_since > QUIET_S:
                    break
                if col.count != last:
                    last, quiet_since = col.count, now
                time.sleep(0.01)
            sub.undeclare()
            info.update(gw.engine.stats)
            info["published"] = gw.published
            info["gateway"] = {k: v for k, v in gw.stats.items() if k != "buses"}
    finally:
        if rec is not None:
            rec.close()
            info["recording"] = str(record)
            info["recorded_messages"] = rec.stats.written
    info["wall_s"] = round(time.perf_counter() - t0, 2)
    info["lockstep_wait_s"] = round(waits["lockstep_s"], 2)
    if waits["gave_up"]:
        info["lockstep_gave_up"] = waits["gave_up"]
    info["efforts_expected"] = col.expected
    info["efforts_received"] = col.count
    return trace, col.est, info


def _decoder(col: Collector):
    from gateway import codec

    def on_sample(sample) -> None:
        try:
            col.add(codec.decode(bytes(sample.payload)))
        except codec.CodecError:
            pass
    return on_sample


# --- accuracy --------------------------------------------------------------------------------

def lowpass(x: np.ndarray, hz: float = BAND_HZ, fs: float = 1000.0) -> np.ndarray:
    """Zero-phase 4th-order Butterworth low-pass (for the band-limited figures)."""
    from scipy.signal import butter, filtfilt

    b, a = butter(4, hz, fs=fs)
    return filtfilt(b, a, x, axis=0)


def _fill(x: np.ndarray) -> np.ndarray:
    """Holds the last value over NaN gaps (epochs without an estimate) so filters can run."""
    x = x.copy()
    for j in range(x.shape[1]):
        col = x[:, j]
        bad = np.isnan(col)
        if bad.all():
            col[:] = 0.0
        elif bad.any():
            idx = np.where(~bad, np.arange(len(col)), 0)
            np.maximum.accumulate(idx, out=idx)
            col[:] = col[idx]
            col[:np.argmax(~bad)] = col[np.argmax(~bad)]
    return x


def channel_stats(est: np.ndarray, act: np.ndarray) -> dict:
    e = est - act
    ok = ~np.isnan(e)
    peak = float(np.max(np.abs(act)))
    rms = float(np.sqrt(np.mean(e[ok] ** 2))) if ok.any() else float("nan")
    return {"nrmse": rms / peak if peak > 0 else float("nan"), "max_err": float(np.max(np.abs(e[ok]))) if ok.any()
            else float("nan"), "peak": peak, "missing": int((~ok).sum())}


def accuracy(trace, est: Estimates, joint_names: list[str], first_joints: set[str]) -> dict:
    """The figures of report.json: raw and band-limited, judged against the targets."""
    A = trace.arrays
    out: dict = {"thrusters": {}, "joints": {}, "band_limited_20hz": {"thrusters": {}, "joints": {}}}
    act = A["thr_act"]
    peaks = np.max(np.abs(act), axis=0)
    kind_peak = {"force": peaks[:3].max(), "moment": peaks[3:].max()}
    est_f, act_f = lowpass(_fill(est.thrusters)), lowpass(act)
    for i, ax in enumerate(AXES):
        kind = "force" if i < 3 else "moment"
        s = channel_stats(est.thrusters[:, i], act[:, i])
        # an axis that never fired has nothing to judge (its NRMSE divides by a zero peak)
        s["judged"] = bool(s["peak"] > 0 and s["peak"] >= JUDGE_FRACTION * kind_peak[kind])
        s["target"] = TARGETS[kind]
        s["pass"] = (not s["judged"]) or s["nrmse"] <= TARGETS[kind]
        out["thrusters"][ax] = s
        out["band_limited_20hz"]["thrusters"][ax] = channel_stats(est_f[:, i], act_f[:, i])
    tau = A["tau_act"]
    full_f, simp_f, tau_f = lowpass(_fill(est.full)), lowpass(_fill(est.simplified)), lowpass(tau)
    for j, name in enumerate(joint_names):
        sf = channel_stats(est.full[:, j], tau[:, j])
        ss = channel_stats(est.simplified[:, j], tau[:, j])
        sf["target"] = TARGETS["full"]
        sf["pass"] = sf["nrmse"] <= TARGETS["full"]
        first = name in first_joints
        ss["judged"] = first
        if first:
            ss["target"] = TARGETS["simplified_first_joint"]
        ss["pass"] = (not first) or ss["nrmse"] <= TARGETS["simplified_first_joint"]
        out["joints"][name] = {"simplified": ss, "full": sf, "peak": sf["peak"]}
        out["band_limited_20hz"]["joints"][name] = {"simplified": channel_stats(simp_f[:, j], tau_f[:, j]),
                                                    "full": channel_stats(full_f[:, j], tau_f[:, j])}
    out["pass"] = (all(s["pass"] for s in out["thrusters"].values())
                   and all(v["simplified"]["pass"] and v["full"]["pass"] for v in out["joints"].values()))
    return out


CONTACT_GRACE_S = 0.5      # after a contact ends, the flag may take this long to drop (not a false contact)


def contacts(trace, est: Estimates, robot, items: list[dict]) -> dict:
    """What the gateway made of the scenario's ``[[contact]]`` tables (report.json ``contacts``).

    Per table: when the arm's contact flag rose after the onset (``flagged_after_s``, None if
    never during the contact), how long after the contact's end it dropped (``released_after_s``),
    and the published wrench against the truth while flagged within the contact (RMS, force N and
    moment about the end effector N m, spacecraft body axes). ``false_contact_s``: flagged time
    outside every contact of the arm (and its grace), per arm."""
    import pinocchio as pin

    from simulator.contact import Contacts

    c = Contacts(robot, items)
    A = trace.arrays
    t = A["t_s"]
    n = len(t)
    dt = float(t[1] - t[0]) if n > 1 else 1e-3
    flagged = ~np.isnan(est.contact[:, :, 0]) if est.contact is not None else np.zeros((n, len(robot.arms)), bool)
    model, data = robot.model, robot.model.createData()
    truth = np.zeros((n, len(robot.arms), 6))
    busy = np.zeros((n, len(robot.arms)), dtype=bool)
    for item in c.items:
        k0, k1 = int(round(item.onset / dt)), min(n, int(round(item.end / dt)))
        busy[k0:min(n, k1 + int(round(CONTACT_GRACE_S / dt))), item.arm] = True
        for k in range(k0, k1):
            q = A["q"][k]
            pin.forwardKinematics(model, data, q)
            w = c.world_wrench(float(t[k]), data.oMi)[item.arm]
            R = pin.Quaternion(q[6], q[3], q[4], q[5]).matrix()     # body -> world (xyzw)
            truth[k, item.arm] = np.concatenate([R.T @ w[:3], R.T @ w[3:]])
    out: dict = {"contacts": [], "false_contact_s": {}}
    for item in c.items:
        a = item.arm
        k0, k1 = int(round(item.onset / dt)), min(n, int(round(item.end / dt)))
        during = flagged[k0:k1, a]
        row = {"arm": robot.arms[a].name, "onset_s": round(item.onset, 4), "end_s": round(item.end, 4),
               "peak_force_n": round(float(np.abs(truth[k0:k1, a, :3]).max(initial=0.0)
                                           if k1 > k0 else 0.0), 3),
               "flagged_after_s": round(float(np.argmax(during)) * dt, 4) if during.any() else None,
               "released_after_s": None, "force_rms_error_n": None, "moment_rms_error_nm": None}
        after = flagged[k1:, a]
        if during.any():
            row["released_after_s"] = round(float(np.argmin(after)) * dt, 4) if (~after).any() else None
            sel = np.flatnonzero(during) + k0
            err = est.contact[sel, a] - truth[sel, a]
            row["force_rms_error_n"] = round(float(np.sqrt((err[:, :3] ** 2).sum(axis=1).mean())), 3)
            row["moment_rms_error_nm"] = round(float(np.sqrt((err[:, 3:] ** 2).sum(axis=1).mean())), 3)
        out["contacts"].append(row)
    for a, arm in enumerate(robot.arms):
        out["false_contact_s"][arm.name] = round(float((flagged[:, a] & ~busy[:, a]).sum()) * dt, 4)
    return out


def format_contacts(rep: dict) -> str:
    """:func:`contacts` as the demo prints it."""
    def ms(x):
        return "never" if x is None else f"{1000 * x:.0f} ms"

    rows = [("contact (scenario)", "force", "flagged after", "released after", "force error", "moment error")]
    for c in rep["contacts"]:
        rows.append((f"{c['arm']} {c['onset_s']:g}-{c['end_s']:g} s", f"{c['peak_force_n']:.1f} N",
                     ms(c["flagged_after_s"]), ms(c["released_after_s"]),
                     "-" if c["force_rms_error_n"] is None else f"{c['force_rms_error_n']:.2f} N",
                     "-" if c["moment_rms_error_nm"] is None else f"{c['moment_rms_error_nm']:.2f} N m"))
    false = ", ".join(f"{a} {s:g} s" for a, s in rep["false_contact_s"].items() if s) or "none"
    return "\n".join(columns(rows, "lrrrrr") + [f"(RMS errors of the published contact wrench while flagged; "
                                                 f"flagged outside every contact: {false})"])


def summary_row(acc: dict) -> dict:
    """Worst judged NRMSE per kind: the one-line figures of the sweep and robustness tables
    (NaN for a kind with nothing judged, e.g. no thruster fired in a short run)."""
    thr = acc["thrusters"]
    judged = {k: v for k, v in thr.items() if v["judged"]}
    nan = float("nan")
    return {
        "force_nrmse_max": max((v["nrmse"] for k, v in judged.items() if k.startswith("f")), default=nan),
        "moment_nrmse_max": max((v["nrmse"] for k, v in judged.items() if k.startswith("m")), default=nan),
        "simplified_first_joint_nrmse_max": max((v["simplified"]["nrmse"] for v in acc["joints"].values()
                                                 if v["simplified"]["judged"]), default=nan),
        "full_nrmse_max": max((v["full"]["nrmse"] for v in acc["joints"].values()), default=nan),
        "pass": acc["pass"],
    }


def missed(acc: dict) -> list[str]:
    """The judged figures that missed their target, one phrase each (``arm0/j2 full 3.10 % > 2 %``)."""
    out = [f"thruster {ax} {pct(s['nrmse'])} > {pct(s['target'], 0)}"
           for ax, s in acc["thrusters"].items() if not s["pass"]]
    for name, v in acc["joints"].items():
        for form in ("simplified", "full"):
            s = v[form]
            if not s["pass"]:
                out.append(f"{name} {form} {pct(s['nrmse'])} > {pct(s['target'], 0)}")
    return out


def pct(x: float, digits: int = 2) -> str:
    """A fraction as a percentage for the tables (``0.0135`` -> ``1.35 %``), ``-`` when undefined."""
    return f"{100 * x:.{digits}f} %" if np.isfinite(x) else "-"


def columns(rows: list[tuple[str, ...]], align: str) -> list[str]:
    """Cells -> lines, each column as wide as its widest cell (``align``: ``l``/``r`` per column),
    so long joint names (``left_arm/elbow_pitch``) keep the columns straight."""
    widths = [max(len(r[i]) for r in rows) for i in range(len(align))]
    return ["  ".join(c.ljust(w) if a == "l" else c.rjust(w) for c, w, a in zip(r, widths, align)).rstrip()
            for r in rows]


def quantities(values: list[float], units: list[str]) -> list[str]:
    """``12.3 N`` / ``7.7 N m`` cells whose numbers line up (one column of a table)."""
    nums = [f"{v:.1f}" if np.isfinite(v) else "-" for v in values]
    w, wu = max(map(len, nums)), max(map(len, units))
    return [f"{n:>{w}} {u:<{wu}}" for n, u in zip(nums, units)]


def format_table(acc: dict) -> str:
    """The accuracy tables ``bsc demo`` prints: thruster axes, joints, and what is judged."""
    frac = pct(JUDGE_FRACTION, 0)
    thr = acc["thrusters"]
    units = ["N" if ax.startswith("f") else "N m" for ax in thr]
    err = quantities([s["max_err"] for s in thr.values()], units)
    peak = quantities([s["peak"] for s in thr.values()], units)
    rows = [("thruster axis", "NRMSE", "target", "max error", "peak", "judged", "")]
    for (ax, s), e, p in zip(thr.items(), err, peak):
        kind = "force" if ax.startswith("f") else "moment"
        judged = ("yes" if s["judged"] else "no: never fired" if not s["peak"] > 0
                  else f"no: peak below {frac} of the largest {kind}")
        rows.append((ax, pct(s["nrmse"]), pct(s["target"], 0), e, p, judged, "" if s["pass"] else "MISSED"))
    lines = columns(rows, "lrrrrll")
    joints = acc["joints"]
    peak = quantities([v["peak"] for v in joints.values()], ["N m"] * len(joints))
    rows = [("joint", "simplified", "", "full", "", "peak", "")]
    for (name, v), p in zip(joints.items(), peak):
        simp, full = v["simplified"], v["full"]
        rows.append((name, pct(simp["nrmse"]), "judged" if simp["judged"] else "reported", pct(full["nrmse"]),
                     "judged", p, "" if simp["pass"] and full["pass"] else "MISSED"))
    lines += [""] + columns(rows, "lrlrlrl") + [""]
    lines += [
        "NRMSE = RMS error / peak of the actual value, at 1 kHz. judged: held to its target (joints "
        f"{pct(TARGETS['full'], 0)});",
        f"reported: printed only, never a miss. A thruster axis whose peak is below {frac} of the largest",
        "of its kind is reported. The full joint torque is judged on every joint; the simplified one (the",
        "paper's form, link inertia neglected) is exact only next to the sensor: judged on each arm's first",
        "joint, reported on the others.",
    ]
    return "\n".join(lines)
