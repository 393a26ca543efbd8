"""Typed sensor samples: what the drivers make of CAN frames, in SI units.

These frozen dataclasses are the contract between the bytes (``drivers``), the sensor firmware
of the simulator (which encodes the same readings) and the gateway (which estimates from them).
Time is integer nanoseconds (``t_ns``): the CAN timestamp of the sample's first frame (of a one-frame
sample, its frame): the closest to when the device sampled.
Frames are named in every docstring; conventions follow docs/method.md.
"""
from __future__ import annotations

from dataclasses import dataclass

Vec3 = tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class WrenchSample:
    """One six-axis F/T reading of arm ``device``.

    The wrench the SPACECRAFT exerts ON the arm (docs/method.md): force in N and moment in N m about
    the sensor origin S_j, both in the sensor frame. ``saturated`` is set when any channel was at
    the end of its range (the value is then clamped, never wrapped).
    """

    device: str
    t_ns: int
    counter: int
    force_n: Vec3
    torque_nm: Vec3
    saturated: bool = False
    status: int = 0


@dataclass(frozen=True, slots=True)
class ImuSample:
    """One spacecraft IMU sample, in the IMU frame.

    ``accel_m_s2``: specific force (non-gravitational acceleration of the IMU point; in orbit
    this is what thrusters and arm reactions cause). ``rate_rad_s``: angular rate.
    ``quat_wxyz``: attitude, IMU frame -> inertial frame, scalar first (Xsens order).
    """

    t_ns: int
    counter: int
    quat_wxyz: tuple[float, float, float, float]
    rate_rad_s: Vec3
    accel_m_s2: Vec3
    saturated: bool = False
    status: int = 0


@dataclass(frozen=True, slots=True)
class JointSample:
    """One joint drive report: encoder angle and the drive's velocity estimate.

    ``device`` is ``<arm>/<joint>`` as in the robot description (e.g. ``arm0/j1``).
    """

    device: str
    t_ns: int
    counter: int
    angle_rad: float
    rate_rad_s: float
    saturated: bool = False
    status: int = 0


@dataclass(frozen=True, slots=True)
class TorqueCommand:
    """The motor torque the controller commanded to joint ``device`` (``<arm>/<joint>``), N m."""

    device: str
    t_ns: int
    counter: int
    torque_nm: float
    saturated: bool = False


@dataclass(frozen=True, slots=True)
class ThrusterCommand:
    """The thruster wrench the controller commanded: body frame, force through and moment about C.

    ``valves`` is the bit mask of thruster valves open in the same control cycle (bit i =
    thruster i of the configured layout). ``allowed``: the thrusters the controller may fire in
    this cycle, its keep-out mask (``THRUSTER_CMD_ALLOWED``); -1 when the controller does not
    send it (and in logs from before it existed): unknown, not "all". (Not None: Foxglove takes
    one scalar type per field.)
    """

    t_ns: int
    counter: int
    force_n: Vec3
    moment_nm: Vec3
    valves: int = 0
    saturated: bool = False
    allowed: int = -1


@dataclass(frozen=True, slots=True)
class ValveCommand:
    """The valve commands of one millisecond from the PWPFM modulator (``THRUSTER_VALVE_CMD``):
    bit i of ``valves`` = thruster i of the configured layout commanded open. What the valves
    actually deliver (gain, misalignment, a stuck valve) is what the estimator measures."""

    t_ns: int
    counter: int
    valves: int


Sample = WrenchSample | ImuSample | JointSample | TorqueCommand | ThrusterCommand | ValveCommand


@dataclass(frozen=True, slots=True)
class DeviceHealth:
    """Health of one device (``<arm>``, ``<arm>/<joint>``, ``imu``, ``thrusters``, or a command
    stream), a snapshot taken at ``t_ns`` (host clock, same base as frame timestamps).

    ``rejected``: frames or samples dropped, by reason (sorted ``(reason, count)`` pairs; reasons
    are listed in drivers/health.py). ``lost``: samples skipped in the counter sequence.
    ``stale``: no sample within ``stale_periods`` nominal periods (or none yet).
    ``faults``: the device's last status with only its fault bits kept (0 = healthy).
    ``lost_at_least``: ``lost`` is a lower bound: a silence hid an unknown multiple of 256 samples
    (the source's clock rate was not known; drivers/health.py).
    """

    device: str
    bus: str
    t_ns: int
    samples: int
    lost: int
    saturated: int
    rejected: tuple[tuple[str, int], ...]
    last_t_ns: int
    stale: bool
    status: int = 0
    faults: int = 0
    lost_at_least: bool = False


@dataclass(frozen=True, slots=True)
class BusHealth:
    """Health of one CAN bus, a snapshot at ``t_ns``.

    ``frames``: all frames seen; ``rejected``: bus-level rejections by reason (unknown ids,
    error/remote frames, ...). ``load``: measured worst-case (bit-stuffed) load since the
    previous snapshot, fraction of the bit rate. ``nodes``: last heartbeat state per node.
    """

    bus: str
    t_ns: int
    frames: int
    rejected: tuple[tuple[str, int], ...]
    load: float
    nodes: tuple[tuple[str, int], ...] = ()


Health = DeviceHealth | BusHealth
