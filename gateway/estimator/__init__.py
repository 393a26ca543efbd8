"""The estimator: actual joint torques and thruster wrench from the base F/T sensors (docs/method.md).

The product runs :class:`.core.EstimatorCore` (the sync policy, compiled), which calls the
compiled kernels :mod:`.chain_kernel` (base motion, joint accelerations and torques) and
:mod:`.thruster_kernel` (the valve-aided thruster filter). The functions exported here are their
reference forms, the test oracles, shaped like Pinocchio's algorithms: build an
:class:`EstimatorModel` once from a ``robot_description.Robot``, make one :class:`EstimatorData`
per thread, then call e.g. ``joint_torques(model, data, q, dq, ddq, ft, a_s, w_s, dw_s)``. No I/O,
no transport. Equations, frames and filters: docs/estimator.md.
"""
from .model import EstimatorData, EstimatorError, EstimatorModel, EstimatorModelError
from .torques import bias_torques, joint_torque_matrix, joint_torques, joint_torques_simplified
from .wrench import arm_reaction, body_to_inertial, imu_to_body, spacecraft_inertial_moment, thruster_wrench

__all__ = [
    "EstimatorData", "EstimatorError", "EstimatorModel", "EstimatorModelError",
    "arm_reaction", "bias_torques", "body_to_inertial", "imu_to_body", "joint_torque_matrix",
    "joint_torques", "joint_torques_simplified", "spacecraft_inertial_moment", "thruster_wrench",
]
