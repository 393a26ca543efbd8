"""Scenario files: TOML that selects robot, task, friction, thrusters, noise, degradations, seed.

Every scenario is read over the packaged default (``scenarios/capture.toml``): a file only states
what differs. Unknown keys and wrong types are errors that name the key, so a typo never
silently runs the default.
"""
from __future__ import annotations

import copy
import tomllib
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

from simulator.errors import SimulatorError

SCENARIO_DIR = Path(__file__).parent / "scenarios"
BUILTIN = {p.stem: p for p in sorted(SCENARIO_DIR.glob("*.toml"))}
DEFAULT = "capture"
# the flight software's tasks (controller.task): the paper's capture, or a thruster checkout
TASKS = ("capture", "checkout")

DEGRADE_KINDS = {
    "friction_growth": {"joint": str, "onset_s": float, "to_fraction": float, "ramp_s": float},
    "thruster_loss": {"thruster": int, "onset_s": float, "factor": float},
    "thruster_stuck": {"thruster": int, "onset_s": float, "state": str},
    "thruster_leak": {"thruster": int, "onset_s": float, "factor": float},
    "thruster_misalign": {"thruster": int, "onset_s": float, "angle_deg": float},
    "ft_bias_drift": {"arm": str, "onset_s": float, "force_n_per_s": list, "torque_nm_per_s": list},
}
# keys whose value is a free-form table (not checked against the default)
# (the default file may leave them out); ``faults`` is checked by simulator.firmware.Faults
FREE_TABLES = {"friction.per_joint", "thrusters.pwpfm", "faults"}
# keys whose value is an array of tables ([[...]] rows); thrusters.custom is checked row by row
# by robot_description.thrusters, which the gateway shares
ARRAYS_OF_TABLES = {"thrusters.custom"}


class ScenarioError(SimulatorError, ValueError):
    """The scenario file cannot be read or has an invalid key or value."""


@dataclass(frozen=True)
class Scenario:
    """A validated scenario. ``cfg`` mirrors the TOML tables as attributes (``cfg.noise.ft.rate_hz``)."""

    name: str
    text: str            # the user's file as written (logs carry it)
    data: dict           # merged over the defaults
    cfg: SimpleNamespace

    @property
    def duration_s(self) -> float:
        return float(self.data["duration_s"])

    @property
    def seed(self) -> int:
        return int(self.data["seed"])

    @property
    def robot(self) -> str:
        return str(self.data["robot"])

    def replace(self, **changes) -> "Scenario":
        """A copy with dotted keys changed, e.g. ``replace(**{"friction.coulomb_fraction": 0})``."""
        data = copy.deepcopy(self.data)
        for dotted, value in changes.items():
            node = data
            *path, last = dotted.split(".")
            for k in path:
                node = node[k]
            if last not in node:
                raise ScenarioError(f"no scenario key {dotted!r}")
            node[last] = value
        return _build(self.name, self.text, data)


def _defaults() -> dict:
    return tomllib.loads(BUILTIN[DEFAULT].read_text())


def load(scenario: str | Path | None = None, overrides: dict | None = None) -> Scenario:
    """A built-in scenario name (``capture``...) or a TOML path, merged over the defaults."""
    scenario = DEFAULT if scenario is None else scenario
    if str(scenario) in BUILTIN:
        path = BUILTIN[str(scenario)]
    else:
        path = Path(scenario)
        if not path.is_file():
            raise ScenarioError(f"no such scenario: {scenario!s} (built-in: {', '.join(BUILTIN)}; or a .toml path)")
    text = path.read_text()
    try:
        user = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{path}: not valid TOML: {exc}") from exc
    thrusters = user.get("thrusters")
    if isinstance(thrusters, dict) and "custom" in thrusters and "layout" in thrusters:
        raise ScenarioError(f"{path}: [thrusters] has both layout = {thrusters['layout']!r} and "
                            "[[thrusters.custom]] rows; give one")
    data = _merge(_defaults(), user, "")
    # A file placed next to a custom URDF may name it relatively.
    robot = data.get("robot", "")
    if robot.endswith(".urdf") and not Path(robot).is_absolute():
        data["robot"] = str((path.parent / robot).resolve())
    if "name" not in user:              # (the default file's name is "capture")
        data["name"] = path.stem
    sc = _build(str(data.get("name") or path.stem), text, data)
    return sc.replace(**overrides) if overrides else sc


def _merge(base: dict, user: dict, where: str) -> dict:
    out = copy.deepcopy(base)
    for key, value in user.items():
        dotted = f"{where}{key}"
        if key in ("degrade", "contact") and not where:
            out[key] = value
            continue
        if dotted in ARRAYS_OF_TABLES:
            if not isinstance(value, list) or not all(isinstance(row, dict) for row in value):
                raise ScenarioError(f"scenario key {dotted!r} must be an array of tables ([[{dotted}]] rows)")
            out[key] = value
        elif dotted in FREE_TABLES:
            if not isinstance(value, dict):
                raise ScenarioError(f"scenario key {dotted!r} must be a table")
            out[key] = value
        elif key not in base:
            raise ScenarioError(f"unknown scenario key {dotted!r}")
        elif isinstance(base[key], dict):
            if not isinstance(value, dict):
                raise ScenarioError(f"scenario key {dotted!r} must be a table")
            out[key] = _merge(base[key], value, dotted + ".")
        else:
            out[key] = _coerce(dotted, base[key], value)
    return out


def _coerce(dotted: str, default, value):
    if isinstance(default, bool) or isinstance(value, bool):
        if not isinstance(value, bool) or not isinstance(default, bool):
            raise ScenarioError(f"scenario key {dotted!r} must be {type(default).__name__}")
        return value
    if isinstance(default, (int, float)) and isinstance(value, (int, float)):
        return float(value) if isinstance(default, float) else value
    if isinstance(default, list) and isinstance(value, list):
        return value
    if isinstance(default, str) and isinstance(value, str):
        return value
    raise ScenarioError(f"scenario key {dotted!r} must be {type(default).__name__}, got {value!r}")


def _check_degrade(items) -> None:
    if not isinstance(items, list):
        raise ScenarioError("'degrade' must be an array of tables ([[degrade]])")
    for i, d in enumerate(items):
        kind = d.get("kind")
        if kind not in DEGRADE_KINDS:
            raise ScenarioError(f"degrade[{i}]: kind must be one of {', '.join(DEGRADE_KINDS)}, got {kind!r}")
        want = DEGRADE_KINDS[kind]
        for k in d:
            if k != "kind" and k not in want:
                raise ScenarioError(f"degrade[{i}] ({kind}): unknown key {k!r}")
        for k in want:
            if k not in d:
                raise ScenarioError(f"degrade[{i}] ({kind}): missing key {k!r}")


def _ns(obj):
    if isinstance(obj, dict):
        return SimpleNamespace(**{k: _ns(v) for k, v in obj.items()})
    return obj


def _check_thrusters(table: dict) -> None:
    """The layout's rows, and that it can push the spacecraft both ways along and about every
    axis: the flight software holds the base's pose with the thrusters alone."""
    from robot_description.thrusters import ThrusterLayout, ThrusterLayoutError

    try:
        layout = ThrusterLayout.from_config(table)
    except ThrusterLayoutError as exc:
        raise ScenarioError(str(exc)) from None
    missing = layout.uncontrollable()
    if not missing:
        return
    where = "thrusters.custom" if "custom" in table else f"thrusters.layout {table['layout']!r}"
    if layout.n < 7:
        raise ScenarioError(f"{where}: {layout.n} thruster(s) cannot control the spacecraft's 6 degrees of "
                            "freedom: thrust only pushes, so it takes at least 7 (ring18 has 18)")
    raise ScenarioError(f"{where}: no combination of the {layout.n} thrusters gives {', '.join(missing)} (thrust "
                        "only pushes: every axis needs thrusters pushing each way, for force and for moment)")


def _build(name: str, text: str, data: dict) -> Scenario:
    _check_degrade(data.get("degrade", []))
    _check_thrusters(data["thrusters"])
    if data["duration_s"] <= 0:
        raise ScenarioError("duration_s must be positive")
    ctrl = data["controller"]
    if ctrl["task"] not in TASKS:
        raise ScenarioError(f"controller.task must be one of {', '.join(TASKS)}, got {ctrl['task']!r}")
    for key in ("probe_force_n", "probe_moment_nm"):
        if not 0.0 <= ctrl[key] < float("inf"):
            raise ScenarioError(f"controller.{key} must be a size >= 0, got {ctrl[key]!r}")
    if not 0.0 < ctrl["probe_dwell_s"] < float("inf"):
        raise ScenarioError(f"controller.probe_dwell_s must be positive, got {ctrl['probe_dwell_s']!r}")
    if "faults" in data:
        from simulator.firmware import Faults, FirmwareError

        try:
            Faults.from_table(data["faults"])
        except (FirmwareError, TypeError) as exc:
            raise ScenarioError(str(exc)) from None
    return Scenario(name=name, text=text, data=data, cfg=_ns(data))
