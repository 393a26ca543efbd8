"""Replay a recorded session: offline through drivers + estimator, or live onto CAN / zenoh.

Three engines over one reader:

- :func:`replay_offline` feeds the raw CAN frames of a log, in the order the live gateway fed
  them, through a fresh :class:`gateway.pipeline.Pipeline` as fast as it can, records every
  sample, health report and effort it emits to a new MCAP file, and writes ``report.json``.
  Same frames in the same order give the same emits, so the efforts are byte-identical to the
  ones recorded live (``tests/gateway/log/test_replay.py``).
- :func:`play_can` puts the raw frames back on python-can buses with their original spacing
  (scaled by ``rate``).
- :func:`play_zenoh` republishes the recorded samples, health and efforts on their keys, with
  their original spacing, payloads encoded by :mod:`gateway.codec` (byte-identical to what the
  gateway published).

Order: frames are read in FILE order, not log-time order. The recorder writes messages in the
order ``record*`` was called, so file order is the order the live gateway recorded (and fed)
them, even where timestamps of two buses interleave out of order. Log time (``t_ns``) gives
the timing of live playback and the log time of every replayed emit.

Bad input (empty, foreign, corrupt) raises :class:`ReplayError` or
:class:`gateway.errors.McapFileError`, both ``ValueError`` with one readable line; a truncated
file (killed recorder) is recovered into a temporary copy first (:func:`readable`).
"""
from __future__ import annotations

import collections
import contextlib
import dataclasses
import fnmatch
import heapq
import json
import os
import re
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from gateway.log.context import LogContext, read_context, resolve_robot, session_context
from gateway.log.errors import LogError, McapFileError
from gateway.log.names import (CAN_TOPIC_PREFIX, DBC_ATTACHMENT_PREFIX, RECORDING_METADATA, SCENARIO_ATTACHMENT,
                               SESSION_METADATA)
from gateway.log.reader import Warn, iter_can_frames, iter_file_order, json_record, no_warn, readable

REPORT_NAME = "report.json"
OUTPUT_NAME = "replay.mcap"
_SLEEP_MIN_S = 0.0002          # closer than this to a frame's time: send now, not sleep
REORDER_WINDOW_NS = 1_000_000_000   # live playback: messages are put in log-time order within this
LATE_US = 500.0                # live playback: a message sent this much after its due time is late


class ReplayError(LogError):
    """A log cannot be replayed as asked (nothing to replay, no robot, no pipeline...)."""


# ----------------------------------------------------------------------------- the log


# ----------------------------------------------------------------------------- robots


# ----------------------------------------------------------------------------- offline

def _default_pipeline_factory():
    try:
        from gateway.pipeline import Pipeline
    except ImportError as exc:
        raise ReplayError("offline replay needs gateway.pipeline (the drivers + estimator core), "
                          f"which this build does not have ({exc})") from None
    return Pipeline


@dataclasses.dataclass(slots=True)
class OfflineReport:
    """What ``report.json`` holds (see :func:`replay_offline`)."""

    source: str
    output: str
    robot: str
    source_recovered: bool = False
    frames_in: int = 0
    frames_skipped: dict[str, int] = dataclasses.field(default_factory=dict)
    samples: int = 0
    efforts: int = 0
    good_efforts: int = 0
    health_reports: int = 0
    alerts: int = 0
    valve_wrenches: int = 0                      # the thruster filter's learned per-valve wrenches
    rejections: dict[str, int] = dataclasses.field(default_factory=dict)
    rejections_by_device: dict[str, dict[str, int]] = dataclasses.field(default_factory=dict)
    by_key: dict[str, int] = dataclasses.field(default_factory=dict)
    log_start_ns: int | None = None
    log_end_ns: int | None = None
    log_duration_s: float = 0.0
    wall_s: float = 0.0
    speed_x_realtime: float = 0.0
    frames_per_s: float = 0.0
    recorder: dict[str, Any] = dataclasses.field(default_factory=dict)
    check: dict[str, Any] | None = None          # check=True: EffortCheck.to_json()

    def to_json(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


CHECK_RTOL = 1e-9


@dataclasses.dataclass(slots=True)
class EffortCheck:
    """The replayed efforts against the ones the log recorded (:func:`compare_efforts`).

    ``identical``: byte for byte; ``close``: not, but every number within :data:`CHECK_RTOL`
    relative (of the larger magnitude; 1e-12 absolute near zero) and everything else equal;
    ``differ``: the rest, and efforts only one side has. The same kernels (:data:`gateway.KERNELS`)
    must give identical bytes; a log from other kernels may be ``close``."""

    recorded: int = 0
    replayed: int = 0
    identical: int = 0
    close: int = 0
    differ: int = 0
    first_difference: str | None = None
    kernels_recorded: str | None = None
    kernels_now: str = ""
    not_in_log: dict[str, int] = dataclasses.field(default_factory=dict)   # topic -> replayed, not compared

    @property
    def same_kernels(self) -> bool:
        return self.kernels_recorded == self.kernels_now

    @property
    def ok(self) -> bool:
        return self.differ == 0 and self.recorded == self.replayed and (self.close == 0 or not self.same_kernels)

    def summary(self) -> str:
        """One line for the user."""
        rec = ("unrecorded (a log from before kernel versions were recorded)" if self.kernels_recorded is None
               else f"v{self.kernels_recorded}")
        if self.recorded == 0:
            return "the log holds no efforts to compare with"
        note = "".join(f" ({n} on {t} not compared: the log has none, recorded before the gateway published them)"
                       for t, n in sorted(self.not_in_log.items()))
        if self.ok and self.identical == self.recorded:
            kern = f"kernels v{self.kernels_now}" if self.same_kernels else f"kernels {rec}, now v{self.kernels_now}"
            return f"all {self.recorded} efforts byte-identical to the log's ({kern})" + note
        if self.ok:
            return (f"the log's efforts came from kernels {rec}, these are v{self.kernels_now}: "
                    f"{self.identical} byte-identical, {self.close} within {CHECK_RTOL:g} relative, none beyond"
                    + note)
        why = [f"{self.differ} beyond {CHECK_RTOL:g} relative"] if self.differ else []
        if self.close and self.same_kernels:
            why.append(f"{self.close} not byte-identical although the kernels are the same (v{self.kernels_now})")
        if self.recorded != self.replayed:
            why.append(f"{self.recorded} recorded, {self.replayed} replayed")
        return (f"efforts DIFFER from the log's (kernels {rec}, now v{self.kernels_now}): " + "; ".join(why)
                + (f"; first: {self.first_difference}" if self.first_difference else "") + note)

    def to_json(self) -> dict[str, Any]:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d.update(ok=self.ok, summary=self.summary())
        return d


def _near(a, b, path: str = "") -> str | None:
    """None when ``a`` and ``b`` (parsed JSON) agree within CHECK_RTOL, else where they do not."""
    if isinstance(a, bool) or isinstance(b, bool) or not isinstance(a, (int, float)) or not isinstance(b, (int, float)):
        if isinstance(a, dict) and isinstance(b, dict):
            if a.keys() != b.keys():
                return f"{path or 'the message'}: fields {sorted(a)} vs {sorted(b)}"
            for k in a:
                why = _near(a[k], b[k], f"{path}.{k}" if path else k)
                if why:
                    return why
            return None
        if isinstance(a, list) and isinstance(b, list):
            if len(a) != len(b):
                return f"{path}: {len(a)} vs {len(b)} values"
            for i, (x, y) in enumerate(zip(a, b)):
                why = _near(x, y, f"{path}[{i}]")
                if why:
                    return why
            return None
        return None if a == b else f"{path}: {a!r} vs {b!r}"
    if a == b or abs(a - b) <= max(CHECK_RTOL * max(abs(a), abs(b)), 1e-12):
        return None
    return f"{path}: {a!r} recorded, {b!r} replayed"


def _without_envelope(record: dict) -> dict:
    return {k: v for k, v in record.items() if k not in ("type", "v")}


LATER_EFFORT_TOPICS = ("/efforts/valves",)
"""Effort topics a gateway did not always publish: a log without any of them is compared on the rest."""


def compare_efforts(recorded: str | os.PathLike[str], replayed: str | os.PathLike[str]) -> EffortCheck:
    """Every effort message of ``replayed`` against ``recorded``'s, topic by topic in file order."""
    from gateway import KERNELS

    def efforts(p):
        out: dict[str, list] = {}
        for topic, _, m in iter_file_order(p, lambda t, s: "/efforts/" in t):
            out.setdefault(topic, []).append((m.log_time, bytes(m.data)))
        return out

    ctx = read_context(recorded)
    check = EffortCheck(kernels_recorded=ctx.metadata.get(SESSION_METADATA, {}).get("kernels"), kernels_now=KERNELS)
    old, new = efforts(recorded), efforts(replayed)
    for topic in sorted(set(new) - set(old)):
        if topic.endswith(LATER_EFFORT_TOPICS):           # a log from before they were published
            check.not_in_log[topic] = len(new.pop(topic))
    for topic in sorted(set(old) | set(new)):
        a, b = old.get(topic, []), new.get(topic, [])
        check.recorded += len(a)
        check.replayed += len(b)
        for (t, x), (_, y) in zip(a, b):
            if x == y:
                check.identical += 1
                continue
            dx, dy = json.loads(x), json.loads(y)
            if _without_envelope(dx) == _without_envelope(dy) and ("type" in dx) != ("type" in dy):
                check.identical += 1              # a log from before the one JSON form: the same values
                continue
            why = _near(dx, dy)
            if why is None:
                check.close += 1
            else:
                check.differ += 1
                if check.first_difference is None:
                    check.first_difference = f"{topic} at log time {t} ns, {why}"
        extra = abs(len(a) - len(b))
        check.differ += extra
        if extra and check.first_difference is None:
            check.first_difference = f"{topic}: {len(a)} recorded, {len(b)} replayed"
    return check


def replay_offline(path: str | os.PathLike[str], out_dir: str | os.PathLike[str], *,
                   robot: str | None = None, model: str | None = None, fd: bool | None = None,
                   start_s: float | None = None, duration_s: float | None = None,
                   can_ids: Iterable[int] | None = None, topics: Iterable[str] | None = None,
                   copy_can: bool = False, overwrite: bool = False, samples: bool = False,
                   check: bool = False,
                   pipeline_factory: Callable[..., Any] | None = None,
                   progress: bool = False, warn: Warn = no_warn) -> OfflineReport:
    """Feed the raw frames of ``path`` through a fresh pipeline; write ``OUT/replay.mcap`` and
    ``OUT/report.json``; return the report.

    Every emit ``(key, obj)`` is recorded on topic ``key`` with log time = the timestamp of the
    frame whose feed produced it; after the last frame the pipeline is flushed (as the live
    gateway does when it stops; those emits get the last frame's time) and one health snapshot per bus and device
    (at the last frame's time) is recorded and its rejection counters fill the report.
    ``robot`` overrides the log's URDF (``model`` the estimator's belief, default the same).
    ``copy_can`` also copies the replayed raw frames, making the output replayable itself;
    ``samples`` also records every decoded sample (by default the output holds the efforts and the
    health). ``check`` compares the replayed efforts with the ones the log recorded
    (:func:`compare_efforts`; the report's ``check``): it needs the whole log, with its own robot.
    ``topics`` (globs over ``/can/<bus>``) and ``can_ids`` select frames; ``start_s`` and
    ``duration_s`` a window relative to the log's first message.
    """
    if check and any(x is not None for x in (robot, model, start_s, duration_s, can_ids, topics)):
        raise ReplayError("a check compares with the efforts the log recorded: replay the whole log with its "
                          "own robot (no other robot or model, no time window, no CAN id or topic selection)",
                          option="check")
    from drivers.samples import BusHealth, DeviceHealth
    from gateway.efforts import Alert, JointEfforts, ThrusterEffort, ValveWrenches
    from gateway.engine import Session, Sink
    from gateway.engine.deferred import deferred
    from gateway.engine.sinks import RecorderSink
    from gateway.log.frames import batched, mcap_frames, read_ahead
    from gateway.log.recorder import Recorder

    import robot_description
    from robot_description.thrusters import ThrusterLayout

    out_dir = Path(out_dir)
    with readable(path, warn) as src:
        ctx = read_context(src)
        if not ctx.buses:
            raise ReplayError(f"{path}: no raw CAN channels ({CAN_TOPIC_PREFIX}<bus>) to replay"
                              + (" (empty log)" if ctx.message_count == 0 else ""))
        Pipeline = pipeline_factory or _default_pipeline_factory()
        pick = _topic_pred(topics)
        buses = [b for b in ctx.buses if pick(CAN_TOPIC_PREFIX + b)]
        if not buses:
            raise ReplayError(f"{path}: the topics selected are none of the raw CAN channels "
                              f"({', '.join(CAN_TOPIC_PREFIX + b for b in ctx.buses)})", option="topics")
        rob = resolve_robot(ctx, robot)
        model_robot = robot_description.load(model) if model is not None else None
        use_fd = ctx.fd if fd is None else fd
        start_ns, end_ns = ctx.window(start_s, duration_s)
        out_dir.mkdir(parents=True, exist_ok=True)
        out_path = out_dir / OUTPUT_NAME
        report_path = out_dir / REPORT_NAME
        for p in (out_path, report_path):
            if p.exists() and not overwrite:
                raise FileExistsError(f"{p} exists")

        kinds: Counter[str] = Counter()
        by_key: Counter[str] = Counter()
        dbcs = {name[len(DBC_ATTACHMENT_PREFIX):]: data for name, (_, data)
                in ctx.attachments.items() if name.startswith(DBC_ATTACHMENT_PREFIX)}
        scenario = ctx.attachments.get(SCENARIO_ATTACHMENT)
        context = session_context(
            rob, fd=use_fd, dbc_files=dbcs or None,
            scenario_text=scenario[1].decode("utf-8", "replace") if scenario else None,
            extra={"replay_of": Path(path).name,
                   "replay_of_session": ctx.metadata.get(RECORDING_METADATA, {}).get("session", ""),
                   "mode": "offline replay",
                   **({"model": str(model)} if model is not None else {})})
        with _replaced_on_success(out_path) as part, Recorder(part, overwrite=True) as rec:
            rec.add_session_context(**context)

            class Count(Sink):
                """What the replay wrote, for the report (rows: no object built for it)."""

                rows = True

                def sample_rows(self, session, events, log_ns) -> None:
                    table = session.encoders().sample_key
                    kinds["samples"] += len(events)
                    # a count per (kind, device) of the batch, not a Python step per sample
                    pair = events["kind"].astype(np.int64) << 32 | events["device"].astype(np.int64)
                    for p, n in zip(*(a.tolist() for a in np.unique(pair, return_counts=True))):
                        by_key[table[p >> 32][p & 0xFFFFFFFF]] += n

                def effort_rows(self, session, rows, log_ns) -> None:
                    names = session.encoders().effort_key
                    for key in names:
                        by_key[key] += len(rows)
                    kinds["efforts"] += len(rows) * len(names)
                    kinds["good_efforts"] += session.pipeline.estimator.good_efforts(rows)

                def valve_rows(self, session, rows, log_ns) -> None:
                    by_key[session.encoders().valve_key] += len(rows)
                    kinds["valve_wrenches"] += len(rows)

                def emit(self, key: str, obj, log_ns: int) -> None:
                    by_key[key] += 1
                    if isinstance(obj, (DeviceHealth, BusHealth)):
                        kinds["health"] += 1
                    elif isinstance(obj, Alert):
                        kinds["alerts"] += 1
                    elif isinstance(obj, ValveWrenches):
                        kinds["valve_wrenches"] += 1
                    elif isinstance(obj, (JointEfforts, ThrusterEffort)):
                        kinds["efforts"] += 1
                        kinds["good_efforts"] += bool(obj.good)
                    else:
                        kinds["samples"] += 1

            # the thruster layout the session flew (a custom [[thrusters.custom]] one too): the
            # filter's prior, without which its wrenches differ from the live run's
            layout = (ThrusterLayout.from_scenario_text(scenario[1].decode("utf-8", "replace"),
                                                        f"{path}: {SCENARIO_ATTACHMENT}") if scenario else None)
            # the output encoded and written by a thread of its own while the next frames are
            # estimated (gateway/engine/deferred.py): the same calls in the same order, on two cores
            with deferred([RecorderSink(rec, frames=copy_can, offline=True, rows=True), Count()]) as sinks:
                ses = Session(rob, sinks,
                              model_robot=model_robot, fd=use_fd, layout=layout, pipeline_factory=Pipeline,
                              samples=samples)
                known = set(ses.buses)
                skipped: Counter[str] = Counter()
                bar = _bar(progress, ctx, start_ns, end_ns, "replay")
                frames = 0
                first = last = None
                last_bar = None
                t0 = time.perf_counter()

                def advanced(t_first: int, t_last: int) -> None:
                    """Frames up to log time ``t_last`` fed: the log's span so far, the progress bar."""
                    nonlocal first, last, last_bar
                    if first is None:
                        first = last_bar = t_first
                    last = t_last
                    if bar is not None and last - last_bar >= 100_000_000:
                        bar.update((last - last_bar) / 1e9)
                        last_bar = last

                # rows straight from the chunks; copied frames need all of each record (its channel),
                # which rows do not keep: then record by record
                chunks = None if copy_can else mcap_frames(src, buses, start_ns=start_ns, end_ns=end_ns,
                                                           can_ids=can_ids)
                if chunks is not None:
                    chunks = read_ahead(batched(chunks))     # merged in the reader's thread
                    to_session = np.array([ses.buses.index(b) if b in known else -1 for b in buses], dtype=np.int64)
                    for chunk in chunks:
                        idx = to_session[chunk.frames["bus"]]
                        rows, log = chunk.frames, chunk.log_ns
                        if (idx < 0).any():
                            for b in np.unique(idx_bus := chunk.frames["bus"][idx < 0]).tolist():
                                skipped[f"unknown_bus:{buses[b]}"] += int((idx_bus == b).sum())
                            rows, log, idx = rows[idx >= 0], log[idx >= 0], idx[idx >= 0]
                        if not len(rows):
                            continue
                        # copied as bytes: numpy copies a structured row field by field, 4x the time
                        rows = rows.view(np.dtype((np.void, rows.dtype.itemsize))).copy().view(rows.dtype)
                        rows["bus"] = idx
                        ses.feed_frames(rows, log)
                        frames += len(rows)
                        advanced(int(log[0]), int(log[-1]))
                else:                             # no summary, or frames copied: record by record
                    for bus, t, msg in iter_can_frames(src, buses=buses, can_ids=can_ids,
                                                       start_ns=start_ns, end_ns=end_ns):
                        if bus not in known:
                            skipped[f"unknown_bus:{bus}"] += 1
                            continue
                        ses.feed(bus, msg, log_ns=t)
                        frames += 1
                        advanced(t, t)
                if bar is not None:
                    bar.close()
                final = ses.close()              # end of input: epochs still waiting, last health
            rejections, per_device = _rejections(final)
        wall = time.perf_counter() - t0              # the output written and closed too
        if frames == 0:
            out_path.unlink(missing_ok=True)
            raise ReplayError(f"{path}: no CAN frames match the filters / time window")
        dur = (last - first) / 1e9 if first is not None else 0.0
        report = OfflineReport(
            source=str(path), output=str(out_path), robot=rob.name,
            source_recovered=Path(src) != Path(path), frames_in=frames,
            frames_skipped=dict(skipped), samples=kinds["samples"], efforts=kinds["efforts"],
            good_efforts=kinds["good_efforts"], health_reports=kinds["health"],
            alerts=kinds["alerts"], valve_wrenches=kinds["valve_wrenches"], rejections=rejections,
            rejections_by_device=per_device,
            by_key=dict(sorted(by_key.items())), log_start_ns=first, log_end_ns=last,
            log_duration_s=dur, wall_s=wall, speed_x_realtime=dur / wall if wall > 0 else 0.0,
            frames_per_s=frames / wall if wall > 0 else 0.0,
            recorder=dataclasses.asdict(rec.stats) | {"dropped": rec.stats.dropped,
                                                      "files": [str(out_path)]})
    if check:
        report.check = compare_efforts(src, out_path).to_json()
    tmp = report_path.with_name(f".{report_path.name}.tmp")
    tmp.write_text(json.dumps(report.to_json(), indent=1) + "\n")
    os.replace(tmp, report_path)
    return report


@contextlib.contextmanager
def _replaced_on_success(path: Path) -> Iterator[Path]:
    """A temporary name beside ``path`` to write to; renamed to ``path`` when the block ends
    normally, deleted when it raises (a replay that fails part-way, or is interrupted, leaves no
    file that looks complete, and an earlier output stays as it was)."""
    part = path.with_name(f".{path.name}.{os.getpid()}.part")
    try:
        yield part
    except BaseException:
        part.unlink(missing_ok=True)
        raise
    os.replace(part, path)


def output_dirs(files: list[Path], out_dir: Path) -> list[Path]:
    """Where each of several logs replays to: ``out_dir/<stem>`` when the names differ, else
    the logs' paths below their common folder, without the suffix (``runs/day1/session.mcap``
    and ``runs/day2/session.mcap`` -> ``out/day1/session``, ``out/day2/session``)."""
    files = [Path(f).absolute() for f in files]
    stems = [f.stem for f in files]
    if len(set(stems)) == len(stems):
        return [out_dir / s for s in stems]
    if len(set(files)) != len(files):
        dup = next(f for f in files if files.count(f) > 1)
        raise ReplayError(f"{dup} is given twice")
    common = Path(os.path.commonpath([str(f.parent) for f in files]))
    return [out_dir / f.relative_to(common).with_suffix("") for f in files]


class ReplayOutcome(NamedTuple):
    """One log of :func:`replay_many`: its report, or the error that stopped it, and the
    warnings it gave (a truncated log recovered, ...)."""

    source: str
    output: str
    report: OfflineReport | None
    error: str | None
    warnings: list[str]


def _replay_job(job) -> ReplayOutcome:
    path, out, kwargs = job
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    warnings: list[str] = []
    try:
        return ReplayOutcome(path, out, replay_offline(path, out, warn=warnings.append, **kwargs), None, warnings)
    except (ReplayError, McapFileError, OSError, ValueError) as exc:
        return ReplayOutcome(path, out, None, str(exc), warnings)


def replay_many(files, out_dir, *, workers: int | None = None, progress: bool = False,
                done: Callable[[int, ReplayOutcome], None] | None = None, **kwargs) -> list[ReplayOutcome]:
    """:func:`replay_offline` of every log in ``files`` into its own folder of ``out_dir``
    (:func:`output_dirs`), one session per process on ``workers`` processes (default: every
    CPU), a progress bar over the logs. A log that cannot be replayed is reported in its
    outcome and the others go on. Outcomes in the order given; ``done(i, outcome)`` as each ends."""
    from gateway.parallel import map_jobs

    files = [Path(f) for f in files]
    outs = output_dirs(files, Path(out_dir))
    jobs = [(str(f), str(o), kwargs) for f, o in zip(files, outs)]
    return map_jobs(_replay_job, jobs, workers=workers, progress="replay" if progress else None, unit="log",
                    done=done)


def _rejections(health: list) -> tuple[dict[str, int], dict[str, dict[str, int]]]:
    total: Counter[str] = Counter()
    per: dict[str, dict[str, int]] = {}
    for h in health:
        rej = dict(getattr(h, "rejected", ()) or ())
        if not rej:
            continue
        name = getattr(h, "device", None) or f"bus/{getattr(h, 'bus', '?')}"
        per[name] = rej
        total.update(rej)
    return dict(sorted(total.items())), per


# ----------------------------------------------------------------------------- live playback

@dataclasses.dataclass(slots=True)
class PlayStats:
    """What a live playback did. ``sent`` by bus (CAN) or key (zenoh)."""

    sent: Counter = dataclasses.field(default_factory=Counter)
    skipped: Counter = dataclasses.field(default_factory=Counter)
    errors: Counter = dataclasses.field(default_factory=Counter)
    loops: int = 0
    wall_s: float = 0.0
    log_s: float = 0.0
    interrupted: bool = False
    late: int = 0                 # paced messages sent more than LATE_US after their due time
    late_max_us: float = 0.0

    @property
    def total(self) -> int:
        return sum(self.sent.values())

    def line(self, what: str) -> str:
        out = f"{what} {self.total} in {self.wall_s:.2f} s"
        if self.loops > 1:
            out += f" ({self.loops} loops)"
        if self.sent:
            out += " (" + ", ".join(f"{k} {v}" for k, v in sorted(self.sent.items())) + ")"
        if self.skipped:
            out += "; skipped " + ", ".join(f"{k} {v}" for k, v in sorted(self.skipped.items()))
        if self.errors:
            out += "; errors " + ", ".join(f"{k} {v}" for k, v in sorted(self.errors.items()))
        if self.late:
            out += (f"; {self.late} sent more than {LATE_US / 1000:g} ms after their recorded time (max "
                    f"{self.late_max_us / 1000:.1f} ms): a receiver that stamps on arrival sees them late "
                    "(a real-time priority for the player helps)")
        if self.interrupted:
            out += "; interrupted"
        return out


class _Clock:
    """Paces a stream of log times against the monotonic clock, scaled by ``rate`` (0 = no
    pacing); ``stop`` ends a wait early."""

    def __init__(self, rate: float, stop: threading.Event):
        if rate < 0:
            raise ReplayError(f"rate {rate}: must be >= 0 (0 = as fast as possible)", option="rate")
        self.rate, self.stop = rate, stop
        self.t0: int | None = None
        self.wall0 = 0.0

    def restart(self) -> None:
        self.t0 = None

    def wait_for(self, t_ns: int) -> bool:
        """Wait until log time ``t_ns`` is due; False when stopped."""
        if self.t0 is None:
            self.t0, self.wall0 = t_ns, time.monotonic()
            return not self.stop.is_set()
        delay = self.until(t_ns)
        if delay > _SLEEP_MIN_S:
            return not self.stop.wait(delay)
        return not self.stop.is_set()

    def until(self, t_ns: int) -> float:
        """Seconds until log time ``t_ns`` is due (negative: late; 0 when not pacing or not started)."""
        if self.rate <= 0 or self.t0 is None:
            return 0.0
        return self.wall0 + (t_ns - self.t0) / 1e9 / self.rate - time.monotonic()

    def late_us(self, t_ns: int) -> float:
        """How long after its due time log time ``t_ns`` is now (0 when not pacing)."""
        return -self.until(t_ns) * 1e6


READ_AHEAD = 4096              # live playback: messages read and decoded ahead, while waiting


def _read_ahead(items: Iterator[tuple[str, int, Any]], clock: "_Clock") -> Iterator[tuple[str, int, Any]]:
    """``items`` through a buffer filled while the next message is not yet due: reading and
    decoding the log happen in the gaps, so a burst of messages goes out back to back as it was
    recorded, not spread by the reader's cost per message."""
    buf: collections.deque = collections.deque()
    it = iter(items)
    more = True

    def pull(n: int) -> None:
        nonlocal more
        for _ in range(n):
            try:
                buf.append(next(it))
            except StopIteration:
                more = False
                return

    while True:
        if not buf:
            if not more:
                return
            pull(64)
            if not buf:
                return
        while more and len(buf) < READ_AHEAD and clock.until(buf[0][1]) > 0.0005:
            pull(16)                                  # idle time: read ahead
        yield buf.popleft()


def _time_ordered(items: Iterator[tuple[str, int, Any]], window_ns: int = REORDER_WINDOW_NS
                  ) -> Iterator[tuple[str, int, Any]]:
    """``items`` in log-time order, as far as a message is less than ``window_ns`` out of place
    (ties keep the recording order; a message read after others more than ``window_ns`` newer
    went out is sent as soon as it is read). A gateway records in the order it processed, which
    interleaves its buses in runs of a few frames; live playback must keep each message's time."""
    heap: list = []
    push, pop = heapq.heappush, heapq.heappop
    for seq, (name, t, obj) in enumerate(items):
        push(heap, (t, seq, name, obj))
        while heap[0][0] <= t - window_ns:
            t0, _, n0, o0 = pop(heap)
            yield n0, t0, o0
    while heap:
        t0, _, n0, o0 = pop(heap)
        yield n0, t0, o0


def _bar(progress: bool, ctx: LogContext, start_ns, end_ns, desc: str):
    if not progress or ctx.start_ns is None:
        return None
    from tqdm import tqdm

    lo = ctx.start_ns if start_ns is None else max(start_ns, ctx.start_ns)
    hi = ctx.end_ns if end_ns is None else min(end_ns, ctx.end_ns)
    return tqdm(total=round(max(hi - lo, 0) / 1e9, 1), unit="s", desc=desc, leave=False,
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} s log "
                           "[{elapsed}<{remaining}]")


def _topic_pred(globs: Iterable[str] | None) -> Callable[[str], bool]:
    pats = list(globs or ())
    if not pats:
        return lambda topic: True
    return lambda topic: any(fnmatch.fnmatchcase(topic, p) for p in pats)


def _play(ctx: LogContext, items: Callable[[], Iterator[tuple[str, int, Any]]],
          send: Callable[[str, Any], None], stats: PlayStats, *, rate: float, loop: bool,
          stop: threading.Event | None, progress: bool, start_ns, end_ns, desc: str) -> None:
    stop = stop or threading.Event()
    clock = _Clock(rate, stop)
    t_begin = time.monotonic()
    try:
        while True:
            clock.restart()
            bar = _bar(progress, ctx, start_ns, end_ns, desc if not loop else
                       f"{desc} (loop {stats.loops + 1})")
            first = last_bar = None
            n = 0
            try:
                for name, t, obj in _read_ahead(_time_ordered(items()), clock):
                    if not clock.wait_for(t):
                        stats.interrupted = True
                        return
                    send(name, obj)
                    late = clock.late_us(t)
                    if late > LATE_US:
                        stats.late += 1
                        if late > stats.late_max_us:
                            stats.late_max_us = late
                    n += 1
                    if first is None:
                        first = last_bar = t
                    stats.log_s = max(stats.log_s, (t - first) / 1e9)
                    if bar is not None and t - last_bar >= 50_000_000:
                        bar.update((t - last_bar) / 1e9)
                        last_bar = t
            finally:
                if bar is not None:
                    bar.close()
            stats.loops += 1
            if not loop or n == 0 or stop.is_set():
                return
    except KeyboardInterrupt:
        stats.interrupted = True
    finally:
        stats.wall_s = time.monotonic() - t_begin


def play_can(path: str | os.PathLike[str], buses: Mapping[str, Any], *, rate: float = 1.0,
             loop: bool = False, start_s: float | None = None, duration_s: float | None = None,
             can_ids: Iterable[int] | None = None, topics: Iterable[str] | None = None,
             stop: threading.Event | None = None, progress: bool = False,
             warn: Warn = no_warn) -> PlayStats:
    """Send the raw frames of ``path`` on ``buses`` (logical bus -> open ``can.BusABC``) with
    their recorded spacing divided by ``rate`` (0: as fast as possible), in log-time order (each
    bus's frames keep their recorded order; see :func:`_time_ordered`). ``stats.late`` counts the
    frames that went out more than :data:`LATE_US` after their due time.

    Frames of buses not in ``buses`` are skipped (counted). ``can_ids`` and ``topics``
    (globs over ``/can/<bus>``) filter; ``start_s``/``duration_s`` cut a window relative to the
    log's first message. ``loop`` repeats until ``stop`` is set. A frame the bus refuses
    (``CanError``: buffer full, bus off) is counted in ``errors`` and playback goes on.
    """
    import can

    stats = PlayStats()
    with readable(path, warn) as src:
        ctx = read_context(src)
        pick = _topic_pred(topics)
        chosen = [b for b in ctx.buses if pick(CAN_TOPIC_PREFIX + b)]
        if not ctx.buses:
            raise ReplayError(f"{path}: no raw CAN channels ({CAN_TOPIC_PREFIX}<bus>) to replay"
                              + (" (empty log)" if ctx.message_count == 0 else ""))
        unknown = set(buses) - set(ctx.buses)
        if unknown:
            raise ReplayError(f"channels: the log has buses {', '.join(ctx.buses)}, not "
                              f"{', '.join(sorted(unknown))}", option="channels")
        play = [b for b in chosen if b in buses]
        if not play:
            raise ReplayError(f"{path}: no bus left to play (log buses {', '.join(ctx.buses)})")
        start_ns, end_ns = ctx.window(start_s, duration_s)
        ids = None if can_ids is None else list(can_ids)

        def items():
            return iter_can_frames(src, buses=play, can_ids=ids, start_ns=start_ns,
                                   end_ns=end_ns)

        def send(bus: str, msg) -> None:
            try:
                buses[bus].send(msg)
                stats.sent[bus] += 1
            except can.CanError as exc:
                stats.errors[f"{bus}: {type(exc).__name__}"] += 1

        _play(ctx, items, send, stats, rate=rate, loop=loop, stop=stop, progress=progress,
              start_ns=start_ns, end_ns=end_ns, desc="CAN")
    return stats


def sample_types() -> dict[str, type]:
    """Schema name (qualified dataclass name, as the recorder writes it) -> codec type."""
    from gateway import codec

    return {f"{t.__module__}.{t.__qualname__}": t for t in codec.TYPES.values()}


_KEY_OK = re.compile(r"^[^/*$?#\s][^*$?#\s]*$")


def play_zenoh(path: str | os.PathLike[str], session, *, rate: float = 1.0, loop: bool = False,
               start_s: float | None = None, duration_s: float | None = None,
               topics: Iterable[str] | None = None, stop: threading.Event | None = None,
               progress: bool = False, wait_s: float = 0.0, warn: Warn = no_warn) -> PlayStats:
    """Republish the recorded samples, health, efforts and alerts of ``path`` on their keys
    (the topic is the key) with their recorded spacing divided by ``rate``.

    Payloads are re-encoded with :mod:`gateway.codec` from the recorded fields, which gives the
    bytes the gateway published. Publishers block rather than drop (a replay is meant to be
    complete); ``wait_s`` > 0 first waits up to that long for every publisher to have a
    matching subscriber. Topics that are not keys (``/can/...``) or not codec types are skipped.
    """
    import zenoh

    from gateway import codec

    stats = PlayStats()
    types_ = sample_types()
    with readable(path, warn) as src:
        ctx = read_context(src)
        pick = _topic_pred(topics)
        eligible = sorted(t for t, s in ctx.topics.items()
                          if s in types_ and _KEY_OK.match(t) and pick(t))
        if not eligible:
            raise ReplayError(f"{path}: no recorded samples or efforts to publish on zenoh"
                              + (" (empty log)" if ctx.message_count == 0 else
                                 " (only raw CAN? play it onto CAN buses instead)"))
        start_ns, end_ns = ctx.window(start_s, duration_s)
        wanted = set(eligible)
        pubs = {}
        try:
            for key in eligible:
                pubs[key] = session.declare_publisher(
                    key, congestion_control=zenoh.CongestionControl.BLOCK)
            if wait_s > 0:
                deadline = time.monotonic() + wait_s
                while unmatched := [k for k, p in pubs.items() if not p.matching_status.matching]:
                    if time.monotonic() >= deadline:
                        warn(f"no subscriber within {wait_s:g} s for {len(unmatched)} of {len(pubs)} "
                             f"keys (first: {unmatched[0]}); publishing anyway")
                        break
                    if stop is not None and stop.is_set():
                        return stats
                    time.sleep(0.01)

            def items():
                for topic, schema, m in iter_file_order(src, lambda t, s: t in wanted,
                                                        start_ns, end_ns):
                    cls = types_[schema]
                    fields = json_record(src, topic, m.data)
                    try:
                        payload = codec.encode(codec.decode(json.dumps(
                            {"type": cls.__name__, "v": codec.VERSION, **fields})))
                    except (ValueError, TypeError) as exc:
                        stats.skipped[f"unencodable: {exc}"[:80]] += 1
                        continue
                    yield topic, m.log_time, payload

            def send(key: str, payload: bytes) -> None:
                codec.put(pubs[key], payload)
                stats.sent[key] += 1

            _play(ctx, items, send, stats, rate=rate, loop=loop, stop=stop, progress=progress,
                  start_ns=start_ns, end_ns=end_ns, desc="zenoh")
        finally:
            for p in pubs.values():
                with contextlib.suppress(Exception):
                    p.undeclare()
    return stats


def parse_can_ids(specs: Iterable[str]) -> list[int]:
    """``["0x200,0x201", "768"]`` -> ids; hex needs ``0x``. ``ValueError`` with the bad item."""
    out = []
    for spec in specs:
        for item in spec.split(","):
            item = item.strip()
            if not item:
                continue
            try:
                value = int(item, 0)
            except ValueError:
                raise ReplayError(f"CAN id {item!r}: not an integer (hex as 0x200)", option="can_ids") from None
            if not 0 <= value < 1 << 29:
                raise ReplayError(f"CAN id {item}: outside 0 .. 0x1FFFFFFF", option="can_ids")
            out.append(value)
    return out


__all__ = ["OfflineReport", "PlayStats", "ReplayError", "parse_can_ids", "play_can", "play_zenoh",
           "replay_offline"]
