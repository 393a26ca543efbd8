"""One recorded session -> identified actuator and sensor parameters (pure numpy, no plotting).

Inputs are what the gateway recorded: ``JointEfforts`` and ``ThrusterEffort`` (recognised by
their schema, whatever the topic), optionally ``DeviceHealth``/``BusHealth``, and the MCAP
metadata (``bsc.series`` gives the session's index in a series). Only ``good`` estimates with a
fresh command (``commanded_t_ns`` within :data:`COMMAND_MAX_AGE_NS`) are used.

Per joint, friction from the torque residual ``r = commanded - estimated`` (commanded motor
torque minus estimated actual torque = the friction torque that opposed the motion)::

    r = Fc sign(dq) + Fv dq + c          least squares over samples with |dq| > v_min

``Fc`` Coulomb (N m), ``Fv`` viscous (N m s/rad), ``c`` an offset (N m) that friction cannot
make (friction is odd in dq): model error, or a bias of the arm's F/T sensor, which shifts the
residual by ``A_tau(q) b`` whatever the direction of motion. ``Fc`` is the half-difference of
the residual between the two directions, so a bias moves ``c`` and leaves ``Fc`` nearly alone.

Per thruster axis (``fx fy fz mx my mz``, body frame about C)::

    est = eta cmd + c                    least squares over the session

``eta`` the efficiency (actual / commanded), ``c`` an offset: with no thruster firing, the
estimated thruster wrench is the momentum balance of F/T sensors and IMU and must be zero, so
``c`` is the momentum (in)consistency between them (an F/T or IMU bias), not a thruster fault.

Per arm, the bias of its F/T sensor as the gateway's joint filter learnt it (``ft_bias`` of
``JointEfforts``, sensor frame, N and N m): the mean over the second half of the session's good
estimates, when the filter has long left its prior. With the joint filter the full torques no
longer carry the bias, so this, not the residual offset ``c``, shows a drifting sensor; logs of
gateways without the filter have none, and ``c`` still does.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from gateway.errors import GatewayError

JOINT_SCHEMA = "gateway.efforts.JointEfforts"
THRUSTER_SCHEMA = "gateway.efforts.ThrusterEffort"
DEVICE_HEALTH_SCHEMA = "drivers.samples.DeviceHealth"
BUS_HEALTH_SCHEMA = "drivers.samples.BusHealth"
AXES = ("fx", "fy", "fz", "mx", "my", "mz")

COMMAND_MAX_AGE_NS = 50_000_000      # a command older than 50 ms does not explain the torque
V_MIN_RAD_S = 0.02                    # below: stick-slip, friction is anywhere in +-stiction
MIN_SAMPLES_PER_SIGN = 50             # Coulomb friction needs motion both ways
AXIS_MIN_CMD_RMS = 10.0               # N or N m: an axis commanded less has no efficiency
MIN_AXIS_SAMPLES = 100
QUIET_GUARD_NS = 20_000_000           # "no thruster firing": valves closed 20 ms either side
MIN_QUIET_SAMPLES = 20
MIN_BIAS_SAMPLES = 100                # per half session: an F/T bias needs the filter settled
FT_AXES = AXES                        # the F/T bias's components, sensor frame


class AnalysisError(GatewayError, ValueError):
    """A log that cannot be analysed (not MCAP, truncated, no efforts)."""


@dataclass(frozen=True)
class JointFit:
    """Friction of one joint in one session. ``identifiable`` False: too little motion."""

    target: str
    coulomb_nm: float
    viscous_nms: float
    offset_nm: float
    rms_nm: float            # residual after the fit
    samples: int
    positive: int
    negative: int
    identifiable: bool


@dataclass(frozen=True)
class AxisFit:
    """Efficiency and offset of one thruster axis in one session."""

    axis: str
    efficiency: float
    offset: float             # N or N m
    cmd_rms: float
    rms: float
    samples: int
    identifiable: bool
    quiet_offset: float = float("nan")   # mean estimate while no valve was open (should be 0)
    quiet_samples: int = 0


@dataclass
class SessionFeatures:
    path: str
    robot: str
    index: int | None           # bsc.series session_index, when present
    start_ns: int               # first message's log time
    end_ns: int
    joints: dict[str, JointFit] = field(default_factory=dict)
    axes: dict[str, AxisFit] = field(default_factory=dict)
    arms: dict[str, list[str]] = field(default_factory=dict)    # arm -> its joints, proximal first
    health: dict[str, dict[str, float]] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)          # e.g. analysed from a truncated log's intact part
    thruster_faults: list[dict] = field(default_factory=list)   # within the session (analysis.fdi.ThrusterAlarm)
    ft_bias: dict[str, list[float]] = field(default_factory=dict)   # arm -> F/T bias (fx fy fz N, mx my mz N m)
    # arm -> its contacts in the session (JointEfforts.contact): count, seconds in contact, largest force (N)
    contacts: dict[str, dict[str, float]] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return Path(self.path).stem

    def to_json(self) -> dict:
        d = asdict(self)
        d["name"] = self.name
        return d

    @classmethod
    def from_json(cls, d: dict) -> "SessionFeatures":
        d = dict(d)
        d.pop("name", None)
        d["joints"] = {k: JointFit(**v) for k, v in d["joints"].items()}
        d["axes"] = {k: AxisFit(**v) for k, v in d["axes"].items()}
        return cls(**d)


# --- fitting -----------------------------------------------------------------------------------------

def fit_friction(residual_nm: np.ndarray, rate_rad_s: np.ndarray, target: str = "",
                 v_min: float = V_MIN_RAD_S, min_per_sign: int = MIN_SAMPLES_PER_SIGN) -> JointFit:
    """Least squares ``r = Fc sign(v) + Fv v + c`` over ``|v| > v_min``, one pass of outlier
    rejection (residuals beyond 6 robust sigmas, e.g. a stiction breakaway, are dropped)."""
    r = np.asarray(residual_nm, dtype=float)
    v = np.asarray(rate_rad_s, dtype=float)
    keep = np.isfinite(r) & np.isfinite(v) & (np.abs(v) > v_min)
    r, v = r[keep], v[keep]
    pos, neg = int((v > 0).sum()), int((v < 0).sum())
    if pos < min_per_sign or neg < min_per_sign:
        return JointFit(target, float("nan"), float("nan"), float("nan"), float("nan"), int(r.size), pos, neg, False)
    X = np.column_stack((np.sign(v), v, np.ones_like(v)))
    beta = np.linalg.lstsq(X, r, rcond=None)[0]
    e = r - X @ beta
    mad = 1.4826 * np.median(np.abs(e - np.median(e)))
    if mad > 0:
        ok = np.abs(e) <= 6 * mad
        if ok.sum() > 3 and not ok.all():
            X, r = X[ok], r[ok]
            beta = np.linalg.lstsq(X, r, rcond=None)[0]
            e = r - X @ beta
    return JointFit(target, float(beta[0]), float(beta[1]), float(beta[2]), float(np.sqrt(np.mean(e ** 2))),
                    int(r.size), pos, neg, True)


def fit_efficiency(estimated: np.ndarray, commanded: np.ndarray, axis: str = "",
                   min_cmd_rms: float = AXIS_MIN_CMD_RMS) -> AxisFit:
    """Least squares ``est = eta cmd + c`` for one axis."""
    y = np.asarray(estimated, dtype=float)
    x = np.asarray(commanded, dtype=float)
    keep = np.isfinite(x) & np.isfinite(y)
    x, y = x[keep], y[keep]
    if x.size < MIN_AXIS_SAMPLES:
        return AxisFit(axis, float("nan"), float("nan"), float("nan"), float("nan"), int(x.size), False)
    cmd_rms = float(np.sqrt(np.mean(x ** 2)))
    X = np.column_stack((x, np.ones_like(x)))
    beta = np.linalg.lstsq(X, y, rcond=None)[0]
    e = y - X @ beta
    ident = cmd_rms >= min_cmd_rms and float(np.std(x)) > 0
    eta = float(beta[0]) if ident else float("nan")
    offset = float(beta[1]) if ident else float(np.mean(y))
    return AxisFit(axis, eta, offset, cmd_rms, float(np.sqrt(np.mean(e ** 2))), int(x.size), ident)


# --- reading ----------------------------------------------------------------------------------------

def _topics_with_schemas(path: Path, schemas) -> list[str]:
    """Topics whose schema is one of ``schemas`` (raw CAN and samples are skipped unread)."""
    from mcap.reader import SeekingReader

    from gateway.log.errors import McapFileError
    from gateway.log.scan import check_footer

    ok, why = check_footer(path)
    if not ok:
        raise McapFileError(f"{path}: file is truncated ({why}); run `bsc recover {path}` first")
    with open(path, "rb") as f:
        summary = SeekingReader(f).get_summary()
    if summary is None:
        return []
    return sorted(c.topic for c in summary.channels.values()
                  if c.schema_id in summary.schemas and summary.schemas[c.schema_id].name in schemas)


def read_metadata(path: str | os.PathLike[str]) -> dict[str, dict[str, str]]:
    """The metadata records of a log; of a truncated one (no summary), those that survive."""
    from mcap.reader import SeekingReader
    from mcap.records import Metadata

    from gateway.log.scan import check_footer, scan

    if not check_footer(path)[0]:
        found: dict[str, dict[str, str]] = {}

        def keep(rec) -> None:
            if isinstance(rec, Metadata):
                found.setdefault(rec.name, dict(rec.metadata))

        scan(path, on_record=keep)
        return found
    with open(path, "rb") as f:
        return {m.name: dict(m.metadata) for m in SeekingReader(f).iter_metadata()}


def analyze_session(path: str | os.PathLike[str], *, thrusters: bool = True) -> SessionFeatures:
    """Read one session log and identify its friction, efficiencies and sensor checks. A log cut
    short (a killed recorder, a full disk) or damaged is analysed from what is intact in it, as
    ``bsc replay`` does, with a note; one that is not an MCAP log at all raises AnalysisError.
    ``thrusters``: also look for thruster faults within the session (:mod:`.fdi`; needs the raw
    CAN frames, a note says when the log has none)."""
    from gateway.log.errors import LogError
    from gateway.log.reader import readable

    path = Path(path)
    notes: list[str] = []
    try:
        with readable(path, warn=notes.append) as src:
            feats = _analyze_file(path, Path(src))
            if thrusters:
                from .fdi import NoRawFrames, analyze_thrusters

                try:
                    found = analyze_thrusters(src)
                except NoRawFrames:
                    pass                      # a log of efforts only: the per-axis figures are all there is
                except AnalysisError as exc:
                    feats.notes.append(f"{path}: thruster faults not checked: {exc}")
                else:
                    feats.thruster_faults = [a.to_json() for a in found.alarms]
    except (LogError, OSError) as exc:
        raise AnalysisError(str(exc) if str(exc).startswith(str(path)) else f"{path}: {exc}") from None
    feats.notes.extend(n.replace("replaying", "analysing") for n in notes)
    return feats


def _analyze_file(path: Path, src: Path) -> SessionFeatures:
    """:func:`analyze_session` of the complete log ``src`` (``path`` itself, or its recovered copy)."""
    from gateway.log.errors import McapFileError
    from gateway.log.reader import read_messages

    try:
        meta = read_metadata(src)
    except Exception as exc:  # noqa: BLE001 - any reader failure means: not a readable log
        raise AnalysisError(f"{path}: not a readable MCAP log ({exc})") from None
    joint_rows: dict[str, list] = {}
    bias_rows: dict[str, list] = {}
    touch: dict[str, dict[str, float]] = {}
    arm_joints: dict[str, list[str]] = {}
    thr_rows: list = []
    health: dict[str, dict[str, float]] = {}
    robot = ""
    start = end = None
    counts = {"joint_efforts": 0, "thruster_efforts": 0, "not_good": 0, "stale_command": 0}
    wanted = (JOINT_SCHEMA, THRUSTER_SCHEMA, DEVICE_HEALTH_SCHEMA, BUS_HEALTH_SCHEMA)
    try:
        topics = _topics_with_schemas(src, wanted)
        for m in (read_messages(src, topics) if topics else ()):
            start = m.log_time_ns if start is None else start
            end = m.log_time_ns
            d = m.data
            if m.schema_name == JOINT_SCHEMA:
                robot = robot or _robot_of(m.topic)
                counts["joint_efforts"] += 1
                if d["good"] and len(d.get("ft_bias") or ()) == 6:
                    bias_rows.setdefault(d["arm"], []).append(d["ft_bias"])
                _contact(touch, d)
                if not d["good"] or not d["commanded_nm"]:
                    counts["not_good"] += 1
                    continue
                if abs(d["t_ns"] - d["commanded_t_ns"]) > COMMAND_MAX_AGE_NS:
                    counts["stale_command"] += 1
                    continue
                arm_joints.setdefault(d["arm"], list(d["joints"]))
                joint_rows.setdefault(d["arm"], []).append(
                    (*d["commanded_nm"], *d["full_nm"], *d["rate_rad_s"]))
            elif m.schema_name == THRUSTER_SCHEMA:
                robot = robot or _robot_of(m.topic)
                counts["thruster_efforts"] += 1
                if not d["good"]:
                    counts["not_good"] += 1
                    continue
                if d["commanded_t_ns"] == 0 or abs(d["t_ns"] - d["commanded_t_ns"]) > COMMAND_MAX_AGE_NS * 4:
                    counts["stale_command"] += 1
                    continue
                thr_rows.append((*d["force_n"], *d["moment_nm"], *d["commanded_force_n"],
                                 *d["commanded_moment_nm"], d["valves"], d["t_ns"]))
            elif m.schema_name == DEVICE_HEALTH_SCHEMA:
                h = health.setdefault(f"device/{d['device']}", {})
                h["samples"] = d["samples"]
                h["lost"] = d["lost"]
                h["loss_rate"] = d["lost"] / max(1, d["samples"] + d["lost"])
                h["stale"] = float(d["stale"])
            elif m.schema_name == BUS_HEALTH_SCHEMA:
                h = health.setdefault(f"bus/{d['bus']}", {})
                h["load_max"] = max(h.get("load_max", 0.0), d["load"])
    except McapFileError as exc:
        raise AnalysisError(str(exc)) from None
    if start is None or (not joint_rows and not thr_rows):
        raise AnalysisError(f"{path}: no JointEfforts or ThrusterEffort messages (was the estimator running?)")
    series = meta.get("bsc.series", {})
    index = int(series["session_index"]) if series.get("session_index", "").isdigit() else None
    feats = SessionFeatures(str(path), robot or meta.get("bsc.session", {}).get("robot", ""), index,
                            int(start), int(end), arms=arm_joints, health=health, metadata=meta, counts=counts)
    feats.contacts = {arm: {k: v for k, v in c.items() if not k.startswith("_")} for arm, c in touch.items()
                      if c["count"]}
    for arm, rows in bias_rows.items():
        if len(rows) >= 2 * MIN_BIAS_SAMPLES:
            feats.ft_bias[arm] = [float(v) for v in np.mean(np.asarray(rows[len(rows) // 2:], dtype=float), axis=0)]
    for arm, rows in joint_rows.items():
        a = np.asarray(rows, dtype=float)
        n = len(arm_joints[arm])
        cmd, est, rate = a[:, :n], a[:, n:2 * n], a[:, 2 * n:3 * n]
        for i, name in enumerate(arm_joints[arm]):
            feats.joints[name] = fit_friction(cmd[:, i] - est[:, i], rate[:, i], name)
    if thr_rows:
        a = np.asarray(thr_rows, dtype=float)
        quiet = quiet_mask(a[:, 12].astype(np.int64), a[:, 13].astype(np.int64))
        for i, axis in enumerate(AXES):
            fit = fit_efficiency(a[:, i], a[:, 6 + i], axis)
            if quiet.sum() >= MIN_QUIET_SAMPLES:
                fit = replace(fit, quiet_offset=float(np.mean(a[quiet, i])), quiet_samples=int(quiet.sum()))
            feats.axes[axis] = fit
    return feats


def _contact(touch: dict[str, dict[str, float]], d: dict) -> None:
    """One JointEfforts message into its arm's contact tally: a contact begins where the published
    contact wrench appears; it lasts over the consecutive messages that carry one."""
    c = touch.setdefault(d["arm"], {"count": 0, "seconds": 0.0, "max_force_n": 0.0, "_in": 0.0, "_t": 0.0})
    w = d.get("contact") or ()
    t = d["t_ns"] * 1e-9
    if len(w) == 6:
        if c["_in"]:
            c["seconds"] += t - c["_t"]
        else:
            c["count"] += 1
        c["_in"] = 1.0
        c["max_force_n"] = max(c["max_force_n"], math.hypot(w[0], w[1], w[2]))
    else:
        c["_in"] = 0.0
    c["_t"] = t


def quiet_mask(valves: np.ndarray, t_ns: np.ndarray, guard_ns: int = QUIET_GUARD_NS) -> np.ndarray:
    """Samples with every valve closed from ``guard_ns`` before to ``guard_ns`` after (the
    estimate's filters have settled): there the thruster wrench is zero by construction."""
    closed = valves == 0
    if not closed.any():
        return closed
    # time of the nearest firing sample before and after each sample
    fire_t = t_ns[~closed]
    if fire_t.size == 0:
        return closed
    i = np.searchsorted(fire_t, t_ns)
    before = np.where(i > 0, t_ns - fire_t[np.maximum(i - 1, 0)], np.iinfo(np.int64).max)
    after = np.where(i < fire_t.size, fire_t[np.minimum(i, fire_t.size - 1)] - t_ns, np.iinfo(np.int64).max)
    return closed & (before > guard_ns) & (after > guard_ns)


def _robot_of(topic: str) -> str:
    parts = topic.split("/")
    return parts[1] if len(parts) > 2 and parts[0] == "bsc" else ""


def session_order_key(path: str | os.PathLike[str]) -> tuple:
    """Sort key of a session file: series index, else first log time, else name."""
    try:
        meta = read_metadata(path)
    except Exception:  # noqa: BLE001 - unreadable files sort last, analyze reports them
        return (2, 0, str(path))
    series = meta.get("bsc.series", {})
    if series.get("start_ns", "").isdigit():
        return (0, int(series["start_ns"]), str(path))
    start = meta.get("bsc.recording", {}).get("session_start_utc", "")
    return (1, start, str(path))


def dumps(feats: SessionFeatures) -> str:
    return json.dumps(feats.to_json(), allow_nan=True)
