"""The spacecraft's reaction-control thrusters as data: positions, force directions, max thrust.

Shared like the URDF: the simulator fires these thrusters, the gateway's estimator uses the same
NOMINAL layout as its prior for what each valve delivers (it then measures the actual force of
each valve, see docs/estimator.md). Frames: spacecraft body frame, origin at its centre of mass
C; a thruster's direction is that of the force it exerts ON the spacecraft. Bit i of a valve
mask on the wire is thruster i of the layout.

A layout is a named table here, or a TOML file with ``[[thruster]]`` tables
(``pos_m = [x, y, z]``, ``dir = [x, y, z]``, optional ``max_thrust_n``), or a scenario's
``[thrusters]`` table (``layout = NAME`` or ``[[thrusters.custom]]`` rows of the same keys).
Every row is checked and a bad one named with its field: positions finite, directions non-zero
and finite (then normalised: ``dir`` gives only the direction, ``max_thrust_n`` the magnitude),
thrust positive. Whether a layout can control all six axes is a separate question
(:meth:`ThrusterLayout.uncontrollable`): the gateway estimates any layout's wrench, the
simulator's flight software needs all six.
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from robot_description.errors import DescriptionError

# rows (x, y, z, fx, fy, fz): positions in m, force directions (normalised on load).
# "ring18" for the paper's 4.2 m cylinder (rim radius 2.1 m, height 2 m), target on +x:
# tangential pairs at four azimuths for in-plane force and yaw; two canted thrusters at the
# front so that the spacecraft can back away from the target without pointing a plume at it;
# eight axial thrusters for the out-of-plane axes.
_C = math.cos(math.radians(60.0))
_S = math.sin(math.radians(60.0))
LAYOUTS: dict[str, list[tuple[float, ...]]] = {
    "ring18": [
        (2.1, 0.0, 0.0, 0.0, 1.0, 0.0), (2.1, 0.0, 0.0, 0.0, -1.0, 0.0),
        (2.1, 0.0, 0.0, -_C, -_S, 0.0), (2.1, 0.0, 0.0, -_C, _S, 0.0),
        (0.0, 2.1, 0.0, 1.0, 0.0, 0.0), (0.0, 2.1, 0.0, -1.0, 0.0, 0.0),
        (-2.1, 0.0, 0.0, 0.0, 1.0, 0.0), (-2.1, 0.0, 0.0, 0.0, -1.0, 0.0),
        (0.0, -2.1, 0.0, 1.0, 0.0, 0.0), (0.0, -2.1, 0.0, -1.0, 0.0, 0.0),
        (2.1, 0.0, 1.0, 0.0, 0.0, -1.0), (2.1, 0.0, -1.0, 0.0, 0.0, 1.0),
        (0.0, 2.1, 1.0, 0.0, 0.0, -1.0), (0.0, 2.1, -1.0, 0.0, 0.0, 1.0),
        (-2.1, 0.0, 1.0, 0.0, 0.0, -1.0), (-2.1, 0.0, -1.0, 0.0, 0.0, 1.0),
        (0.0, -2.1, 1.0, 0.0, 0.0, -1.0), (0.0, -2.1, -1.0, 0.0, 0.0, 1.0),
    ],
}
DEFAULT_LAYOUT = "ring18"             # the scenario defaults (simulator/scenarios/capture.toml)
DEFAULT_MAX_THRUST_N = 100.0
MAX_THRUSTERS = 32                    # bits of the valve mask on the wire
ROW_KEYS = ("pos_m", "dir", "max_thrust_n")
AXES = ("force x", "force y", "force z", "moment x", "moment y", "moment z")


class ThrusterLayoutError(DescriptionError):
    """A layout that is unknown or malformed."""


def wrench_matrix(pos: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """6 x N map from thrust magnitudes to the body wrench about C ``[force; moment]``."""
    return np.vstack([dirs.T, np.cross(pos, dirs).T])


@dataclass
class ThrusterLayout:
    pos_m: np.ndarray        # (N, 3) body frame, from C
    dir: np.ndarray          # (N, 3) unit force direction on the spacecraft, body frame
    max_n: np.ndarray        # (N,) nominal thrust, N

    @property
    def n(self) -> int:
        return len(self.max_n)

    @property
    def B(self) -> np.ndarray:
        """6 x N: thrust magnitudes -> body wrench about C."""
        return wrench_matrix(self.pos_m, self.dir)

    @property
    def nominal_wrenches(self) -> np.ndarray:
        """(N, 6): the wrench each thruster delivers at nominal thrust, ``[force; moment about C]``."""
        return (self.B * self.max_n).T

    @classmethod
    def from_rows(cls, rows, maxes) -> "ThrusterLayout":
        a = np.array(rows, dtype=float)
        if a.ndim != 2 or a.shape[1] != 6 or not 1 <= len(a) <= MAX_THRUSTERS:
            raise ThrusterLayoutError(f"a layout needs 1..{MAX_THRUSTERS} rows of (x, y, z, fx, fy, fz)")
        norm = np.linalg.norm(a[:, 3:], axis=1, keepdims=True)
        if not np.all(np.isfinite(a)) or np.any(norm < 1e-9):
            raise ThrusterLayoutError("thruster positions and directions must be finite, directions non-zero")
        m = np.array(maxes, dtype=float)
        if np.any(~np.isfinite(m)) or np.any(m <= 0):
            raise ThrusterLayoutError("max thrust must be positive")
        return cls(a[:, :3].copy(), a[:, 3:] / norm, m)

    @classmethod
    def named(cls, name: str = DEFAULT_LAYOUT, max_thrust_n: float = DEFAULT_MAX_THRUST_N) -> "ThrusterLayout":
        if name not in LAYOUTS:
            raise ThrusterLayoutError(f"unknown thruster layout {name!r} (known: {', '.join(LAYOUTS)})")
        rows = LAYOUTS[name]
        return cls.from_rows(rows, [max_thrust_n] * len(rows))

    @classmethod
    def from_table(cls, rows, max_thrust_n: float = DEFAULT_MAX_THRUST_N,
                   where: str = "thrusters.custom") -> "ThrusterLayout":
        """From rows ``{pos_m, dir, max_thrust_n (optional, default max_thrust_n)}`` (TOML
        tables); errors name the row as ``where[i]`` (i: the thruster's index, its valve bit)."""
        if not isinstance(rows, list) or not 1 <= len(rows) <= MAX_THRUSTERS:
            n = len(rows) if isinstance(rows, list) else "no"
            raise ThrusterLayoutError(f"{where}: {n} rows; a layout has 1..{MAX_THRUSTERS} thrusters "
                                      "(the valve mask on the wire has 32 bits)")
        pos, dirs, maxes = [], [], []
        for i, row in enumerate(rows):
            at = f"{where}[{i}]"
            if not isinstance(row, dict):
                raise ThrusterLayoutError(f"{at}: must be a table with pos_m, dir and optional max_thrust_n, "
                                          f"got {row!r}")
            for key in row:
                if key not in ROW_KEYS:
                    raise ThrusterLayoutError(f"{at}: unknown key {key!r} (a thruster has pos_m, dir, max_thrust_n)")
            for key in ROW_KEYS[:2]:
                if key not in row:
                    raise ThrusterLayoutError(f"{at}: missing key {key!r}")
            p = _vector(row["pos_m"])
            if p is None:
                raise ThrusterLayoutError(f"{at}: pos_m must be 3 finite numbers [x, y, z] (m, body frame, from the "
                                          f"centre of mass C), got {row['pos_m']!r}")
            d = _vector(row["dir"])
            norm = 0.0 if d is None else math.sqrt(sum(x * x for x in d))
            if d is None or norm < 1e-9:
                raise ThrusterLayoutError(f"{at}: dir must be a non-zero vector of 3 finite numbers (the direction of "
                                          f"the force on the spacecraft, body frame), got {row['dir']!r}")
            m = row.get("max_thrust_n", max_thrust_n)
            if not _positive(m):
                raise ThrusterLayoutError(f"{at}: max_thrust_n must be a positive number of N, got {m!r}")
            pos.append(p)
            dirs.append([x / norm for x in d])
            maxes.append(float(m))
        return cls(np.array(pos), np.array(dirs), np.array(maxes))

    @classmethod
    def from_config(cls, cfg) -> "ThrusterLayout":
        """From a scenario's ``[thrusters]`` table, as a dict or a namespace (``layout``,
        ``max_thrust_n``, optional ``custom`` rows, which replace the named layout)."""
        table = cfg if isinstance(cfg, dict) else vars(cfg)
        max_n = table.get("max_thrust_n", DEFAULT_MAX_THRUST_N)
        if not _positive(max_n):
            raise ThrusterLayoutError(f"thrusters.max_thrust_n must be a positive number of N, got {max_n!r}")
        if "custom" in table:
            rows = table["custom"]
            if isinstance(rows, list):
                rows = [vars(r) if hasattr(r, "__dict__") else r for r in rows]
            return cls.from_table(rows, float(max_n), "thrusters.custom")
        return cls.named(table.get("layout", DEFAULT_LAYOUT), float(max_n))

    @classmethod
    def from_scenario_text(cls, text: str, source: str = "scenario") -> "ThrusterLayout":
        """The layout of a scenario file's text (as logs carry it): its ``[thrusters]`` table,
        the default ring18 at 100 N where it says nothing."""
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ThrusterLayoutError(f"{source}: not valid TOML: {exc}") from None
        table = data.get("thrusters", {})
        if not isinstance(table, dict):
            raise ThrusterLayoutError(f"{source}: 'thrusters' must be a table")
        return cls.from_config(table)

    @classmethod
    def load(cls, spec: str | Path | None = None, max_thrust_n: float = DEFAULT_MAX_THRUST_N) -> "ThrusterLayout":
        """A layout by name (``ring18``), or from a TOML file: ``[[thruster]]`` rows, or a
        scenario with a ``[thrusters]`` table."""
        if spec is None:
            return cls.named(DEFAULT_LAYOUT, max_thrust_n)
        if str(spec) in LAYOUTS:
            return cls.named(str(spec), max_thrust_n)
        path = Path(spec)
        if not path.is_file():
            raise ThrusterLayoutError(f"thruster layout {str(spec)!r}: not a known name ({', '.join(LAYOUTS)}) "
                                      "nor a file")
        try:
            data = tomllib.loads(path.read_text())
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise ThrusterLayoutError(f"{path}: not a thruster layout file ({exc})") from None
        try:
            if "thruster" in data:
                return cls.from_table(data["thruster"], data.get("max_thrust_n", max_thrust_n), "thruster")
            if isinstance(data.get("thrusters"), dict):
                return cls.from_config(data["thrusters"])
        except ThrusterLayoutError as exc:
            raise ThrusterLayoutError(f"{path}: {exc}") from None
        raise ThrusterLayoutError(f"{path}: not a thruster layout file (no [[thruster]] rows, no [thrusters] table)")

    @staticmethod
    def scenario_text(spec: str | Path | None = None, max_thrust_n: float = DEFAULT_MAX_THRUST_N) -> str | None:
        """What a log carries as its scenario so that :meth:`from_scenario_text` rebuilds exactly
        the layout :meth:`load` gives for ``spec`` (None for the default, which needs nothing):
        a scenario file's own text, a named layout's ``[thrusters]`` table, or ``[[thruster]]``
        rows as ``[[thrusters.custom]]`` rows with the file's own numbers (so directions are
        normalised once, from the same values, and the bits agree)."""
        if spec is None:
            return None
        cls = ThrusterLayout
        cls.load(spec, max_thrust_n)                    # the same checks and errors as loading it
        if str(spec) in LAYOUTS:
            return f'[thrusters]\nlayout = "{spec}"\nmax_thrust_n = {float(max_thrust_n)!r}\n'
        text = Path(spec).read_text()
        data = tomllib.loads(text)
        if "thruster" not in data:
            return text
        default = data.get("max_thrust_n", max_thrust_n)
        out = ["[thrusters]"]
        for row in data["thruster"]:
            vec = ", ".join
            out += ["", "[[thrusters.custom]]", f"pos_m = [{vec(repr(float(x)) for x in row['pos_m'])}]",
                    f"dir = [{vec(repr(float(x)) for x in row['dir'])}]",
                    f"max_thrust_n = {float(row.get('max_thrust_n', default))!r}"]
        return "\n".join(out) + "\n"

    def uncontrollable(self) -> list[str]:
        """The body-wrench directions (``+force x`` ... ``-moment z``) that no combination of
        thrusts produces. Thrust only pushes (u >= 0), so controlling all six axes takes at
        least 7 thrusters whose wrenches positively span R^6; empty when they do."""
        from scipy.optimize import nnls

        B = self.B * self.max_n
        out = []
        for k, axis in enumerate(AXES):
            for sign in (1.0, -1.0):
                e = np.zeros(6)
                e[k] = sign * float(np.abs(B[k]).max(initial=0.0) or 1.0)
                _, resid = nnls(B, e)
                if resid > 1e-6 * abs(e[k]):
                    out.append(f"{'+' if sign > 0 else '-'}{axis}")
        return out


def _positive(x) -> bool:
    """A positive finite number (a TOML boolean is not one)."""
    return not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x) and x > 0


def _vector(value) -> list[float] | None:
    """3 finite numbers (not booleans) from a TOML value, or None."""
    if not isinstance(value, list) or len(value) != 3:
        return None
    if any(isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) for x in value):
        return None
    return [float(x) for x in value]
