"""Foxglove's well-known message types for what bsc records, so that Foxglove's own panels show it
without configuration (its Log panel takes ``foxglove.Log`` messages on any topic).

An alert is recorded twice by ``bsc record``: as itself on its zenoh key (``gateway.efforts.Alert``,
every field, what bsc reads back) and as a ``foxglove.Log`` line on :data:`ALERT_LOG_TOPIC`. The
schema below is written for bsc from Foxglove's documented message definition; the Foxglove tier
of CI validates these messages against the published schema (npm ``@foxglove/schemas``).
"""
from __future__ import annotations

import math
from typing import Any

ALERT_LOG_TOPIC = "/foxglove/alerts"
LOG_SCHEMA_NAME = "foxglove.Log"

# foxglove.LogLevel: 0 unknown, 1 debug, 2 info, 3 warning, 4 error, 5 fatal
_LEVEL = {"info": 2, "warning": 3, "critical": 4}

LOG_SCHEMA: dict[str, Any] = {
    "title": LOG_SCHEMA_NAME,
    "description": "A log line (Foxglove's Log panel): a bsc alert raised or cleared",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object", "title": "time", "description": "when the alert changed state (sensor time)",
                      "properties": {"sec": {"type": "integer", "minimum": 0},
                                     "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}},
        # foxglove.LogLevel as published: an enum of integer consts
        "level": {"title": "foxglove.LogLevel",
                  "description": "2 info (a cleared alert), 3 warning, 4 error (critical)",
                  "oneOf": [{"title": t, "const": i} for i, t in
                            enumerate(("UNKNOWN", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL"))]},
        "message": {"type": "string"},
        "name": {"type": "string", "description": "bsc/<robot>/<kind>/<target> [<rule>]"},
        "file": {"type": "string"},
        "line": {"type": "integer", "minimum": 0},
    },
    "required": ["timestamp", "level", "message", "name", "file", "line"],
}


def alert_log(alert) -> dict[str, Any]:
    """The ``foxglove.Log`` message of a :class:`gateway.efforts.Alert`: a raised alert at its
    severity's level, a cleared one at info."""
    sec, nsec = divmod(max(0, int(alert.t_ns)), 1_000_000_000)
    level = _LEVEL.get(alert.severity, 0) if alert.state == "raised" else _LEVEL["info"]
    return {"timestamp": {"sec": sec, "nsec": nsec}, "level": level,
            "message": f"{alert.state} {alert.severity}: {alert.message}",
            "name": f"bsc/{alert.robot}/{alert.kind}/{alert.target} [{alert.rule}]", "file": "", "line": 0}


# -- the robot in Foxglove's 3D panel ---------------------------------------------------------
# Every recorded session carries the robot's frame tree over time on TF_TOPIC and its URDF (with
# <visual> geometry) on ROBOT_DESCRIPTION_TOPIC, the topic the 3D panel's URDF layer reads
# (``message.data``, any schema): with both, the panel draws the robot moving.
TF_TOPIC = "/tf"
FRAME_TRANSFORMS_SCHEMA_NAME = "foxglove.FrameTransforms"
ROBOT_DESCRIPTION_TOPIC = "/robot_description"
ROBOT_DESCRIPTION_SCHEMA_NAME = "bsc.RobotDescription"
WORLD_FRAME = "world"
TF_PERIOD_NS = 20_000_000            # 50 Hz: smooth in the 3D panel, 0.2 % of a session's messages
# Quaternion components are written to 1e-9 (a nanoradian, far below the 20-bit encoders' 6e-6
# rad): all 17 digits of a double made the transforms 14 % larger in a compressed log.
DIGITS = 9
SMALL_BATCH = 16                     # sample rows taken one by one up to this many, with numpy above

_TIME_SCHEMA: dict[str, Any] = {
    "type": "object", "title": "time", "description": "the log time the transform holds at",
    "properties": {"sec": {"type": "integer", "minimum": 0},
                   "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}}

# Foxglove's published foxglove.FrameTransform (npm @foxglove/schemas, jsonschema.js), field for
# field; the Foxglove tier of CI checks that it is the published one but for the descriptions.
FRAME_TRANSFORM_SCHEMA: dict[str, Any] = {
    "title": "foxglove.FrameTransform",
    "description": "The child frame's pose in the parent frame",
    "type": "object",
    "properties": {
        "timestamp": _TIME_SCHEMA,
        "parent_frame_id": {"type": "string", "description": "the parent link (or world)"},
        "child_frame_id": {"type": "string", "description": "the child link, a URDF link name"},
        "translation": {"title": "foxglove.Vector3", "type": "object",
                        "description": "the child frame's origin in the parent frame, m",
                        "properties": {"x": {"type": "number"}, "y": {"type": "number"},
                                       "z": {"type": "number"}},
                        "required": ["x", "y", "z"]},
        "rotation": {"title": "foxglove.Quaternion", "type": "object",
                     "description": "the child frame's orientation in the parent frame",
                     "properties": {"x": {"type": "number"}, "y": {"type": "number"},
                                    "z": {"type": "number"}, "w": {"type": "number"}},
                     "required": ["x", "y", "z", "w"]},
    },
    "required": ["timestamp", "parent_frame_id", "child_frame_id", "translation", "rotation"],
}

FRAME_TRANSFORMS_SCHEMA: dict[str, Any] = {
    "title": FRAME_TRANSFORMS_SCHEMA_NAME,
    "description": "The robot's frame tree at one time: world -> spacecraft (IMU attitude) and every "
                   "URDF joint, parent link -> child link (joint angles from the encoders)",
    "type": "object",
    "properties": {"transforms": {"type": "array", "items": FRAME_TRANSFORM_SCHEMA}},
    "required": ["transforms"],
}

ROBOT_DESCRIPTION_SCHEMA: dict[str, Any] = {
    "title": ROBOT_DESCRIPTION_SCHEMA_NAME,
    "description": "The robot's URDF, for Foxglove's 3D panel (its URDF layer reads the data field "
                   "of /robot_description)",
    "type": "object",
    "properties": {"data": {"type": "string", "description": "URDF (XML) text"},
                   "robot": {"type": "string", "description": "the robot's name"}},
    "required": ["data", "robot"],
}


def _qmul(a: tuple, b: tuple) -> tuple:
    """Hamilton product of quaternions (w, x, y, z)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)


def _q_rpy(r: float, p: float, y: float) -> tuple:
    """(w, x, y, z) of URDF's fixed-axis roll, pitch, yaw: R = Rz(y) Ry(p) Rx(r)."""
    return _qmul(_qmul((math.cos(y / 2), 0.0, 0.0, math.sin(y / 2)), (math.cos(p / 2), 0.0, math.sin(p / 2), 0.0)),
                 (math.cos(r / 2), math.sin(r / 2), 0.0, 0.0))


def _q_matrix(R) -> tuple:
    """(w, x, y, z), w >= 0, of a rotation matrix (Shepperd's method: the largest pivot)."""
    m = [[float(R[i][j]) for j in range(3)] for i in range(3)]
    tr = m[0][0] + m[1][1] + m[2][2]
    k = max(range(4), key=lambda i: (tr, m[0][0], m[1][1], m[2][2])[i])
    if k == 0:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        q = (s / 4, (m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s)
    elif k == 1:
        s = 2.0 * math.sqrt(max(1.0 + m[0][0] - m[1][1] - m[2][2], 0.0))
        q = ((m[2][1] - m[1][2]) / s, s / 4, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s)
    elif k == 2:
        s = 2.0 * math.sqrt(max(1.0 - m[0][0] + m[1][1] - m[2][2], 0.0))
        q = ((m[0][2] - m[2][0]) / s, (m[0][1] + m[1][0]) / s, s / 4, (m[1][2] + m[2][1]) / s)
    else:
        s = 2.0 * math.sqrt(max(1.0 - m[0][0] - m[1][1] + m[2][2], 0.0))
        q = ((m[1][0] - m[0][1]) / s, (m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, s / 4)
    n = math.sqrt(sum(c * c for c in q))
    return tuple(c / n * (1 if q[0] >= 0 else -1) for c in q)


_ORIGIN = {"x": 0.0, "y": 0.0, "z": 0.0}


def _rotation(q: tuple) -> dict[str, float]:
    """foxglove.Quaternion of (w, x, y, z), to :data:`DIGITS` decimals."""
    return {"x": round(q[1], DIGITS), "y": round(q[2], DIGITS), "z": round(q[3], DIGITS), "w": round(q[0], DIGITS)}


class FrameTransforms:
    """The robot's frame tree over time, from its samples: ``foxglove.FrameTransforms`` messages
    at most one per ``period_ns`` of log time (default 50 Hz).

    Each message holds, at one time (the log time of the sample that completed the period):

    - ``world`` -> ``spacecraft``: the attitude of the latest IMU sample (``quat_wxyz``: IMU frame
      -> inertial), turned into the body's by the IMU's mounting (``Robot.R_imu``). Translation
      zero: the gateway estimates no position, so ``world`` is the inertial axes with their origin
      at the spacecraft's centre of mass C. Left out until an IMU sample came.
    - every URDF joint, parent link -> child link: its origin, then for a revolute joint the
      latest encoder angle about its axis (left out until that joint's first sample).

    Frame ids are the URDF's link names, so Foxglove's URDF layer hangs each link's visuals on
    them. A sample that is not finite (or a quaternion of no length) is ignored: the previous
    value holds. A pure computation, no I/O: :class:`TransformWriter` records what it returns.
    """

    def __init__(self, robot, *, period_ns: int = TF_PERIOD_NS):
        import robot_description

        if not period_ns > 0:
            raise ValueError(f"period_ns {period_ns}: must be positive")
        self.period_ns = int(period_ns)
        self.devices = list(robot.joint_names)                   # <arm>/<joint>, the angles' order
        by_urdf_name = {robot.model.names[j]: f"{arm.name}/{jn}" for arm in robot.arms
                        for j, jn in zip(arm.joints, arm.joint_names)}
        self._index = index = {d: i for i, d in enumerate(self.devices)}
        # (parent, child, xyz dict, origin quaternion, axis, angle index or -1, rotation dict at 0)
        self._joints = []
        for j in robot_description.urdf_joints(robot.urdf):
            moving = j.kind in ("revolute", "continuous") and j.name in by_urdf_name
            q0 = _q_rpy(*j.rpy)
            self._joints.append((j.parent, j.child, dict(zip("xyz", j.xyz)), q0, j.axis,
                                 index[by_urdf_name[j.name]] if moving else -1, _rotation(q0)))
        self._q_imu_in_body = _q_matrix(robot.R_imu)
        self.angles: list[float | None] = [None] * len(self.devices)
        self.attitude: tuple | None = None        # world <- spacecraft, (w, x, y, z)
        self._next: int | None = None
        self._map = None                          # (the drivers' joint names, their index here)
        self.ignored = 0                          # samples not finite, counted

    # -- input ---------------------------------------------------------------------------------
    def set_attitude(self, quat_wxyz) -> bool:
        """The IMU's attitude (IMU frame -> inertial, scalar first); False if ignored."""
        try:
            q = tuple(float(c) for c in quat_wxyz)
        except (TypeError, ValueError):
            q = ()
        n = math.sqrt(sum(c * c for c in q)) if len(q) == 4 and all(map(math.isfinite, q)) else 0.0
        if not (n > 1e-6 and math.isfinite(n)):
            self.ignored += 1
            return False
        w, x, y, z = (c / n for c in q)
        a, b, c, d = self._q_imu_in_body
        self.attitude = _qmul((w, x, y, z), (a, -b, -c, -d))     # world <- imu <- body
        return True

    def set_angle(self, k: int, angle_rad: float) -> bool:
        """Joint ``k``'s angle (rad, in :attr:`devices` order); False if ignored."""
        try:
            a = float(angle_rad)
        except (TypeError, ValueError):
            a = math.nan
        if not math.isfinite(a):
            self.ignored += 1
            return False
        self.angles[k] = a
        return True

    def due(self, log_ns: int) -> bool:
        """Whether a message is due at ``log_ns`` (the first call starts the period grid)."""
        if self._next is None:
            self._next = (log_ns // self.period_ns + 1) * self.period_ns
            return False
        return log_ns >= self._next

    def message(self, log_ns: int) -> dict[str, Any]:
        """The message at ``log_ns`` from the values so far; the next is due one period on."""
        self._next = (log_ns // self.period_ns + 1) * self.period_ns
        sec, nsec = divmod(max(0, int(log_ns)), 1_000_000_000)
        stamp = {"sec": sec, "nsec": nsec}
        out = []
        if self.attitude is not None:
            out.append({"timestamp": stamp, "parent_frame_id": WORLD_FRAME, "child_frame_id": "spacecraft",
                        "translation": _ORIGIN, "rotation": _rotation(self.attitude)})
        for parent, child, xyz, q0, axis, k, fixed in self._joints:
            rotation = fixed
            if k >= 0:
                a = self.angles[k]
                if a is None:
                    continue
                s = math.sin(a / 2)
                rotation = _rotation(_qmul(q0, (math.cos(a / 2), axis[0] * s, axis[1] * s, axis[2] * s)))
            out.append({"timestamp": stamp, "parent_frame_id": parent, "child_frame_id": child,
                        "translation": xyz, "rotation": rotation})
        return {"transforms": out}

    def sample(self, obj, log_ns: int | None = None) -> dict[str, Any] | None:
        """Take one :class:`drivers.samples.ImuSample` or :class:`~drivers.samples.JointSample`
        (anything else is ignored); returns the message it makes due, or None."""
        from drivers.samples import ImuSample, JointSample

        if isinstance(obj, ImuSample):
            self.set_attitude(obj.quat_wxyz)
        elif isinstance(obj, JointSample):
            k = self._index.get(obj.device)
            if k is None:
                return None
            self.set_angle(k, obj.angle_rad)
        else:
            return None
        t = obj.t_ns if log_ns is None else log_ns
        if not isinstance(t, int):
            return None
        return self.message(t) if self.due(t) else None

    def rows(self, events, log_ns, joint_names) -> list[tuple[int, dict[str, Any]]]:
        """Take the drivers' event rows (:data:`drivers.kernel.EVENT_DTYPE`; a JOINT row's
        ``device`` indexes ``joint_names``, ``<arm>/<joint>``) with their log times; returns the
        messages that came due, ``(log_ns, message)``, in order."""
        import numpy as np

        from drivers.kernel import IMU, JOINT

        to_mine = self._map
        if to_mine is None or to_mine[0] is not joint_names:
            to_mine = self._map = (joint_names, np.array(
                [self._index.get(n, -2) for n in joint_names] + [-2], dtype=np.int64))
        to_mine = to_mine[1]
        kinds = events["kind"]
        out: list[tuple[int, dict[str, Any]]] = []
        if len(events) <= SMALL_BATCH:         # live, a frame at a time: a loop costs less than numpy's calls
            mine = to_mine.tolist()
            top = len(joint_names)
            for i, (kind, dev, t) in enumerate(zip(kinds.tolist(), events["device"].tolist(), log_ns.tolist())):
                if kind == JOINT:
                    k = mine[min(max(dev, -1), top)]
                    if k < 0:
                        continue
                    self.set_angle(k, events["values"][i, 0])
                elif kind == IMU:
                    self.set_attitude(events["values"][i, :4].tolist())
                else:
                    continue
                if self.due(t):
                    out.append((t, self.message(t)))
            return out
        sel = np.flatnonzero((kinds == JOINT) | (kinds == IMU))
        if not len(sel):
            return out
        dev = np.clip(events["device"][sel].astype(np.int64), -1, len(joint_names))
        which = np.where(kinds[sel] == IMU, -1, to_mine[dev])
        known = which != -2                  # a joint the robot does not have: not even its time
        sel, which = sel[known], which[known]
        values = events["values"][sel, :4]
        logs = np.asarray(log_ns)[sel]
        # what set_attitude / set_angle refuse, refused here for the batch: such a row still counts
        # for the timing (as in the loop above), its value never
        with np.errstate(over="ignore", invalid="ignore"):
            norm = np.sqrt((values * values).sum(axis=1))
        good = np.where(which == -1, np.isfinite(values).all(axis=1) & np.isfinite(norm) & (norm > 1e-6),
                        np.isfinite(values[:, 0]))
        self.ignored += int((~good).sum())
        which = np.where(good, which, -2)
        start, n = 0, len(sel)
        while start < n:
            if self._next is None:
                self.due(int(logs[start]))
            hit = np.flatnonzero(logs[start:] >= self._next)
            stop = n if not len(hit) else start + int(hit[0]) + 1
            self._apply(which[start:stop], values[start:stop])
            if len(hit):
                t = int(logs[stop - 1])
                out.append((t, self.message(t)))
            start = stop
        return out

    def _apply(self, which, values) -> None:
        """The last value of each joint and of the attitude among these rows (in order; -2: a row
        to skip)."""
        import numpy as np

        if not len(which):
            return
        kinds, first = np.unique(which[::-1], return_index=True)
        for k, i in zip(kinds.tolist(), (len(which) - 1 - first).tolist()):
            if k == -1:
                self.set_attitude(values[i].tolist())
            elif k >= 0:
                self.angles[k] = float(values[i, 0])


class TransformWriter:
    """Records a robot's :class:`FrameTransforms` on :data:`TF_TOPIC` into a
    :class:`gateway.log.recorder.Recorder`, with the URDF on :data:`ROBOT_DESCRIPTION_TOPIC` at the
    log time of the first transforms of each file (the 3D panel's URDF layer takes the latest
    message on that topic; a rotated file gets its own copy). Not thread-safe: one caller at a
    time (:class:`gateway.commands.record.Recording` holds a lock)."""

    def __init__(self, recorder, robot, *, period_ns: int = TF_PERIOD_NS):
        self.recorder, self.robot = recorder, robot
        self.tf = FrameTransforms(robot, period_ns=period_ns)
        self._declared = False
        self._urdf_file = -1                  # the file index the URDF was last written into
        self.written = 0

    def write(self, log_ns: int, message: dict[str, Any]) -> bool:
        """Record one message; False if the recorder refused it (counted there)."""
        rec = self.recorder
        if not self._declared:
            rec.add_channel(TF_TOPIC, FRAME_TRANSFORMS_SCHEMA)
            rec.add_channel(ROBOT_DESCRIPTION_TOPIC, ROBOT_DESCRIPTION_SCHEMA)
            self._declared = True
        ok = True
        files = len(rec.paths)
        if files != self._urdf_file:
            self._urdf_file = files
            ok = rec.record(ROBOT_DESCRIPTION_TOPIC, {"data": self.robot.urdf, "robot": self.robot.name},
                            log_time_ns=log_ns)
        ok = rec.record(TF_TOPIC, message, log_time_ns=log_ns) and ok
        self.written += 1
        return ok

    def sample(self, obj, log_ns: int | None = None) -> bool:
        msg = self.tf.sample(obj, log_ns)
        return True if msg is None else self.write(obj.t_ns if log_ns is None else log_ns, msg)

    def rows(self, events, log_ns, joint_names) -> tuple[int, int]:
        """(messages recorded, refused)."""
        refused = 0
        out = self.tf.rows(events, log_ns, joint_names)
        for t, msg in out:
            refused += not self.write(t, msg)
        return len(out), refused
