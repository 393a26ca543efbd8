"""The simulated robot's joint drives taking their commands from outside its flight software."""
from __future__ import annotations

import numpy as np
import pytest

from simulator import scenario
from simulator.engine import DriveCommandError, Simulation


@pytest.fixture(scope="module")
def short():
    return scenario.load("capture", {"duration_s": 0.3})


def _steps(sim, drive=None):
    while sim.k < sim.n_steps:
        sim.step()
        if drive is not None:
            sim.command_drives(drive(sim))
    return sim.trace.arrays


def test_external_drives_without_a_command_are_the_flight_softwares_bit_for_bit(short):
    a = _steps(Simulation(short))
    b = _steps(Simulation(short, external_drives=True))
    for name in ("q", "v", "tau_cmd", "tau_act", "ft_meas", "ee"):
        assert np.array_equal(a[name], b[name]), name


def test_the_drives_apply_the_external_command_and_the_trace_keeps_the_desired_torque(short):
    sim = Simulation(short, external_drives=True)
    extra = np.array([50.0, -20.0, 0.0, 10.0])
    A = _steps(sim, lambda s: s.trace.arrays["tau_cmd"][s.k - 1] + extra)
    ref = _steps(Simulation(short))
    # tau_cmd stays the flight software's output (the desired torque on the arm bus)
    assert not np.array_equal(A["q"], ref["q"])
    # from the second step on the drives applied the previous step's desired torque + extra
    # (saturated at the limits), and the actual torque is that plus the friction
    np.testing.assert_array_equal(sim.drive_applied[1:],
                                  np.clip(A["tau_cmd"][:-1] + extra, -sim.robot.effort_limit, sim.robot.effort_limit))
    np.testing.assert_allclose(A["tau_act"], sim.drive_applied + A["tau_friction"], rtol=0, atol=1e-12)


def test_a_drive_command_is_saturated_at_the_torque_limits_as_a_drive_would(short):
    sim = Simulation(short, external_drives=True)
    sim.step()
    sim.command_drives(np.full(sim.robot.n_joints, 1e6))
    sim.step()
    np.testing.assert_array_equal(sim.drive_applied[1], sim.robot.effort_limit)


def test_bad_drive_commands_get_a_clear_error(short):
    with pytest.raises(DriveCommandError, match="external_drives=True"):
        Simulation(short).command_drives(np.zeros(4))
    sim = Simulation(short, external_drives=True)
    with pytest.raises(DriveCommandError, match="expected 4 finite torques"):
        sim.command_drives(np.zeros(3))
    with pytest.raises(DriveCommandError, match="expected 4 finite torques"):
        sim.command_drives([0.0, np.nan, 0.0, 0.0])


def test_the_outer_loop_can_leave_the_drives_headroom(short):
    A = _steps(Simulation(short, command_limit=0.5))
    limit = Simulation(short).robot.effort_limit
    assert np.all(np.abs(A["tau_cmd"]) <= 0.5 * limit + 1e-12)
    with pytest.raises(ValueError, match="command limit"):
        Simulation(short, command_limit=0.0)
