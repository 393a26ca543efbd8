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

from numba import njit

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
        self._quat: tuple | None = None           # the latest IMU quaternion, normalised
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
        self._set_normalised(tuple(c / n for c in q))
        return True

    def _set_normalised(self, q: tuple) -> None:
        self._quat = q                                              # the IMU's, normalised
        a, b, c, d = self._q_imu_in_body
        self.attitude = _qmul(q, (a, -b, -c, -d))                   # world <- imu <- body

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

        out: list[tuple[int, dict[str, Any]]] = []
        if len(events) <= SMALL_BATCH:         # live, a frame at a time: a loop costs less than numpy's calls
            to_mine = self._map
            if to_mine is None or to_mine[0] is not joint_names:
                to_mine = self._map = (joint_names, np.array(
                    [self._index.get(n, -2) for n in joint_names] + [-2], dtype=np.int64))
            kinds = events["kind"]
            mine = to_mine[1].tolist()
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
        # a batch: one compiled pass keeps the latest values and snapshots them at each due time
        return self.messages(*self.snapshots(events, log_ns, joint_names))

    def messages(self, times, angles, quats, m: int) -> list[tuple[int, dict[str, Any]]]:
        """The messages of :meth:`snapshots`, ``(log_ns, message)``; the current values stay."""
        out = []
        latest, nxt = (self.angles, self._quat), self._next
        for r in range(m):
            self._restore(angles[r], quats[r])
            t = int(times[r])
            out.append((t, self.message(t)))
        self.angles, self._next = latest[0], nxt
        if latest[1] is not None:
            self._set_normalised(latest[1])
        return out

    def snapshots(self, events, log_ns, joint_names) -> tuple:
        """:meth:`rows` of a batch up to the messages: ``(times, angles, quaternions, m)``, the
        values at each of the ``m`` due times (first ``m`` rows; angles in :attr:`devices` order,
        NaN: none yet; the IMU's normalised quaternion, NaN: none yet), for a writer of their
        messages (:mod:`gateway.engine.tfjson`); the batch's latest values are then the current
        ones, and the next due time the one after the last message."""
        import numpy as np

        from drivers.kernel import IMU, JOINT

        to_mine = self._map
        if to_mine is None or to_mine[0] is not joint_names:
            to_mine = self._map = (joint_names, np.array(
                [self._index.get(n, -2) for n in joint_names] + [-2], dtype=np.int64))
        n, nj = len(events), len(self.angles)
        angles = np.array([math.nan if a is None else a for a in self.angles], dtype=np.float64)
        quat = np.full(4, math.nan) if self._quat is None else np.array(self._quat, dtype=np.float64)
        state = np.array([-1 if self._next is None else self._next, self.period_ns, 0], dtype=np.int64)
        snap_t = np.empty(n, dtype=np.int64)
        snap_a = np.empty((n, nj), dtype=np.float64)
        snap_q = np.empty((n, 4), dtype=np.float64)
        m = _scan(events["kind"], events["device"], events["values"], np.ascontiguousarray(log_ns, dtype=np.int64),
                  to_mine[1], len(joint_names), JOINT, IMU, angles, quat, state, snap_t, snap_a, snap_q)
        self.ignored += int(state[2])
        self._restore(angles, quat)
        self._next = None if state[0] < 0 else int(state[0])
        return snap_t, snap_a, snap_q, m

    def _restore(self, angles, quat) -> None:
        """The state :func:`_scan` kept: angles (NaN: none yet), the IMU's normalised quaternion."""
        self.angles = [None if a != a else a for a in angles.tolist()]
        q = quat.tolist()
        if q[0] != q[0]:
            self._quat = self.attitude = None
        elif tuple(q) != self._quat:
            self._set_normalised(tuple(q))


class TransformWriter:
    """Records a robot's :class:`FrameTransforms` on :data:`TF_TOPIC` into a
    :class:`gateway.log.recorder.Recorder`, with the URDF on :data:`ROBOT_DESCRIPTION_TOPIC` at the
    log time of the first transforms of each file (the 3D panel's URDF layer takes the latest
    message on that topic; a rotated file gets its own copy). Not thread-safe: one caller at a
    time (:class:`gateway.commands.record.Recording` holds a lock).

    ``encoder``: made from the :class:`FrameTransforms`, something whose ``messages(times,
    angles, quaternions, m)`` gives the JSON of :meth:`FrameTransforms.snapshots` as the
    recorder would write the messages (or None: then they are written as objects); a batch of
    rows is then written through it (``gateway.engine.tfjson.TransformJson``, compiled)."""

    def __init__(self, recorder, robot, *, period_ns: int = TF_PERIOD_NS, encoder=None):
        self.recorder, self.robot = recorder, robot
        self.tf = FrameTransforms(robot, period_ns=period_ns)
        self.encoder = None if encoder is None else encoder(self.tf)
        self._declared = False
        self._urdf_file = -1                  # the file index the URDF was last written into
        self.written = 0

    def _start(self, log_ns: int) -> bool:
        """The topics declared, the URDF recorded if this file has none yet; False if refused."""
        rec = self.recorder
        if not self._declared:
            rec.add_channel(TF_TOPIC, FRAME_TRANSFORMS_SCHEMA)
            rec.add_channel(ROBOT_DESCRIPTION_TOPIC, ROBOT_DESCRIPTION_SCHEMA)
            self._declared = True
        files = len(rec.paths)
        if files != self._urdf_file:
            self._urdf_file = files
            return rec.record(ROBOT_DESCRIPTION_TOPIC, {"data": self.robot.urdf, "robot": self.robot.name},
                              log_time_ns=log_ns)
        return True

    def write(self, log_ns: int, message: dict[str, Any]) -> bool:
        """Record one message; False if the recorder refused it (counted there)."""
        ok = self._start(log_ns)
        ok = self.recorder.record(TF_TOPIC, message, log_time_ns=log_ns) and ok
        self.written += 1
        return ok

    def sample(self, obj, log_ns: int | None = None) -> bool:
        msg = self.tf.sample(obj, log_ns)
        return True if msg is None else self.write(obj.t_ns if log_ns is None else log_ns, msg)

    def rows(self, events, log_ns, joint_names) -> tuple[int, int]:
        """(messages recorded, refused)."""
        if self.encoder is None or len(events) <= SMALL_BATCH:
            refused = 0
            out = self.tf.rows(events, log_ns, joint_names)
            for t, msg in out:
                refused += not self.write(t, msg)
            return len(out), refused
        tf = self.tf
        times, angles, quats, m = tf.snapshots(events, log_ns, joint_names)
        if not m:
            return 0, 0
        data = self.encoder.messages(times, angles, quats, m)
        if data is None:                      # a value the encoder does not write: as objects
            refused = 0
            for t, msg in tf.messages(times, angles, quats, m):
                refused += not self.write(t, msg)
            return m, refused
        refused = 0
        record = self.recorder.record_encoded
        for d, t in zip(data, times[:m].tolist()):
            ok = self._start(t)
            refused += not (record(TF_TOPIC, None, d, t) and ok)
        self.written += m
        return m, refused


@njit(cache=True, nogil=True)
def _scan(kinds, devices, values, logs, to_mine, top, joint, imu, angles, quat, state, snap_t, snap_a, snap_q):
    """:meth:`FrameTransforms.rows` of a batch in one pass, as its row-by-row loop does it: a joint
    row (``to_mine`` maps its device; -2: not this robot's, not even its time) or an IMU row
    updates ``angles`` / ``quat`` (normalised) when finite (else counted in ``state[2]``), then at
    a due time (``state[0]``: the next, -1 before the first row; ``state[1]``: the period) the
    values are copied to the next ``snap_*`` row. Returns the number of snapshots."""
    m = 0
    period = state[1]
    for i in range(kinds.shape[0]):
        kd = kinds[i]
        if kd == joint:
            d = devices[i]
            if d < -1:
                d = -1
            if d > top:
                d = top
            k = to_mine[d]
            if k == -2:
                continue
            v = values[i, 0]
            if math.isfinite(v):
                angles[k] = v
            else:
                state[2] += 1
        elif kd == imu:
            q0, q1, q2, q3 = values[i, 0], values[i, 1], values[i, 2], values[i, 3]
            ok = math.isfinite(q0) and math.isfinite(q1) and math.isfinite(q2) and math.isfinite(q3)
            n = math.sqrt(0.0 + q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3) if ok else 0.0
            if n > 1e-6 and math.isfinite(n):
                quat[0], quat[1], quat[2], quat[3] = q0 / n, q1 / n, q2 / n, q3 / n
            else:
                state[2] += 1
        else:
            continue
        t = logs[i]
        if state[0] < 0:
            state[0] = (t // period + 1) * period
            continue
        if t >= state[0]:
            snap_t[m] = t
            for k in range(angles.shape[0]):
                snap_a[m, k] = angles[k]
            for k in range(4):
                snap_q[m, k] = quat[k]
            m += 1
            state[0] = (t // period + 1) * period
    return m
