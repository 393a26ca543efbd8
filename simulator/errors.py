"""The root of the simulator's errors: a scenario that cannot run, firmware options that do not go
together, a simulation that diverged."""


class SimulatorError(Exception):
    """Root of the simulator's exceptions."""
