"""Every zenoh key expression of bsc, in one place.

Scheme (``<robot>`` = the robot description's name, e.g. ``paper_robot``)::

    bsc/<robot>/sensors/wrench/<arm>              WrenchSample      F/T sensor of arm <arm>
    bsc/<robot>/sensors/joint/<arm>/<joint>       JointSample       joint drive report
    bsc/<robot>/sensors/imu                       ImuSample         spacecraft IMU
    bsc/<robot>/sensors/commands/torque/<arm>/<joint>  TorqueCommand  commanded motor torque,
                                                                    as observed on the CAN bus
    bsc/<robot>/sensors/commands/thrusters        ThrusterCommand   commanded thruster wrench (observed)
    bsc/<robot>/sensors/commands/valves           ValveCommand      valve commands, 1 kHz (observed)
    bsc/<robot>/health/bus/<bus>                  BusHealth         per CAN bus
    bsc/<robot>/health/device/<device...>         DeviceHealth      per device (<arm>, <arm>/<joint>,
                                                                    <arm>/torque_cmd, imu, thrusters)
    bsc/<robot>/efforts/joints/<arm>              JointEfforts      estimated joint torques of an arm
    bsc/<robot>/efforts/thrusters                 ThrusterEffort    estimated thruster wrench
    bsc/<robot>/efforts/valves                    ValveWrenches     the thruster filter's learned per-valve
                                                                    wrenches (at most every 5 ms)
    bsc/<robot>/alerts                            Alert             monitor / analyze alerts
    bsc/<robot>/commands/drives/<arm>             DriveCommand      the compensator's drive command
                                                                    (bsc control; gateway/control/)
    bsc/<robot>/commands/thrusters                ThrusterValves    the compensator's valve commands
    bsc/<robot>/commands/status                   Alert             the compensator's loop transitions

Payloads are encoded by :mod:`gateway.codec`. Subscribe to ``sensors(robot)`` for every sample
the gateway decodes from the buses (commands included), ``ROOT/**`` for everything.

The commands the gateway sees on the CAN buses are observations, so they live under
``sensors/commands/``. ``bsc/<robot>/commands/**`` (:func:`commands`) is left to the robot's
controller: in a deployment only a configured controller may publish there
(deploy/zenoh/router.json5), and the gateway never does.
"""
from __future__ import annotations

from gateway.errors import GatewayError
from drivers.samples import (BusHealth, DeviceHealth, ImuSample, JointSample, ThrusterCommand, TorqueCommand,
                             ValveCommand, WrenchSample)
from gateway.efforts import Alert, JointEfforts, ThrusterEffort, ValveWrenches

ROOT = "bsc"
_FORBIDDEN = set("*$?#/ ")


class KeyExprError(GatewayError, ValueError):
    """A name that cannot be a key expression chunk."""


def _chunk(name: str) -> str:
    if not name or _FORBIDDEN & set(name):
        raise KeyExprError(f"{name!r} cannot be a key expression chunk (empty, or contains one of '*$?#/ ')")
    return name


def _path(name: str) -> str:
    return "/".join(_chunk(c) for c in name.split("/"))


def robot_root(robot: str) -> str:
    return f"{ROOT}/{_chunk(robot)}"


def wrench(robot: str, arm: str) -> str:
    return f"{robot_root(robot)}/sensors/wrench/{_chunk(arm)}"


def joint(robot: str, device: str) -> str:
    """``device`` is ``<arm>/<joint>``."""
    return f"{robot_root(robot)}/sensors/joint/{_path(device)}"


def imu(robot: str) -> str:
    return f"{robot_root(robot)}/sensors/imu"


def torque_command(robot: str, device: str) -> str:
    return f"{robot_root(robot)}/sensors/commands/torque/{_path(device)}"


def thruster_command(robot: str) -> str:
    return f"{robot_root(robot)}/sensors/commands/thrusters"


def valve_command(robot: str) -> str:
    return f"{robot_root(robot)}/sensors/commands/valves"


def bus_health(robot: str, bus: str) -> str:
    return f"{robot_root(robot)}/health/bus/{_chunk(bus)}"


def device_health(robot: str, device: str) -> str:
    return f"{robot_root(robot)}/health/device/{_path(device)}"


def joint_efforts(robot: str, arm: str) -> str:
    return f"{robot_root(robot)}/efforts/joints/{_chunk(arm)}"


def thruster_effort(robot: str) -> str:
    return f"{robot_root(robot)}/efforts/thrusters"


def valve_wrenches(robot: str) -> str:
    """The thruster filter's learned per-valve wrenches (:class:`gateway.efforts.ValveWrenches`)."""
    return f"{robot_root(robot)}/efforts/valves"


def alerts(robot: str) -> str:
    return f"{robot_root(robot)}/alerts"


def schema(robot: str, type_name: str) -> str:
    """The JSON schema of payload type ``type_name`` (``JointEfforts``, ...), queryable."""
    return f"{robot_root(robot)}/schemas/{type_name}"


def schemas(robot: str) -> str:
    return f"{robot_root(robot)}/schemas/**"


def efforts(robot: str) -> str:
    return f"{robot_root(robot)}/efforts/**"


def sensors(robot: str) -> str:
    return f"{robot_root(robot)}/sensors/**"


def observed_commands(robot: str) -> str:
    return f"{robot_root(robot)}/sensors/commands/**"


def commands(robot: str) -> str:
    """The controller's key space (the gateway never publishes here)."""
    return f"{robot_root(robot)}/commands/**"


def drive_command(robot: str, arm: str) -> str:
    """One arm's drive command, published by the compensator (``bsc control``)."""
    return f"{robot_root(robot)}/commands/drives/{_chunk(arm)}"


def drive_commands(robot: str) -> str:
    """Every arm's drive commands of ``robot``."""
    return f"{robot_root(robot)}/commands/drives/**"


def thruster_valves(robot: str) -> str:
    """The thrusters' valve commands, published by the compensator (``bsc control``)."""
    return f"{robot_root(robot)}/commands/thrusters"


def control_status(robot: str) -> str:
    """The compensator's loop transitions (Alert records), in the controller's key space because
    that role may publish nowhere else."""
    return f"{robot_root(robot)}/commands/status"


def health(robot: str) -> str:
    return f"{robot_root(robot)}/health/**"


def everything(robot: str) -> str:
    return f"{robot_root(robot)}/**"


def for_sample(robot: str, sample) -> str:
    """The key a decoded sample or health report is published under."""
    if isinstance(sample, WrenchSample):
        return wrench(robot, sample.device)
    if isinstance(sample, JointSample):
        return joint(robot, sample.device)
    if isinstance(sample, ImuSample):
        return imu(robot)
    if isinstance(sample, TorqueCommand):
        return torque_command(robot, sample.device)
    if isinstance(sample, ThrusterCommand):
        return thruster_command(robot)
    if isinstance(sample, ValveCommand):
        return valve_command(robot)
    if isinstance(sample, BusHealth):
        return bus_health(robot, sample.bus)
    if isinstance(sample, DeviceHealth):
        return device_health(robot, sample.device)
    if isinstance(sample, JointEfforts):
        return joint_efforts(robot, sample.arm)
    if isinstance(sample, ThrusterEffort):
        return thruster_effort(robot)
    if isinstance(sample, ValveWrenches):
        return valve_wrenches(robot)
    if isinstance(sample, Alert):
        return alerts(robot)
    raise TypeError(f"no key for {type(sample).__name__}")
