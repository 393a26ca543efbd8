"""Simulated degradation series: N recorded sessions of the capture task with a known fault.

    write_series("friction-growth", 12, "series/fg")  ->  series/fg/session_0000.mcap ... _0011.mcap
                                                          series/fg/series.json (the ground truth)

Each session is a short capture run (its own seed: sensor noise, thruster scatter) of the SAME
robot; the degradation advances ACROSS sessions, as a fleet's logs would show it over months.
The table :data:`SERIES` says what degrades, from which session (``onset``), and how much per
session. Sessions are numbered in time order: session ``k`` starts ``k`` days after
:data:`EPOCH_NS` (its MCAP log times), and its ``bsc.series`` metadata holds ``session_index``,
so ``bsc analyze`` orders them without trusting file names.

A session is made by the real path: ``simulator.firmware.Firmware`` turns each simulator step
into CAN frames, ``gateway.pipeline.Pipeline`` decodes them and estimates, and the recorder keeps
the raw frames and everything the pipeline emits (samples, health, efforts) under their zenoh
keys, as ``bsc gateway --record`` would.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable


class SeriesError(ValueError):
    """A degradation series that cannot be made as asked (the harness's errors)."""


EPOCH_NS = 1_798_761_600_000_000_000       # 2027-01-01T00:00:00Z: session 0 of every series
SESSION_SPACING_NS = 86_400 * 1_000_000_000  # one session a day
SERIES_METADATA = "bsc.series"
SERIES_FILE = "series.json"
DEFAULT_DURATION_S = 8.0
BASE_SEED = 1000


@dataclass(frozen=True)
class SeriesSpec:
    """One degradation series. ``onset(n)``: first degraded session of an ``n``-session series
    (``None`` for healthy). ``kind``/``target``: what ``bsc analyze`` must report (the truth the
    detection delay is measured against). ``toml(k, onset, n)``: the session's scenario TOML
    additions (friction per joint, ``[[degrade]]`` tables), ``truth(k, onset, n)``: the
    degradation's size in that session, in named numbers."""

    name: str
    description: str
    kind: str | None
    target: str | None
    toml: Callable[[int, int | None, int], str]
    truth: Callable[[int, int | None, int], dict]

    def onset(self, n: int) -> int | None:
        return None if self.kind is None else default_onset(n)


def default_onset(n: int) -> int:
    """Onset session of an ``n``-session series: a third in, never before session 3 (the first
    three are the change detector's baseline), never the last."""
    if n < 5:
        raise SeriesError(f"a degradation series needs at least 5 sessions, got {n}")
    return min(n - 2, max(3, math.ceil(n / 3)))


# --- the table ------------------------------------------------------------------------------------

FRICTION_JOINT = "arm0/j2"
FRICTION_FROM, FRICTION_TO = 0.30, 0.60      # Coulomb friction, fraction of the joint's torque limit
THRUSTER = 2                                  # the ring18 thruster that fires most in the capture task
THRUSTER_FACTOR = 0.70                        # 30 % thrust loss
FT_ARM = "arm0"
FT_STEP_N = (6.0, -4.0, 0.0)                  # F/T bias added per session after onset, force, N
FT_STEP_NM = (0.0, 0.0, 3.0)                  # moment, N m
FT_DRIFT_S = 10.0                             # the step is the drift of this many seconds


def _friction_fraction(k: int, onset: int | None, n: int) -> float:
    if onset is None or k < onset:
        return FRICTION_FROM
    return FRICTION_FROM + (FRICTION_TO - FRICTION_FROM) * (k - onset + 1) / (n - onset)


def _friction_toml(k, onset, n):
    if onset is None or k < onset:
        return ""
    return f'[friction.per_joint]\n"{FRICTION_JOINT}" = {_friction_fraction(k, onset, n)!r}\n'


def _thruster_toml(k, onset, n):
    if onset is None or k < onset:
        return ""
    return (f'[[degrade]]\nkind = "thruster_loss"\nthruster = {THRUSTER}\nonset_s = 0.0\n'
            f'factor = {THRUSTER_FACTOR!r}\n')


def _ft_steps(k, onset) -> int:
    return 0 if onset is None or k < onset else k - onset + 1


def _ft_toml(k, onset, n):
    steps = _ft_steps(k, onset)
    if not steps:
        return ""
    # a drift at a constant rate that began steps * FT_DRIFT_S before this session's start
    rate_f = [v / FT_DRIFT_S for v in FT_STEP_N]
    rate_t = [v / FT_DRIFT_S for v in FT_STEP_NM]
    return (f'[[degrade]]\nkind = "ft_bias_drift"\narm = "{FT_ARM}"\nonset_s = {-steps * FT_DRIFT_S!r}\n'
            f'force_n_per_s = {rate_f!r}\ntorque_nm_per_s = {rate_t!r}\n')


SERIES: dict[str, SeriesSpec] = {s.name: s for s in (
    SeriesSpec("healthy", "no degradation: every session healthy (the false-alarm test)", None, None,
               lambda k, o, n: "", lambda k, o, n: {}),
    SeriesSpec("friction-growth",
               f"Coulomb friction of {FRICTION_JOINT} climbs from {FRICTION_FROM:.0%} to {FRICTION_TO:.0%} of "
               "its torque limit, in equal steps from the onset session to the last",
               "actuator", FRICTION_JOINT, _friction_toml,
               lambda k, o, n: {"coulomb_fraction": _friction_fraction(k, o, n)}),
    SeriesSpec("thruster-loss",
               f"thruster {THRUSTER} (ring18) delivers {THRUSTER_FACTOR:.0%} of its thrust from the onset session on",
               "thruster", f"thruster{THRUSTER}", _thruster_toml,
               lambda k, o, n: {"thrust_factor": THRUSTER_FACTOR if o is not None and k >= o else 1.0}),
    SeriesSpec("ft-bias-drift",
               f"the F/T sensor of {FT_ARM} drifts: +{list(FT_STEP_N)} N, +{list(FT_STEP_NM)} N m of bias per "
               "session from the onset (a sensor fault, not an actuator fault)",
               "sensor", FT_ARM, _ft_toml,
               lambda k, o, n: {"force_bias_n": [v * _ft_steps(k, o) for v in FT_STEP_N],
                                "torque_bias_nm": [v * _ft_steps(k, o) for v in FT_STEP_NM]}),
)}


# --- writing ----------------------------------------------------------------------------------------

def session_path(out_dir: Path, k: int) -> Path:
    return Path(out_dir) / f"session_{k:04d}.mcap"


def session_toml(spec: SeriesSpec, k: int, n: int, duration_s: float) -> str:
    onset = spec.onset(n)
    return (f'# bsc series {spec.name!r}, session {k} of {n} (onset {onset})\n'
            f'name = "capture-{spec.name}-{k:04d}"\nduration_s = {float(duration_s)!r}\n'
            f'seed = {BASE_SEED + k}\n' + spec.toml(k, onset, n))


def write_series(name: str, sessions: int, out_dir: str | os.PathLike[str], *,
                 duration_s: float = DEFAULT_DURATION_S, progress: bool = True,
                 workers: int | None = None, overwrite: bool = False, save_truth: bool = False,
                 first: int = 0) -> list[Path]:
    """Write ``sessions`` recorded sessions of series ``name`` into ``out_dir``; the file paths.

    Sessions run in parallel worker processes (``workers``, default: the CPU count). The
    ground truth (onset, per-session degradation) goes to ``out_dir/series.json``; with
    ``save_truth`` each session's full truth trace goes beside it (``session_XXXX.truth.npz``).
    ``first``: write only sessions ``first`` to ``sessions - 1`` (their paths are returned). A
    session before the onset is the same run in every series (same seed, nothing degraded yet),
    so several series of one length can share the healthy series' first sessions.
    """
    if name not in SERIES:
        raise SeriesError(f"no series {name!r} (series: {', '.join(SERIES)})")
    spec = SERIES[name]
    if sessions < 1:
        raise SeriesError("sessions must be at least 1")
    if duration_s <= 0:
        raise SeriesError("duration_s must be positive")
    if not 0 <= first < sessions:
        raise SeriesError(f"first must be a session of the series (0 to {sessions - 1}), got {first}")
    onset = spec.onset(sessions)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [session_path(out, k) for k in range(sessions)]
    if not overwrite:
        existing = [p for p in paths[first:] if p.exists()]
        if existing:
            raise FileExistsError(f"{existing[0]} exists (overwrite=True replaces the series)")
    jobs = [(name, k, sessions, float(duration_s), str(paths[k]), save_truth) for k in range(first, sessions)]
    from gateway.parallel import map_jobs

    map_jobs(_session_job, jobs, workers=workers, progress=f"series {name}" if progress else None, unit="session")
    truth = {"series": name, "description": spec.description, "sessions": sessions, "onset_session": onset,
             "expected_kind": spec.kind, "expected_target": spec.target, "duration_s": float(duration_s),
             "files": [p.name for p in paths],
             "per_session": [spec.truth(k, onset, sessions) for k in range(sessions)]}
    (out / SERIES_FILE).write_text(json.dumps(truth, indent=1) + "\n")
    return paths[first:]


def _session_job(job) -> str:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    name, k, n, duration_s, path, save_truth = job
    spec = SERIES[name]
    onset = spec.onset(n)
    text = session_toml(spec, k, n, duration_s)
    meta = {"series": name, "session_index": str(k), "sessions": str(n),
            "onset_session": "" if onset is None else str(onset),
            "start_ns": str(EPOCH_NS + k * SESSION_SPACING_NS),
            "truth": json.dumps(spec.truth(k, onset, n))}
    _record_session(text, Path(path), meta, save_truth)
    return path


def _load_scenario(text: str, path: Path):
    from simulator import scenario

    toml_path = path.with_suffix(".scenario.toml")
    toml_path.write_text(text)
    try:
        return scenario.load(toml_path)
    finally:
        toml_path.unlink()


def _record_session(text: str, path: Path, meta: dict, save_truth: bool) -> None:
    from gateway.engine import Session
    from gateway.engine.sinks import RecorderSink
    from gateway.log.recorder import Recorder
    from robot_description.thrusters import ThrusterLayout
    from simulator.engine import Simulation
    from simulator.firmware import Firmware

    sc = _load_scenario(text, path)
    sim = Simulation(sc)
    with Recorder(path, overwrite=True, metadata={SERIES_METADATA: meta}) as rec:
        rec.add_session_context(urdf_text=sim.robot.urdf, scenario_text=text,
                                extra={"scenario": sc.name, "robot": sim.robot.name})
        # log time = series start + the frames' (sensor) time; health every 0.5 s of it, as bsc gateway
        with Session(sim.robot, [RecorderSink(rec, offline=True)], layout=ThrusterLayout.from_config(sc.cfg.thrusters),
                     health_period_ns=500_000_000, log_offset_ns=int(meta["start_ns"])) as ses:
            fw = Firmware(sim.robot)
            while sim.k < sim.n_steps:
                # a step's frames arrive together (as the live gateway drains its sockets): one
                # pass of the kernels for them, the same efforts as frame by frame (20 % faster)
                ses.feed_messages(list(fw.frames(sim.step())))
    if save_truth:
        sim.trace.save(path.with_suffix(".truth.npz"))
