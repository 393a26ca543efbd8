"""Alert rules: thresholds with hysteresis, hold times and severity, read from a TOML file.

The file format is documented in the shipped default, ``gateway/rules/default.toml`` (and
docs/monitoring.md). :class:`RuleEngine` turns metric updates into :class:`~gateway.efforts.Alert`
transitions. Per ``(robot, rule, target)`` a small state machine::

    ok --(value beyond raise)--> pending --(held hold_s)--> RAISED --(value back beyond clear)-->
    clearing --(held clear_hold_s)--> ok (CLEARED)

A value between ``clear`` and ``raise`` keeps the current state (hysteresis); a pending raise
that falls back resets, as does a clearing that goes bad again. ``since_ns`` of an alert is when
the value first crossed ``raise`` (so the hold time is part of the evidence, not hidden).
"""
from __future__ import annotations

import fnmatch
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from gateway.errors import GatewayError
from gateway.efforts import Alert

DEFAULT_RULES = Path(__file__).resolve().parent.parent / "rules" / "default.toml"
KINDS = ("actuator", "thruster", "sensor")
SEVERITIES = ("info", "warning", "critical")
LIVE_METRICS = ("friction_nm", "friction_fraction", "residual_nm", "efficiency", "residual",
                "staleness_s", "loss_rate", "bus_load")


class RulesError(GatewayError, ValueError):
    """A rules file that cannot be read, or a rule with a bad key or value."""


@dataclass(frozen=True)
class Rule:
    name: str
    kind: str
    metric: str
    raise_level: float
    clear_level: float
    above: bool = True
    targets: str = "*"
    hold_s: float = 0.0
    clear_hold_s: float = 0.0
    severity: str = "warning"

    def matches(self, kind: str, target: str) -> bool:
        return kind == self.kind and fnmatch.fnmatchcase(target, self.targets)

    def bad(self, value: float) -> bool:
        return value > self.raise_level if self.above else value < self.raise_level

    def good(self, value: float) -> bool:
        return value < self.clear_level if self.above else value > self.clear_level


@dataclass(frozen=True)
class MonitorSettings:
    tau_s: float = 20.0
    min_weight_s: float = 2.0
    v_min_rad_s: float = 0.02


@dataclass(frozen=True)
class RuleSet:
    rules: tuple[Rule, ...]
    monitor: MonitorSettings = MonitorSettings()
    detectors: tuple = ()          # gateway.analysis.change.Detector, from [[analysis.detector]]
    baseline_sessions: int = 3
    path: str = ""


_RULE_KEYS = {"name": str, "kind": str, "metric": str, "targets": str, "above": bool, "raise": (int, float),
              "clear": (int, float), "hold_s": (int, float), "clear_hold_s": (int, float), "severity": str}
_DET_KEYS = {"name": str, "metric": str, "kind": str, "direction": str, "floor_abs": (int, float),
             "floor_rel": (int, float), "k_ref": (int, float), "h": (int, float), "critical_z": (int, float),
             "severity": str, "description": str, "clear_z": (int, float), "clear_sessions": int}


def _check(table: dict, allowed: dict, where: str, required: tuple[str, ...]) -> None:
    for k, v in table.items():
        if k not in allowed:
            raise RulesError(f"{where}: unknown key {k!r} (keys: {', '.join(allowed)})")
        want = allowed[k]
        if isinstance(v, bool) and want is not bool:
            raise RulesError(f"{where}: {k} must be a number or string, got {v!r}")
        if not isinstance(v, want):
            raise RulesError(f"{where}: {k} has the wrong type ({v!r})")
    for k in required:
        if k not in table:
            raise RulesError(f"{where}: missing key {k!r}")


def load_rules(path: str | Path | None = None) -> RuleSet:
    """Read a rules file (the shipped default when ``path`` is None)."""
    from gateway.analysis.change import METRICS, Detector

    path = Path(path) if path is not None else DEFAULT_RULES
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise RulesError(f"no rules file {path}") from None
    except tomllib.TOMLDecodeError as exc:
        raise RulesError(f"{path}: not valid TOML: {exc}") from None
    unknown = set(data) - {"monitor", "rule", "analysis"}
    if unknown:
        raise RulesError(f"{path}: unknown table(s) {', '.join(sorted(unknown))}")
    mon = data.get("monitor", {})
    _check(mon, {"tau_s": (int, float), "min_weight_s": (int, float), "v_min_rad_s": (int, float)},
           f"{path} [monitor]", ())
    settings = MonitorSettings(**{k: float(v) for k, v in mon.items()})
    if settings.tau_s <= 0:
        raise RulesError(f"{path} [monitor]: tau_s must be positive")
    rules = []
    names = set()
    for i, r in enumerate(data.get("rule", [])):
        where = f"{path} rule[{i}]" + (f" ({r.get('name')})" if isinstance(r, dict) and "name" in r else "")
        if not isinstance(r, dict):
            raise RulesError(f"{where}: must be a table ([[rule]])")
        _check(r, _RULE_KEYS, where, ("name", "kind", "metric", "raise", "clear"))
        if r["kind"] not in KINDS:
            raise RulesError(f"{where}: kind must be one of {', '.join(KINDS)}")
        if r["metric"] not in LIVE_METRICS:
            raise RulesError(f"{where}: metric must be one of {', '.join(LIVE_METRICS)}")
        sev = r.get("severity", "warning")
        if sev not in SEVERITIES:
            raise RulesError(f"{where}: severity must be one of {', '.join(SEVERITIES)}")
        above = r.get("above", True)
        if (above and r["clear"] > r["raise"]) or (not above and r["clear"] < r["raise"]):
            raise RulesError(f"{where}: clear must be on the safe side of raise (hysteresis)")
        if r["name"] in names:
            raise RulesError(f"{where}: duplicate rule name {r['name']!r}")
        names.add(r["name"])
        rules.append(Rule(r["name"], r["kind"], r["metric"], float(r["raise"]), float(r["clear"]), above,
                          r.get("targets", "*"), float(r.get("hold_s", 0.0)), float(r.get("clear_hold_s", 0.0)),
                          sev))
    an = data.get("analysis", {})
    _check(an, {"baseline_sessions": int, "detector": list}, f"{path} [analysis]", ())
    detectors = []
    for i, d in enumerate(an.get("detector", [])):
        where = f"{path} analysis.detector[{i}]"
        _check(d, _DET_KEYS, where, ("name", "metric", "kind"))
        if d.get("direction", "both") not in ("up", "down", "both"):
            raise RulesError(f"{where}: direction must be up, down or both")
        if d["metric"] not in METRICS:
            raise RulesError(f"{where}: metric must be one of {', '.join(METRICS)}")
        detectors.append(Detector(**{k: (float(v) if isinstance(v, int) and k != "clear_sessions" else v)
                                     for k, v in d.items()}))
    baseline = an.get("baseline_sessions", 3)
    if baseline < 1:
        raise RulesError(f"{path} [analysis]: baseline_sessions must be at least 1")
    return RuleSet(tuple(rules), settings, tuple(detectors), baseline, str(path))


@dataclass
class _State:
    raised: bool = False
    pending_since: int | None = None     # first crossing of raise (while not raised)
    clearing_since: int | None = None
    since_ns: int = 0
    last_value: float = float("nan")


@dataclass
class RuleEngine:
    """Evaluates rules on metric updates; returns the alert transitions (raised / cleared)."""

    rules: tuple[Rule, ...]
    states: dict[tuple[str, str, str], _State] = field(default_factory=dict)

    def update(self, robot: str, kind: str, target: str, metric: str, value: float, t_ns: int,
               evidence: dict[str, float] | None = None) -> list[Alert]:
        out = []
        for rule in self.rules:
            if rule.metric != metric or not rule.matches(kind, target):
                continue
            st = self.states.setdefault((robot, rule.name, target), _State())
            st.last_value = value
            if value != value:       # NaN: no information, keep the state
                continue
            if not st.raised:
                if rule.bad(value):
                    if st.pending_since is None:
                        st.pending_since = t_ns
                    if t_ns - st.pending_since >= rule.hold_s * 1e9:
                        st.raised, st.since_ns, st.clearing_since = True, st.pending_since, None
                        out.append(self._alert(robot, rule, target, "raised", st.since_ns, t_ns, value, evidence))
                else:
                    st.pending_since = None
            else:
                if rule.good(value):
                    if st.clearing_since is None:
                        st.clearing_since = t_ns
                    if t_ns - st.clearing_since >= rule.clear_hold_s * 1e9:
                        st.raised, st.pending_since = False, None
                        out.append(self._alert(robot, rule, target, "cleared", st.since_ns, t_ns, value, evidence))
                        st.clearing_since = None
                else:
                    st.clearing_since = None
        return out

    def active(self) -> list[tuple[str, str, str]]:
        return [k for k, s in self.states.items() if s.raised]

    @staticmethod
    def _alert(robot, rule: Rule, target, state, since_ns, t_ns, value, evidence) -> Alert:
        cmp = ">" if rule.above else "<"
        if state == "raised":
            msg = f"{rule.kind} {target}: {rule.metric} = {value:.4g} {cmp} {rule.raise_level:g} for {rule.hold_s:g} s"
        else:
            msg = f"{rule.kind} {target}: {rule.metric} = {value:.4g} back past {rule.clear_level:g}"
        ev = [(rule.metric, float(value)), ("raise", rule.raise_level), ("clear", rule.clear_level),
              ("hold_s", rule.hold_s)]
        ev += [(k, float(v)) for k, v in sorted((evidence or {}).items()) if k != rule.metric]
        return Alert(robot=robot, kind=rule.kind, target=target, rule=rule.name,
                     severity=rule.severity if state == "raised" else "info", state=state,
                     since_ns=int(since_ns), t_ns=int(t_ns), message=msg, evidence=tuple(ev))
