"""CAN logs of other tools in and out: every format python-can's ``LogReader``/``Logger`` know.

``candump -L`` (``.log``), Vector ASC (``.asc``) and BLF (``.blf``), PEAK TRC (``.trc``) and
python-can CSV (``.csv``), each also ``.gz`` compressed.

In: :func:`import_log` reads such a file in FILE order (the order the frames were fed to the
session, which the estimator's results depend on) and writes a self-contained session MCAP (the
robot's URDF and DBCs, ``/can/<bus>`` raw frames), so that everything that takes an MCAP log
(replay, analyze, info, Foxglove) takes the imported one; :func:`imported` does it into a
temporary file. A log's channels are mapped to the robot's buses (``--bus BUS=CHANNEL``);
frames of a channel that maps to no bus, timestamps that go backwards, error and remote frames,
and a file that ends early (a truncated .blf) are counted (:class:`ImportStats`), never an
exception. What the frames mean (unknown ids, bad lengths, error frames) is judged downstream by
the drivers, which count every frame they reject.

Out: :func:`export_log` writes frames ``(bus, t_ns, can.Message)`` to a file in the format its
name says.

Times: python-can gives float seconds, which at today's epoch resolve about 0.24 us; every
format but BLF and CSV stores microseconds. Log times are the frame times rounded to the
microsecond, in ns. ASC times are read as absolute (its trigger block's date, in local time,
plus each frame's offset), so a session keeps its date.

Channels as the tools show them: names for candump (``can0``), numbers from 1 for ASC, BLF and
TRC (``1`` is CANalyzer's CAN 1, PCAN-View's bus 1; python-can counts ASC and BLF channels
from 0 and TRC channels from 1: corrected here, both ways). CSV holds no channel: its frames
are channel ``-``, and a CSV export holds one bus.
"""
from __future__ import annotations

import contextlib
import dataclasses
import gzip
import io
import os
import tempfile
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from gateway.errors import GatewayError

FORMATS = {".log": "candump -L", ".asc": "Vector ASC", ".blf": "Vector BLF", ".trc": "PEAK TRC",
           ".csv": "python-can CSV"}
NUMBERED = (".asc", ".blf", ".trc")          # channels are numbers (from 1, as the tools show them)
NO_CHANNEL = "-"                             # a frame without a channel (CSV)
_FROM_ZERO = (".asc", ".blf")                # python-can's numbering of these starts at 0
MCAP_MAGIC = b"\x89MCAP0\r\n"
JUMP_NS = 60 * 10**9                         # a bus silent this long: a clock jump, or logs joined


class CanLogError(GatewayError, ValueError):
    """A CAN log that cannot be imported or exported as asked: one readable line."""


def log_format(path: str | os.PathLike[str]) -> str | None:
    """``.log``, ``.asc``, ``.blf``, ``.trc`` or ``.csv`` (also behind ``.gz``) when ``path``
    is named as such a log and is not an MCAP file; else None."""
    p = Path(path)
    if format_of_name(p) not in FORMATS:
        return None
    with contextlib.suppress(OSError), open(p, "rb") as f:
        if f.read(len(MCAP_MAGIC)) == MCAP_MAGIC:
            return None
    return format_of_name(p)


def is_can_log(path: str | os.PathLike[str]) -> bool:
    return log_format(path) is not None


def channel_label(channel: Any, fmt: str) -> str:
    """A frame's channel as the user names it in ``--bus BUS=CHANNEL``."""
    if channel is None or channel == "":
        return NO_CHANNEL
    if isinstance(channel, int) and fmt in _FROM_ZERO:
        return str(channel + 1)
    return str(channel)


def parse_bus_map(specs: Iterable[str], buses: Sequence[str]) -> dict[str, str]:
    """``["arm0=can0", ...]`` -> ``{bus: channel}``; every bus must be one of ``buses``."""
    out: dict[str, str] = {}
    for spec in specs:
        bus, sep, chan = spec.partition("=")
        bus, chan = bus.strip(), chan.strip()
        if not sep or not bus or not chan:
            raise CanLogError(f"bus map {spec!r}: expected BUS=CHANNEL (e.g. arm0=can0)", option="bus_map")
        if bus not in buses:
            raise CanLogError(f"bus map {spec}: the robot has buses {', '.join(buses)}, not {bus}", option="bus_map")
        if bus in out:
            raise CanLogError(f"bus map {spec}: bus {bus} is mapped twice", option="bus_map")
        if chan in out.values():
            raise CanLogError(f"bus map {spec}: channel {chan} is mapped to two buses", option="bus_map")
        out[bus] = chan
    return out


@dataclasses.dataclass(slots=True)
class ImportStats:
    """What an import read, kept and left out (``report.json``'s ``import``)."""

    source: str
    format: str
    channels: dict[str, str] = dataclasses.field(default_factory=dict)   # channel -> bus
    frames_read: int = 0
    frames_written: int = 0
    by_channel: Counter = dataclasses.field(default_factory=Counter)     # every frame read
    unmapped: Counter = dataclasses.field(default_factory=Counter)       # channel -> frames left out
    backwards: Counter = dataclasses.field(default_factory=Counter)      # bus -> times going back
    jumps: Counter = dataclasses.field(default_factory=Counter)          # bus -> silences > JUMP_NS
    error_frames: int = 0
    remote_frames: int = 0
    fd_frames: int = 0
    fd: bool = False                                                     # the session's buses run FD
    ended_early: str | None = None                                       # why reading stopped early
    bad_lines: int = 0                                                   # candump lines that are no frame
    first_bad_line: str | None = None
    first_ns: int | None = None
    last_ns: int | None = None
    min_ns: int | None = None
    max_ns: int | None = None
    unfed: list = dataclasses.field(default_factory=list)               # robot buses no channel maps to

    @property
    def span_s(self) -> float:
        """Seconds from the earliest to the latest frame written."""
        return 0.0 if self.min_ns is None else (self.max_ns - self.min_ns) / 1e9

    def read(self, chan: str, msg) -> None:
        """Count a frame read from the file on channel ``chan``."""
        self.frames_read += 1
        self.by_channel[chan] += 1
        self.error_frames += msg.is_error_frame
        self.remote_frames += msg.is_remote_frame
        self.fd_frames += msg.is_fd

    def timed(self, key: str, t: int, prev: dict[str, int]) -> None:
        """Count the time ``t`` of a frame of ``key`` (a bus, or a channel): going back from
        ``prev[key]`` (the one before, updated), the earliest and latest."""
        before = prev.get(key, t)
        if t < before:
            self.backwards[key] += 1
        elif t - before > JUMP_NS:
            self.jumps[key] += 1
        prev[key] = t
        self.min_ns = t if self.min_ns is None or t < self.min_ns else self.min_ns
        self.max_ns = t if self.max_ns is None or t > self.max_ns else self.max_ns

    def found(self) -> str:
        """The channels the file holds, with their frame counts."""
        if not self.by_channel:
            return "none"
        return ", ".join(f"{c} ({n} frames)" for c, n in sorted(self.by_channel.items()))

    def warnings(self) -> list[str]:
        """One line per thing the user should know about the input."""
        out = []
        if self.unfed:
            out.append(f"no channel maps to the robot's bus {', '.join(self.unfed)}: its devices get no frame and "
                       "no effort can be good (map it: " + " ".join(f"{b}=CHANNEL" for b in self.unfed)
                       + f"; channels found: {self.found()})")
        if self.unmapped:
            out.append("left out (channel maps to no bus): " + ", ".join(
                f"channel {c} {n} frames" for c, n in sorted(self.unmapped.items())))
        if self.backwards:
            out.append("timestamps going backwards (kept in file order): " + ", ".join(
                f"{b} {n}" for b, n in sorted(self.backwards.items())))
        if self.jumps:
            out.append(f"times jumping ahead by more than {JUMP_NS // 10**9} s (a clock set, or logs joined): "
                       + ", ".join(f"{b} {n}" for b, n in sorted(self.jumps.items())))
        if self.error_frames or self.remote_frames:
            out.append(f"{self.error_frames} error frames, {self.remote_frames} remote frames "
                       "(recorded; the drivers reject and count them)")
        if self.fd_frames and not self.fd:
            out.append(f"{self.fd_frames} CAN FD frames on buses imported as classic CAN (the drivers count "
                       "them as fd_on_classic): import them as CAN FD if the buses run FD")
        if self.bad_lines:
            out.append(f"{self.bad_lines} lines that are no frame, skipped (first: {self.first_bad_line})")
        if self.ended_early:
            out.append(f"the file ends early ({self.ended_early}); the {self.frames_read} frames "
                       "before it were read")
        return out

    def to_json(self) -> dict[str, Any]:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        for k in ("by_channel", "unmapped", "backwards", "jumps"):
            d[k] = dict(sorted(d[k].items()))
        return d


class _Counted(io.RawIOBase):
    """A file's bytes, counting those read (how far a read has come: its progress)."""

    def __init__(self, path: Path):
        self.f, self.n = open(path, "rb"), 0

    def readable(self) -> bool:
        return True

    def readinto(self, b) -> int:
        k = self.f.readinto(b) or 0
        self.n += k
        return k

    def close(self) -> None:
        self.f.close()
        super().close()


_READERS = {".asc": ("ASCReader", {"relative_timestamp": False}), ".blf": ("BLFReader", {}),
            ".trc": ("TRCReader", {}), ".csv": ("CSVReader", {})}
PROGRESS_EVERY = 8192                         # frames between two progress calls


def _open(path: Path, fmt: str):
    """``(stream for python-can's reader, byte counter)``: binary for BLF, text for the rest,
    through gzip for ``.gz``."""
    raw = _Counted(path)
    f = io.BufferedReader(raw, 1 << 16)
    if path.suffix.lower() == ".gz":
        f = gzip.GzipFile(fileobj=f, mode="rb")
    if fmt != ".blf":
        f = io.TextIOWrapper(f, encoding="utf-8", errors="replace")
    return f, raw


def read_log(path: str | os.PathLike[str], stats: ImportStats | None = None,
             progress: Callable[[int], None] | None = None) -> Iterator[tuple[str, int, Any]]:
    """``(channel label, t_ns, can.Message)`` of a CAN log in file order. A file that stops
    making sense part way (truncated, garbage) ends the iteration: ``stats.ended_early`` says
    why; nothing read before is lost. A file that yields nothing at all raises
    :class:`CanLogError`. ``progress(bytes read of the file)`` is called now and then."""

    path = Path(path)
    fmt = log_format(path)
    if fmt is None:
        raise CanLogError(f"{path}: not a CAN log python-can reads (by name: "
                          f"{', '.join(FORMATS)}, or .gz of them)")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    f, raw = _open(path, fmt)
    with f:
        frames = _read_candump(path, f, stats) if fmt == ".log" else _read_with(path, fmt, f, stats)
        for n, item in enumerate(frames, 1):
            if progress is not None and n % PROGRESS_EVERY == 0:
                progress(raw.n)
            yield item
    if progress is not None:
        progress(raw.n)


def _read_with(path: Path, fmt: str, f, stats: ImportStats | None) -> Iterator[tuple[str, int, Any]]:
    """:func:`read_log` by python-can's reader of ``fmt``: it stops at the first thing it cannot
    read (``stats.ended_early``)."""
    import can

    name, kwargs = _READERS[fmt]
    n = 0
    try:
        reader = getattr(can, name)(f, **kwargs)
        it = iter(reader)
    except Exception as exc:  # noqa: BLE001 - any reader's complaint about its header
        raise CanLogError(f"{path}: not a readable {FORMATS[fmt]} file ({exc})") from None
    while True:
        try:
            msg = next(it)
        except StopIteration:
            break
        except Exception as exc:  # noqa: BLE001 - a bad line or a cut record: stop there
            why = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
            if n == 0:
                raise CanLogError(f"{path}: not a readable {FORMATS[fmt]} file ({why})") from None
            if stats is not None:
                stats.ended_early = f"after frame {n}: {why}"
            break
        n += 1
        yield channel_label(msg.channel, fmt), round(msg.timestamp * 1e6) * 1000, msg
    # python-can's BLF reader stops quietly at a cut object: the header knows the size
    declared = getattr(reader, "file_size", 0) if fmt == ".blf" else 0
    if declared and path.suffix.lower() != ".gz" and path.stat().st_size < declared and stats is not None:
        stats.ended_early = (f"truncated: {path.stat().st_size} of the {declared} bytes its header "
                             f"announces, after frame {n}")


class _Lines:
    """A text file's lines for python-can's candump reader: counts them, and turns an error of
    the file itself (a cut .gz) into its end, kept in :attr:`error`."""

    def __init__(self, f):
        self.f, self.n, self.last, self.error = f, 0, "", None

    def __iter__(self):
        return self

    def __next__(self) -> str:
        try:
            line = next(self.f)
        except StopIteration:
            raise
        except Exception as exc:  # noqa: BLE001 - EOFError, zlib.error, BadGzipFile...
            self.error = f"{type(exc).__name__}: {exc}"
            raise StopIteration from None
        self.n += 1
        self.last = line
        return line

    def close(self) -> None:
        """python-can's reader closes its file: the caller does."""


def _read_candump(path: Path, f, stats: ImportStats | None) -> Iterator[tuple[str, int, Any]]:
    """:func:`read_log` of a candump log: a line that is no frame is skipped and counted
    (``stats.bad_lines``; python-can's reader stops at the first), the rest is read."""
    import can

    n = 0
    lines = _Lines(f)
    while True:
        try:
            for msg in can.CanutilsLogReader(lines):
                n += 1
                if msg.channel is None and msg.is_error_frame:     # python-can leaves it out
                    parts = lines.last.split()
                    msg.channel = parts[1] if len(parts) > 1 else None
                yield channel_label(msg.channel, ".log"), round(msg.timestamp * 1e6) * 1000, msg
            break
        except Exception as exc:  # noqa: BLE001 - a line that is no frame: skip it, go on
            if stats is not None:
                stats.bad_lines += 1
                if stats.first_bad_line is None:
                    stats.first_bad_line = f"line {lines.n}: {lines.last.strip()[:80]!r} ({type(exc).__name__})"
    if lines.error is not None:
        if n == 0:
            raise CanLogError(f"{path}: not a readable {FORMATS['.log']} file ({lines.error})")
        if stats is not None:
            stats.ended_early = f"after frame {n}: {lines.error}"
    elif n == 0 and lines.n and stats is not None and stats.bad_lines == lines.n:
        raise CanLogError(f"{path}: not a {FORMATS['.log']} file ({stats.first_bad_line})")


def import_frames(path: str | os.PathLike[str], buses: Sequence[str], bus_map: Mapping[str, str],
                  stats: ImportStats, progress: Callable[[int], None] | None = None
                  ) -> Iterator[tuple[str, int, Any]]:
    """``(bus, t_ns, can.Message)`` of the frames of ``path`` whose channel maps to a bus, in
    file order, counting the rest in ``stats``. No ``bus_map``: channels named as buses are
    those buses."""
    chan_to_bus = {c: b for b, c in bus_map.items()} if bus_map else {b: b for b in buses}
    stats.channels = dict(chan_to_bus)
    last: dict[str, int] = {}
    for chan, t, msg in read_log(path, stats, progress):
        stats.read(chan, msg)
        bus = chan_to_bus.get(chan)
        if bus is None:
            stats.unmapped[chan] += 1
            continue
        if t < 0:                                 # before 1970: a clock that was never set
            stats.unmapped[f"{chan} (negative time)"] += 1
            continue
        stats.timed(bus, t, last)
        msg.timestamp = t / 1e9
        stats.frames_written += 1
        stats.first_ns = t if stats.first_ns is None else stats.first_ns
        stats.last_ns = t
        yield bus, t, msg


def _check_mapping(path, stats: ImportStats, buses: Sequence[str], bus_map: Mapping[str, str]) -> None:
    """After a read: the errors a wrong or missing mapping gives, each listing the channels."""
    hint = " ".join(f"{b}=CHANNEL" for b in buses)
    if stats.frames_read == 0:
        raise CanLogError(f"{path}: no CAN frames in the file"
                          + (f" ({stats.ended_early})" if stats.ended_early else ""))
    absent = [f"{b}={c}" for b, c in bus_map.items() if c not in stats.by_channel]
    if absent:
        raise CanLogError(f"{path}: bus map {', '.join(absent)}: no such channel in the file; "
                          f"channels found: {stats.found()}", option="bus_map")
    if stats.frames_written == 0:
        raise CanLogError(f"{path}: no channel maps to a bus of the robot (buses "
                          f"{', '.join(buses)}); channels found: {stats.found()}; map them with {hint}",
                          option="bus_map")
    # a bus of the robot with no channel: legitimate (a CSV log holds one bus), but its devices get
    # nothing and no effort can be good, so the user is told which and how to map it
    stats.unfed = [b for b in buses if b not in set(stats.channels.values())]


def import_log(path: str | os.PathLike[str], out: str | os.PathLike[str], robot, *,
               bus_map: Mapping[str, str] | None = None, fd: bool = False, overwrite: bool = False,
               source_name: str | None = None, progress: bool = False) -> ImportStats:
    """Write the frames of CAN log ``path`` to a session MCAP ``out`` for ``robot`` (a
    :class:`robot_description.Robot`): its URDF and DBCs attached, the frames on ``/can/<bus>``
    in file order at their own times. Returns what was read; raises :class:`CanLogError` (and
    leaves no output) when nothing maps to a bus or a ``--bus`` channel is not in the file."""
    from drivers.wire import WireMap
    from gateway.log.recorder import Recorder
    from gateway.log.context import session_context

    path, out = Path(path), Path(out)
    buses = list(WireMap.from_robot(robot).buses)
    bus_map = dict(bus_map or {})
    fmt = log_format(path) or path.suffix
    stats = ImportStats(source=str(source_name or path), format=FORMATS.get(fmt, fmt), fd=fd)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists")
    ok = False
    bar = _bar(path) if progress else None
    try:
        with Recorder(out, overwrite=overwrite) as rec:
            rec.add_session_context(**session_context(robot, fd=fd, extra={
                "mode": "import", "imported_from": Path(source_name or path).name,
                "import_format": stats.format}))
            moved = (lambda n: bar.update(n - bar.n)) if bar is not None else None
            for i, (bus, t, msg) in enumerate(import_frames(path, buses, bus_map, stats, moved)):
                rec.record_can(bus, msg, t)
                if i % 4096 == 4095 and rec.queue_depth > rec.queue_size // 2:
                    rec.flush()                     # wait for the disk rather than drop
            _check_mapping(path, stats, buses, bus_map)
        ok = rec.stats.dropped == 0
        if not ok:
            raise CanLogError(f"{out}: {rec.stats.dropped} frames not written ({rec.error or 'recorder'})")
    finally:
        if bar is not None:
            bar.close()
        if not ok:
            with contextlib.suppress(Exception):
                for p in rec.paths:
                    p.unlink(missing_ok=True)
            out.unlink(missing_ok=True)
    return stats


def _bar(path: Path):
    """A progress bar over the file's bytes (compressed bytes of a .gz)."""
    from tqdm import tqdm

    return tqdm(total=path.stat().st_size, unit="B", unit_scale=True, desc=f"import {path.name}", leave=False)


@contextlib.contextmanager
def imported(path: str | os.PathLike[str], robot, *, bus_map: Mapping[str, str] | None = None,
             fd: bool = False, progress: bool = False) -> Iterator[tuple[Path, ImportStats]]:
    """:func:`import_log` into a temporary MCAP (named after the log), removed afterwards."""
    with tempfile.TemporaryDirectory(prefix="bsc-import-") as tmp:
        out = Path(tmp) / (Path(path).name + ".mcap")
        stats = import_log(path, out, robot, bus_map=bus_map, fd=fd, progress=progress)
        yield out, stats


def robot_for_log(robot: str | None, path) -> Any:
    """The robot a CAN log is decoded with: ``--robot`` is required (a CAN log names none)."""
    import robot_description

    if robot is None:
        raise CanLogError(f"{path}: a CAN log names no robot: name it, a built-in name or a URDF file "
                          f"(built in: {', '.join(robot_description.BUILTIN)})", option="robot")
    return robot_description.load(robot)


# ----------------------------------------------------------------------------- export

def export_channels(fmt: str, buses: Sequence[str], bus_map: Mapping[str, str]) -> dict[str, str]:
    """bus -> channel label to write: ``bus_map`` when given (only those buses), else the bus
    names (candump), or 1, 2, ... in the robot's bus order (ASC, BLF, TRC)."""
    if bus_map:
        chans = dict(bus_map)
    elif fmt in NUMBERED:
        chans = {b: str(i + 1) for i, b in enumerate(buses)}
    else:
        chans = {b: b for b in buses}
    if fmt in NUMBERED:
        bad = [f"{b}={c}" for b, c in chans.items() if not (c.isdigit() and int(c) >= 1)]
        if bad:
            raise CanLogError(f"bus map {', '.join(bad)}: {FORMATS[fmt]} channels are numbers from 1",
                              option="bus_map")
    if fmt == ".csv" and len(chans) != 1:
        raise CanLogError(f"a CSV log holds no channel, so one bus: choose it, BUS=- "
                          f"(buses {', '.join(chans)})", option="bus_map")
    return chans


def _writer_channel(label: str, fmt: str):
    if fmt in NUMBERED:
        return int(label) - 1              # every python-can writer counts from 0
    return None if fmt == ".csv" else label


@dataclasses.dataclass(slots=True)
class ExportStats:
    written: Counter = dataclasses.field(default_factory=Counter)     # bus -> frames
    skipped: Counter = dataclasses.field(default_factory=Counter)     # reason -> frames


def export_log(out: str | os.PathLike[str], frames: Iterable[tuple[str, int, Any]],
               channels: Mapping[str, str], *, overwrite: bool = False) -> ExportStats:
    """Write ``(bus, t_ns, can.Message)`` of the buses in ``channels`` (bus -> channel label)
    to ``out`` in the format its name says, in the order given. Frames the format cannot hold
    (TRC: error and remote frames) are counted in ``skipped``."""
    import can

    out = Path(out)
    fmt = format_of_name(out)
    if fmt not in FORMATS:
        raise CanLogError(f"{out}: the name says no CAN log format (use {', '.join(FORMATS)}, "
                          "or .gz of them)")
    if fmt == ".blf" and out.suffix.lower() == ".gz":
        raise CanLogError(f"{out}: python-can writes no .blf.gz (BLF compresses itself): write .blf")
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists")
    stats = ExportStats()
    tmp = out.with_name(f".part-{out.name}")      # same suffixes: python-can picks the format by them
    wchan = {b: _writer_channel(c, fmt) for b, c in channels.items()}
    try:
        writer = can.Logger(tmp)
        try:
            first = True
            for bus, t_ns, msg in frames:
                ch = wchan.get(bus, False)
                if ch is False:
                    stats.skipped[f"bus {bus} not exported"] += 1
                    continue
                if fmt == ".trc" and (msg.is_error_frame or msg.is_remote_frame or msg.is_fd):
                    stats.skipped["error, remote and FD frames (TRC holds none)"] += 1
                    continue
                if first:
                    _anchor(writer, fmt, t_ns)
                    first = False
                elif fmt == ".log":
                    writer.last_timestamp = None      # python-can would clamp a time going back
                writer.on_message_received(can.Message(
                    timestamp=t_ns / 1e9, arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
                    is_remote_frame=msg.is_remote_frame, is_error_frame=msg.is_error_frame, is_fd=msg.is_fd,
                    bitrate_switch=msg.bitrate_switch, error_state_indicator=msg.error_state_indicator,
                    is_rx=msg.is_rx, dlc=msg.dlc, data=msg.data, channel=ch, check=False))
                stats.written[bus] += 1
        finally:
            writer.stop()
        if not stats.written:
            raise CanLogError(f"{out}: no CAN frames to write (none of these buses, or none in the window); "
                              "nothing written")
        os.replace(tmp, out)
    finally:
        Path(tmp).unlink(missing_ok=True)
    return stats


def _anchor(writer, fmt: str, t0_ns: int) -> None:
    """Start a writer's relative clock on a whole second, one second before the first frame.

    ASC, BLF and TRC store each frame's time from a start their header gives to the ms or less;
    python-can starts it at the first frame and writes a frame before it (out of order) at the
    start. A whole second, with a second's margin, makes header + offset give every time back
    to the microsecond, and a frame somewhat out of order keeps its time."""
    start = float(max(t0_ns // 1_000_000_000 - 1, 0))
    if fmt == ".asc":
        writer.log_event("bsc export", timestamp=start)
    elif fmt == ".blf":
        writer.start_timestamp = start
    elif fmt == ".trc":
        writer.first_timestamp = start
        writer.write_header(start)           # else the header says the first frame's time


def format_of_name(p: str | os.PathLike[str]) -> str:
    """The format suffix of a file name (``.asc`` of ``x.asc.gz``), lower case."""
    p = Path(p)
    s = [x.lower() for x in p.suffixes[-2:]]
    if s and s[-1] == ".gz":
        s = s[:-1]
    return s[-1] if s else ""


def warn_lines(stats: ImportStats, warn: Callable[[str], None]) -> None:
    for line in stats.warnings():
        warn(line)
