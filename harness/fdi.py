"""Simulated thruster faults for the fault detector: one recorded session per case, judged on truth.

A case is a scenario (``capture`` or ``three_arm``), a seed, and at most one thruster fault
(``stuck_open``, ``stuck_closed``, ``loss`` of a fraction of the thrust, ``leak``, or
``misalign``: its thrust tilted by ``angle_deg``) with its onset. Each
session is made by the real path (simulator -> sensor firmware -> CAN frames -> drivers and
estimator, raw frames recorded, as :mod:`harness.series` makes its sessions), then
``gateway.analysis.fdi.analyze_thrusters`` reads the log as ``bsc analyze`` would, and
:func:`judge` compares what it named with the case: the thruster, the type, the delay from the
onset, and the size against the truth trace (the thrust the valve delivered before the onset).

    python -m harness.fdi --thruster 5 --fault stuck_open --onset 3 --out /tmp/s.mcap

The benchmark (``benchmarks/bench_fdi.py``) runs the family; the tests run a few cases.
"""
from __future__ import annotations

import json
import math
import os
import re
from dataclasses import asdict, dataclass
from pathlib import Path

from harness.series import _record_session

FAULTS = ("stuck_open", "stuck_closed", "loss", "leak", "misalign")
EXPECTED = {"stuck_open": "stuck open", "stuck_closed": "stuck closed", "loss": "partial loss", "leak": "leak",
            "misalign": "misalignment"}


@dataclass(frozen=True)
class FaultCase:
    """One session: ``fault`` None for a healthy one; ``factor``: the thrust left by a loss, the
    fraction of its thrust a leaking valve delivers while closed; ``end_s``: a stuck valve follows
    its command again from then on (None: it stays stuck); ``angle_deg``: a misalignment's tilt of
    the thruster's direction (``[[degrade]] thruster_misalign``)."""

    scenario: str = "capture"
    seed: int = 7
    duration_s: float = 6.0
    thruster: int | None = None
    fault: str | None = None
    onset_s: float = 3.0
    factor: float = 1.0
    end_s: float | None = None
    angle_deg: float = 0.0

    @property
    def name(self) -> str:
        if self.fault is None:
            return f"{self.scenario}-s{self.seed}-healthy"
        size = {"loss": f"-{1 - self.factor:.2f}", "leak": f"-{self.factor:.2f}",
                "misalign": f"-{self.angle_deg:g}deg"}.get(self.fault, "")
        end = f"-to{self.end_s:.2f}" if self.end_s is not None else ""
        return f"{self.scenario}-s{self.seed}-t{self.thruster}-{self.fault}{size}-at{self.onset_s:.2f}{end}"

    def toml(self) -> str:
        """The session's scenario: the base scenario's file with this case's name, duration, seed
        and fault."""
        from simulator.scenario import BUILTIN, DEFAULT

        base = "" if self.scenario == DEFAULT else BUILTIN[self.scenario].read_text()
        # the base's own top-level name, duration and seed give way to the case's (they come
        # before its first table, where top-level keys must be)
        base = re.sub(r"(?m)^(name|duration_s|seed)\s*=.*$", "", base)
        text = f'name = "{self.name}"\nduration_s = {float(self.duration_s)!r}\nseed = {int(self.seed)}\n' + base
        if self.fault in ("loss", "leak"):
            text += (f'\n[[degrade]]\nkind = "thruster_{self.fault}"\nthruster = {self.thruster}\n'
                     f'onset_s = {float(self.onset_s)!r}\nfactor = {float(self.factor)!r}\n')
        elif self.fault == "misalign":
            text += (f'\n[[degrade]]\nkind = "thruster_misalign"\nthruster = {self.thruster}\n'
                     f'onset_s = {float(self.onset_s)!r}\nangle_deg = {float(self.angle_deg)!r}\n')
        elif self.fault is not None:
            state = "open" if self.fault == "stuck_open" else "closed"
            text += (f'\n[[degrade]]\nkind = "thruster_stuck"\nthruster = {self.thruster}\n'
                     f'onset_s = {float(self.onset_s)!r}\nstate = "{state}"\n')
            if self.end_s is not None:
                text += (f'\n[[degrade]]\nkind = "thruster_stuck"\nthruster = {self.thruster}\n'
                         f'onset_s = {float(self.end_s)!r}\nstate = "free"\n')
        return text


def record(case: FaultCase, path: str | os.PathLike[str]) -> Path:
    """Record the case's session to ``path`` (MCAP) and its truth trace beside it
    (``.truth.npz``); the path."""
    path = Path(path)
    _record_session(case.toml(), path, {"start_ns": "0", "fdi_case": json.dumps(asdict(case))}, True)
    return path


def _record_job(job: tuple[FaultCase, str]) -> str:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    case, path = job
    record(case, path)
    return path


def record_many(cases: dict[str, FaultCase], folder: str | os.PathLike[str], workers: int = 2) -> dict[str, Path]:
    """:func:`record` of every case, ``folder/<name>.mcap``, on ``workers`` processes; name -> path."""
    from gateway.parallel import map_jobs

    jobs = [(case, str(Path(folder) / f"{name}.mcap")) for name, case in cases.items()]
    return {name: Path(p) for name, p in zip(cases, map_jobs(_record_job, jobs, workers=workers))}


@dataclass
class Verdict:
    """What the detector said about one case, judged."""

    case: FaultCase
    alarms: list[dict]
    named: bool = False            # the right thruster and type
    delay_s: float = float("nan")  # onset -> the right alarm, s (nan: none)
    theta: float = float("nan")    # its size, fraction of nominal thrust (a misalignment: degrees)
    theta_true: float = float("nan")
    commanded_duty: float = float("nan")   # the thruster's commanded open fraction, 0.5 s from the onset
    commanded_after: float = float("nan")  # ... from the onset to the session's end
    commanded_from_s: float = float("nan")  # onset -> the first step it was commanded open, s (nan: never)
    false_alarms: int = 0          # alarms that name anything else
    cleared_delay_s: float = float("nan")   # a stuck valve that came back (end_s): end -> its clearing, s
    # thruster wrench from the alarm to the end, band-limited (20 Hz) NRMSE against the truth
    # (RMS error / peak, the worst axis): the offline filter of bsc analyze, and what the live
    # estimator published (both model the fault once it is confirmed)
    nrmse_modelled: float = float("nan")
    nrmse_published: float = float("nan")
    nrmse_axis: str = ""           # the published wrench's worst axis and its peak, e.g. "fz (peak 13.7)"

    def to_json(self) -> dict:
        d = asdict(self)
        d["case"] = asdict(self.case)
        d["name"] = self.case.name
        return d


def judge(case: FaultCase, path: str | os.PathLike[str], result=None) -> Verdict:
    """Analyse the recorded case ``path`` (or take its ``result``) and judge it against the case
    and its truth trace. The truth size of a fault: the thrust the valve delivered while open
    before the onset as a fraction of nominal (``g``; of a stuck-open valve, while stuck):
    stuck open and closed ``g``, a loss ``(1 - factor) g``."""
    import numpy as np

    from gateway.analysis.fdi import analyze_thrusters

    path = Path(path)
    res = result if result is not None else analyze_thrusters(path)
    alarms = [a.to_json() for a in res.alarms]
    v = Verdict(case, alarms)
    if case.fault is None:
        v.false_alarms = len(alarms)
        return v
    tr = np.load(path.with_suffix(".truth.npz"))
    t = tr["t_s"]
    j = case.thruster
    is_open = tr["valves"][:, j].astype(bool)
    # a stuck-open valve's size is the thrust it delivers while stuck, a leak's the thrust while
    # closed; otherwise the thrust the valve delivered while open before the onset
    after = t >= case.onset_s
    sel = (is_open & after if case.fault == "stuck_open" else ~is_open & after if case.fault == "leak"
           else is_open & ~after)
    thrust = tr["thrust"][sel, j].mean() if sel.any() else float("nan")
    g = thrust / _max_thrust(case)
    v.theta_true = ((1 - case.factor) * g if case.fault == "loss" else case.angle_deg if case.fault == "misalign"
                    else g)
    on = int(case.onset_s * 1e9)
    after = (res.valve_t_ns >= on) & (res.valve_t_ns < on + 500_000_000)
    if after.any():
        v.commanded_duty = float(((res.valve_masks[after] >> j) & 1).mean())
    after = res.valve_t_ns >= on
    if after.any():
        v.commanded_after = float(((res.valve_masks[after] >> j) & 1).mean())
        opened = np.flatnonzero(after & (((res.valve_masks >> j) & 1) == 1))
        if len(opened):
            v.commanded_from_s = float(res.valve_t_ns[opened[0]] - on) / 1e9
    want = EXPECTED[case.fault]
    for a in res.alarms:
        if (case.end_s is not None and v.named and a.thruster == j and a.fault == "cleared"
                and math.isnan(v.cleared_delay_s) and a.t_ns >= case.end_s * 1e9):
            v.cleared_delay_s = a.t_ns / 1e9 - case.end_s
        elif a.thruster == j and a.fault == want and not v.named:
            v.named = True
            v.delay_s = a.t_ns / 1e9 - case.onset_s
            v.theta = a.theta
            v.nrmse_modelled = _nrmse(res.valve_t_ns, res.wrench, tr["thr_act"], a.t_ns)[0]
            v.nrmse_published, axis, peak = _nrmse(res.live_t_ns, res.live_wrench, tr["thr_act"], a.t_ns)
            v.nrmse_axis = f"{AXES[axis]} (peak {peak:.1f})" if axis >= 0 else ""
        elif not (a.thruster == j and a.fault == want):
            v.false_alarms += 1
    return v


AXES = ("fx", "fy", "fz", "mx", "my", "mz")


def _nrmse(t_ns, wrench, act, from_ns: int, min_peak: float = 10.0) -> tuple[float, int, float]:
    """Band-limited (20 Hz) NRMSE of a wrench estimate (at ``t_ns``, 1 kHz steps of the truth)
    against the truth ``act`` after ``from_ns`` (an alarm: its own epoch was published before the
    IMU update that raised it) to the end: the worst axis whose peak is at least ``min_peak``
    (N, N m), that axis (-1: none) and its peak. Steps without an estimate hold the previous one.
    Only that segment is band-limited: filtered over the whole session, the zero-phase filter
    carried the unmodelled fault before the alarm (a whole thruster's thrust) into the first 50 ms
    judged (thruster 0 stuck open: 8.5 N of error in fy there against 0.5 N after)."""
    import numpy as np

    from harness.demo import lowpass

    k = np.asarray(t_ns) // 1_000_000
    ok = (k >= 0) & (k < len(act))
    est = np.full(act.shape, np.nan)
    est[k[ok]] = wrench[ok]
    for c in range(6):                       # hold over gaps
        col = est[:, c]
        idx = np.where(np.isnan(col), 0, np.arange(len(col)))
        np.maximum.accumulate(idx, out=idx)
        est[:, c] = col[idx]
    start = max(int(from_ns // 1_000_000) + 1, int(np.argmax(~np.isnan(est[:, 0]))))
    if start >= len(act) - 50:
        return float("nan"), -1, float("nan")
    e_lp, a_lp = lowpass(np.nan_to_num(est[start:])), lowpass(act[start:])
    worst, axis, at = float("nan"), -1, float("nan")
    for c in range(6):
        peak = float(np.abs(a_lp[:, c]).max())
        if peak >= min_peak:
            err = float(np.sqrt(np.mean((e_lp[:, c] - a_lp[:, c]) ** 2))) / peak
            if not worst >= err:
                worst, axis, at = err, c, peak
    return worst, axis, at


def _max_thrust(case: FaultCase) -> float:
    from robot_description.thrusters import ThrusterLayout
    from simulator import scenario

    return float(ThrusterLayout.from_config(scenario.load(case.scenario).data["thrusters"]).max_n[case.thruster])


def run_case(job) -> dict:
    """Record and judge one case in ``out_dir`` (a worker job: ``(case, out_dir, keep)``); the
    verdict as JSON (``{"name", "case", "error"}`` when the case failed). ``keep`` False deletes
    the session files afterwards."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    case, out_dir, keep = job
    path = Path(out_dir) / f"{case.name}.mcap"
    try:
        record(case, path)
        return judge(case, path).to_json()
    except Exception as exc:  # noqa: BLE001 - one failed case is reported with the rest, not lost with them
        return {"name": case.name, "case": asdict(case), "error": f"{type(exc).__name__}: {exc}"}
    finally:
        if not keep:
            path.unlink(missing_ok=True)
            path.with_suffix(".truth.npz").unlink(missing_ok=True)


def main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="python -m harness.fdi", description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="capture")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--duration", type=float, default=6.0)
    p.add_argument("--thruster", type=int)
    p.add_argument("--fault", choices=FAULTS)
    p.add_argument("--onset", type=float, default=3.0)
    p.add_argument("--factor", type=float, default=0.7,
                   help="thrust left by a loss; with --fault leak, the fraction of its thrust a closed valve gives")
    p.add_argument("--end", type=float, help="a stuck valve follows its command again from this time, s")
    p.add_argument("--angle", type=float, default=10.0, help="with --fault misalign, the tilt of the thruster, degrees")
    p.add_argument("--out", type=Path, required=True, help="the session's .mcap")
    a = p.parse_args(argv)
    factor = a.factor if a.fault in ("loss", "leak") else 1.0
    case = FaultCase(a.scenario, a.seed, a.duration, a.thruster, a.fault, a.onset, factor,
                     a.end if a.fault in ("stuck_open", "stuck_closed") else None,
                     a.angle if a.fault == "misalign" else 0.0)
    record(case, a.out)
    print(json.dumps(judge(case, a.out).to_json(), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
