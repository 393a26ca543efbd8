"""Across sessions: baselines, CUSUM change detection, and attribution to actuator, thruster or sensor.

Every tracked quantity (a *metric* of a *target*: the Coulomb friction of ``arm0/j2``, the
efficiency of axis ``mz``...) is a series ``x_0, x_1, ...`` in session order. Its baseline is the
mean ``mu`` of the first ``baseline_sessions`` identifiable sessions, and its scale
``sigma = max(std, floor_abs, floor_rel * |mu|)``: three sessions cannot estimate a spread, so
the floors (documented in docs/monitoring.md, set in the rules file) keep the detector from
alarming on the natural session-to-session scatter. Then, with ``z = (x - mu) / sigma``, the
one- or two-sided CUSUM::

    S+_k = max(0, S+_{k-1} + z_k - k_ref)        (direction "up" or "both")
    S-_k = max(0, S-_{k-1} - z_k - k_ref)        (direction "down" or "both")

alarms when ``S > h``. An alarm clears once ``|z| <= clear_z`` for ``clear_sessions`` sessions
in a row (the CUSUM itself would remember a long fault for as many sessions), then restarts. ``k_ref`` is half the shift
(in sigmas) the detector is tuned for; ``h`` trades delay for false alarms (with ``k_ref = 0.5``
and ``h = 5`` the in-control average run length is about 900 sessions one-sided).

Attribution uses the structure of the faults (docs/method.md):

- friction acts with ``sign(dq)`` on ONE joint: a Coulomb alarm -> ``actuator`` on that joint;
- a thruster loss scales the delivered wrench: an efficiency DROP on an axis -> ``thruster``;
- an F/T bias ``b`` on arm j adds ``A_tau(q) b`` to the residual of EVERY joint of arm j,
  whatever the direction of motion, so it shows in the residual's offset, not in its Coulomb
  part; and it adds a constant wrench to the thruster estimate, visible while no thruster fires
  (momentum inconsistency between F/T sensors and IMU): an offset alarm on a joint -> ``sensor``
  on its arm's F/T (target ``<arm>``); a momentum alarm with no arm offset -> ``sensor`` ``imu``.
  Over a task the pose correlates with the direction of motion, so part of ``A_tau(q) b`` leaks
  into the Coulomb fit; a Coulomb change small next to the arm's offset change (:data:`LEAK_RATIO`)
  is counted as the bias's, not as friction.
- with the joint filter (docs/estimator.md, section 2b) the gateway estimates each F/T sensor's
  bias and takes it out of the joint torques, so the offsets stay put and the bias itself is
  tracked: a component of an arm's F/T bias off its baseline (``ft_bias_n``, ``ft_bias_nm``,
  targets ``<arm>/fx`` .. ``<arm>/mz``) -> ``sensor`` on that arm.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .session import FT_AXES, SessionFeatures


@dataclass(frozen=True)
class Detector:
    """How one metric is watched across sessions (the ``[[analysis.detector]]`` table)."""

    name: str                  # rule name, reported in alerts
    metric: str                # coulomb_nm | efficiency | offset_nm | quiet_offset | ft_bias_n | ft_bias_nm
    kind: str                  # actuator | thruster | sensor
    direction: str = "both"    # up | down | both
    floor_abs: float = 0.0
    floor_rel: float = 0.0
    k_ref: float = 0.5
    h: float = 5.0
    critical_z: float = 10.0   # |z| at or above this: severity critical, else warning
    clear_z: float = 2.0       # an alarm clears once |z| <= clear_z ...
    clear_sessions: int = 2    # ... for this many sessions in a row (then the CUSUM restarts)
    severity: str = "warning"
    description: str = ""


DEFAULT_DETECTORS = (
    Detector("friction-change", "coulomb_nm", "actuator", "up", 2.0, 0.03,
             description="Coulomb friction of a joint above its baseline"),
    Detector("thruster-efficiency-drop", "efficiency", "thruster", "down", 0.02, 0.0,
             description="delivered / commanded wrench on a thruster axis below its baseline"),
    Detector("ft-offset", "offset_nm", "sensor", "both", 2.0, 0.02,
             description="direction-independent joint torque residual (F/T bias) off its baseline"),
    Detector("momentum-inconsistency", "quiet_offset", "sensor", "both", 5.0, 0.0,
             description="thruster wrench estimate with no thruster firing (F/T vs IMU) off its baseline"),
    Detector("ft-bias-force", "ft_bias_n", "sensor", "both", 1.0, 0.0,
             description="a force component of an arm's F/T bias (the joint filter's estimate) off its baseline"),
    Detector("ft-bias-moment", "ft_bias_nm", "sensor", "both", 1.0, 0.0,
             description="a moment component of an arm's F/T bias (the joint filter's estimate) off its baseline"),
)

METRICS = ("coulomb_nm", "efficiency", "offset_nm", "quiet_offset", "ft_bias_n", "ft_bias_nm")
"""What a detector may watch (the rules file's ``metric``)."""


@dataclass
class Track:
    """One metric of one target across sessions: values, z, CUSUM, alarm flags."""

    detector: Detector
    target: str
    values: list[float] = field(default_factory=list)
    z: list[float] = field(default_factory=list)
    s_up: list[float] = field(default_factory=list)
    s_down: list[float] = field(default_factory=list)
    alarm: list[bool] = field(default_factory=list)
    mu: float = float("nan")
    sigma: float = float("nan")
    baseline_n: int = 0

    def first_alarm(self) -> int | None:
        return next((i for i, a in enumerate(self.alarm) if a), None)


def cusum_track(det: Detector, target: str, values, baseline_sessions: int = 3) -> Track:
    """Baseline, z and CUSUM of one series (NaN = not identifiable in that session: skipped)."""
    tr = Track(det, target, [float(v) for v in values])
    base = [v for v in tr.values if math.isfinite(v)][:baseline_sessions]
    tr.baseline_n = len(base)
    if base:
        tr.mu = float(np.mean(base))
        spread = float(np.std(base, ddof=1)) if len(base) > 1 else 0.0
        tr.sigma = max(spread, det.floor_abs, det.floor_rel * abs(tr.mu), 1e-12)
    up = down = 0.0
    seen = normal = 0
    alarmed = False
    for v in tr.values:
        ok = math.isfinite(v) and tr.baseline_n > 0
        z = (v - tr.mu) / tr.sigma if ok else float("nan")
        if ok:
            seen += 1
        # the baseline sessions define "normal": no alarm while still inside them
        if ok and seen > baseline_sessions:
            if det.direction in ("up", "both"):
                up = max(0.0, up + z - det.k_ref)
            if det.direction in ("down", "both"):
                down = max(0.0, down - z - det.k_ref)
            if not alarmed:
                alarmed = max(up, down) > det.h
                normal = 0
            else:
                # the CUSUM remembers a long fault for long: clear on the values instead, once
                # they are back within clear_z sigmas for clear_sessions sessions, then restart
                normal = normal + 1 if abs(z) <= det.clear_z else 0
                if normal >= det.clear_sessions:
                    alarmed, up, down = False, 0.0, 0.0
        tr.z.append(z)
        tr.s_up.append(up)
        tr.s_down.append(down)
        tr.alarm.append(alarmed)
    return tr


@dataclass(frozen=True)
class Finding:
    """One alert of ``bsc analyze``: a detector's alarm began (``raised``) or ended (``cleared``)."""

    session: str
    session_index: int           # position in the analysed order
    kind: str
    target: str
    rule: str
    severity: str
    state: str
    since_session: str
    message: str
    evidence: dict

    def to_json(self) -> dict:
        return {"session": self.session, "session_index": self.session_index, "kind": self.kind,
                "target": self.target, "rule": self.rule, "severity": self.severity, "state": self.state,
                "since_session": self.since_session, "message": self.message,
                "evidence": {k: _round(v) for k, v in self.evidence.items()}}


def _round(v):
    if isinstance(v, float):
        return round(v, 6) if math.isfinite(v) else None
    return v


@dataclass
class SeriesResult:
    sessions: list[SessionFeatures]
    tracks: list[Track]
    findings: list[Finding]


def build_tracks(sessions: list[SessionFeatures], detectors=DEFAULT_DETECTORS,
                 baseline_sessions: int = 3) -> list[Track]:
    tracks = []
    for det in detectors:
        if det.metric in ("coulomb_nm", "offset_nm"):
            targets = sorted({t for s in sessions for t in s.joints})
            for t in targets:
                vals = [_joint_value(s, t, det.metric) for s in sessions]
                tracks.append(cusum_track(det, t, vals, baseline_sessions))
        elif det.metric in ("efficiency", "quiet_offset"):
            targets = [a for a in ("fx", "fy", "fz", "mx", "my", "mz") if any(a in s.axes for s in sessions)]
            for t in targets:
                vals = [_axis_value(s, t, det.metric) for s in sessions]
                tracks.append(cusum_track(det, t, vals, baseline_sessions))
        elif det.metric in ("ft_bias_n", "ft_bias_nm"):
            comps = range(3) if det.metric == "ft_bias_n" else range(3, 6)
            for arm in sorted({a for s in sessions for a in s.ft_bias}):
                for i in comps:
                    vals = [s.ft_bias[arm][i] if arm in s.ft_bias else float("nan") for s in sessions]
                    tracks.append(cusum_track(det, f"{arm}/{FT_AXES[i]}", vals, baseline_sessions))
        else:
            raise ValueError(f"detector {det.name}: unknown metric {det.metric!r}")
    return tracks


def _joint_value(s: SessionFeatures, t: str, metric: str) -> float:
    j = s.joints.get(t)
    return getattr(j, metric) if j is not None and j.identifiable else float("nan")


def _axis_value(s: SessionFeatures, t: str, metric: str) -> float:
    a = s.axes.get(t)
    if a is None:
        return float("nan")
    if metric == "efficiency" and not a.identifiable:
        return float("nan")
    return getattr(a, metric)


def attribute(sessions: list[SessionFeatures], tracks: list[Track]) -> list[Finding]:
    """Alarms -> findings with kind and target, raised when an attributed alarm begins and
    cleared when it ends."""
    n = len(sessions)
    arm_of = {j: arm for s in sessions for arm, js in s.arms.items() for j in js}
    findings: list[Finding] = []
    active: dict[tuple[str, str, str], int] = {}     # (kind, target, rule) -> since session
    for k in range(n):
        now: dict[tuple[str, str, str], tuple[Track, list[Track]]] = {}
        for tr in tracks:
            if not tr.alarm[k]:
                continue
            det = tr.detector
            if det.metric == "coulomb_nm":
                now.setdefault(("actuator", tr.target, det.name), (tr, []))[1].append(tr)
            elif det.metric == "efficiency":
                if tr.z[k] < 0:
                    now.setdefault(("thruster", tr.target, det.name), (tr, []))[1].append(tr)
            elif det.metric in ("offset_nm", "ft_bias_n", "ft_bias_nm"):
                # one finding per F/T sensor, whichever of its indicators alarms (the rule of
                # the one that raised it stays while it is active)
                arm = (arm_of.get(tr.target, tr.target.split("/")[0]) if det.metric == "offset_nm"
                       else tr.target.rsplit("/", 1)[0])
                key = next((k for k in (*active, *now) if k[0] == "sensor" and k[1] == arm), ("sensor", arm, det.name))
                now.setdefault(key, (tr, []))[1].append(tr)
        momentum = [tr for tr in tracks if tr.detector.metric == "quiet_offset" and tr.alarm[k]]
        if momentum:
            arms = [key for key in now if key[0] == "sensor"]
            if arms:       # supporting evidence for the arm's F/T fault
                for key in arms:
                    now[key][1].extend(momentum)
            else:
                now[("sensor", "imu", momentum[0].detector.name)] = (momentum[0], momentum)
        _explain_by_bias(now, k, arm_of)
        for key, (lead, group) in sorted(now.items()):
            if key not in active:
                active[key] = k
                findings.append(_finding(sessions, k, key, lead, group, "raised", k))
        for key in [key for key in active if key not in now]:
            since = active.pop(key)
            lead = next(tr for tr in tracks if tr.detector.name == key[2])
            findings.append(_finding(sessions, k, key, lead, [], "cleared", since))
    return findings


LEAK_RATIO = 0.25
"""A Coulomb change on a joint of an arm whose F/T sensor is in alarm, smaller than this fraction
of the arm's largest offset change, is the bias leaking into the friction fit (the pose, hence
``A_tau(q) b``, correlates with the direction of motion over a task): reported as evidence of
the sensor fault, not as an actuator fault. Measured leak in the ft-bias-drift series: 0.08-0.12."""


def _explain_by_bias(now: dict, k: int, arm_of: dict) -> None:
    for key in [key for key in now if key[0] == "actuator"]:
        arm = arm_of.get(key[1], key[1].split("/")[0])
        sensor = next((sk for sk in now if sk[0] == "sensor" and sk[1] == arm), None)
        if sensor is None:
            continue
        fric = now[key][0]
        offsets = [tr for tr in now[sensor][1] if tr.detector.metric == "offset_nm"]
        shift = max((abs(tr.values[k] - tr.mu) for tr in offsets if math.isfinite(tr.values[k])), default=0.0)
        dfc = abs(fric.values[k] - fric.mu)
        if shift > 0 and dfc < LEAK_RATIO * shift:
            now[sensor][1].append(fric)
            del now[key]


def _finding(sessions, k, key, lead: Track, group: list[Track], state: str, since: int) -> Finding:
    kind, target, rule = key
    ev: dict = {}
    worst = 0.0
    for tr in group:
        m = tr.detector.metric
        ev[f"{tr.target}.{m}"] = tr.values[k]
        ev[f"{tr.target}.{m}.baseline"] = tr.mu
        ev[f"{tr.target}.{m}.sigma"] = tr.sigma
        ev[f"{tr.target}.{m}.z"] = tr.z[k]
        ev[f"{tr.target}.{m}.cusum"] = max(tr.s_up[k], tr.s_down[k])
        worst = max(worst, abs(tr.z[k]) if math.isfinite(tr.z[k]) else 0.0)
    if group:
        ev["threshold_h"] = lead.detector.h
        ev["k_ref"] = lead.detector.k_ref
    sev = ("critical" if worst >= lead.detector.critical_z else lead.detector.severity) if state == "raised" else "info"
    biases = [tr for tr in group if tr.detector.metric in ("ft_bias_n", "ft_bias_nm")]
    if kind == "sensor" and biases:
        moved = ", ".join(f"{tr.target.rsplit('/', 1)[1]} {tr.values[k]:+.2f} (baseline {tr.mu:+.2f})"
                          for tr in biases if math.isfinite(tr.values[k]))
        sensor = f"F/T sensor of {target}: bias moved, as the joint filter estimates it: {moved} N / N m"
    elif lead.detector.metric in ("ft_bias_n", "ft_bias_nm"):
        sensor = f"F/T sensor of {target}: bias (the joint filter's estimate) off its baseline"
    else:
        sensor = f"F/T sensor of {target}: bias (joint residual offsets moved, friction did not)"
    what = {"actuator": f"joint {target}: Coulomb friction changed",
            "thruster": f"thruster axis {target}: efficiency dropped",
            "sensor": (sensor if target != "imu"
                       else "IMU vs F/T sensors: momentum inconsistency while no thruster fired")}[kind]
    if kind == "actuator" and group:
        tr = group[0]
        what += f" to {tr.values[k]:.1f} N m (baseline {tr.mu:.1f} N m)"
    if kind == "thruster" and group:
        tr = group[0]
        what += f" to {tr.values[k]:.3f} (baseline {tr.mu:.3f})"
    msg = what if state == "raised" else f"cleared: {what}"
    return Finding(sessions[k].name, k, kind, target, rule, sev, state, sessions[since].name, msg, ev)


THRUSTER_FAULT_RULE = "thruster-fault"
"""The rule name of thruster faults found within one session (gateway/analysis/fdi.py)."""


def session_findings(sessions: list[SessionFeatures]) -> list[Finding]:
    """Thruster faults found within each session (no baseline): one raised finding each, a stuck
    valve critical, a partial loss, a leak or a misalignment a warning."""
    from gateway.estimator.fdi import size_text

    out = []
    for k, s in enumerate(sessions):
        for a in s.thruster_faults:
            sev = "critical" if a["fault"] in ("stuck open", "stuck closed") else "warning"
            msg = (f"thruster {a['thruster']}: {a['fault']}, named {a['t_s']:.2f} s into the session "
                   f"({size_text(a['fault'], a['theta'])})")
            ev = {key: a[key] for key in ("fault", "t_s", "detected_t_s", "theta", "stat", "window", "efficiency")}
            out.append(Finding(s.name, k, "thruster", a["target"], THRUSTER_FAULT_RULE, sev, "raised", s.name, msg, ev))
    return out


def analyze_series(sessions: list[SessionFeatures], detectors=DEFAULT_DETECTORS,
                   baseline_sessions: int = 3) -> SeriesResult:
    tracks = build_tracks(sessions, detectors, baseline_sessions)
    findings = attribute(sessions, tracks)
    within = session_findings(sessions)
    if within:
        findings = sorted(findings + within, key=lambda f: f.session_index)
    return SeriesResult(sessions, tracks, findings)
