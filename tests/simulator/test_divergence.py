"""A state that stops being finite stops the simulation at that step, saying what and where."""
from __future__ import annotations

import dataclasses

import numpy as np
import pinocchio as pin
import pytest

import robot_description
from simulator import scenario
from simulator.dynamics import DivergenceError, Dynamics, Friction
from simulator.engine import Simulation


def test_a_nan_input_is_named_and_the_state_kept():
    robot = robot_description.load()
    dyn = Dynamics(robot.model, Friction.none(robot.n_joints), 1e-3, robot.joint_names)
    dyn.v[6:] = 0.1
    q0, v0 = dyn.q.copy(), dyn.v.copy()
    tau = np.zeros(robot.n_joints)
    tau[robot.joint_names.index("arm0/j2")] = np.nan
    with pytest.raises(DivergenceError, match=r"^simulation diverged: the motor torque of joint arm0/j2 is NaN \("):
        dyn.step(np.zeros(6), tau)
    assert np.array_equal(dyn.q, q0) and np.array_equal(dyn.v, v0)   # left at the step's start


def test_a_massless_link_stops_the_run_at_the_first_step():
    """A model that skipped the description's checks: arm0/j2 moves a body of zero mass."""
    robot = robot_description.load()
    model = robot.model.copy()
    j2 = robot.arms[0].joints[1]
    model.inertias[j2] = pin.Inertia(0.0, np.zeros(3), np.zeros((3, 3)))
    broken = dataclasses.replace(robot, model=model)
    sim = Simulation(scenario.load("capture", {"duration_s": 0.05}), robot=broken)
    with pytest.raises(DivergenceError) as err:
        sim.run()
    assert str(err.value) == ("simulation diverged at t = 0.001 s: every velocity (spacecraft and joints) is NaN; "
                              "the body joint arm0/j2 moves has mass 0 kg "
                              "(check the robot's inertias and the controller gains)")
    assert err.value.t_s == pytest.approx(1e-3) and sim.k == 0


def test_a_finite_but_absurd_input_is_caught_in_the_state():
    """1e308 N is a finite input; the state it produces is not, and no body is to blame."""
    robot = robot_description.load()
    dyn = Dynamics(robot.model, Friction.none(robot.n_joints), 1e-3)
    with pytest.raises(DivergenceError) as err:
        dyn.step(np.array([1e308, 0.0, 0.0, 0.0, 0.0, 0.0]), np.zeros(robot.n_joints))
    assert str(err.value) == ("simulation diverged: every velocity (spacecraft and joints) is NaN "
                              "(check the robot's inertias and the controller gains)")
