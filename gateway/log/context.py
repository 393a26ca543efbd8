"""What a session log says about itself, written and read back: the robot (its URDF), the
DBCs, the zenoh key scheme, the scenario, and the ``bsc.session`` metadata
(:func:`session_context`, given to the recorder), then :func:`read_context` (a
:class:`LogContext` from the summary, the metadata and the attachments of a complete log) and
:func:`resolve_robot` (the robot a log is decoded with).

The summary section is parsed with ``struct`` (:func:`read_summary`): the library builds an
object per record and a dict per chunk index, about 40 ms for an 8 s log.
"""
from __future__ import annotations

import dataclasses
import io
import os
import re
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

from gateway.log.errors import LogError, McapFileError
from gateway.log.names import CAN_SCHEMA_NAME, CAN_TOPIC_PREFIX, SESSION_METADATA, URDF_ATTACHMENT
from gateway.log.scan import PARSE_ERRORS, check_footer, scan_header


class _Chunk(NamedTuple):
    start_ns: int
    end_ns: int
    offset: int
    channels: frozenset


class Summary(NamedTuple):
    """What a log's summary section says, parsed with ``struct`` (the library builds an object
    per record and a dict per chunk index: about 40 ms for an 8 s log)."""

    schemas: dict            # schema id -> name
    channels: dict           # channel id -> (topic, schema id)
    chunks: list             # _Chunk per chunk
    message_count: int
    start_ns: int | None
    end_ns: int | None
    metadata: list           # (offset, length, name) of every metadata record
    attachments: list        # (offset, length, name) of every attachment record


def read_summary(path: Path) -> Summary | None:
    """The summary of a complete log (None: it has none, or it is not readable)."""
    u8, u4, u2 = struct.Struct("<Q"), struct.Struct("<I"), struct.Struct("<H")
    with open(path, "rb") as f:
        f.seek(0, 2)
        size = f.tell()
        if size < 8 + 29 + 8:
            return None
        f.seek(size - 8 - 29)
        foot = f.read(29)
        if foot[0] != 0x02:
            return None
        start, offset_start = struct.unpack_from("<QQ", foot, 9)
        if start == 0 or start >= size:
            return None
        f.seek(start)
        data = f.read((offset_start or size - 8 - 29) - start)

    def string(p):
        (n,) = u4.unpack_from(data, p)
        return data[p + 4:p + 4 + n].decode("utf-8", "replace"), p + 4 + n

    schemas, channels, chunks, meta, atts = {}, {}, [], [], []
    count, t0s, t1s = 0, None, None
    p = 0
    while p + 9 <= len(data):
        op = data[p]
        (n,) = u8.unpack_from(data, p + 1)
        b, p = p + 9, p + 9 + n
        if p > len(data):
            return None
        if op == 0x03:                                       # Schema
            (sid,) = u2.unpack_from(data, b)
            schemas[sid], _ = string(b + 2)
        elif op == 0x04:                                     # Channel
            cid, sid = struct.unpack_from("<HH", data, b)
            topic, _ = string(b + 4)
            channels[cid] = (topic, sid)
        elif op == 0x08:                                     # ChunkIndex
            t0, t1, off, _ = struct.unpack_from("<QQQQ", data, b)
            (m,) = u4.unpack_from(data, b + 32)
            chans = frozenset(u2.unpack_from(data, b + 36 + 10 * k)[0] for k in range(m // 10))
            chunks.append(_Chunk(t0, t1, off, chans))
        elif op == 0x0B:                                     # Statistics
            (count,) = u8.unpack_from(data, b)
            t0s, t1s = struct.unpack_from("<QQ", data, b + 8 + 2 + 4 * 4)
        elif op == 0x0D:                                     # MetadataIndex
            off, ln = struct.unpack_from("<QQ", data, b)
            meta.append((off, ln, string(b + 16)[0]))
        elif op == 0x0A:                                     # AttachmentIndex
            off, ln = struct.unpack_from("<QQ", data, b)
            atts.append((off, ln, string(b + 40)[0]))
    if not count:
        t0s = t1s = None
    return Summary(schemas, channels, chunks, count, t0s, t1s, meta, atts)


@dataclasses.dataclass(frozen=True, slots=True)
class LogContext:
    """What a complete log says about itself (from its summary, metadata and attachments)."""

    path: Path
    metadata: dict[str, dict[str, str]]
    attachments: dict[str, tuple[str, bytes]]      # name -> (media type, data)
    topics: dict[str, str]                         # topic -> schema name
    message_count: int
    start_ns: int | None
    end_ns: int | None

    @property
    def buses(self) -> list[str]:
        """Logical CAN buses with a raw channel (``/can/<bus>``), in channel order."""
        return [t[len(CAN_TOPIC_PREFIX):] for t, s in self.topics.items()
                if t.startswith(CAN_TOPIC_PREFIX) and s == CAN_SCHEMA_NAME]

    @property
    def session(self) -> dict[str, str]:
        return self.metadata.get(SESSION_METADATA, {})

    @property
    def urdf_text(self) -> str | None:
        att = self.attachments.get(URDF_ATTACHMENT)
        return att[1].decode("utf-8", "replace") if att else None

    @property
    def robot_name(self) -> str | None:
        """``bsc.session`` ``robot``, else the URDF's ``<robot name=...>``."""
        name = self.session.get("robot")
        if name:
            return name
        m = re.search(r"<robot\b[^>]*\bname\s*=\s*[\"']([^\"']+)[\"']", self.urdf_text or "")
        return m.group(1) if m else None

    @property
    def fd(self) -> bool:
        return self.session.get("fd", "false").lower() == "true"

    def window(self, start_s: float | None, duration_s: float | None) -> tuple[int | None, int | None]:
        """``[start_ns, end_ns)`` from offsets relative to the log's first message."""
        if start_s is not None and start_s < 0:
            raise LogError(f"start {start_s} s: must be >= 0", option="start")
        if duration_s is not None and duration_s <= 0:
            raise LogError(f"duration {duration_s} s: must be positive", option="duration")
        if self.start_ns is None:
            return None, None
        start = self.start_ns + round((start_s or 0.0) * 1e9) if start_s is not None else None
        end = None
        if duration_s is not None:
            end = (start if start is not None else self.start_ns) + round(duration_s * 1e9)
        return start, end


def read_context(path: str | os.PathLike[str]) -> LogContext:
    """The summary, metadata and attachments of a complete log (see :func:`readable`)."""
    from mcap.reader import SeekingReader
    from mcap.records import Attachment, Metadata

    path = Path(path)
    scan_header(path)
    ok, why = check_footer(path)
    if not ok:
        raise McapFileError(f"{path}: file is truncated ({why}); run `bsc recover {path}` first")

    try:
        summary = read_summary(path)
        if summary is None:                   # no summary section: the library walks the records
            with open(path, "rb") as f:
                reader = SeekingReader(f, validate_crcs=True)
                metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
                attachments = {a.name: (a.media_type, a.data) for a in reader.iter_attachments()}
            return LogContext(path, metadata, attachments, {}, 0, None, None)
        metadata, attachments = {}, {}
        with open(path, "rb") as f:           # the few records the summary points at
            for off, ln, _ in summary.metadata:
                rec = _record_at(f, off, ln, Metadata)
                metadata[rec.name] = dict(rec.metadata)
            for off, ln, _ in summary.attachments:
                rec = _record_at(f, off, ln, Attachment)
                attachments[rec.name] = (rec.media_type, rec.data)
    except (PARSE_ERRORS + (struct.error,)) as exc:
        raise McapFileError(f"{path}: corrupt summary ({exc}); `bsc recover {path}` "
                            "rebuilds it") from exc
    topics: dict[str, str] = {}
    for topic, sid in summary.channels.values():
        topics.setdefault(topic, summary.schemas.get(sid, ""))
    return LogContext(path, metadata, attachments, topics, summary.message_count, summary.start_ns,
                      summary.end_ns)


def _record_at(f, offset: int, length: int, kind):
    """The record of type ``kind`` (an ``mcap.records`` class) at ``offset`` of ``length`` bytes."""
    from mcap.data_stream import ReadDataStream

    f.seek(offset)
    head = f.read(9)
    if len(head) < 9:
        raise ValueError(f"no record at offset {offset}")
    (n,) = struct.unpack_from("<Q", head, 1)
    body = f.read(n)
    if len(body) < n or n + 9 != length:
        raise ValueError(f"record at offset {offset} is cut short")
    return kind.read(ReadDataStream(io.BytesIO(body)))


def resolve_robot(ctx: LogContext, robot: str | None = None):
    """The robot to decode with: ``robot`` (name or URDF path) if given, else the log's
    ``robot.urdf`` attachment, else the built-in robot named in its metadata."""
    import robot_description

    if robot is not None:
        return robot_description.load(robot)
    name = ctx.robot_name
    if ctx.urdf_text is not None:
        return robot_description.from_urdf_text(ctx.urdf_text, name=name or "robot")
    if name:
        return robot_description.load(name)
    raise LogError(f"{ctx.path}: the log names no robot (no {URDF_ATTACHMENT} attachment, "
                      f"no robot in {SESSION_METADATA}): name the robot (a built-in name or a URDF file)",
                      option="robot")


def key_scheme(wire_map) -> dict[str, str]:
    """Every zenoh key this robot's gateway publishes under, by name (the ``zenoh.keys``
    metadata of a session)."""
    from gateway import keys

    robot = wire_map.robot
    out = {"everything": keys.everything(robot), "sensors": keys.sensors(robot),
           "observed_commands": keys.observed_commands(robot), "health": keys.health(robot),
           "efforts": keys.efforts(robot), "imu": keys.imu(robot),
           "thruster_command": keys.thruster_command(robot), "valve_command": keys.valve_command(robot),
           "thruster_effort": keys.thruster_effort(robot), "valve_wrenches": keys.valve_wrenches(robot),
           "alerts": keys.alerts(robot),
           "health/device/imu": keys.device_health(robot, "imu"),
           "health/device/thrusters": keys.device_health(robot, "thrusters")}
    for name, spec in wire_map.buses.items():
        out[f"health/bus/{name}"] = keys.bus_health(robot, name)
        if spec.arm is None:
            continue
        arm = spec.arm
        out[f"wrench/{arm}"] = keys.wrench(robot, arm)
        out[f"joint_efforts/{arm}"] = keys.joint_efforts(robot, arm)
        out[f"health/device/{arm}"] = keys.device_health(robot, arm)
        for j in spec.joints:
            dev = f"{arm}/{j}"
            out[f"joint/{dev}"] = keys.joint(robot, dev)
            out[f"torque_command/{dev}"] = keys.torque_command(robot, dev)
            out[f"health/device/{dev}"] = keys.device_health(robot, dev)
    return out


def session_context(robot, *, fd: bool = False, scenario_text: str | None = None,
                    dbc_files: Mapping[str, bytes | str] | None = None,
                    extra: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Keyword arguments for :meth:`Recorder.add_session_context` that make a log of this robot
    replayable on its own: URDF, the DBCs, the key scheme, software version, robot name, fd."""
    from drivers.wire import DBC_FILES, WireMap
    from gateway import __version__

    wm = WireMap.from_robot(robot)
    dbcs = dict(dbc_files) if dbc_files is not None else {
        p.name: p.read_text() for p in DBC_FILES.values()}
    session = {"robot": robot.name, "fd": str(bool(fd)).lower(),
               "buses": ",".join(wm.buses)}
    session.update(extra or {})
    return dict(urdf_text=robot.urdf, dbc_files=dbcs, scenario_text=scenario_text,
                zenoh_keys=key_scheme(wm), software=f"bsc {__version__}", extra=session)
