"""Contact at an end effector (simulator/contact.py): the impulse it gives the robot, the forces
the F/T sensors see with it, and the scenario's errors."""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

import robot_description
from simulator import scenario
from simulator.contact import ContactError, Contacts
from simulator.dynamics import Dynamics, Friction
from simulator.engine import Simulation


@pytest.mark.parametrize("frame", ["world", "ee"])
def test_momentum_changes_by_the_contacts_impulse(frame):
    """No thrusters, no friction, internal motor torques: the robot's momentum (linear, and
    angular about the inertial origin) changes by the contact's impulse, summed over the 1 ms
    steps from the truth ``world_wrench`` at each step's start."""
    robot = robot_description.load("paper_robot")
    dyn = Dynamics(robot.model, Friction.none(robot.n_joints), 1e-3)
    dyn.contacts = Contacts(robot, [{"arm": "arm1", "onset_s": 0.05, "duration_s": 0.3, "force_n": [3.0, -20.0, 1.0],
                                     "moment_nm": [0.0, 0.5, 2.0], "frame": frame, "ramp_s": 0.0}])
    q = robot.neutral()
    q[7:] = [0.3, 1.2, -0.4, -1.0]
    dyn.q = q
    h0 = dyn.momentum_world()
    d = robot.model.createData()
    impulse = np.zeros(6)
    ee = robot.arms[1].ee_frame
    for k in range(500):
        pin.forwardKinematics(robot.model, d, dyn.q)
        pin.updateFramePlacements(robot.model, d)
        w = dyn.contacts.world_wrench(k * 1e-3, d.oMi)[1]
        p = d.oMf[ee].translation
        impulse += 1e-3 * np.concatenate([w[:3], w[3:] + np.cross(p, w[:3])])
        dyn.step(np.zeros(6), 5.0 * np.sin(np.arange(4) + k * 1e-2))
    dh = dyn.momentum_world() - h0
    if frame == "world":
        assert np.abs(impulse[:3] - [3.0 * 0.3, -20 * 0.3, 0.3]).max() < 1e-12
    # the contact is held over each step in its joint's axes, at the step start's placement:
    # within a step it turns and moves with the link, O(dt) of the impulse (measured 7e-5 of it)
    assert np.abs(dh - impulse).max() < 1e-3 * np.abs(impulse).max(), (dh, impulse)


def test_ft_truth_sees_the_contact():
    """A run with and a run without a contact: the same F/T truth up to its onset, then the
    touched arm's differs at once (the exact value is RNEA's with the external forces: the
    test below)."""
    base = scenario.load("capture").replace(duration_s=0.6)
    touched = base.replace()
    touched.data["contact"] = [{"arm": "arm0", "onset_s": 0.3, "duration_s": 0.2, "force_n": [0.0, 20.0, 0.0]}]
    a = Simulation(base).run().arrays
    b = Simulation(touched).run().arrays
    before = slice(0, 300)
    assert np.array_equal(a["ft_true"][before], b["ft_true"][before])
    onset = slice(301, 305)              # 20 N within the 20 ms ramp: 1 N per step
    diff = np.abs(a["ft_true"][onset, 0, :3] - b["ft_true"][onset, 0, :3]).max(axis=1)
    assert (diff > 0.2).all() and (np.diff(diff) > 0.2).all() and (diff < 5.0).all(), diff


def test_dynamics_f_is_rnea_with_the_external_forces():
    robot = robot_description.load("three_arm")
    dyn = Dynamics(robot.model, Friction.none(robot.n_joints), 1e-3)
    dyn.contacts = Contacts(robot, [{"arm": robot.arms[2].name, "onset_s": 0.0, "duration_s": 1.0,
                                     "force_n": [5.0, 2.0, -7.0], "moment_nm": [1.0, 0.0, 0.0], "ramp_s": 0.0}])
    rng = np.random.default_rng(3)
    q = robot.neutral()
    q[7:] = rng.uniform(-1, 1, robot.n_joints)
    v = np.zeros(robot.nv)
    v[6:] = rng.uniform(-0.5, 0.5, robot.n_joints)
    dyn.q, dyn.v = q.copy(), v.copy()
    tau_m = rng.uniform(-5, 5, robot.n_joints)
    a = dyn.step(np.zeros(6), tau_m)
    d = robot.model.createData()
    fext = dyn.contacts.fext(0.0, d, q)
    tau = np.concatenate([np.zeros(6), tau_m])
    assert np.abs(pin.rnea(robot.model, d, q, v, a, fext) - tau).max() < 1e-9
    for j in range(1, robot.model.njoints):
        assert np.abs(dyn.data_start.f[j].vector - d.f[j].vector).max() < 1e-9


@pytest.mark.parametrize("table, message", [
    ({"arm": "arm9", "onset_s": 1.0, "duration_s": 1.0, "force_n": [1, 0, 0]}, "no arm 'arm9'"),
    ({"arm": "arm0", "onset_s": 1.0, "duration_s": 0.0, "force_n": [1, 0, 0]}, "duration_s must be a number > 0"),
    ({"arm": "arm0", "onset_s": 1.0, "duration_s": 1.0, "force_n": [1, 0]}, "force_n must be 3 finite numbers"),
    ({"arm": "arm0", "onset_s": 1.0, "duration_s": 1.0}, "missing key(s) force_n"),
    ({"arm": "arm0", "onset_s": 1.0, "duration_s": 1.0, "force_n": [1, 0, 0], "where": "tip"}, "unknown key(s) where"),
    ({"arm": "arm0", "onset_s": 1.0, "duration_s": 1.0, "force_n": [1, 0, 0], "frame": "base"}, "frame must be"),
])
def test_bad_contact_tables_are_named(tmp_path, table, message):
    lines = ["[[contact]]"] + [f"{k} = {v!r}".replace("'", '"') for k, v in table.items()]
    path = tmp_path / "c.toml"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ContactError, match=message.replace("(", r"\(").replace(")", r"\)")):
        Simulation(scenario.load(path))
