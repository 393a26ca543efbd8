"""The gateway's configuration: one typed, frozen tree, read from a TOML file, flags over it.

``bsc gateway --config gateway.toml`` reads it; every flag of the command overrides its key; what
neither gives keeps the default documented here (:data:`DOCS`, one line per key). ``bsc gateway
--print-config`` prints the configuration a run would use, as TOML: save it and edit it.
``deploy/gateway.toml`` is that output for the defaults (a test keeps the two equal)::

    [can]          the robot's buses: interface, channels, bit rates, how frames are received
    [zenoh]        the zenoh session: a zenoh JSON5 file, mode, endpoints
    [robot]        the robot description, the gateway's model of it, the nominal thruster layout
    [service]      publication: health period, samples or not, backlog, bus reopening
    [drivers]      device timing: the frame clock's rate, when a silent device is stale
    [estimator]    the sync policy (gateway/estimator/core.py CoreSettings)
    [estimator.thrusters]   the thruster filter's noise figures and priors (ThrusterFilterSettings)
    [estimator.joints]      the joint filter's noise figures (JointFilterSettings)
    [recording]    the MCAP file the session is recorded to

Sections are frozen dataclasses; the estimator's are the estimator's own (``CoreSettings``,
``ThrusterFilterSettings``), so a default lives in one place. Paths in a file are relative to
the file. An unknown key, a wrong type or a value out of range is one :class:`ConfigError` that
names the file, the key and what is expected.
"""
from __future__ import annotations

import dataclasses
import json
import math
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivers.health import DEFAULT_STALE_PERIODS, SourceTiming
from gateway.errors import GatewayError
from gateway.estimator.core import CoreSettings

RECEIVE_MODES = ("auto", "direct", "threads")
DEFAULT_MAX_BACKLOG = 10_000         # frames waiting for the worker (all buses together)


class ConfigError(GatewayError, ValueError):
    """A configuration file or value that cannot be used: the file, the key and why."""


@dataclass(frozen=True)
class CanConfig:
    interface: str | None = None
    channels: tuple[str, ...] = ()
    fd: bool = False
    bitrate: int | None = None
    data_bitrate: int | None = None
    bus_kwargs: tuple[tuple[str, Any], ...] = ()
    receive: str = "auto"

    def __post_init__(self) -> None:
        if self.receive not in RECEIVE_MODES:
            raise ConfigError(f"receive must be one of {', '.join(RECEIVE_MODES)}, got {self.receive!r}")
        for name in ("bitrate", "data_bitrate"):
            value = getattr(self, name)
            if value is not None and not 0 < value <= 20_000_000:
                raise ConfigError(f"{name} {value!r}: whole bit/s up to 20 Mbit/s")
        for key, _ in self.bus_kwargs:
            if key in ("interface", "channel", "bustype"):
                raise ConfigError(f"bus_kwargs: {key} is a key of [can] itself")


@dataclass(frozen=True)
class ZenohConfig:
    config_file: Path | None = None
    mode: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    multicast_scouting: bool = False

    def __post_init__(self) -> None:
        if self.mode not in (None, "peer", "client", "router"):
            raise ConfigError(f"mode must be peer, client or router, got {self.mode!r}")


@dataclass(frozen=True)
class RobotConfig:
    description: str | None = None
    model: str | None = None
    thrusters: str | None = None


@dataclass(frozen=True)
class ServiceConfig:
    health_period_s: float = 0.5
    publish_samples: bool = True
    estimate: bool = True
    max_backlog: int = DEFAULT_MAX_BACKLOG
    retry_s: float = 0.5
    duration_s: float | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.health_period_s) and self.health_period_s > 0):
            raise ConfigError(f"health_period_s must be > 0, got {self.health_period_s!r}")
        if not (isinstance(self.max_backlog, int) and self.max_backlog >= 1):
            raise ConfigError(f"max_backlog must be a positive number of frames, got {self.max_backlog!r}")
        if not (math.isfinite(self.retry_s) and self.retry_s > 0):
            raise ConfigError(f"retry_s must be > 0, got {self.retry_s!r}")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ConfigError(f"duration_s must be > 0, got {self.duration_s!r}")


def _source_rate(value: Any, where: str) -> float | None:
    if isinstance(value, str) and value.strip().lower() == "lockstep":
        return None
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    raise ConfigError(f"{where}: a positive number of device seconds per second, or \"lockstep\"; got {value!r}")


@dataclass(frozen=True)
class DriversConfig:
    source_rate: float | None = field(default=1.0, metadata={"toml": _source_rate})
    stale_periods: int = DEFAULT_STALE_PERIODS

    def __post_init__(self) -> None:
        try:
            self.timing()
        except ValueError as exc:
            raise ConfigError(str(exc)) from None

    def timing(self) -> SourceTiming:
        return SourceTiming(rate=self.source_rate, stale_periods=self.stale_periods)


@dataclass(frozen=True)
class RecordingConfig:
    path: Path | None = None


@dataclass(frozen=True)
class GatewayConfig:
    can: CanConfig = field(default_factory=CanConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    robot: RobotConfig = field(default_factory=RobotConfig)
    service: ServiceConfig = field(default_factory=ServiceConfig)
    drivers: DriversConfig = field(default_factory=DriversConfig)
    estimator: CoreSettings = field(default_factory=CoreSettings)
    recording: RecordingConfig = field(default_factory=RecordingConfig)

    @classmethod
    def load(cls, path: str | Path) -> "GatewayConfig":
        """The configuration in the TOML file ``path`` (what it does not give: the defaults)."""
        path = Path(path)
        if path.suffix.lower() in (".json5", ".json"):
            raise ConfigError(f"{path}: a zenoh configuration (JSON5), not the gateway's (TOML): it goes "
                              f"in [zenoh] config_file")
        try:
            table = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ConfigError(f"{path}: no such configuration file") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{path}: cannot read: {exc}") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: not TOML: {exc}") from None
        return _build(cls, table, str(path), path.resolve().parent)

    def updated(self, **sections: dict[str, Any]) -> "GatewayConfig":
        """A copy with keys of some sections replaced: ``updated(service={"retry_s": 0.05})``."""
        out = {}
        for name, values in sections.items():
            current = getattr(self, name)
            try:
                out[name] = _replace(current, values, name)
            except TypeError as exc:
                raise ConfigError(f"[{name}]: {exc}") from None
        return dataclasses.replace(self, **out)

    def to_toml(self, *, docs: bool = True) -> str:
        """The configuration as TOML that :meth:`load` reads back equal (with the keys' documentation)."""
        lines = ["# bsc gateway configuration: bsc gateway --config FILE (flags override it). Written by",
                 "# `bsc gateway --print-config`. A key written as a comment (# key =) is unset."]
        for f in dataclasses.fields(self):
            _dump(getattr(self, f.name), f.name, lines, docs)
        return "\n".join(lines) + "\n"


def _replace(obj, values: dict[str, Any], where: str):
    nested = {}
    flat = {}
    for key, value in values.items():
        sub = getattr(obj, key, None)
        if dataclasses.is_dataclass(sub) and isinstance(value, dict):
            nested[key] = _replace(sub, value, f"{where}.{key}")
        else:
            flat[key] = value
    return dataclasses.replace(obj, **flat, **nested)


# --- one line of documentation per key (the generated TOML's comments; a test requires every key) ---
DOCS = {
    "can": "The robot's CAN buses (docs/wire.md): one per arm plus the spacecraft bus.",
    "can.interface": "python-can interface: socketcan, udp_multicast, pcan, kvaser, vector, virtual, ... "
                     "(required, here or --interface)",
    "can.channels": "one prefix ([\"bsc\"]: bsc-arm0, bsc-arm1, bsc-spacecraft), or \"BUS=CHANNEL\" for every bus "
                    "(required, here or --channel)",
    "can.fd": "the buses run CAN FD (same frames, bit-rate switch)",
    "can.bitrate": "nominal bit rate of every bus, bit/s (unset: python-can's configuration, else the DBC's 1 Mbit/s)",
    "can.data_bitrate": "CAN FD data-phase bit rate, bit/s (unset: python-can's configuration, else 5 Mbit/s)",
    "can.bus_kwargs": "any other argument of the python-can bus class, e.g. serial = 12345",
    "can.receive": "auto, direct (the worker polls the buses' sockets) or threads (a notifier thread per bus)",
    "zenoh": "The zenoh session (docs/security.md for deployments with access control).",
    "zenoh.config_file": "a zenoh JSON5 configuration file, read first (e.g. deploy/zenoh/gateway.json5)",
    "zenoh.mode": "peer, client or router (unset: peer, or the file's)",
    "zenoh.connect": "endpoints to connect to, e.g. [\"tcp/127.0.0.1:7447\"]",
    "zenoh.listen": "endpoints to listen on (unset and no file: nothing listens)",
    "zenoh.multicast_scouting": "allow multicast scouting (off unless asked for)",
    "robot": "What the gateway estimates for.",
    "robot.description": "robot description: a built-in name or a URDF file (unset: paper_robot)",
    "robot.model": "the gateway's model of the robot when it differs from the description (unset: the same)",
    "robot.thrusters": "nominal thruster layout: a name, a [[thruster]] file or a scenario .toml (unset: ring18)",
    "service": "What the gateway publishes, and how it copes with load and lost buses.",
    "service.health_period_s": "health publication period, s",
    "service.publish_samples": "publish every decoded sample (false: efforts and health only, ~15 % less CPU)",
    "service.estimate": "run the estimator (false: decoded samples and health only)",
    "service.max_backlog": "frames waiting for the worker, all buses together, before new frames are shed",
    "service.retry_s": "longest wait between attempts to reopen a failed bus, s",
    "service.duration_s": "stop after this many seconds (unset: run until stopped)",
    "drivers": "Device timing (docs/faults.md).",
    "drivers.source_rate": "device seconds per second of the frame timestamps: 1.0 real time, 2.0 a log played "
                           "at twice its speed, \"lockstep\" a simulation paced by its computation",
    "drivers.stale_periods": "a device with no sample for this many of its nominal periods is stale (health)",
    "estimator": "The estimator's sync policy (docs/estimator.md).",
    "estimator.max_open": "epochs waiting for their samples before the oldest is computed with what it has",
    "estimator.imu_max_age_periods": "an epoch's IMU sample may be this many IMU periods old (older: stale:imu)",
    "estimator.pending_capacity": "slower-stream samples waiting for their epoch (the oldest dropped beyond)",
    "estimator.held_capacity": "samples held while the epoch grid's phase is learnt",
    "estimator.thrusters": "The valve-aided thruster filter's noise figures and priors (docs/estimator.md).",
    "estimator.thrusters.accel_sigma": "accelerometer noise per IMU sample, m/s^2",
    "estimator.thrusters.gyro_sigma": "gyro noise per IMU sample, rad/s",
    "estimator.thrusters.gain_sigma": "prior of each thruster's own gain (force along its direction), fraction of max",
    "estimator.thrusters.common_gain_sigma": "prior of the gain all thrusters share (one propellant feed), fraction",
    "estimator.thrusters.lateral_sigma": "prior of each thruster's force across its direction, fraction of max",
    "estimator.thrusters.moment_sigma_nm": "prior of each thruster's moment not explained by position x force, N m",
    "estimator.thrusters.walk_force": "random walk of each thruster's force, fraction of max per sqrt(s)",
    "estimator.thrusters.walk_moment_nm": "random walk of each thruster's moment, N m per sqrt(s)",
    "estimator.thrusters.bias_force_sigma_n": "prior of the bias states seen as force, N",
    "estimator.thrusters.bias_moment_sigma_nm": "prior of the bias states seen as moment, N m",
    "estimator.joints": "The joint filter: joint accelerations and F/T bias per arm from the F/T sensor and the "
                        "encoder rates (docs/estimator.md, section 2b).",
    "estimator.joints.enabled": "false: joint accelerations by least squares from the F/T wrench alone, torques "
                                "from the sensor side (the estimator before the joint filter)",
    "estimator.joints.jerk_psd": "white jerk of each joint, rad^2/s^5 (how fast joint accelerations may change)",
    "estimator.joints.rate_sigma_rad_s": "encoder rate noise per sample with the wire's resolution, rad/s",
    "estimator.joints.force_sigma_n": "F/T force noise per sample with the wire's resolution, N",
    "estimator.joints.torque_sigma_nm": "F/T moment noise per sample with the wire's resolution, N m",
    "estimator.joints.accel_prior": "initial joint acceleration uncertainty beyond the least-squares start, rad/s^2",
    "estimator.joints.bias_prior_n": "F/T force bias after taring, 1 sigma, N",
    "estimator.joints.bias_prior_nm": "F/T moment bias after taring, 1 sigma, N m",
    "estimator.joints.bias_walk_n": "random walk of the F/T bias state (the bias, and model error it absorbs), "
                                    "N per sqrt(s)",
    "estimator.joints.bias_walk_nm": "the same, moment, N m per sqrt(s)",
    "estimator.joints.max_gap_s": "a longer silence between epochs restarts the joint filter, s",
    "estimator.joints.model_uncertainty": "relative error of the model's masses and inertias, 1 sigma: weighs the "
                                          "distal side (model) against the sensor side (F/T) per joint",
    "estimator.joints.contact": "detect contact: a wrench on an arm that the model does not know (docs/estimator.md, "
                                "section 2c); published as JointEfforts.contact",
    "estimator.joints.contact_significance": "a contact begins when the averaged residual's squared length in its "
                                             "noise stays above this for a window (about 6 without contact)",
    "estimator.joints.contact_force_n": "and the force it means at the end effector is above this, N",
    "estimator.joints.contact_moment_nm": "or the moment about the end effector above this, N m (a contact ends "
                                          "below half of both, or a quarter of the significance, for a window)",
    "estimator.joints.contact_window_s": "time constant of the averaged residual (and the window of each verdict), s",
    "estimator.joints.contact_floor_n": "what the model misses in the averaged residual, force, 1 sigma, N",
    "estimator.joints.contact_floor_nm": "the same, moment, N m",
    "estimator.joints.contact_model_error": "the model wrench's relative error a contact must stand out of, until "
                                            "the arm's motion out of contact has taught it",
    "estimator.joints.contact_model_error_min": "the least relative error of the model wrench the contact test "
                                                "learns",
    "estimator.joints.contact_walk_n": "how fast a contact force may change, random walk, N per sqrt(s)",
    "estimator.joints.contact_walk_nm": "the same, moment, N m per sqrt(s)",
    "estimator.fdi": "The thruster fault detector (docs/fdi.md); fdi = false in [estimator] turns it off.",
    "estimator.fdi.short_s": "gross faults: the GLR's forgetting window, s",
    "estimator.fdi.h_short": "gross faults: alarm threshold of the GLR (chi-squared; healthy sessions peak near 20)",
    "estimator.fdi.theta_min_short": "gross faults: smallest fault size alarmed, fraction of nominal thrust",
    "estimator.fdi.hold_short": "gross faults: IMU updates in a row with the same best hypothesis above threshold",
    "estimator.fdi.confirm_short": "gross faults: IMU updates after that over which the size (and type) is estimated",
    "estimator.fdi.theta1": "partial losses: the fault size the CUSUM tests for, fraction of nominal thrust",
    "estimator.fdi.h_long": "partial losses: alarm threshold of the CUSUM",
    "estimator.fdi.theta_min_long": "partial losses: smallest fault size alarmed, fraction of nominal thrust",
    "estimator.fdi.hold_long": "partial losses: IMU updates in a row with the same best hypothesis above threshold",
    "estimator.fdi.confirm_long": "partial losses: IMU updates after that over which the size is estimated",
    "estimator.fdi.suspect": "above this GLR (or 3/4 of h_long) the thruster filter stops learning",
    "estimator.fdi.warmup_s": "no alarm while the filter converges from its prior, s",
    "estimator.fdi.tilt_s": "misalignment changes: the forgetting window of each thruster's tilt GLR, s",
    "estimator.fdi.tilt_min_deg": "misalignment changes: smallest tilt alarmed, degrees",
    "estimator.fdi.hold_valve": "partial losses: above this loss CUSUM the valve's wrench is held, not learnt (0: off)",
    "recording": "Recording the session (docs/recording.md).",
    "recording.path": "record the session to this MCAP file (unset: no recording)",
}


def _section(hint: Any) -> tuple[type | None, bool]:
    """``(the dataclass of a section, whether it may be None)`` for a field's type hint; (None, _)
    for a plain key. A section that may be None (``fdi: FdiSettings | None``: off) is written
    ``fdi = false`` in a file."""
    if dataclasses.is_dataclass(hint):
        return hint, False
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        inner = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(inner) == 1 and dataclasses.is_dataclass(inner[0]) and len(typing.get_args(hint)) == 2:
            return inner[0], True
    return None, False


def documented_keys(cls=GatewayConfig, prefix: str = "") -> list[str]:
    """Every section and key of the configuration, dotted (what :data:`DOCS` must document)."""
    out = []
    for f in dataclasses.fields(cls):
        name = prefix + f.name
        out.append(name)
        sec, _ = _section(typing.get_type_hints(cls)[f.name])
        if sec is not None:
            out += documented_keys(sec, name + ".")
    return out


# --- reading: a table of TOML into a dataclass, strictly ---

def _build(cls, table: Any, where: str, base: Path | None, key: str = ""):
    label = f"{where}: [{key}]" if key else where
    if not isinstance(table, dict):
        raise ConfigError(f"{label}: expected a table, got {table!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - set(fields))
    if unknown:
        raise ConfigError(f"{label}: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(unknown)} "
                          f"(known: {', '.join(fields)})")
    kw = {}
    for name, value in table.items():
        dotted = f"{key}.{name}" if key else name
        convert = fields[name].metadata.get("toml")
        sec, optional = _section(hints[name])
        if convert is not None:
            kw[name] = convert(value, f"{where}: {dotted}")
        elif sec is not None and optional and value is False:
            kw[name] = None                       # a section turned off: "fdi = false"
        elif sec is not None:
            kw[name] = _build(sec, value, where, base, dotted)
        else:
            kw[name] = _value(hints[name], value, f"{where}: {dotted}", base)
    try:
        return cls(**kw)
    except ConfigError as exc:
        raise ConfigError(f"{label}: {exc}") from None
    except ValueError as exc:
        raise ConfigError(f"{label}: {exc}") from None


def _value(t, value: Any, where: str, base: Path | None):
    origin, args = typing.get_origin(t), typing.get_args(t)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        return _value(inner[0], value, where, base)
    if t is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected true or false, got {value!r}")
    if t is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected an integer, got {value!r}")
    if t is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
        raise ConfigError(f"{where}: expected a number, got {value!r}")
    if t is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{where}: expected a string, got {value!r}")
    if t is Path:
        if isinstance(value, str) and value:
            p = Path(value).expanduser()
            return p if p.is_absolute() or base is None else base / p
        raise ConfigError(f"{where}: expected a path (a string), got {value!r}")
    if origin is tuple and args[-1] is Ellipsis and args[0] is str:
        if isinstance(value, list) and all(isinstance(v, str) for v in value):
            return tuple(value)
        raise ConfigError(f"{where}: expected a list of strings, got {value!r}")
    if origin is tuple:                 # key-value pairs: a TOML table of scalars
        if isinstance(value, dict) and all(not isinstance(v, (dict, list)) for v in value.values()):
            return tuple(value.items())
        raise ConfigError(f"{where}: expected a table of KEY = VALUE, got {value!r}")
    raise ConfigError(f"{where}: cannot read {value!r}")   # pragma: no cover - a field type not handled


# --- writing ---

def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, Path):
        return json.dumps(str(value))
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"no TOML for {value!r}")


def _dump(section, name: str, lines: list[str], docs: bool) -> None:
    lines.append("")
    if docs and name in DOCS:
        lines.append(f"# {DOCS[name]}")
    lines.append(f"[{name}]")
    subs = []
    for f in dataclasses.fields(section):
        value = getattr(section, f.name)
        dotted = f"{name}.{f.name}"
        if dataclasses.is_dataclass(value) or f.name == "bus_kwargs":
            subs.append((dict(value) if f.name == "bus_kwargs" else value, dotted))
            continue
        if docs and dotted in DOCS:
            lines.append(f"# {f.name}: {DOCS[dotted]}")
        if f.name == "source_rate" and value is None:
            lines.append(f'{f.name} = "lockstep"')
        elif value is None and _section(typing.get_type_hints(type(section))[f.name])[1]:
            lines.append(f"{f.name} = false")      # a section turned off
        elif value is None:
            lines.append(f"# {f.name} =")
        else:
            lines.append(f"{f.name} = {_toml_value(value)}")
    for value, dotted in subs:
        if isinstance(value, dict):
            lines.append("")
            if docs and dotted in DOCS:
                lines.append(f"# {DOCS[dotted]}")
            lines.append(f"[{dotted}]")
            lines += [f"{k} = {_toml_value(v)}" for k, v in value.items() if v is not None]
        else:
            _dump(value, dotted, lines, docs)
