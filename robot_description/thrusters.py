"""The spacecraft's reaction-control thrusters as data: positions, force directions, max thrust.

Shared like the URDF: the simulator fires these thrusters, the gateway's estimator uses the same
NOMINAL layout as its prior for what each valve delivers (it then measures the actual force of
each valve, see docs/estimator.md). Frames: spacecraft body frame, origin at its centre of mass
C; a thruster's direction is that of the force it exerts ON the spacecraft. Bit i of a valve
mask on the wire is thruster i of the layout.

A layout is a named table here, or a TOML file with ``[[thruster]]`` tables
(``pos_m = [x, y, z]``, ``dir = [x, y, z]``, optional ``max_thrust_n``), or a scenario's
``[thrusters]`` namespace (``layout = NAME`` or ``[[thrusters.custom]]``).
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

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
DEFAULT_LAYOUT = "ring18"
DEFAULT_MAX_THRUST_N = 100.0
MAX_THRUSTERS = 32                    # bits of the valve mask on the wire


class ThrusterLayoutError(ValueError):
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
    def from_config(cls, cfg) -> "ThrusterLayout":
        """From a scenario's ``[thrusters]`` namespace (``layout``, ``max_thrust_n``, optional ``custom``)."""
        custom = getattr(cfg, "custom", None)
        if custom:
            rows = [tuple(t.pos_m) + tuple(t.dir) for t in custom]
            maxes = [float(getattr(t, "max_thrust_n", cfg.max_thrust_n)) for t in custom]
            return cls.from_rows(rows, maxes)
        return cls.named(cfg.layout, float(cfg.max_thrust_n))

    @classmethod
    def load(cls, spec: str | Path | None = None, max_thrust_n: float = DEFAULT_MAX_THRUST_N) -> "ThrusterLayout":
        """A layout by name (``ring18``) or from a TOML file of ``[[thruster]]`` tables."""
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
            rows = [tuple(t["pos_m"]) + tuple(t["dir"]) for t in data["thruster"]]
            maxes = [float(t.get("max_thrust_n", data.get("max_thrust_n", max_thrust_n))) for t in data["thruster"]]
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError, KeyError, TypeError) as exc:
            raise ThrusterLayoutError(f"{path}: not a thruster layout file ({exc})") from None
        return cls.from_rows(rows, maxes)
