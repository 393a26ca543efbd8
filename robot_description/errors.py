"""The root of the robot description's errors: a URDF or a thruster layout that cannot describe a
bsc robot."""


class DescriptionError(ValueError):
    """The URDF cannot be read, or does not follow the bsc robot convention."""
