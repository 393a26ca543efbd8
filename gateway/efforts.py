"""What the gateway publishes beyond the raw samples: estimated efforts and alerts.

These frozen dataclasses are the product of ``bsc gateway`` (efforts) and ``bsc monitor``
(alerts); they travel through :mod:`gateway.codec` under the keys of :mod:`gateway.keys`
(``bsc/<robot>/efforts/joints/<arm>``, ``bsc/<robot>/efforts/thrusters``, ``bsc/<robot>/efforts/valves``,
``bsc/<robot>/alerts``).

Times: ``t_ns`` is SENSOR time, the timestamp of the F/T sample epoch the estimate belongs to
(same clock as the CAN frame timestamps). The publish time is not part of the payload, so that a
replay of the same frames gives byte-identical payloads: it travels as the zenoh attachment
``publish_ns`` (decimal ASCII) and as the MCAP log time.

Quality: ``good`` is False whenever an input was missing, stale, saturated or the filters were
still warming up; ``flags`` says why (sorted strings such as ``stale:imu``, ``stale:arm0/j2``,
``missing:arm1``, ``saturated:arm0``, ``warmup``, ``fault:imu``). Consumers must ignore
estimates that are not good; they are published so that the gap is visible.
"""
from __future__ import annotations

from dataclasses import dataclass

Vec3 = tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class JointEfforts:
    """Estimated actual torques (motor minus friction, N m) of one arm's joints at sensor time ``t_ns``.

    ``joints``: ``<arm>/<joint>``, proximal first. ``full_nm``: the full estimate (link dynamics
    from the model); ``simplified_nm``: the paper's projection of the sensor wrench.
    ``commanded_nm``: the latest commanded motor torques seen on the arm bus (``()`` before the
    first command), received at ``commanded_t_ns`` (0 if none). ``rate_rad_s``: the joint rates
    the estimate used (what friction analysis plots torque residuals against). ``ft_bias``: the
    bias of the arm's F/T sensor the joint filter has learnt, in the sensor's frame, force (N)
    then moment (N m); ``()`` while the filter starts, or with it off. ``contact``: while the arm
    is in contact (a wrench on it that the model does not know, docs/estimator.md), that wrench on
    the end effector, spacecraft body axes, force (N) then moment about the end effector (N m);
    ``()`` out of contact.
    """

    arm: str
    t_ns: int
    joints: tuple[str, ...]
    full_nm: tuple[float, ...]
    simplified_nm: tuple[float, ...]
    commanded_nm: tuple[float, ...]
    commanded_t_ns: int
    rate_rad_s: tuple[float, ...]
    good: bool
    flags: tuple[str, ...] = ()
    ft_bias: tuple[float, ...] = ()
    contact: tuple[float, ...] = ()


@dataclass(frozen=True, slots=True)
class ThrusterEffort:
    """Estimated net thruster wrench at sensor time ``t_ns``: body frame, force through the
    spacecraft's centre of mass C (N), moment about C (N m).

    ``commanded_*``: the latest commanded wrench seen on the spacecraft bus (zeros before the
    first), received at ``commanded_t_ns`` (0 if none); ``valves``: its valve mask.
    """

    t_ns: int
    force_n: Vec3
    moment_nm: Vec3
    commanded_force_n: Vec3
    commanded_moment_nm: Vec3
    commanded_t_ns: int
    valves: int
    good: bool
    flags: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class ValveWrenches:
    """The thruster filter's learned per-valve wrenches as of the epoch at sensor time ``t_ns``
    (:mod:`gateway.estimator.thrusters`): ``wrench`` the n x 6 numbers, valve by valve, of what
    each valve exerts while open ``[force (N); moment about C (N m)]``, body frame;
    ``force_sigma_n`` (n,) each one's force uncertainty (1 sigma, N: the root of its force
    covariance's trace); ``good`` and ``flags`` those of the same epoch's :class:`ThrusterEffort`.
    Published at most every 5 ms of sensor time (:mod:`gateway.pipeline`); what the thruster loop
    of ``bsc control`` allocates with (:mod:`gateway.control.thrusters`)."""

    t_ns: int
    wrench: tuple[float, ...]
    force_sigma_n: tuple[float, ...]
    good: bool
    flags: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class Alert:
    """One alert transition of ``bsc monitor`` / ``bsc analyze``.

    ``kind``: ``actuator`` | ``thruster`` | ``sensor``. ``target``: ``arm0/j2``, a thruster axis
    (``fx`` .. ``mz``), or a sensor/device (``arm0``, ``imu``). ``rule``: the rule's name in the
    rules file. ``severity``: ``info`` | ``warning`` | ``critical``. ``state``: ``raised`` or
    ``cleared``. ``since_ns``: when the condition began (sensor time); ``t_ns``: this transition.
    ``evidence``: named numbers that justify it (e.g. ``("friction_nm", 182.0)``,
    ``("threshold_nm", 150.0)``).
    """

    robot: str
    kind: str
    target: str
    rule: str
    severity: str
    state: str
    since_ns: int
    t_ns: int
    message: str
    evidence: tuple[tuple[str, float], ...] = ()


Effort = JointEfforts | ThrusterEffort
