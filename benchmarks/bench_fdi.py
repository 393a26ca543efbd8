"""Thruster fault detection and isolation on the scenario family: detection rate, delay, false alarms.

    python -m benchmarks.bench_fdi [--quick] [--workers 2] [--json FILE] [--fault leak]   (or bsc bench --only fdi)
    python -m benchmarks.bench_fdi --fault loss --loss-runs 10 --thrusters 0,1,2,3,6 --loss-sizes 0.1,0.15
    python -m benchmarks.bench_fdi --scenario checkout --fault loss --fault healthy --loss-sizes 0.1,0.15

Every case is one recorded session made by the real path (simulator -> firmware -> CAN frames ->
drivers + estimator -> MCAP; harness/fdi.py) and read as ``bsc analyze`` reads it
(gateway/analysis/fdi.py), judged against the simulator's truth. The family (seeded, so a run is
repeatable):

- stuck open and stuck closed: every thruster of the capture scenario's ring18 layout, onset
  uniform in [2, 4] s, session onset + 2 s. Target: the right thruster and type within 0.5 s of
  the onset in >= 95 % of runs (stuck closed: of the runs where the thruster is commanded in the
  0.5 s after the onset; one never commanded does nothing a sensor could see);
- partial loss of 10 %, 15 %, 20 % and 30 % of the thrust: every thruster, onset uniform in
  [2, 3] s, session onset + :data:`LOSS_WINDOW_S` (10 s: the target is a loss named within 10 s;
  the capture task's spacecraft keeps manoeuvring after its 8 s), judged on the thrusters that
  fired before the onset and were commanded after it (within one session a loss is a change of
  what the valve delivered; a valve that never fired before has nothing to compare with). Until
  2026-11-27 these sessions lasted 8 s, 5-6 s after the onset: thruster 3, commanded after the
  onset only in the last 0.12 s, was counted missed at every size;
- leak of 10 %, 20 % and 30 % of the thrust (a closed valve that still thrusts): every thruster,
  onset uniform in [2, 3] s, 8 s sessions, judged on every thruster (a leak shows whenever the
  valve is closed); its size is the thrust delivered closed, of nominal;
- misalignment change of 10 and 20 degrees (a thruster's direction tilted, ``[[degrade]]
  thruster_misalign``): every thruster, onset uniform in [2, 3] s, 8 s sessions, judged on the
  thrusters commanded at least :data:`MISALIGN_DUTY` of the time after the onset (a tilt shows
  only while the valve is open: a valve opened for a few pulses in 5 s shows almost nothing);
  its size is the angle;
- healthy: 20 capture and 20 three_arm sessions (seeds 500..519), no alarm allowed;
- with ``--loss-runs K``: K partial-loss sessions per thruster and size (the family's and K - 1
  more, each with its own onset and seed, :func:`loss_repeats`), so the target's probability is
  measured: the summary's ``loss_rate`` gives per thruster and size the runs named within 10 s of
  those judged and the rate's one-sided 95 % lower bound (Clopper-Pearson: 59 of 59 is the fewest
  runs that show 95 %); ``--thrusters`` keeps the faults of those thrusters only;
- with ``--scenario checkout``: the same faults in a thruster checkout (simulator/scenarios/
  checkout.toml: probe wrenches make every thruster fire, 6-11 % of the time), so that every
  thruster is judged, not only the 5 of 18 the capture task fires before and after an onset; the
  onsets come :data:`LATER_S` (one probe cycle, 3 s) later, once every valve has fired in each of
  its probe directions; the healthy sessions are 20 checkouts of 16 s;
- with ``--early``: stuck open and stuck closed of every thruster with the onset in the first
  1.5 s (uniform in [0.3, 1.5] s, session onset + 2 s; :func:`early_family`), judged as the others
  and summarised apart (``stuck_open early``).

``--warmup S`` judges every recorded session a second time with the detector's warm-up at S
seconds (``FdiSettings(warmup_s=S)``, offline as ``bsc analyze`` runs it; the live run that
recorded the session, and so the published wrench, keeps the default): the summary's
``warmup_S`` block.

Besides the detection, the thruster wrench from the alarm to the session's end against the truth
(band-limited NRMSE, worst axis): the one the live estimator published (it models the fault once
confirmed; target 5 %), the offline filter of ``bsc analyze``, and the offline filter given the
valves as they really were from the session's start (:func:`oracle_nrmse`: the fault modelled
perfectly from its onset; the filter's own floor in that session).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

LOSS_SIZES = (0.10, 0.15, 0.20, 0.30)
LEAK_SIZES = (0.10, 0.20, 0.30)
LOSS_WINDOW_S = 10.0         # a partial loss: named within this of its onset (the target)
MISALIGN_DEG = (10.0, 20.0)
MISALIGN_DUTY = 0.05
EARLY_S = 1.5                # an onset before this: a fault in the filter's first convergence
N_HEALTHY = 20
TARGET_RATE = 0.95
# A checkout's faults begin one probe cycle (3 s) later than the capture task's: every valve has
# then fired in each of its probe directions, so the session knows what it delivered before
LATER_S = {"checkout": 3.0}
TARGET_DELAY_S = 0.5


def family(quick: bool = False, seed: int = 2026, scenario: str = "capture") -> list:
    """The cases (harness.fdi.FaultCase) of a run; ``quick``: a third of the thrusters, two loss
    sizes, 4 healthy sessions of each scenario; ``scenario``: the faults' sessions (the healthy
    ones: capture and three_arm for ``capture``, else that scenario, :func:`healthy`)."""
    from harness.fdi import FaultCase
    from robot_description.thrusters import ThrusterLayout

    rng = np.random.default_rng(seed)
    later = LATER_S.get(scenario, 0.0)
    n = ThrusterLayout.named().n
    thrusters = list(range(0, n, 3)) if quick else list(range(n))
    sizes = (0.15, 0.30) if quick else LOSS_SIZES
    cases = []
    k = 0
    for fault in ("stuck_open", "stuck_closed"):
        for j in thrusters:
            onset = round(float(rng.uniform(2.0, 4.0)) + later, 3)
            cases.append(FaultCase(scenario, 100 + k, onset + 2.0, j, fault, onset))
            k += 1
    for size in sizes:
        for j in thrusters:
            onset = round(float(rng.uniform(2.0, 3.0)) + later, 3)
            cases.append(FaultCase(scenario, 100 + k, onset + LOSS_WINDOW_S, j, "loss", onset,
                                   round(1.0 - size, 3)))
            k += 1
    for size in (0.30,) if quick else LEAK_SIZES:
        for j in thrusters:
            onset = round(float(rng.uniform(2.0, 3.0)) + later, 3)
            cases.append(FaultCase(scenario, 700 + k, 8.0 + later, j, "leak", onset, size))
            k += 1
    for angle in (20.0,) if quick else MISALIGN_DEG:
        for j in thrusters:
            onset = round(float(rng.uniform(2.0, 3.0)) + later, 3)
            cases.append(FaultCase(scenario, 900 + k, 8.0 + later, j, "misalign", onset, angle_deg=angle))
            k += 1
    return cases + healthy(4 if quick else N_HEALTHY, scenario)


def healthy(n: int, scenario: str = "capture") -> list:
    """``n`` healthy sessions (seeds 500 on) of capture (8 s) and of three_arm (4 s) for
    ``capture``, else of ``scenario`` as long as its partial loss's longest sessions."""
    from harness.fdi import FaultCase

    if scenario == "capture":
        return [FaultCase("capture", 500 + i, 8.0) for i in range(n)] + \
            [FaultCase("three_arm", 500 + i, 4.0) for i in range(n)]
    return [FaultCase(scenario, 500 + i, 3.0 + LATER_S.get(scenario, 0.0) + LOSS_WINDOW_S) for i in range(n)]


def loss_repeats(runs: int, thrusters: list[int] | None = None, sizes: tuple[float, ...] = LOSS_SIZES,
                 seed: int = 2028, scenario: str = "capture") -> list:
    """``runs`` more partial-loss cases per thruster (``thrusters``: these only) and size, each with
    its own onset (uniform in [2, 3] s, :data:`LATER_S` later in a checkout) and seed (1300 on), so
    a thruster's detection rate at a size is measured over ``runs + 1`` sessions with the family's."""
    from harness.fdi import FaultCase
    from robot_description.thrusters import ThrusterLayout

    rng = np.random.default_rng(seed)
    later = LATER_S.get(scenario, 0.0)
    thrusters = list(range(ThrusterLayout.named().n)) if thrusters is None else list(thrusters)
    cases = []
    k = 0
    for size in sizes:
        for j in thrusters:
            for _ in range(runs):
                onset = round(float(rng.uniform(2.0, 3.0)) + later, 3)
                cases.append(FaultCase(scenario, 1300 + k, onset + LOSS_WINDOW_S, j, "loss", onset,
                                       round(1.0 - size, 3)))
                k += 1
    return cases


def lower_bound(named: int, judged: int, confidence: float = 0.95) -> float:
    """The one-sided Clopper-Pearson lower bound of a detection probability from ``named`` of
    ``judged`` runs: the smallest p for which seeing ``named`` or more is still ``1 - confidence``
    likely (0 runs: nan). 20 of 20 gives 0.861; 59 of 59 is the fewest to show 95 %."""
    if judged == 0:
        return float("nan")
    if named == 0:
        return 0.0

    def tail(p: float) -> float:              # P(X >= named), X ~ Binomial(judged, p)
        return sum(math.comb(judged, i) * p ** i * (1 - p) ** (judged - i) for i in range(named, judged + 1))

    lo, hi = 0.0, 1.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if tail(mid) < 1.0 - confidence:
            lo = mid
        else:
            hi = mid
    return lo


def early_family(quick: bool = False, seed: int = 2027, scenario: str = "capture") -> list:
    """Stuck open and stuck closed of every thruster (``quick``: a third) with the onset uniform in
    [0.3, 1.5] s, session onset + 2 s (seeds 300 on), in any scenario (no :data:`LATER_S`)."""
    from harness.fdi import FaultCase
    from robot_description.thrusters import ThrusterLayout

    rng = np.random.default_rng(seed)
    n = ThrusterLayout.named().n
    thrusters = list(range(0, n, 3)) if quick else list(range(n))
    cases = []
    k = 0
    for fault in ("stuck_open", "stuck_closed"):
        for j in thrusters:
            onset = round(float(rng.uniform(0.3, EARLY_S)), 3)
            cases.append(FaultCase(scenario, 300 + k, onset + 2.0, j, fault, onset))
            k += 1
    return cases


def oracle_nrmse(path, from_s: float) -> float:
    """The thruster wrench of the offline filter given the valves as they really were (the truth
    trace's, the fault included, from the session's start), from ``from_s`` to the end, judged as
    the published one (band-limited NRMSE, worst axis of peak >= 10): what modelling the fault
    perfectly from its onset would give, the filter's own floor in that session."""
    from pathlib import Path

    from gateway.analysis import fdi as afdi
    from harness.fdi import _nrmse

    path = Path(path)
    tr = np.load(path.with_suffix(".truth.npz"))
    ctx, rob, layout = afdi._layout_and_robot(path)
    samples, efforts, core = afdi._decode(path, ctx, rob, layout)
    stream = afdi.event_stream(samples, efforts, core)
    step = stream["kind"] == 0
    k = np.clip(stream["t_ns"][step] // 1_000_000, 0, len(tr["valves"]) - 1)
    valves = tr["valves"][k].astype(np.int64)
    stream["masks"][step] = (valves << np.arange(valves.shape[1])).sum(axis=1)
    afdi.detect(stream, core, layout)
    return _nrmse(stream["t_ns"][step], stream["wrench"][step], tr["thr_act"], int(from_s * 1e9))[0]


def _run_case(job) -> dict:
    """Record and judge one case (a worker job: ``(case, out_dir, warmup_s)``); the verdict as JSON,
    with ``alt``, the verdict of the detector with its warm-up at ``warmup_s`` (None: none)."""
    from dataclasses import asdict
    from pathlib import Path

    from gateway.analysis.fdi import analyze_thrusters
    from gateway.estimator.fdi import FdiSettings
    from harness.fdi import judge, record

    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    case, out_dir, warmup_s = job
    path = Path(out_dir) / f"{case.name}.mcap"
    try:
        record(case, path)
        v = judge(case, path).to_json()
        if v["named"]:
            v["nrmse_oracle"] = oracle_nrmse(path, case.onset_s + v["delay_s"])
        if warmup_s is not None:
            v["alt"] = judge(case, path, analyze_thrusters(path, settings=FdiSettings(warmup_s=warmup_s))).to_json()
        return v
    except Exception as exc:  # noqa: BLE001 - one failed case is reported with the rest, not lost with them
        return {"name": case.name, "case": asdict(case), "error": f"{type(exc).__name__}: {exc}"}
    finally:
        path.unlink(missing_ok=True)
        path.with_suffix(".truth.npz").unlink(missing_ok=True)


def run(quick: bool = False, workers: int | None = None, progress: bool = False, early: bool = False,
        warmup_s: float | None = None, faults: list[str] | None = None, loss_runs: int = 1,
        thrusters: list[int] | None = None, loss_sizes: tuple[float, ...] | None = None,
        scenario: str = "capture") -> list[dict]:
    """Record and judge every case (``faults``: only the cases of these fault types, ``healthy``
    for the healthy sessions; ``thrusters``: only the faults of these thrusters; ``loss_runs``:
    that many partial-loss sessions per thruster and size, :func:`loss_repeats`; ``loss_sizes``: only
    the losses of these sizes; ``scenario``: the faults' sessions, :func:`family`); the verdicts
    (harness.fdi.Verdict as JSON; ``alt``: judged again with the detector's warm-up at ``warmup_s``)."""
    from gateway.parallel import map_jobs

    cases = family(quick, scenario=scenario) + (early_family(quick, scenario=scenario) if early else [])
    sizes = loss_sizes or ((0.15, 0.30) if quick else LOSS_SIZES)
    if loss_runs > 1:
        cases += loss_repeats(loss_runs - 1, thrusters, sizes, scenario=scenario)
    cases = [c for c in cases if c.fault != "loss" or any(abs(1.0 - c.factor - x) < 1e-9 for x in sizes)]
    if faults:
        cases = [c for c in cases if (c.fault or "healthy") in faults]
    if thrusters is not None:
        cases = [c for c in cases if c.fault is None or c.thruster in thrusters]
    with tempfile.TemporaryDirectory(prefix="bsc-bench-fdi-") as tmp:
        return map_jobs(_run_case, [(c, tmp, warmup_s) for c in cases], workers=workers,
                        progress="fdi cases" if progress else None, unit="session")


def _med(xs) -> float:
    xs = [x for x in xs if math.isfinite(x)]
    return float(np.median(xs)) if xs else float("nan")


def _max(xs) -> float:
    xs = [x for x in xs if math.isfinite(x)]
    return float(max(xs)) if xs else float("nan")


def _group(case: dict) -> str | None:
    """A case's row of the summary: its fault, ``stuck_open early`` for an onset before :data:`EARLY_S`."""
    fault = case["fault"]
    if fault in ("stuck_open", "stuck_closed") and case["onset_s"] < EARLY_S:
        return f"{fault} early"
    return fault


def _named_block(vs: list[dict], judged: list[dict], err_key: str) -> dict:
    """A summary row of the runs ``vs`` of one fault and size, judged on ``judged``: how many were
    named, their delay and size error (``err_key``), the wrong alarms of all, the published wrench."""
    ok = [v for v in judged if v["named"]]
    return {
        "runs": len(vs), "judged": len(judged), "named": len(ok),
        "rate": len(ok) / len(judged) if judged else float("nan"),
        "delay_median_s": _med([v["delay_s"] for v in ok]), "delay_max_s": _max([v["delay_s"] for v in ok]),
        err_key: _max([abs(v["theta"] - v["theta_true"]) for v in ok]),
        "wrong_alarms": sum(v["false_alarms"] for v in vs),
        "missed": sorted(v["case"]["thruster"] for v in judged if not v["named"]),
        "nrmse_published_median": _med([v["nrmse_published"] for v in ok]),
        "nrmse_published_max": _max([v["nrmse_published"] for v in ok]),
        "nrmse_published_over_5": sorted(f"t{v['case']['thruster']} {100 * v['nrmse_published']:.1f} % "
                                         f"{v.get('nrmse_axis', '')}".strip()
                                         for v in ok if v["nrmse_published"] > 0.05),
    }


def _first_command(v: dict) -> float:
    """Onset -> the thruster's first commanded step, s: 0 for a stuck-open valve (it shows at
    once) and where the verdict does not say (an older one)."""
    t = v.get("commanded_from_s", float("nan"))
    return t if v["case"]["fault"] == "stuck_closed" and math.isfinite(t) else 0.0


def _in_time(v: dict) -> bool:
    """Whether a verdict's fault was named in time: a partial loss within :data:`LOSS_WINDOW_S`
    of its onset (the target), any other fault within its session."""
    return bool(v["named"]) and (v["case"]["fault"] != "loss" or v["delay_s"] <= LOSS_WINDOW_S)


def _loss_judged(v: dict) -> bool:
    """Whether a partial loss's run is judged: a loss shows only while the valve is commanded, and
    within one session only against what the valve delivered before, so where it fired before the
    onset (the truth's size is known) and was commanded after it; a named one always."""
    return bool(v["named"]) or (v.get("commanded_after", 1.0) > 0 and math.isfinite(v["theta_true"]))


def summarise(verdicts: list[dict]) -> dict:
    """Rates, delays and false alarms per fault type and loss size, and per thruster."""
    out: dict = {"stuck": {}, "loss": {}, "leak": {}, "misalign": {}, "healthy": {}, "per_thruster": {},
                 "loss_rate": {}, "errors": [f"{v['name']}: {v['error']}" for v in verdicts if "error" in v]}
    verdicts = [v for v in verdicts if "error" not in v]
    for fault in ("stuck_open", "stuck_closed", "stuck_open early", "stuck_closed early"):
        vs = [v for v in verdicts if _group(v["case"]) == fault]
        if not vs and fault.endswith("early"):
            continue
        fault = fault.split()[0]
        judged = [v for v in vs if fault == "stuck_open" or v["commanded_duty"] > 0]
        ok = [v for v in judged if v["named"] and v["delay_s"] <= TARGET_DELAY_S]
        # a valve stuck closed shows nothing until it is commanded: the delay from that first command
        # too (a probe may first command it 0.45 s after the onset; nan in older verdicts: from the onset)
        ok_cmd = [v for v in judged if v["named"] and v["delay_s"] - _first_command(v) <= TARGET_DELAY_S]
        out["stuck"][_group(vs[0]["case"]) if vs else fault] = {
            "runs": len(vs), "judged": len(judged), "named_in_time": len(ok),
            "rate": len(ok) / len(judged) if judged else float("nan"),
            "delay_median_s": _med([v["delay_s"] for v in ok]), "delay_max_s": _max([v["delay_s"] for v in ok]),
            "named_in_time_from_command": len(ok_cmd),
            "rate_from_command": len(ok_cmd) / len(judged) if judged else float("nan"),
            "first_command_max_s": _max([_first_command(v) for v in judged]),
            "theta_err_max": _max([abs(v["theta"] - v["theta_true"]) for v in ok]),
            "wrong_alarms": sum(v["false_alarms"] for v in vs),
            "not_named": sorted(v["case"]["thruster"] for v in judged if v not in ok),
            "never_commanded": sorted(v["case"]["thruster"] for v in vs if v not in judged),
            "nrmse_modelled_median": _med([v["nrmse_modelled"] for v in ok]),
            "nrmse_modelled_max": _max([v["nrmse_modelled"] for v in ok]),
            "nrmse_published_median": _med([v["nrmse_published"] for v in ok]),
            "nrmse_published_max": _max([v["nrmse_published"] for v in ok]),
            "nrmse_oracle_median": _med([v.get("nrmse_oracle", float("nan")) for v in ok]),
            "nrmse_oracle_max": _max([v.get("nrmse_oracle", float("nan")) for v in ok]),
            "nrmse_published_over_5": sorted(f"t{v['case']['thruster']} {100 * v['nrmse_published']:.1f} % "
                                             f"{v.get('nrmse_axis', '')}".strip()
                                             for v in ok if v["nrmse_published"] > 0.05),
        }
    for v in verdicts:
        c = v["case"]
        if c["fault"] is None or _group(c) != c["fault"]:
            continue
        key = {"loss": f"loss {1 - c['factor']:.0%}", "leak": f"leak {c['factor']:.0%}",
               "misalign": f"tilt {c.get('angle_deg', 0.0):g} deg"}.get(c["fault"], c["fault"])
        if c["fault"] == "stuck_closed":
            judged = v["commanded_duty"] > 0
        elif c["fault"] == "misalign":
            judged = v.get("commanded_after", 1.0) >= MISALIGN_DUTY
        elif c["fault"] == "loss":
            judged = _loss_judged(v)
        else:
            judged = True
        # a thruster's first run of each fault and size (the family's; the rates over repeated
        # losses are in loss_rate)
        out["per_thruster"].setdefault(str(c["thruster"]), {}).setdefault(
            key, f"{v['delay_s']:.2f} s" if _in_time(v) else ("missed" if judged else "-"))
    sizes = sorted({round(1 - v["case"]["factor"], 3) for v in verdicts if v["case"]["fault"] == "loss"})
    for size in sizes:
        vs = [v for v in verdicts if v["case"]["fault"] == "loss" and round(1 - v["case"]["factor"], 3) == size]
        judged = [v for v in vs if _loss_judged(v)]
        ok = [v for v in judged if _in_time(v)]
        out["loss"][f"{size:.2f}"] = {
            "runs": len(vs), "judged": len(judged), "named": len(ok),
            "rate": len(ok) / len(judged) if judged else float("nan"),
            "delay_median_s": _med([v["delay_s"] for v in ok]), "delay_max_s": _max([v["delay_s"] for v in ok]),
            "theta_err_max": _max([abs(v["theta"] - v["theta_true"]) for v in ok]),
            "wrong_alarms": sum(v["false_alarms"] for v in vs),
            "missed": sorted(v["case"]["thruster"] for v in judged if v not in ok),
            "nrmse_published_median": _med([v["nrmse_published"] for v in ok]),
            "nrmse_published_max": _max([v["nrmse_published"] for v in ok]),
            "nrmse_oracle_median": _med([v.get("nrmse_oracle", float("nan")) for v in ok]),
            "nrmse_oracle_max": _max([v.get("nrmse_oracle", float("nan")) for v in ok]),
        }
    for size in sorted({v["case"]["factor"] for v in verdicts if v["case"]["fault"] == "leak"}):
        vs = [v for v in verdicts if v["case"]["fault"] == "leak" and v["case"]["factor"] == size]
        out["leak"][f"{size:.2f}"] = _named_block(vs, vs, "theta_err_max")
    for angle in sorted({v["case"].get("angle_deg", 0.0) for v in verdicts if v["case"]["fault"] == "misalign"}):
        vs = [v for v in verdicts if v["case"]["fault"] == "misalign" and v["case"]["angle_deg"] == angle]
        judged = [v for v in vs if v["named"] or v.get("commanded_after", 1.0) >= MISALIGN_DUTY]
        out["misalign"][f"{angle:g}"] = _named_block(vs, judged, "angle_err_max_deg")
        out["misalign"][f"{angle:g}"]["rarely_commanded"] = sorted(v["case"]["thruster"] for v in vs
                                                                   if v not in judged)
    # per thruster and loss size: named in time of judged, and the 95 % lower bound of the rate
    for v in verdicts:
        c = v["case"]
        if c["fault"] != "loss" or not _loss_judged(v):
            continue
        cell = out["loss_rate"].setdefault(str(c["thruster"]), {}).setdefault(f"{1 - c['factor']:.2f}", [0, 0])
        cell[0] += _in_time(v)
        cell[1] += 1
    for row in out["loss_rate"].values():
        for size, (a, b) in row.items():
            row[size] = {"named": a, "judged": b, "lower95": lower_bound(a, b)}
    # per thruster, the smallest loss named (the detection-delay vs fault-size curve's edge)
    for row in out["per_thruster"].values():
        named = [float(k.split()[1].rstrip("%")) for k, val in row.items()
                 if k.startswith("loss") and val.endswith(" s")]
        row["smallest loss named"] = f"{min(named):.0f} %" if named else "-"
    seen = {v["case"]["scenario"] for v in verdicts if v["case"]["fault"] is None}
    for scen in ["capture", "three_arm"] + sorted(seen - {"capture", "three_arm"}):
        vs = [v for v in verdicts if v["case"]["fault"] is None and v["case"]["scenario"] == scen]
        out["healthy"][scen] = {"sessions": len(vs), "false_alarms": sum(v["false_alarms"] for v in vs)}
    return out


def _named_note(d: dict, size_error: str) -> str:
    """The note of a summary row (:func:`_named_block`)."""
    return (f"{d['named']}/{d['judged']}; median delay {d['delay_median_s']:.2f} s, max {d['delay_max_s']:.2f} s; "
            f"{size_error}; wrong alarms {d['wrong_alarms']}; missed {d['missed']}; published wrench NRMSE after "
            f"the alarm median {100 * d['nrmse_published_median']:.1f} %, max {100 * d['nrmse_published_max']:.1f} %")


def figures(quick: bool = False) -> list[dict]:
    """The suite's rows (``bsc bench --only fdi``)."""
    from benchmarks.anchors import row

    t0 = time.perf_counter()
    verdicts = run(quick)
    s = summarise(verdicts)
    wall = time.perf_counter() - t0
    rows = []
    for fault, d in s["stuck"].items():
        what = fault.replace("_", " ")
        rows.append(row(f"{what}: right thruster + type within 0.5 s", 100 * d["rate"], "% of runs",
                        target=">= 95 %", ok=d["rate"] >= TARGET_RATE,
                        note=f"{d['named_in_time']}/{d['judged']} runs; median delay {d['delay_median_s']:.2f} s, "
                             f"max {d['delay_max_s']:.2f} s; wrong alarms {d['wrong_alarms']}"
                             + (f"; never commanded (not judged): {d['never_commanded']}"
                                if d["never_commanded"] else "")))
        if fault.startswith("stuck_closed"):
            rows.append(row(f"{what}: right thruster + type within 0.5 s of its first command",
                            100 * d["rate_from_command"], "% of runs", target=">= 95 %",
                            ok=d["rate_from_command"] >= TARGET_RATE,
                            note=f"{d['named_in_time_from_command']}/{d['judged']} runs; a valve stuck closed shows "
                                 f"nothing until commanded, the last first command came "
                                 f"{d['first_command_max_s']:.2f} s after its onset"))
        rows.append(row(f"{what}: published wrench NRMSE after the alarm, worst run", 100 * d["nrmse_published_max"],
                        "%", target="<= 5 %", ok=d["nrmse_published_max"] <= 0.05,
                        note=f"median {100 * d['nrmse_published_median']:.1f} %; above 5 %: "
                             f"{'; '.join(d['nrmse_published_over_5']) or 'none'}; the offline filter of bsc "
                             f"analyze: median {100 * d['nrmse_modelled_median']:.1f} %, max "
                             f"{100 * d['nrmse_modelled_max']:.1f} %; given the true valves from the start: "
                             f"median {100 * d['nrmse_oracle_median']:.1f} %, max "
                             f"{100 * d['nrmse_oracle_max']:.1f} %"))
    for size, d in s["loss"].items():
        rows.append(row(f"partial loss {float(size):.0%}: named within {LOSS_WINDOW_S:g} s", 100 * d["rate"],
                        "% of judged runs", target=">= 95 %" if float(size) >= 0.15 else None,
                        ok=(d["rate"] >= TARGET_RATE) if float(size) >= 0.15 else None,
                        note=_named_note(d, f"size error max {d['theta_err_max']:.3f}")))
    for size, d in s["leak"].items():
        rows.append(row(f"leak {float(size):.0%}: named within the session", 100 * d["rate"], "% of runs",
                        note=_named_note(d, f"size error max {d['theta_err_max']:.3f}")))
    for angle, d in s["misalign"].items():
        rows.append(row(f"misalignment {angle} deg: named within the session", 100 * d["rate"], "% of judged runs",
                        note=_named_note(d, f"angle error max {d['angle_err_max_deg']:.1f} deg")))
    for scen, d in s["healthy"].items():
        rows.append(row(f"false alarms, {d['sessions']} healthy {scen} sessions", d["false_alarms"], "alarms",
                        target="0", ok=d["false_alarms"] == 0))
    rows.append(row("family wall time", wall, "s", note=f"{len(verdicts)} sessions recorded and analysed"
                    + (f"; {len(s['errors'])} failed: {'; '.join(s['errors'][:3])}" if s["errors"] else "")))
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_fdi", description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--json", metavar="FILE", help="write the verdicts and the summary here")
    p.add_argument("--early", action="store_true", help="also stuck valves with the onset in the first 1.5 s")
    p.add_argument("--warmup", type=float, metavar="S",
                   help="also judge every session with the detector's warm-up at S seconds (offline)")
    p.add_argument("--fault", action="append",
                   choices=("stuck_open", "stuck_closed", "loss", "leak", "misalign", "healthy"),
                   help="only the cases of this fault type (repeatable; default: all)")
    p.add_argument("--loss-runs", type=int, default=1, metavar="K",
                   help="K partial-loss sessions per thruster and size, each with its own onset and seed "
                        "(the rate per thruster and its 95 %% lower bound: the summary's loss_rate)")
    p.add_argument("--thrusters", type=lambda t: [int(x) for x in t.split(",")], metavar="J,K,...",
                   help="only the faults of these thrusters (the healthy sessions stay)")
    p.add_argument("--loss-sizes", type=lambda t: tuple(float(x) for x in t.split(",")), metavar="A,B,...",
                   help="only the partial losses of these sizes (fractions of nominal thrust, e.g. 0.1,0.15)")
    p.add_argument("--scenario", default="capture", metavar="NAME",
                   help="the faults' sessions: capture (default; healthy: capture and three_arm) or checkout "
                        "(every thruster fires; healthy: checkout)")
    a = p.parse_args(argv)
    if a.loss_runs < 1:
        p.error("--loss-runs must be 1 or more")
    t0 = time.perf_counter()
    verdicts = run(a.quick, a.workers, progress=sys.stderr.isatty(), early=a.early, warmup_s=a.warmup,
                   faults=a.fault, loss_runs=a.loss_runs, thrusters=a.thrusters, loss_sizes=a.loss_sizes,
                   scenario=a.scenario)
    s = summarise(verdicts)
    if a.warmup is not None:
        s[f"warmup_{a.warmup:g}"] = summarise([v["alt"] for v in verdicts if "alt" in v])
    s["wall_s"] = time.perf_counter() - t0
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"summary": s, "verdicts": verdicts}, f, indent=1, default=float)
    print(json.dumps(s, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
