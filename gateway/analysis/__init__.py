"""Offline analysis of recorded sessions (``bsc analyze``).

:mod:`.session` identifies, per session, joint friction, thruster-axis efficiency and the sensor
consistency checks; :mod:`.change` follows them across sessions (baseline + CUSUM) and attributes
alarms to an actuator, a thruster axis or a sensor; :mod:`.report` writes Markdown + PNG plots.
:func:`run` ties them together (sessions in parallel worker processes).
"""
from __future__ import annotations

import os
from pathlib import Path

from .change import DEFAULT_DETECTORS, Detector, Finding, SeriesResult, analyze_series
from .session import AnalysisError, SessionFeatures, analyze_session, session_order_key

__all__ = ["AnalysisError", "DEFAULT_DETECTORS", "Detector", "Finding", "SeriesResult", "SessionFeatures",
           "analyze_series", "analyze_session", "collect_sessions", "run", "session_order_key"]


def collect_sessions(paths) -> list[Path]:
    """Files and folders (every ``*.mcap`` below, recursively) -> session files in time order."""
    files: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            files += sorted(q for q in p.rglob("*.mcap") if q.is_file())
        elif p.is_file():
            files.append(p)
        else:
            raise FileNotFoundError(f"no such file or folder: {p}")
    seen: set[Path] = set()
    unique = [f for f in files if not (f.resolve() in seen or seen.add(f.resolve()))]
    if not unique:
        raise AnalysisError("no .mcap session found in " + ", ".join(map(str, paths)))
    return sorted(unique, key=session_order_key)


def _analyze_one(path: str):
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    try:
        return analyze_session(path)
    except AnalysisError as exc:
        return exc


def run(paths, *, detectors=None, baseline_sessions: int = 3, workers: int | None = None,
        progress: bool = False) -> tuple[SeriesResult, list[str]]:
    """Analyse sessions (in parallel processes) and the series; ``(result, skipped reasons)``."""
    files = collect_sessions(paths)
    from gateway.parallel import map_jobs

    results = map_jobs(_analyze_one, [str(f) for f in files], workers=workers,
                       progress="analyze" if progress else None, unit="session")
    sessions, skipped = [], []
    for i in range(len(files)):
        r = results[i]
        if isinstance(r, Exception):
            skipped.append(str(r))
        else:
            sessions.append(r)
    if not sessions:
        raise AnalysisError("no session could be analysed: " + "; ".join(skipped))
    return analyze_series(sessions, detectors or DEFAULT_DETECTORS, baseline_sessions), skipped
