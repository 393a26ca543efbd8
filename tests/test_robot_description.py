"""The URDF convention: any number of arms and joints, clear errors otherwise."""
from __future__ import annotations

import numpy as np
import pytest

import robot_description as rd
from robot_description.generate import PAPER, SPECS, urdf_text


def test_paper_robot_matches_the_paper():
    r = rd.load()
    assert [a.name for a in r.arms] == ["arm0", "arm1"]
    assert r.spacecraft_mass == 2400.0 and r.spacecraft_inertia[2, 2] == 5808.0
    m = r.model
    masses = [m.inertias[j].mass for j in r.arms[0].joints]
    assert masses == [200.0, 100.0]
    # mounted on the 2.1 m rim, 90 degrees apart
    a, b = r.arms[0].r_sc, r.arms[1].r_sc
    assert np.linalg.norm(a) == pytest.approx(2.1) and float(a @ b) == pytest.approx(0.0, abs=1e-9)


def test_three_arms_of_three_joints():
    r = rd.load("three_arm")
    assert len(r.arms) == 3 and all(a.n == 3 for a in r.arms)
    assert r.joint_names[:3] == ["center/j1", "center/j2", "center/j3"]


def test_shipped_urdfs_are_the_generators_output():
    for name, spec in SPECS.items():
        assert rd.BUILTIN[name].read_text() == urdf_text(spec)


@pytest.mark.parametrize("edit, match", [
    (lambda t: t.replace('<link name="imu"/>', '<link name="imu_x"/>').replace('<child link="imu"/>', '<child link="imu_x"/>'), "no 'imu' link"),
    (lambda t: t.replace("arm0_ee", "arm0_tool"), "arm0_ee"),
    (lambda t: t.replace('<origin xyz="0 0 0" rpy="0 0 0"/>\n      <mass value="2400"/>', '<origin xyz="0.1 0 0" rpy="0 0 0"/>\n      <mass value="2400"/>'), "centre of mass"),
    (lambda t: "<robot", "cannot parse"),
])
def test_convention_violations_are_named(edit, match):
    with pytest.raises(rd.DescriptionError, match=match):
        rd.from_urdf_text(edit(urdf_text(PAPER)))


def test_unknown_robot_is_a_clear_error():
    with pytest.raises(rd.DescriptionError, match="no such robot"):
        rd.load("no_such_robot")
