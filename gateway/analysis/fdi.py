"""Thruster faults within one recorded session: which thruster, which fault, when (``bsc analyze``).

The log's raw CAN frames go through fresh drivers and the estimator (as ``bsc replay`` does);
the valve-aided thruster filter then runs again over the same trusted steps and IMU samples with
the detector of :mod:`gateway.estimator.fdi` after every update (the maths the live gateway
would run, one implementation). Each epoch's arms' wrench is the F/T sensors' (``arm_reaction``),
its valves the command of that epoch; which epochs are trusted and where each sample belongs
are the estimator's own decisions (the epochs it computed and their flags). No baseline session
is needed: a stuck or leaking valve, or a lost fraction of a thruster's thrust, shows against the
valve-explained wrench within the session.
"""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from .session import AnalysisError


class NoRawFrames(AnalysisError):
    """A log without the raw CAN frames of the robot's buses (efforts only): nothing to check."""


@dataclass(frozen=True)
class ThrusterAlarm:
    """One thruster fault found in a session. ``t_s``: when it was raised, s from the session's
    first epoch; ``theta``: the fault's size as a fraction of nominal thrust (the leak or the
    lost part; a misalignment's tilt in degrees); ``stat``: the GLR statistic when raised;
    ``window``: ``short`` (gross faults) or ``long``; ``efficiency``: the thruster's learned
    efficiency at the end of the session;
    ``detected_t_s``: when the detector first named the thruster (the type then takes
    :attr:`FdiSettings.confirm_short` or ``confirm_long`` more updates)."""

    thruster: int
    fault: str
    t_s: float
    t_ns: int
    detected_t_s: float
    theta: float
    stat: float
    window: str
    efficiency: float

    @property
    def target(self) -> str:
        return f"thruster{self.thruster}"

    def message(self) -> str:
        from gateway.estimator.fdi import size_text

        size = size_text(self.fault, self.theta)
        return (f"thruster {self.thruster} {self.fault}, named {self.t_s:.2f} s into the session "
                f"({size}; GLR {self.stat:.0f})")

    def to_json(self) -> dict:
        return asdict(self) | {"target": self.target}


@dataclass
class FdiResult:
    """The detector's findings in one session, and its traces for plots and benchmarks."""

    path: str
    alarms: list[ThrusterAlarm] = field(default_factory=list)
    t0_ns: int = 0
    imu_t_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    stat: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))    # short T, its hyp., long T, its hyp.
    efficiency: np.ndarray = field(default_factory=lambda: np.zeros(0))   # learned, end of session
    updates: int = 0
    epochs: int = 0
    valve_t_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))   # trusted steps
    valve_masks: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # their commands
    wrench: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))   # per trusted step, faults modelled
    live_t_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))    # every epoch
    live_wrench: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))  # what the estimator published

    def first(self, thruster: int | None = None) -> ThrusterAlarm | None:
        for a in self.alarms:
            if thruster is None or a.thruster == thruster:
                return a
        return None


def _layout_and_robot(src: Path, robot_name: str | None = None):
    from gateway.log.context import read_context, resolve_robot
    from gateway.log.names import SCENARIO_ATTACHMENT
    from robot_description.thrusters import ThrusterLayout

    ctx = read_context(src)
    if not ctx.buses:
        raise NoRawFrames(f"{src}: no raw CAN frames to analyse for thruster faults")
    rob = resolve_robot(ctx, robot_name)
    scenario = ctx.attachments.get(SCENARIO_ATTACHMENT)
    layout = (ThrusterLayout.from_scenario_text(scenario[1].decode("utf-8", "replace"), f"{src}: scenario")
              if scenario else ThrusterLayout.named())
    return ctx, rob, layout


def _decode(src: Path, ctx, rob, layout):
    """Sample rows and effort rows of the log's raw frames, through a fresh Session."""
    from gateway.engine import Session, Sink
    from gateway.log.frames import batched, mcap_frames
    from gateway.log.reader import iter_can_frames

    samples: list[np.ndarray] = []
    efforts: list[np.ndarray] = []

    class Collect(Sink):
        rows = True

        def sample_rows(self, session, events, log_ns) -> None:
            samples.append(events.copy())

        def effort_rows(self, session, rows, log_ns) -> None:
            efforts.append(rows.copy())

    ses = Session(rob, [Collect()], layout=layout, samples=True)
    known = set(ses.buses)
    buses = [b for b in ctx.buses if b in known]
    if not buses:
        raise NoRawFrames(f"{src}: no raw CAN frames of the robot's buses to analyse for thruster faults")
    chunks = mcap_frames(src, buses)
    if chunks is not None:
        chunks = batched(chunks)                 # fewer, larger calls; the same bits
        to_session = np.array([ses.buses.index(b) for b in buses], dtype=np.int64)
        for chunk in chunks:
            rows = chunk.frames.copy()
            rows["bus"] = to_session[rows["bus"]]
            ses.feed_frames(rows, chunk.log_ns)
    else:
        for bus, t, msg in iter_can_frames(src, buses=buses):
            ses.feed(bus, msg, log_ns=t)
    ses.close()
    core = ses.pipeline.estimator
    if not samples or not efforts:
        raise AnalysisError(f"{src}: the raw frames gave no samples or no epochs")
    return np.concatenate(samples), np.concatenate(efforts), core


def event_stream(samples: np.ndarray, efforts: np.ndarray, core) -> dict[str, np.ndarray]:
    """The thruster filter's inputs as the estimator applied them: one STEP per trusted epoch (its
    arms' wrench from the F/T samples, its valve mask) and one IMU event per IMU sample at its
    epoch's time, in time order (a step before the IMU sample that ends on it)."""
    from drivers import kernel
    from gateway.estimator import thruster_kernel as tk
    from gateway.estimator.wrench import arm_reaction

    if not len(efforts):
        raise AnalysisError("no epochs were computed (is the log missing its F/T or valve frames?)")
    t_ep = efforts["t_ns"].astype(np.int64)
    order = np.argsort(t_ep, kind="stable")
    t_ep = t_ep[order]
    flags = efforts["flags"][order].astype(bool)
    names = core.flag_names
    bad = [k for k, f in enumerate(names) if f == "missing:valves" or any(f == f"{w}:{a}" for a in core.arms
                                                                           for w in ("missing", "saturated", "fault"))]
    trusted = ~flags[:, bad].any(axis=1)
    half = core.period_ns // 2

    def slot(t):
        i = np.clip(np.searchsorted(t_ep, t), 1, len(t_ep) - 1) if len(t_ep) > 1 else np.zeros(len(t), dtype=int)
        i = np.where(np.abs(t_ep[i - 1] - t) <= np.abs(t_ep[i] - t), i - 1, i) if len(t_ep) > 1 else i
        return i, np.abs(t_ep[i] - t) < half

    p = core.n_arms
    ft = np.zeros((len(t_ep), p, 6))
    have_ft = np.zeros((len(t_ep), p), dtype=bool)
    mask = np.zeros(len(t_ep), dtype=np.int64)
    s = samples
    w = s[s["kind"] == kernel.WRENCH]
    i, ok = slot(w["t_ns"])
    ft[i[ok], w["device"][ok]] = w["values"][ok, :6]
    have_ft[i[ok], w["device"][ok]] = True
    v = s[s["kind"] == kernel.VALVE]
    i, ok = slot(v["t_ns"])
    mask[i[ok]] = v["valves"][ok]
    trusted &= have_ft.all(axis=1)
    arm = arm_reaction(core.model, ft)
    imu = s[s["kind"] == kernel.IMU]
    i, ok = slot(imu["t_ns"])
    imu, gi = imu[ok], i[ok]
    ks = np.flatnonzero(trusted)
    n_step, n_imu = len(ks), len(imu)
    kind = np.concatenate([np.full(n_step, tk.STEP), np.full(n_imu, tk.IMU)]).astype(np.int64)
    t = np.concatenate([t_ep[ks], t_ep[gi]]).astype(np.int64)
    key = np.lexsort((kind, t))
    arm_rows = np.concatenate([arm[ks], np.zeros((n_imu, 6))])
    masks = np.concatenate([mask[ks], np.zeros(n_imu, dtype=np.int64)])
    accel = np.concatenate([np.zeros((n_step, 3)), imu["values"][:, 7:10]])
    rate = np.concatenate([np.zeros((n_step, 3)), imu["values"][:, 4:7]])
    return {"kind": np.ascontiguousarray(kind[key]), "t_ns": np.ascontiguousarray(t[key]),
            "arm": np.ascontiguousarray(arm_rows[key]), "masks": np.ascontiguousarray(masks[key]),
            "accel": np.ascontiguousarray(accel[key]), "rate": np.ascontiguousarray(rate[key]),
            "epochs": len(t_ep)}


def detect(stream: dict, core, layout, settings=None, max_events: int = 64):
    """Run the thruster filter and the detector over an event stream (:func:`event_stream`);
    ``(events (k, 7), stat (N, 4), filter)``; the stream gains ``wrench`` (N, 6), each step's
    thruster wrench with the faults found so far modelled."""
    from gateway.estimator import fdi
    from gateway.estimator import thruster_kernel as tk

    s = core.settings
    kf = tk.CompiledThrusterFilter(core.model, layout, dt=core.period_ns * 1e-9,
                                   imu_steps=max(1, int(core.cfg[4]) // core.period_ns), settings=s.thrusters)
    settings = settings or fdi.FdiSettings()
    st = fdi.new_state(layout.n, max_events)
    cfg = settings.config(layout.n, core.cfg[4] * 1e-9)
    Wnom = fdi.signatures(layout, kf.W)
    Ha = np.ascontiguousarray(kf.state[3][tk._HA:tk._HA + 18])
    tap = np.zeros(tk.tap_size(layout.n))
    out = np.zeros((len(stream["kind"]), 4))
    wrench = np.zeros((len(stream["kind"]), 6))
    try:
        fdi.run_events(*kf.state, stream["kind"], stream["t_ns"], stream["arm"], stream["masks"], stream["accel"],
                       stream["rate"], st, cfg, Wnom, Ha, tap, out, wrench)
    except ValueError as exc:
        raise AnalysisError(f"the thruster filter failed: {exc}") from None
    stream["wrench"] = wrench
    return fdi.events(st, layout.n), out, kf


def analyze_thrusters(path: str | os.PathLike[str], *, robot: str | None = None, settings=None) -> FdiResult:
    """Thruster faults in the session log ``path`` (an MCAP log with raw CAN frames)."""
    from gateway.estimator import fdi
    from gateway.log.errors import LogError
    from gateway.log.reader import readable

    path = Path(path)
    try:
        with readable(path) as src:
            ctx, rob, layout = _layout_and_robot(Path(src), robot)
            samples, efforts, core = _decode(Path(src), ctx, rob, layout)
    except (LogError, OSError) as exc:
        raise AnalysisError(str(exc) if str(exc).startswith(str(path)) else f"{path}: {exc}") from None
    stream = event_stream(samples, efforts, core)
    ev, stat, kf = detect(stream, core, layout, settings)
    t0 = int(stream["t_ns"][0]) if len(stream["t_ns"]) else 0
    imu = stream["kind"] == 1
    eff = kf.efficiency()
    step = stream["kind"] == 0
    res = FdiResult(str(path), t0_ns=t0, imu_t_ns=stream["t_ns"][imu], stat=stat[imu], efficiency=eff,
                    updates=kf.updates, epochs=stream["epochs"], valve_t_ns=stream["t_ns"][step],
                    valve_masks=stream["masks"][step], wrench=stream["wrench"][step],
                    live_t_ns=efforts["t_ns"].astype(np.int64), live_wrench=efforts["thruster"].copy())
    for row in ev:
        t_ns, j, typ, theta, T, w, det_ns = row.tolist()
        j = int(j)
        res.alarms.append(ThrusterAlarm(j, fdi.TYPES[int(typ)], (int(t_ns) - t0) / 1e9, int(t_ns),
                                        (int(det_ns) - t0) / 1e9, float(theta), float(T),
                                        "short" if w == 0 else "long", float(eff[j])))
    return res
