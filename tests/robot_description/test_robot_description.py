"""The URDF convention: any number of arms and joints, clear errors otherwise."""
from __future__ import annotations

import subprocess
import sys

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
    (lambda t: t.replace('<link name="imu">', '<link name="imu_x">')
     .replace('<child link="imu"/>', '<child link="imu_x"/>'), "no 'imu' link"),
    (lambda t: t.replace("arm0_ee", "arm0_tool"), "arm0_ee"),
    (lambda t: t.replace('<origin xyz="0 0 0" rpy="0 0 0"/>\n      <mass value="2400"/>',
                         '<origin xyz="0.1 0 0" rpy="0 0 0"/>\n      <mass value="2400"/>'), "centre of mass"),
    (lambda t: "<robot", "cannot parse"),
])
def test_convention_violations_are_named(edit, match):
    with pytest.raises(rd.DescriptionError, match=match):
        rd.from_urdf_text(edit(urdf_text(PAPER)))


def test_unknown_robot_is_a_clear_error():
    with pytest.raises(rd.DescriptionError, match="no such robot"):
        rd.load("no_such_robot")


# One field of the paper robot's URDF broken at a time. The first occurrences are arm0's:
# <mass value="100"/> and ixx="5.3" are arm0_link2's, <axis> is arm0_j1's, effort="300" arm0_j2's.
_LINK2_INERTIAL = ('    <inertial>\n      <origin xyz="1.5 0 0" rpy="0 0 0"/>\n      <mass value="100"/>\n'
                   '      <inertia ixx="5.3" ixy="0" ixz="0" iyy="106" iyz="0" izz="106"/>\n    </inertial>\n')
BAD_URDFS = {
    "no inertial": (lambda t: t.replace(_LINK2_INERTIAL, "", 1),
                    "link 'arm0_link2' in {f}: no mass, yet joint 'arm0_j2' moves it (add an <inertial>"),
    "negative mass": (lambda t: t.replace('<mass value="100"/>', '<mass value="-3"/>', 1),
                      "link 'arm0_link2' in {f}: mass -3 kg must be positive (set <mass value=...>"),
    "zero mass": (lambda t: t.replace('<mass value="100"/>', '<mass value="0"/>', 1),
                  "link 'arm0_link2' in {f}: mass 0 kg must be positive"),
    "NaN mass": (lambda t: t.replace('<mass value="100"/>', '<mass value="nan"/>', 1),
                 "link 'arm0_link2' in {f}: mass \"nan\" must be a finite number of kg"),
    "mass without value": (lambda t: t.replace('<mass value="100"/>', '<mass/>', 1),
                           "link 'arm0_link2' in {f}: <inertial> has no <mass value=...>"),
    "infinite inertia": (lambda t: t.replace('ixx="5.3"', 'ixx="inf"', 1),
                         "link 'arm0_link2' in {f}: <inertia ixx=\"inf\"> must be a finite number"),
    "negative moment": (lambda t: t.replace('iyy="106" iyz="0" izz="106"', 'iyy="-106" iyz="0" izz="106"', 1),
                        "link 'arm0_link2' in {f}: rotational inertia is not positive definite"),
    "products too large": (lambda t: t.replace('ixx="5.3" ixy="0"', 'ixx="5.3" ixy="50"', 1),
                           "link 'arm0_link2' in {f}: rotational inertia is not positive definite"),
    "triangle inequality": (lambda t: t.replace('iyy="106" iyz="0" izz="106"', 'iyy="10" iyz="0" izz="106"', 1),
                            "link 'arm0_link2' in {f}: principal moments 5.3, 10, 106 kg m^2 break the triangle"),
    "inertial origin": (lambda t: t.replace('<origin xyz="1.5 0 0"', '<origin xyz="1.5 0 inf"', 1),
                        "link 'arm0_link2' in {f}: <inertial><origin xyz=\"1.5 0 inf\"> must be 3 finite numbers"),
    "joint origin": (lambda t: t.replace('<origin xyz="4 0 0"', '<origin xyz="4 nan 0"', 1),
                     "joint 'arm0_j2' in {f}: <origin xyz=\"4 nan 0\"> must be 3 finite numbers"),
    "zero axis": (lambda t: t.replace('<axis xyz="0 0 1"/>', '<axis xyz="0 0 0"/>', 1),
                  "joint 'arm0_j1' in {f}: <axis xyz=\"0 0 0\"> must be a non-zero vector"),
    "NaN axis": (lambda t: t.replace('<axis xyz="0 0 1"/>', '<axis xyz="0 nan 1"/>', 1),
                 "joint 'arm0_j1' in {f}: <axis xyz=\"0 nan 1\"> must be a non-zero vector"),
    "negative torque limit": (lambda t: t.replace('effort="300"', 'effort="-300"', 1),
                              "joint 'arm0_j2' in {f}: <limit effort=\"-300\"> must be positive"),
    "massless spacecraft": (lambda t: t.replace(
        '    <inertial>\n      <origin xyz="0 0 0" rpy="0 0 0"/>\n      <mass value="2400"/>\n'
        '      <inertia ixx="3446" ixy="0" ixz="0" iyy="3446" iyz="0" izz="5808"/>\n    </inertial>\n', "", 1),
        "link 'spacecraft' in {f}: the spacecraft (root link) has no mass"),
}


def _bad_urdf(tmp_path, case):
    edit, message = BAD_URDFS[case]
    text = urdf_text(PAPER)
    broken = edit(text)
    assert broken != text, "the edit must break something"
    path = tmp_path / "my_robot.urdf"
    path.write_text(broken)
    return path, message.format(f=path)


@pytest.mark.parametrize("case", sorted(BAD_URDFS))
def test_unphysical_links_are_named_with_their_fix(tmp_path, case):
    path, message = _bad_urdf(tmp_path, case)
    with pytest.raises(rd.PhysicalValueError) as err:
        rd.load(path)
    assert message in str(err.value)


@pytest.mark.parametrize("case", sorted(BAD_URDFS))
def test_bsc_sim_reports_an_unphysical_robot_in_one_line(tmp_path, case):
    path, message = _bad_urdf(tmp_path, case)
    r = subprocess.run([sys.executable, "-m", "gateway.cli", "sim", "--robot", str(path), "--duration", "0.01",
                        "--out", str(tmp_path / "out"), "--quiet", "--no-plots", "--no-compare"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.startswith("bsc sim: error: ") and message in r.stderr, r.stderr


def test_a_thin_rod_on_the_triangle_bound_is_accepted():
    """Principal moments a + b = c (a thin rod) are physical; rounding just past it is tolerated."""
    text = urdf_text(PAPER).replace('ixx="5.3" ixy="0" ixz="0" iyy="106" iyz="0" izz="106"',
                                    'ixx="0.0001" ixy="0" ixz="0" iyy="106" iyz="0" izz="106.0002"', 1)
    robot = rd.from_urdf_text(text)
    assert robot.model.inertias[robot.arms[0].joints[1]].inertia[2, 2] == pytest.approx(106.0002)


def test_messages_name_the_file_given():
    with pytest.raises(rd.PhysicalValueError, match=r"in paper_robot\.urdf:"):
        rd.from_urdf_text(urdf_text(PAPER).replace('<mass value="100"/>', '<mass value="-3"/>', 1), name="paper_robot")


@pytest.mark.parametrize("name", sorted(SPECS))
def test_every_link_has_visual_geometry_and_the_dynamics_ignore_it(name):
    """Foxglove's 3D panel (and RViz) draw a link from its <visual>; the inertias come from
    <inertial> alone: the model without any <visual> is the same model."""
    import re
    import xml.etree.ElementTree as ET

    text = urdf_text(SPECS[name])
    links = ET.fromstring(text).findall("link")
    assert links and all(link.find("visual/geometry") is not None for link in links)
    bare = rd.from_urdf_text(re.sub(r"\s*<visual>.*?</visual>", "", text, flags=re.S))
    assert "<visual>" in text and "<visual>" not in bare.urdf
    full = rd.from_urdf_text(text)
    assert full.model.nq == bare.model.nq and full.model.nframes == bare.model.nframes
    for a, b in zip(full.model.inertias, bare.model.inertias):
        assert np.array_equal(a.toDynamicParameters(), b.toDynamicParameters())


def test_urdf_joints_are_the_link_to_link_transforms():
    """At q = 0 each URDF joint's origin is the child link's placement in the parent link's, as
    Pinocchio's frames give it."""
    import pinocchio as pin

    r = rd.load("three_arm")
    data = r.data()
    pin.framesForwardKinematics(r.model, data, r.neutral())
    joints = rd.urdf_joints(r.urdf)
    assert {j.kind for j in joints} == {"fixed", "revolute"} and len(joints) == len(_links(r.urdf)) - 1
    for j in joints:
        M = data.oMf[r.model.getFrameId(j.parent, pin.FrameType.BODY)].actInv(
            data.oMf[r.model.getFrameId(j.child, pin.FrameType.BODY)])
        assert np.allclose(M.translation, j.xyz, atol=1e-9)
        assert np.allclose(M.rotation, pin.rpy.rpyToMatrix(*j.rpy), atol=1e-9)
    with pytest.raises(rd.DescriptionError, match="origin and axis"):
        rd.urdf_joints(r.urdf.replace('<axis xyz="0 0 1"/>', '<axis xyz="0 0 0"/>', 1))


def _links(text):
    import xml.etree.ElementTree as ET

    return ET.fromstring(text).findall("link")
