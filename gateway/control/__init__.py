"""The inner loop the paper left open: corrections to the actuators' commands from the gateway's
estimates of what they really deliver.

- :mod:`gateway.control.joints`: the joint loop (:class:`JointCompensator`), a pure core fed the
  outer loop's desired torques and the gateway's efforts, returning the drives' commands;
- :mod:`gateway.control.thrusters`: the thruster loop (:class:`ThrusterCompensator`): allocation
  and valve timing on the gateway's learned per-valve wrenches instead of the nominal layout;
- :mod:`gateway.control.messages`: what it publishes (:class:`DriveCommand`, :class:`ThrusterValves`)
  and under which keys;
- :mod:`gateway.control.service`: ``bsc control``, the core on zenoh.

docs/control.md describes the loop, its safety behaviour and what it achieves.
"""
from gateway.control.joints import JointCompensator, JointLoopSettings, LoopEvent
from gateway.control.messages import ControlError, DriveCommand, ThrusterValves, ValveWrenches
from gateway.control.thrusters import ThrusterCompensator, ThrusterLoopSettings

__all__ = ["ControlError", "DriveCommand", "JointCompensator", "JointLoopSettings", "LoopEvent",
           "ThrusterCompensator", "ThrusterLoopSettings", "ThrusterValves", "ValveWrenches"]
