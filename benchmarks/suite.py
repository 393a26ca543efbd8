"""The benchmark suite: ``python -m benchmarks`` / ``bsc bench``.

Runs the anchors (benchmarks/anchors.py) and every benchmark module's ``figures(quick)``, then
prints one table: each figure beside its anchor measured in the same run and the ratio
``value / anchor``, with the target and whether it is met. The header says when, on which
machine, under which load and with which library versions. ``--json`` prints one JSON document
instead (same rows), ``--markdown`` the table as Markdown (for the README).

Row shape (every ``figures()`` returns a list of these dicts)::

    name    str            what was measured
    value   float | None   the figure (None: not measured, see note)
    unit    str
    target  str | None     as text, e.g. ">= 50k frames/s"
    ok      bool | None    target met (None: no target, or not judged)
    anchor  str | None     an anchor of benchmarks/anchors.py, or a local anchor's name
    ratio   float | None   value / anchor figure
    note    str            optional: how it was measured, caveats

The suite adds ``group`` (the module's key). A row naming one of the four anchors without a
ratio gets it filled here; a module may also name a local anchor of its own (e.g. one Pinocchio
ABA call of the same run) and give the ratio itself. Speed targets stated as ratios (e.g.
"batch decode >= 10x cantools") are judged on the ratio; absolute ones on the value, with the
ratio beside it to show how fast the machine was at the time.

Exit status: 0 when every selected benchmark ran (targets missed are reported, not errors),
1 when one raised (its row says why), 2 for bad options; ``--strict`` also makes a missed
target exit 1.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import importlib
import json
import math
import os
import platform
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, TextIO

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from benchmarks import anchors  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

# key -> (module, what it measures, runs by default)
BENCHMARKS: dict[str, tuple[str, str, bool]] = {
    "drivers": ("benchmarks.bench_drivers", "CAN drivers: live and batch decode", True),
    "estimator": ("benchmarks.bench_estimator", "estimator kernels and core, per call and batched", True),
    "recorder": ("benchmarks.bench_recorder", "MCAP recorder throughput", True),
    "sim": ("benchmarks.bench_sim", "simulator real-time factor", True),
    "replay": ("benchmarks.bench_replay", "offline replay through drivers + estimator", True),
    "latency": ("benchmarks.bench_latency", "gateway end-to-end latency (CAN -> zenoh subscriber)", True),
    "fdi": ("benchmarks.bench_fdi", "thruster fault detection on the scenario family: rate, delay, false alarms "
            "(148 simulated sessions, about 15 minutes on 2 cores; only with --only fdi)", False),
    "accuracy": ("benchmarks.bench_accuracy", "joint torques of any robot, sensor side against distal side, on "
                 "simulated sessions against the truth (issue 17; only with --only accuracy)", False),
    "gyro": ("benchmarks.bench_gyro_noise", "thruster filter with the gyro-difference noise modelled exactly, "
             "against the kernel's white treatment (4 simulated sessions, a few minutes; only with --only gyro)",
             False),
    "contact": ("benchmarks.bench_contact", "contact at an end effector: time to flag, wrench error, false contacts "
                "(34 simulated sessions, a few minutes; only with --only contact)", False),
    "fuzz": ("benchmarks.fuzz_drivers", "driver fuzzing, 1 M frames (only with --fuzz or --only fuzz)", False),
    "capacity": ("benchmarks.bench_capacity", "whole system for 60 s: firmware + gateway --record + monitor, "
                 "frames shed (root; only with --only capacity)", False),
}
# Rows of these groups that carry no "anchor" key at all get this anchor when the units agree.
DEFAULT_ANCHOR = {"latency": "zenoh_rtt"}
KEYS = ("name", "value", "unit", "target", "ok", "anchor", "ratio")


# --- machine ---------------------------------------------------------------------------------

def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _load() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def _versions() -> dict[str, str]:
    from importlib import metadata

    out = {"python": platform.python_version()}
    for dist, key in (("numpy", "numpy"), ("eclipse-zenoh", "zenoh"), ("python-can", "python-can"),
                      ("cantools", "cantools"), ("pin", "pinocchio"), ("mcap", "mcap")):
        try:
            out[key] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            pass
    return out


def _commit() -> str | None:
    """Short commit of the source tree, ``+`` when it has uncommitted changes (read-only git)."""
    try:
        head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, timeout=5)
        if head.returncode != 0:
            return None
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=5)
        return head.stdout.strip() + ("+" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return None


def machine() -> dict:
    try:
        affinity = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        affinity = None
    return {"date": _dt.datetime.now().astimezone().isoformat(timespec="seconds"),
            "host": socket.gethostname(), "cpu": _cpu_model(), "cores": os.cpu_count(),
            "cores_usable": affinity, "load_start": _load(), "versions": _versions(),
            "commit": _commit(), "openblas_threads": os.environ.get("OPENBLAS_NUM_THREADS")}


# --- running ---------------------------------------------------------------------------------

def selection(only: list[str] | None, fuzz: bool) -> tuple[list[str], list[str]]:
    """``(anchor names, benchmark keys)`` to run; ``only`` may name either (or ``anchors``)."""
    if not only:
        return list(anchors.ANCHORS), [k for k, (_, _, d) in BENCHMARKS.items() if d or (k == "fuzz" and fuzz)]
    valid = ["anchors", *anchors.ANCHORS, *BENCHMARKS]
    bad = [n for n in only if n not in valid]
    if bad:
        raise ValueError(f"unknown benchmark {', '.join(bad)} (choose from {', '.join(valid)})")
    a = list(anchors.ANCHORS) if "anchors" in only else [n for n in anchors.ANCHORS if n in only]
    b = [k for k in BENCHMARKS if k in only or (k == "fuzz" and fuzz)]
    return a, b


def _num(v) -> float | None:
    if isinstance(v, bool) or v is None:
        return None if v is None else float(v)
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def normalise(group: str, r: dict) -> dict:
    """A module's row in the common shape (missing keys None, NaN -> None), ratio filled in."""
    out = {"group": group}
    for k in KEYS:
        out[k] = r.get(k)
    if r.get("note"):
        out["note"] = str(r["note"])
    raw = r.get("value")
    out["value"] = _num(raw)
    if out["value"] is None and raw is not None:
        out["note"] = (out.get("note", "") + f" (value {raw!r})").strip()
    if out["ratio"] is not None:
        out["ratio"] = _num(out["ratio"])
    if "anchor" not in r and group in DEFAULT_ANCHOR:
        a = DEFAULT_ANCHOR[group]
        if anchors.ANCHORS[a][0] == out["unit"]:
            out["anchor"] = a
    if out["ratio"] is None and out["value"] is not None and out["anchor"] in anchors.ANCHORS:
        out["ratio"] = anchors.ratio(out["value"], out["anchor"])
    if out["ok"] is not None:
        out["ok"] = bool(out["ok"])
    return out


def run_group(key: str, quick: bool) -> list[dict]:
    """Rows of one benchmark module (an absent optional module or a crash becomes a row)."""
    module, what, _ = BENCHMARKS[key]
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name != module:
            raise
        path = module.replace(".", "/") + ".py"
        return [{"group": key, "name": what, "value": None, "unit": "", "target": None, "ok": None,
                 "anchor": None, "ratio": None, "note": f"not measured: {path} does not exist"}]
    fn = getattr(mod, "figures", None)
    if not callable(fn):
        return [{"group": key, "name": what, "value": None, "unit": "", "target": None, "ok": None,
                 "anchor": None, "ratio": None, "note": f"not measured: {module} has no figures()"}]
    return [normalise(key, r) for r in fn(quick=quick)]


def run(quick: bool = False, only: list[str] | None = None, fuzz: bool = False,
        progress: Callable[[str], None] | None = None) -> dict:
    """Run the selection; the whole result as one JSON-able document."""
    say = progress or (lambda s: None)
    want_anchors, groups = selection(only, fuzz)
    doc = {"suite": "bsc benchmarks", "quick": quick, "machine": machine(), "rows": [],
           "errors": [], "wall_s": {}}
    t_all = time.perf_counter()
    anchors.reset()
    for name in want_anchors:
        t0 = time.perf_counter()
        try:
            anchors.measure(name, quick)
            say(f"anchor {name}: {anchors.get(name):,.1f} {anchors.ANCHORS[name][0]} "
                f"({time.perf_counter() - t0:.1f} s)")
        except Exception as exc:  # noqa: BLE001 - reported as a failed row, the rest still runs
            doc["errors"].append({"group": "anchor", "name": name, "error": f"{type(exc).__name__}: {exc}"})
            say(f"anchor {name}: FAILED {type(exc).__name__}: {exc}")
    rows: list[dict] = []
    for key in groups:
        t0 = time.perf_counter()
        say(f"{key}: running ({BENCHMARKS[key][1]}) ...")
        try:
            got = run_group(key, quick)
        except Exception as exc:  # noqa: BLE001 - one broken benchmark must not hide the others
            err = f"{type(exc).__name__}: {exc}"
            doc["errors"].append({"group": key, "name": BENCHMARKS[key][1], "error": err})
            got = [{"group": key, "name": BENCHMARKS[key][1], "value": None, "unit": "",
                    "target": None, "ok": False, "anchor": None, "ratio": None,
                    "note": f"FAILED: {err}"}]
        dt = time.perf_counter() - t0
        doc["wall_s"][key] = round(dt, 2)
        say(f"{key}: {len(got)} row(s) in {dt:.1f} s")
        rows += got
    anchor_rows = [{"group": "anchor", **r} for r in anchors.measured()]
    for r in anchor_rows:
        r["note"] = f"{anchors.ANCHORS[r['name']][1]}; {r.get('note', '')}".rstrip("; ")
    doc["rows"] = anchor_rows + rows
    doc["machine"]["load_end"] = _load()
    doc["wall_s"]["total"] = round(time.perf_counter() - t_all, 2)
    judged = [r["ok"] for r in doc["rows"] if r.get("ok") is not None]
    doc["targets"] = {"met": sum(judged), "missed": len(judged) - sum(judged)}
    return doc


# --- printing --------------------------------------------------------------------------------

def fmt_value(v: float | None) -> str:
    if v is None:
        return "-"
    a = abs(v)
    if a == 0:
        return "0"
    if a >= 1000:
        return f"{v:,.0f}"
    if a >= 100:
        return f"{v:.0f}"
    if a >= 1:
        return f"{v:.2f}".rstrip("0").rstrip(".") if a < 10 else f"{v:.1f}"
    return f"{v:.3g}"


def fmt_ratio(v: float | None) -> str:
    if v is None:
        return "-"
    a = abs(v)
    if a >= 1000:
        return f"{v:,.0f}"
    if a >= 10:
        return f"{v:.1f}"
    if a >= 0.01:
        return f"{v:.3f}"
    return f"{v:.3g}"


def _ok(v) -> str:
    return "" if v is None else ("yes" if v else "NO")


def header_lines(doc: dict) -> list[str]:
    m = doc["machine"]
    v = m["versions"]
    usable = m.get("cores_usable")
    cores = f"{m['cores']} cores" + (f" ({usable} usable)" if usable not in (None, m["cores"]) else "")
    load = lambda x: " ".join(f"{a:.2f}" for a in x) if x else "?"  # noqa: E731
    return [
        f"bsc benchmarks{' (--quick)' if doc['quick'] else ''}: {m['date']}"
        + (f", commit {m['commit']}" if m.get("commit") else ""),
        f"machine: {m['host']}, {m['cpu']}, {cores}; load average {load(m['load_start'])} at start, "
        f"{load(m.get('load_end'))} at end",
        "versions: " + ", ".join(f"{k} {val}" for k, val in v.items())
        + f"; OPENBLAS_NUM_THREADS={m.get('openblas_threads')}",
    ]


COLUMNS = (("group", "<"), ("figure", "<"), ("value", ">"), ("unit", "<"), ("anchor", "<"),
           ("ratio", ">"), ("target", "<"), ("ok", "<"))


def _cells(r: dict) -> list[str]:
    return [r.get("group", ""), r["name"], fmt_value(r["value"]), r.get("unit") or "",
            r.get("anchor") or "-", fmt_ratio(r.get("ratio")), r.get("target") or "", _ok(r.get("ok"))]


def table(doc: dict, markdown: bool = False, notes: bool = True) -> str:
    rows = [_cells(r) for r in doc["rows"]]
    out = [f"- {h}" for h in header_lines(doc)] if markdown else header_lines(doc)
    out.append("")
    names = [c for c, _ in COLUMNS]
    if markdown:
        out.append("| " + " | ".join(names) + " |")
        out.append("|" + "|".join("---:" if a == ">" else "---" for _, a in COLUMNS) + "|")
        for c in rows:
            out.append("| " + " | ".join(x.replace("|", "/") for x in c) + " |")
    else:
        widths = [max(len(n), *(len(c[i]) for c in rows)) if rows else len(n) for i, n in enumerate(names)]
        line = lambda cells: "  ".join(f"{x:{a}{w}}" for x, (_, a), w in zip(cells, COLUMNS, widths)).rstrip()  # noqa: E731
        out.append(line(names))
        out.append(line(["-" * w for w in widths]))
        prev = None
        for r, c in zip(doc["rows"], rows):
            if prev is not None and r.get("group") != prev:
                out.append("")
            prev = r.get("group")
            out.append(line(c))
    out.append("")
    t = doc["targets"]
    wall = doc["wall_s"]
    out.append(f"targets: {t['met']} met, {t['missed']} missed; wall "
               + ", ".join(f"{k} {v:.0f} s" for k, v in wall.items()))
    out.append("ratio = value / anchor figure measured in this run (what each anchor times: "
               "the notes, benchmarks/anchors.py)")
    if doc["errors"]:
        out.append("errors:")
        out += [f"  {e['group']}/{e['name']}: {e['error']}" for e in doc["errors"]]
    if notes:
        noted = [r for r in doc["rows"] if r.get("note")]
        if noted:
            out.append("notes:")
            out += [f"  {r['group']} / {r['name']}: {r['note']}" for r in noted]
    return "\n".join(out)


# --- command line ----------------------------------------------------------------------------

def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="smaller runs (about 1-2 minutes in all)")
    p.add_argument("--json", action="store_true", help="print one JSON document instead of the table")
    p.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    p.add_argument("--only", nargs="+", metavar="NAME", default=None,
                   help="run only these: " + ", ".join(["anchors", *anchors.ANCHORS, *BENCHMARKS]))
    p.add_argument("--fuzz", action="store_true",
                   help="also run the driver fuzz campaign (1 M frames; 100 k with --quick)")
    p.add_argument("--no-notes", action="store_true", help="leave out the notes under the table")
    p.add_argument("--strict", action="store_true", help="exit 1 when a target is missed")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress lines on stderr")


def run_args(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Run as the options say; a bad ``--only`` name raises ValueError before anything runs."""
    out = out or sys.stdout
    selection(args.only, args.fuzz)
    progress = None if args.quiet else (lambda s: print(f"[bench] {s}", file=sys.stderr, flush=True))
    doc = run(quick=args.quick, only=args.only, fuzz=args.fuzz, progress=progress)
    if args.json:
        print(json.dumps(doc, indent=1), file=out)
    else:
        print(table(doc, markdown=args.markdown, notes=not args.no_notes), file=out)
    if doc["errors"]:
        return 1
    if args.strict and doc["targets"]["missed"]:
        return 1
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.splitlines()[0])
    add_arguments(p)
    args = p.parse_args(argv)
    try:
        return run_args(args)
    except ValueError as exc:
        p.error(str(exc))
        return 2
