"""JSON payloads written straight from rows: the drivers' sample events and the estimator's
effort rows become the bytes Python's ``json`` would write for their objects, without the objects.

One form (:func:`gateway.log.schema.record_of`, ``{"type":"JointEfforts","v":1,<fields>}``): what
``bsc gateway`` publishes on zenoh and what a log holds are the same bytes.

Each message kind is a small program (literal bytes and typed value slots, built once from the
dataclass's fields) run by one compiled interpreter over per-row value arrays; floats go through
:mod:`gateway.engine.floatrepr` (CPython's ``repr``, exactly). A row whose values are not all
finite is written by the Python encoder instead (:func:`gateway.codec.encode` refuses it; the
recorder writes ``NaN``), so the bytes are always the objects'.
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np

from drivers import kernel
from drivers.samples import ImuSample, JointSample, ThrusterCommand, TorqueCommand, ValveCommand, WrenchSample
from gateway.efforts import JointEfforts, ThrusterEffort, ValveWrenches
from gateway.estimator.jitopts import jit
from gateway.log.schema import FORM_VERSION

from .floatrepr import write_float, write_int

_jit = jit   # numba's njit with the estimator kernels' options: no reference counting (they allocate nothing)

# program ops: rows of (op, a, b, c)
LIT, FLT, INT, BOOL, STR, FLTS, FLTS_IF, MIN_IF, FLAGS, GOOD, FLT_IF, INT_IF = range(12)


@_jit
def _lit(buf, o, lit, a, b):
    for k in range(b):
        buf[o + k] = lit[a + k]
    return o + b


@_jit
def _run(prog, lit, tab_start, tab_len, F, I, Fl, flag_bits, flag_start, flag_len, r, buf, o):
    """One message of row ``r`` by ``prog`` into ``buf`` at ``o``; the new offset, or -1 when a
    float is not finite."""
    for p in range(prog.shape[0]):
        op, a, b, c = prog[p, 0], prog[p, 1], prog[p, 2], prog[p, 3]
        if op == LIT:
            o = _lit(buf, o, lit, a, b)
        elif op == FLT:
            o = write_float(F[r, a], buf, o)
            if o < 0:
                return -1
        elif op == INT:
            o = write_int(I[r, a], buf, o)
        elif op == BOOL:
            if I[r, a] != 0:
                o = _lit(buf, o, lit, c, 4)               # "true" at c (b: "false")
            else:
                o = _lit(buf, o, lit, b, 5)
        elif op == STR:                                   # table b, entry I[r, a]
            k = I[r, a]
            o = _lit(buf, o, lit, tab_start[b + k], tab_len[b + k])
        elif op == FLTS or op == FLTS_IF:                 # [F a..a+b) (FLTS_IF: [] unless every I c..c+b)
            have = True
            if op == FLTS_IF:
                for k in range(b):
                    if I[r, c + k] == 0:
                        have = False
            buf[o] = 91                                   # '['
            o += 1
            if have:
                for k in range(b):
                    if k:
                        buf[o] = 44
                        o += 1
                    o = write_float(F[r, a + k], buf, o)
                    if o < 0:
                        return -1
            buf[o] = 93                                   # ']'
            o += 1
        elif op == MIN_IF:                                # min(I a..a+b) if every I c..c+b else 0
            have = True
            m = I[r, a]
            for k in range(b):
                if I[r, c + k] == 0:
                    have = False
                if I[r, a + k] < m:
                    m = I[r, a + k]
            o = write_int(m if have else 0, buf, o)
        elif op == FLAGS or op == GOOD:                   # flag set a (name-sorted bits), with names
            lo, n = flag_start[a], flag_len[a]
            if op == GOOD:
                bad = False
                for k in range(n):
                    if Fl[r, flag_bits[lo + k]]:
                        bad = True
                o = _lit(buf, o, lit, b, 5) if bad else _lit(buf, o, lit, c, 4)
            else:
                buf[o] = 91
                o += 1
                first = True
                for k in range(n):
                    bit = flag_bits[lo + k]
                    if Fl[r, bit]:
                        if not first:
                            buf[o] = 44
                            o += 1
                        first = False
                        o = _lit(buf, o, lit, tab_start[b + bit], tab_len[b + bit])
                buf[o] = 93
                o += 1
        elif op == FLT_IF:                                # F a if I b else 0.0
            o = write_float(F[r, a] if I[r, b] != 0 else 0.0, buf, o)
            if o < 0:
                return -1
        elif op == INT_IF:                                # I a if I b else 0
            o = write_int(I[r, a] if I[r, b] != 0 else 0, buf, o)
    return o


@_jit
def _encode(progs, prog_of, lit, tab_start, tab_len, F, I, Fl, flag_bits, flag_start, flag_len, per_row, buf,
            offsets, failed):
    """Every message of every row: row ``r``'s message ``m`` (0..per_row) by program
    ``prog_of[r, m]`` (an index into the stacked ``progs``: rows [start, end)). Returns the bytes
    written; a message whose floats are not all finite is left empty and flagged in ``failed``."""
    o = 0
    k = 0
    for r in range(F.shape[0]):
        for m in range(per_row):
            offsets[k] = o
            p = prog_of[r, m]
            if p >= 0:
                e = _run(progs[p], lit, tab_start, tab_len, F, I, Fl, flag_bits, flag_start, flag_len, r, buf, o)
                if e < 0:
                    failed[k] = 1
                else:
                    o = e
            k += 1
    offsets[k] = o
    return o


class _Builder:
    """Literal bytes, string tables and flag sets shared by the programs of one encoder."""

    def __init__(self):
        self.lit = bytearray(b"truefalse")
        self.tables: list[list[bytes]] = []
        self.flag_sets: list[list[int]] = []

    def literal(self, text: str | bytes) -> tuple[int, int]:
        data = text.encode() if isinstance(text, str) else text
        at = self.lit.find(data)
        if at < 0:
            at = len(self.lit)
            self.lit += data
        return at, len(data)

    def table(self, strings: list[str]) -> int:
        enc = [json.dumps(s).encode() for s in strings]
        for s in enc:
            if not all(32 <= c < 127 for c in s):
                raise ValueError(f"names must be printable ASCII: {s!r}")
        self.tables.append(enc)
        return sum(len(t) for t in self.tables[:-1])

    def flag_set(self, bits: list[int]) -> int:
        self.flag_sets.append(list(bits))
        return len(self.flag_sets) - 1

    def arrays(self):
        starts, lens = [], []
        for t in self.tables:
            for s in t:
                a, n = self.literal(s)
                starts.append(a)
                lens.append(n)
        bits = [b for fs in self.flag_sets for b in fs]
        fstart = np.cumsum([0] + [len(fs) for fs in self.flag_sets[:-1]]).astype(np.int64) if self.flag_sets \
            else np.zeros(0, dtype=np.int64)
        return (np.frombuffer(bytes(self.lit), dtype=np.uint8).copy(), np.array(starts, dtype=np.int64),
                np.array(lens, dtype=np.int64), np.array(bits, dtype=np.int64), fstart,
                np.array([len(fs) for fs in self.flag_sets], dtype=np.int64))


class _Program:
    """The ops of one message kind: :meth:`field` adds ``"name":`` then a value op."""

    def __init__(self, b: _Builder, type_name: str):
        self.b, self.ops = b, []
        self._pending = "{" + f'"type":{json.dumps(type_name)},"v":{FORM_VERSION},'
        self._first = True

    def _text(self, t: str) -> None:
        self._pending += t

    def _flush(self) -> None:
        if self._pending:
            a, n = self.b.literal(self._pending)
            self.ops.append((LIT, a, n, 0))
            self._pending = ""

    def field(self, name: str, op: int, a: int = 0, b: int = 0, c: int = 0) -> None:
        self._text(("" if self._first else ",") + json.dumps(name) + ":")
        self._first = False
        self._flush()
        if op in (BOOL, GOOD):
            b, c = 4, 0                   # "false" at 4, "true" at 0 in the shared literal
        self.ops.append((op, a, b, c))

    def array(self) -> np.ndarray:
        self._text("}")
        self._flush()
        return np.array(self.ops, dtype=np.int64).reshape(-1, 4)


def _stack(progs: list[np.ndarray]) -> tuple:
    return tuple(progs)


# --- samples ------------------------------------------------------------------------------------

_KIND_CLASS = {kernel.WRENCH: WrenchSample, kernel.JOINT: JointSample, kernel.TORQUE: TorqueCommand,
               kernel.IMU: ImuSample, kernel.THRUSTER: ThrusterCommand, kernel.VALVE: ValveCommand}
# event int columns of the I array
_I_T, _I_COUNTER, _I_STATUS, _I_VALVES, _I_SAT, _I_DEVICE = range(6)
# where each vector field starts in the event's values
_VALUES = {"force_n": 0, "torque_nm": 3, "angle_rad": 0, "rate_rad_s": 1, "quat_wxyz": 0, "accel_m_s2": 7,
           "moment_nm": 3}


class SampleJson:
    """Encodes the drivers' event rows (:data:`drivers.kernel.EVENT_DTYPE`) of one robot as the
    JSON of the sample objects :meth:`drivers.kernel.DriverCore.to_samples` would give."""

    def __init__(self, arm_names: list[str], joint_names: list[str]):
        b = _Builder()
        arm_tab = b.table(arm_names)
        joint_tab = b.table(joint_names)
        progs = []
        for kind, cls in sorted(_KIND_CLASS.items()):
            pr = _Program(b, cls.__name__)
            for f in dataclasses.fields(cls):
                n = f.name
                if n == "device":
                    pr.field(n, STR, _I_DEVICE, arm_tab if kind == kernel.WRENCH else joint_tab)
                elif n == "t_ns":
                    pr.field(n, INT, _I_T)
                elif n == "counter":
                    pr.field(n, INT, _I_COUNTER)
                elif n == "status":
                    pr.field(n, INT, _I_STATUS)
                elif n == "allowed":              # the thruster command's keep-out mask (-1: none)
                    pr.field(n, INT, _I_STATUS)
                elif n == "valves":
                    pr.field(n, INT, _I_VALVES)
                elif n == "saturated":
                    pr.field(n, BOOL, _I_SAT)
                elif n == "rate_rad_s" and kind == kernel.IMU:
                    pr.field(n, FLTS, 4, 3)
                elif n in ("torque_nm",) and kind == kernel.TORQUE:
                    pr.field(n, FLT, 0)
                elif n in ("angle_rad", "rate_rad_s"):
                    pr.field(n, FLT, _VALUES[n])
                elif n in _VALUES:
                    size = 4 if n == "quat_wxyz" else 3
                    pr.field(n, FLTS, _VALUES[n], size)
                else:
                    raise ValueError(f"{cls.__name__}.{n}: no encoding")
            progs.append(pr.array())
        self._progs = tuple(progs)
        self._arrays = b.arrays()

    def encode(self, events: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(buf, offsets)``: message k = ``buf[offsets[k]:offsets[k + 1]]``, one per event."""
        n = len(events)
        F = np.ascontiguousarray(events["values"])
        I = np.empty((n, 6), dtype=np.int64)
        I[:, _I_T] = events["t_ns"]
        I[:, _I_COUNTER] = events["counter"]
        I[:, _I_STATUS] = events["status"]
        I[:, _I_VALVES] = events["valves"]
        I[:, _I_SAT] = events["saturated"]
        I[:, _I_DEVICE] = events["device"]
        prog_of = events["kind"].astype(np.int64).reshape(n, 1)
        return self._run(F, I, np.zeros((n, 0), dtype=np.uint8), prog_of, 1, 320)

    def _run(self, F, I, Fl, prog_of, per_row, max_len):
        lit, ts, tl, bits, fstart, flen = self._arrays
        k = prog_of.size
        buf = np.empty(max(1, k * max_len), dtype=np.uint8)
        off = np.empty(k + 1, dtype=np.int64)
        failed = np.zeros(k, dtype=np.uint8)
        n = _encode(self._progs, prog_of, lit, ts, tl, F, I, Fl, bits, fstart, flen, per_row, buf, off, failed)
        self.failed = failed
        return buf[:n], off

    def messages(self, events: np.ndarray) -> list[bytes]:
        buf, off = self.encode(events)
        raw = buf.tobytes()
        o = off.tolist()
        return [raw[o[k]:o[k + 1]] for k in range(len(events))]


class EffortJson(SampleJson):
    """Encodes the estimator's effort rows (:class:`gateway.estimator.core.EstimatorCore`) as the
    JSON of the objects :meth:`EstimatorCore.efforts` gives: per row one :class:`JointEfforts`
    per arm, then one :class:`ThrusterEffort`."""

    def __init__(self, core):
        self.core = core
        p, nj = core.n_arms, core.n_joints
        self.per_row = p + 1
        b = _Builder()
        flag_tab = b.table(core.flag_names)
        arm_tab = b.table(core.arms)
        # F columns: full | simplified | rate | commanded | thruster 6 | thruster_cmd 6 | ft_bias 6 per arm
        # | contact 6 per arm
        cf, cs, cr, cc, ct, ctc, cb = 0, nj, 2 * nj, 3 * nj, 4 * nj, 4 * nj + 6, 4 * nj + 12
        ccw = cb + 6 * p
        # I columns: t | commanded_have nj | commanded_t nj | thr_cmd_t | thr_cmd_valves | thr_cmd_have
        # | ft_bias_have 6 per arm (each arm's flag six times: FLTS_IF wants one per value) | contact_have
        it, ih, ict = 0, 1, 1 + nj
        itt, itv, ith, ibh = 1 + 2 * nj, 2 + 2 * nj, 3 + 2 * nj, 4 + 2 * nj
        ich = ibh + 6 * p
        progs = []
        col = 0
        for a, names in enumerate(core.arm_joints):
            n = len(names)
            fs = b.flag_set(list(core._arm_bits[a]))
            joints_text = "[" + ",".join(json.dumps(j) for j in names) + "]"
            pr = _Program(b, "JointEfforts")
            pr.field("arm", LIT, *b.literal(json.dumps(core.arms[a])))
            pr.field("t_ns", INT, it)
            pr.field("joints", LIT, *b.literal(joints_text))
            pr.field("full_nm", FLTS, cf + col, n)
            pr.field("simplified_nm", FLTS, cs + col, n)
            pr.field("commanded_nm", FLTS_IF, cc + col, n, ih + col)
            pr.field("commanded_t_ns", MIN_IF, ict + col, n, ih + col)
            pr.field("rate_rad_s", FLTS, cr + col, n)
            pr.field("good", GOOD, fs)
            pr.field("flags", FLAGS, fs, flag_tab)
            pr.field("ft_bias", FLTS_IF, cb + 6 * a, 6, ibh + 6 * a)
            pr.field("contact", FLTS_IF, ccw + 6 * a, 6, ich + 6 * a)
            progs.append(pr.array())
            col += n
        fs = b.flag_set(list(core._thr_bits))
        pr = _Program(b, "ThrusterEffort")
        pr.field("t_ns", INT, it)
        pr.field("force_n", FLTS, ct, 3)
        pr.field("moment_nm", FLTS, ct + 3, 3)
        for name, c0 in (("commanded_force_n", ctc), ("commanded_moment_nm", ctc + 3)):
            pr.field(name, LIT, *b.literal("["))          # [F if have else 0.0, ...]
            for k in range(3):
                if k:
                    pr.ops.append((LIT, *b.literal(","), 0))
                pr.ops.append((FLT_IF, c0 + k, ith, 0))
            pr.ops.append((LIT, *b.literal("]"), 0))
        pr.field("commanded_t_ns", INT_IF, itt, ith)
        pr.field("valves", INT_IF, itv, ith)
        pr.field("good", GOOD, fs)
        pr.field("flags", FLAGS, fs, flag_tab)
        progs.append(pr.array())
        self._progs = tuple(progs)
        self._arrays = b.arrays()
        self._prog_row = np.arange(self.per_row, dtype=np.int64)
        self._prog_of = np.zeros((0, self.per_row), dtype=np.int64)
        self._nj = nj
        self._p = p
        self._arm_tab = arm_tab

    def encode(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(buf, offsets)``: ``per_row`` messages per row, in :meth:`EstimatorCore.efforts` order."""
        n, nj, p = len(rows), self._nj, self._p
        F = np.empty((n, 4 * nj + 12 + 12 * p))
        F[:, :nj] = rows["full_nm"]
        F[:, nj:2 * nj] = rows["simplified_nm"]
        F[:, 2 * nj:3 * nj] = rows["rate_rad_s"]
        F[:, 3 * nj:4 * nj] = rows["commanded_nm"]
        F[:, 4 * nj:4 * nj + 6] = rows["thruster"]
        F[:, 4 * nj + 6:4 * nj + 12] = rows["thruster_cmd"]
        F[:, 4 * nj + 12:4 * nj + 12 + 6 * p] = rows["ft_bias"][:, :p].reshape(n, 6 * p)
        F[:, 4 * nj + 12 + 6 * p:] = rows["contact"][:, :p].reshape(n, 6 * p)
        I = np.empty((n, 4 + 2 * nj + 12 * p), dtype=np.int64)
        I[:, 0] = rows["t_ns"]
        I[:, 1:1 + nj] = rows["commanded_have"]
        I[:, 1 + nj:1 + 2 * nj] = rows["commanded_t_ns"]
        I[:, 1 + 2 * nj] = rows["thruster_cmd_t_ns"]
        I[:, 2 + 2 * nj] = rows["thruster_cmd_valves"]
        I[:, 3 + 2 * nj] = rows["thruster_cmd_have"]
        # each arm's flag six times (broadcast: np.repeat's call costs more than the copy)
        I[:, 4 + 2 * nj:4 + 2 * nj + 6 * p].reshape(n, p, 6)[:] = rows["ft_bias_have"][:, :p, None]
        I[:, 4 + 2 * nj + 6 * p:].reshape(n, p, 6)[:] = rows["contact_have"][:, :p, None]
        if len(self._prog_of) < n:             # the programs of n rows: a slice of rows kept from call to call
            self._prog_of = np.ascontiguousarray(np.broadcast_to(self._prog_row, (max(n, 2 * len(self._prog_of)),
                                                                                   self.per_row)))
        return self._run(F, I, np.ascontiguousarray(rows["flags"]), self._prog_of[:n], self.per_row,
                         400 + 64 * nj + 320 * p + 32 * len(self.core.flag_names))

    def messages(self, rows: np.ndarray) -> list[bytes]:
        buf, off = self.encode(rows)
        raw = buf.tobytes()
        o = off.tolist()
        return [raw[o[k]:o[k + 1]] for k in range(len(rows) * self.per_row)]


class ValveJson(SampleJson):
    """Encodes the estimator's valve rows (:func:`gateway.estimator.core.valve_dtype`) as the JSON
    of the :class:`ValveWrenches` objects :meth:`EstimatorCore.valve_objects` gives."""

    def __init__(self, core):
        self.core = core
        n = self._n = core.kf.n
        b = _Builder()
        flag_tab = b.table(core.flag_names)
        fs = b.flag_set(list(core._thr_bits))
        pr = _Program(b, ValveWrenches.__name__)
        for f in dataclasses.fields(ValveWrenches):                # F: wrench 6 n | force_sigma_n n; I: t
            if f.name == "t_ns":
                pr.field(f.name, INT, 0)
            elif f.name == "wrench":
                pr.field(f.name, FLTS, 0, 6 * n)
            elif f.name == "force_sigma_n":
                pr.field(f.name, FLTS, 6 * n, n)
            elif f.name == "good":
                pr.field(f.name, GOOD, fs)
            elif f.name == "flags":
                pr.field(f.name, FLAGS, fs, flag_tab)
            else:
                raise ValueError(f"ValveWrenches.{f.name}: no encoding")
        self._progs = (pr.array(),)
        self._arrays = b.arrays()
        self._max_len = 200 + 32 * 7 * n + 32 * len(core.flag_names)

    def encode(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(buf, offsets)``: one message per row."""
        k, n = len(rows), self._n
        F = np.empty((k, 7 * n))
        F[:, :6 * n] = rows["wrench"]
        F[:, 6 * n:] = rows["force_sigma_n"]
        I = np.ascontiguousarray(rows["t_ns"], dtype=np.int64).reshape(k, 1)
        return self._run(F, I, np.ascontiguousarray(rows["flags"]), np.zeros((k, 1), dtype=np.int64), 1,
                         self._max_len)

    def messages(self, rows: np.ndarray) -> list[bytes]:
        buf, off = self.encode(rows)
        raw = buf.tobytes()
        o = off.tolist()
        return [raw[o[k]:o[k + 1]] for k in range(len(rows))]


class Encoded:
    """A batch of messages encoded into one buffer: message k goes on ``topics[which[k]]``
    (records of ``classes[which[k]]``), comes from row ``row[k]`` of the batch, and is
    ``data[offsets[k]:offsets[k + 1]]``; ``failed[k]``: a value was not finite, the payload is
    empty and the message must be encoded from its object instead. ``per`` > 0: each row gives
    ``per`` messages, one per topic in order (``which`` and ``row`` then follow, made when asked:
    a live batch is a row or two, and two numpy calls would cost more than its messages). Valid
    while the batch's rows are (the sinks of one batch; samples read their kinds and devices when asked)."""

    __slots__ = ("topics", "classes", "data", "offsets", "failed", "per", "_which", "_row", "_events", "_base")

    def __init__(self, topics: list[str], classes: list[type], data: np.ndarray, offsets: np.ndarray,
                 failed: np.ndarray, *, per: int = 0, events: np.ndarray | None = None,
                 base: np.ndarray | None = None):
        self.topics, self.classes, self.data, self.offsets, self.failed = topics, classes, data, offsets, failed
        self.per, self._events, self._base = per, events, base
        self._which: np.ndarray | None = None
        self._row: np.ndarray | None = None

    @property
    def which(self) -> np.ndarray:
        if self._which is None:
            if self.per:
                self._which = np.tile(np.arange(self.per), len(self.failed) // self.per)
            else:                                # samples: kind k's device d is topic base[k] + d
                ev, base = self._events, self._base
                assert ev is not None and base is not None
                self._which = base[ev["kind"].astype(np.int64)] + ev["device"]
        return self._which

    @property
    def row(self) -> np.ndarray:
        if self._row is None:
            n = len(self.failed)
            self._row = np.repeat(np.arange(n // self.per), self.per) if self.per else np.arange(n)
        return self._row

    def messages(self) -> list[tuple[str, type, bytes | None, int]]:
        """``(key, type, payload, row)`` per message (payload None: encode the row's object)."""
        raw, o, failed = self.data.tobytes(), self.offsets.tolist(), self.failed
        topics, classes, per = self.topics, self.classes, self.per
        if per:
            return [(topics[k % per], classes[k % per], None if failed[k] else raw[o[k]:o[k + 1]], k // per)
                    for k in range(len(failed))]
        ev, base = self._events, self._base
        assert ev is not None and base is not None
        b = base.tolist()
        return [(topics[b[kd] + dv], classes[b[kd] + dv], None if failed[k] else raw[o[k]:o[k + 1]], k)
                for k, (kd, dv) in enumerate(zip(ev["kind"].tolist(), ev["device"].tolist()))]


class RowEncoders:
    """A session's rows as payloads: the encoders and the key of every message."""

    def __init__(self, pipeline):
        from drivers.samples import ImuSample, JointSample, ThrusterCommand, TorqueCommand, ValveCommand, WrenchSample
        from gateway import keys

        robot, name = pipeline.robot, pipeline.name
        arms = [a.name for a in robot.arms]
        joints = robot.joint_names
        self.samples = SampleJson(arms, joints)
        self.efforts = EffortJson(pipeline.estimator) if pipeline.estimator is not None else None
        self.valves = ValveJson(pipeline.estimator) if pipeline.estimator is not None else None
        self.valve_key = keys.valve_wrenches(name)
        self.sample_type = {kernel.WRENCH: WrenchSample, kernel.JOINT: JointSample, kernel.TORQUE: TorqueCommand,
                            kernel.IMU: ImuSample, kernel.THRUSTER: ThrusterCommand, kernel.VALVE: ValveCommand}
        self.sample_key = {kernel.WRENCH: [keys.wrench(name, a) for a in arms],
                           kernel.JOINT: [keys.joint(name, j) for j in joints],
                           kernel.TORQUE: [keys.torque_command(name, j) for j in joints],
                           kernel.IMU: [keys.imu(name)], kernel.THRUSTER: [keys.thruster_command(name)],
                           kernel.VALVE: [keys.valve_command(name)]}
        # the sample topics in one list: kind k's device d is _sample_topics[_sample_base[k] + d]
        kinds = sorted(self.sample_key)
        self._sample_base = np.zeros(max(kinds) + 1, dtype=np.int64)
        self._sample_topics: list[str] = []
        self._sample_classes: list[type] = []
        for kd in kinds:
            self._sample_base[kd] = len(self._sample_topics)
            self._sample_topics += self.sample_key[kd]
            self._sample_classes += [self.sample_type[kd]] * len(self.sample_key[kd])
        self.effort_key = [keys.joint_efforts(name, a) for a in arms] + [keys.thruster_effort(name)]
        self.effort_type = [JointEfforts] * len(arms) + [ThrusterEffort]

    def sample_encoded(self, events: np.ndarray) -> Encoded:
        """Every event of a batch as its sample's JSON."""
        buf, off = self.samples.encode(events)
        return Encoded(self._sample_topics, self._sample_classes, buf, off, self.samples.failed, events=events,
                       base=self._sample_base)

    def effort_encoded(self, rows: np.ndarray) -> Encoded:
        """Every effort row as its messages, in :meth:`EstimatorCore.efforts` order (one
        :class:`JointEfforts` per arm, then the :class:`ThrusterEffort`)."""
        enc = self.efforts
        buf, off = enc.encode(rows)
        return Encoded(self.effort_key, self.effort_type, buf, off, enc.failed, per=enc.per_row)

    def valve_encoded(self, rows: np.ndarray) -> Encoded:
        """Every valve row as its :class:`ValveWrenches` message."""
        enc = self.valves
        buf, off = enc.encode(rows)
        return Encoded([self.valve_key], [ValveWrenches], buf, off, enc.failed, per=1)

    def sample_messages(self, events: np.ndarray) -> list[tuple[str, type, bytes | None, int]]:
        """``(key, type, payload, k)`` per event (payload None: not finite, encode event ``k``'s object)."""
        return self.sample_encoded(events).messages()

    def effort_messages(self, rows: np.ndarray) -> list[tuple[str, type, bytes | None, int]]:
        """``(key, type, payload, row)`` per effort message, in :meth:`EstimatorCore.efforts` order
        (payload None: not finite, encode :meth:`effort_object` instead)."""
        return self.effort_encoded(rows).messages()

    def valve_messages(self, rows: np.ndarray) -> list[tuple[str, type, bytes | None, int]]:
        """``(key, type, payload, row)`` per valve row (payload None: not finite, encode
        :meth:`valve_object` instead)."""
        return self.valve_encoded(rows).messages()

    def valve_object(self, rows: np.ndarray, k: int):
        """The object of valve row ``k``."""
        return self.valves.core.valve_objects(rows[k:k + 1])[0]

    def effort_object(self, rows: np.ndarray, message: int):
        """The object of effort message ``message`` (the index :meth:`effort_messages` counts)."""
        per = self.efforts.per_row
        return self.efforts.core.efforts(rows[message // per:message // per + 1])[message % per]
