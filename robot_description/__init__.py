"""The robot description: a URDF that follows the bsc convention, read into a Pinocchio model.

Both the simulator (its truth) and the gateway (its belief) read the robot through
:func:`load`. The convention (docs/robot-convention.md) in short:

- the root link is the spacecraft; its frame is the body frame, with its origin at the
  spacecraft's centre of mass C (the reference point of the thruster wrench);
- a massless link ``imu`` fixed to the spacecraft is the IMU frame;
- each manipulator ``<arm>`` hangs from a massless link ``<arm>_ft_sensor`` fixed to the
  spacecraft: the six-axis F/T sensor frame (origin S_j, orientation R_j);
- below the sensor, a serial chain of revolute joints, ending in a massless link ``<arm>_ee``.

Arms are found from the links, not from a count: any number of arms with any number of joints.
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from robot_description.errors import DescriptionError  # noqa: F401 - the package's errors' root

URDF_DIR = Path(__file__).parent / "urdf"
BUILTIN = {p.stem: p for p in sorted(URDF_DIR.glob("*.urdf"))}
DEFAULT = "paper_robot"

SENSOR_SUFFIX = "_ft_sensor"
EE_SUFFIX = "_ee"
IMU_FRAME = "imu"




class PhysicalValueError(DescriptionError):
    """A number in the URDF that no physical robot has: a missing or non-positive mass, an
    inertia that is not positive definite or breaks the triangle inequality, a non-finite
    origin, a zero joint axis, a non-positive torque limit. The message names the link or joint,
    the file and the fix."""


@dataclass(frozen=True, slots=True)
class Arm:
    """One manipulator, as indices into the Pinocchio model."""

    name: str
    sensor_frame: int            # frame id of the F/T sensor (fixed to the spacecraft)
    ee_frame: int                # frame id of the end effector
    joints: tuple[int, ...]      # Pinocchio joint ids, proximal first
    joint_names: tuple[str, ...]
    iq: tuple[int, ...]          # indices into q
    iv: tuple[int, ...]          # indices into v (and tau)
    r_sc: np.ndarray             # S_j - C in the spacecraft frame, m
    R_sc: np.ndarray             # sensor frame -> spacecraft frame rotation

    @property
    def n(self) -> int:
        return len(self.joints)


@dataclass(frozen=True, slots=True)
class Robot:
    """A robot model built once from its URDF; make scratch ``Data`` with :meth:`data`."""

    name: str
    urdf: str                    # the URDF text (logs carry it so they are self-contained)
    model: pin.Model             # free-flyer root; gravity zero (orbit)
    arms: tuple[Arm, ...]
    imu_frame: int
    r_imu: np.ndarray            # IMU origin - C, spacecraft frame, m
    R_imu: np.ndarray            # IMU frame -> spacecraft frame

    def data(self) -> pin.Data:
        return self.model.createData()

    @property
    def nq(self) -> int:
        return self.model.nq

    @property
    def nv(self) -> int:
        return self.model.nv

    @property
    def n_joints(self) -> int:
        return self.model.nv - 6

    @property
    def spacecraft_mass(self) -> float:
        return float(self.model.inertias[1].mass)

    @property
    def spacecraft_inertia(self) -> np.ndarray:
        """Inertia of the spacecraft alone about C, body frame, kg m^2."""
        return np.array(self.model.inertias[1].inertia)

    @property
    def joint_names(self) -> list[str]:
        """``<arm>/<joint>`` for every actuated joint, in v order (after the 6 base dofs)."""
        return [f"{a.name}/{j}" for a in self.arms for j in a.joint_names]

    @property
    def effort_limit(self) -> np.ndarray:
        return np.array(self.model.effortLimit[6:])

    def neutral(self) -> np.ndarray:
        return pin.neutral(self.model)


@dataclass(frozen=True, slots=True)
class UrdfJoint:
    """One ``<joint>`` as the URDF states it: the child link's frame in the parent link's frame
    is ``origin`` (``xyz`` m, then ``rpy`` rad: fixed-axis roll, pitch, yaw), then a turn of the
    joint angle about ``axis`` (unit, child frame) for a revolute or continuous joint.

    What a viewer's frame tree is made of (link to link), where Pinocchio's model merges the
    links that fixed joints hold together."""

    name: str
    kind: str                            # revolute, continuous, fixed, ...
    parent: str
    child: str
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]
    axis: tuple[float, float, float]


def urdf_joints(text: str) -> tuple[UrdfJoint, ...]:
    """Every joint of a URDF, in document order (URDF defaults: zero origin, axis x).
    Raises :class:`DescriptionError` for text that is not XML or a joint without its links or
    with an origin or axis that is not 3 finite numbers (:func:`from_urdf_text` checks the rest)."""
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise DescriptionError(f"cannot parse URDF: {exc}") from exc
    out = []
    for j in root.findall("joint"):
        name = j.get("name") or "?"
        parent, child = j.find("parent"), j.find("child")
        if parent is None or child is None or not parent.get("link") or not child.get("link"):
            raise DescriptionError(f"joint {name!r}: needs <parent link=...> and <child link=...>")
        origin, axis_el = j.find("origin"), j.find("axis")
        xyz = _numbers(origin.get("xyz", "0 0 0") if origin is not None else "0 0 0", 3)
        rpy = _numbers(origin.get("rpy", "0 0 0") if origin is not None else "0 0 0", 3)
        axis = _numbers(axis_el.get("xyz") if axis_el is not None else "1 0 0", 3)
        norm = math.hypot(*axis) if axis is not None else 0.0
        if xyz is None or rpy is None or not norm > 1e-12:
            raise DescriptionError(f"joint {name!r}: origin and axis must be 3 finite numbers (a non-zero axis)")
        out.append(UrdfJoint(name, j.get("type") or "fixed", parent.get("link"), child.get("link"),
                             tuple(xyz), tuple(rpy), tuple(a / norm for a in axis)))
    return tuple(out)


def resolve(robot: str | Path | None) -> Path:
    """A built-in robot name (``paper_robot``, ``three_arm``) or a path to a URDF file."""
    if robot is None:
        robot = DEFAULT
    if str(robot) in BUILTIN:
        return BUILTIN[str(robot)]
    path = Path(robot)
    if not path.is_file():
        raise DescriptionError(f"no such robot: {robot!s} (built-in: {', '.join(BUILTIN)}; or a .urdf path)")
    return path


def load(robot: str | Path | None = None) -> Robot:
    """Read a convention-following URDF (built-in name or path) into a :class:`Robot`."""
    path = resolve(robot)
    text = path.read_text()
    return from_urdf_text(text, name=path.stem, source=path.name if str(robot) in BUILTIN else str(path))


def from_urdf_text(text: str, name: str = "robot", source: str | None = None) -> Robot:
    """A :class:`Robot` from URDF text; ``source`` names it in error messages (default
    ``<name>.urdf``)."""
    source = source or f"{name}.urdf"
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise DescriptionError(f"cannot parse URDF {source}: {exc}") from exc
    # Checked before Pinocchio sees the file: its URDF parser drops an <inertial> it cannot
    # read (the link becomes massless) and accepts a zero axis as z, negative masses and
    # impossible inertias, all of which surface later as NaN in the dynamics.
    _check_values(root, source)
    try:
        model = pin.buildModelFromXML(text, pin.JointModelFreeFlyer())
    except (RuntimeError, ValueError) as exc:
        raise DescriptionError(f"cannot parse URDF {source}: {exc}") from exc
    model.gravity.linear[:] = 0.0     # orbit: gravity gradient neglected, accelerometers read 0 g
    _check_masses(model, root, source)
    return _interpret(model, text, name)


# -- physical values -------------------------------------------------------------------------
# Principal moments may break the triangle inequality by this fraction of the largest one:
# a thin rod (Ixx ~ 0, Iyy = Izz) sits on the bound, and exported CAD values are rounded.
TRIANGLE_TOLERANCE = 1e-6
_INERTIA_KEYS = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")


def _numbers(text: str | None, n: int) -> list[float] | None:
    """``n`` finite numbers from a URDF attribute (space separated), or None."""
    try:
        xs = [float(x) for x in (text or "").split()]
    except ValueError:
        return None
    return xs if len(xs) == n and all(math.isfinite(x) for x in xs) else None


def _check_origin(el: ET.Element | None, what: str, where: str) -> None:
    if el is None:
        return
    for attr in ("xyz", "rpy"):
        value = el.get(attr)
        if value is not None and _numbers(value, 3) is None:
            raise PhysicalValueError(f"{what}: {where}<origin {attr}=\"{value}\"> must be 3 finite numbers")


def _check_values(root: ET.Element, source: str) -> None:
    """Every number that reaches the dynamics: inertials, origins, joint axes and limits."""
    moved = {j.find("child").get("link") for j in root.findall("joint")
             if j.get("type") != "fixed" and j.find("child") is not None}
    for link in root.findall("link"):
        what = f"link {link.get('name')!r} in {source}"
        for tag in ("visual", "collision"):
            for el in link.iter(tag):
                _check_origin(el.find("origin"), what, f"<{tag}>")
        inertial = link.find("inertial")
        if inertial is None:
            continue
        # a link a joint moves needs its mass; any other may be massless (no <inertial>)
        fix = ("set <mass value=...> to the link's mass in kg" if link.get("name") in moved else
               "set <mass value=...> to the link's mass in kg, or remove the <inertial> of a massless link")
        _check_origin(inertial.find("origin"), what, "<inertial>")
        mass_el = inertial.find("mass")
        value = None if mass_el is None else mass_el.get("value")
        if value is None:
            raise PhysicalValueError(f"{what}: <inertial> has no <mass value=...> ({fix})")
        mass = _numbers(value, 1)
        if mass is None:
            raise PhysicalValueError(f"{what}: mass \"{value}\" must be a finite number of kg")
        if mass[0] <= 0.0:
            raise PhysicalValueError(f"{what}: mass {mass[0]:g} kg must be positive ({fix})")
        inertia_el = inertial.find("inertia")
        if inertia_el is None:
            raise PhysicalValueError(f"{what}: <inertial> has no <inertia ixx=... iyy=... izz=.../> (the "
                                     "rotational inertia about the centre of mass, kg m^2)")
        values = {}
        for key in _INERTIA_KEYS:
            x = _numbers(inertia_el.get(key), 1)
            if x is None:
                raise PhysicalValueError(f"{what}: <inertia {key}=\"{inertia_el.get(key)}\"> must be a finite "
                                         "number of kg m^2 (all six of ixx ixy ixz iyy iyz izz)")
            values[key] = x[0]
        _check_inertia(values, what)
    for joint in root.findall("joint"):
        what = f"joint {joint.get('name')!r} in {source}"
        _check_origin(joint.find("origin"), what, "")
        kind = joint.get("type")
        axis_el = joint.find("axis")
        if kind in ("revolute", "continuous", "prismatic") and axis_el is not None:
            axis = _numbers(axis_el.get("xyz"), 3)
            if axis is None or math.hypot(*axis) < 1e-12:
                raise PhysicalValueError(f"{what}: <axis xyz=\"{axis_el.get('xyz')}\"> must be a non-zero vector of "
                                         "3 finite numbers (the direction the joint turns about, joint frame)")
        limit = joint.find("limit")
        if limit is None:
            continue
        for attr in ("lower", "upper", "effort", "velocity"):
            value = limit.get(attr)
            if value is not None and _numbers(value, 1) is None:
                raise PhysicalValueError(f"{what}: <limit {attr}=\"{value}\"> must be a finite number")
        effort = limit.get("effort")
        if kind in ("revolute", "continuous", "prismatic") and effort is not None and float(effort) <= 0.0:
            raise PhysicalValueError(f"{what}: <limit effort=\"{effort}\"> must be positive (the motor's torque "
                                     "limit, N m; friction is a fraction of it)")


def _check_inertia(values: dict[str, float], what: str) -> None:
    I = np.array([[values["ixx"], values["ixy"], values["ixz"]],
                  [values["ixy"], values["iyy"], values["iyz"]],
                  [values["ixz"], values["iyz"], values["izz"]]])
    moments = np.linalg.eigvalsh(I)       # ascending: the principal moments
    a, b, c = moments.tolist()
    if a <= 0.0:
        raise PhysicalValueError(
            f"{what}: rotational inertia is not positive definite (principal moments {a:.6g}, {b:.6g}, "
            f"{c:.6g} kg m^2): ixx, iyy, izz must be positive and the products ixy, ixz, iyz small enough")
    if a + b < c * (1.0 - TRIANGLE_TOLERANCE):
        raise PhysicalValueError(
            f"{what}: principal moments {a:.6g}, {b:.6g}, {c:.6g} kg m^2 break the triangle inequality "
            f"({a:.6g} + {b:.6g} < {c:.6g}): no rigid body has them (the inertia is about the centre of "
            "mass, in the <inertial><origin> frame; check ixx, iyy, izz)")


def _check_masses(model: pin.Model, root: ET.Element, source: str) -> None:
    """Every body that moves carries mass: a link with no <inertial> (and none fixed to it)
    makes a joint of zero inertia, so the mass matrix is singular."""
    children = {j.get("name"): j.find("child").get("link") for j in root.findall("joint")
                if j.find("child") is not None}
    roots = {link.get("name") for link in root.findall("link")} - set(children.values())
    for j in range(1, model.njoints):
        if model.inertias[j].mass > 0.0:
            continue
        if j == 1:
            spacecraft = roots.pop() if len(roots) == 1 else "spacecraft"
            raise PhysicalValueError(
                f"link {spacecraft!r} in {source}: the spacecraft (root link) has no mass (add an <inertial> "
                "with <mass value=...> and <inertia .../> about its centre of mass)")
        link = children.get(model.names[j], model.names[j])
        raise PhysicalValueError(
            f"link {link!r} in {source}: no mass, yet joint {model.names[j]!r} moves it (add an <inertial> "
            "with <mass value=...> and <inertia .../>)")


def _frame(model: pin.Model, name: str) -> int | None:
    # A massless link becomes a BODY frame; the fixed joint to it a FIXED_JOINT frame at the same place.
    for i, f in enumerate(model.frames):
        if f.name == name and f.type == pin.FrameType.BODY:
            return i
    return None


def _placement_in_base(model: pin.Model, frame_id: int) -> pin.SE3:
    f = model.frames[frame_id]
    if f.parentJoint != 1:
        raise DescriptionError(f"frame {f.name!r} must be fixed to the spacecraft (root link)")
    return f.placement


def _interpret(model: pin.Model, text: str, name: str) -> Robot:
    if model.njoints < 2 or model.joints[1].shortname() != "JointModelFreeFlyer":
        raise DescriptionError(f"{name}: the root must be the spacecraft on a free-flyer joint")
    base = model.inertias[1]
    if np.linalg.norm(base.lever) > 1e-9:
        raise DescriptionError(
            f"{name}: the spacecraft link origin must be its centre of mass (inertial origin "
            f"{base.lever.round(4).tolist()}); the thruster wrench is referred to C")
    imu = _frame(model, IMU_FRAME)
    if imu is None:
        raise DescriptionError(f"{name}: no '{IMU_FRAME}' link fixed to the spacecraft")
    imu_M = _placement_in_base(model, imu)

    arms = []
    sensors = sorted((f.name[: -len(SENSOR_SUFFIX)], i) for i, f in enumerate(model.frames)
                     if f.name.endswith(SENSOR_SUFFIX) and f.type == pin.FrameType.BODY)
    if not sensors:
        raise DescriptionError(f"{name}: no manipulator (no '<arm>{SENSOR_SUFFIX}' link)")
    for arm_name, sensor in sensors:
        M = _placement_in_base(model, sensor)
        first = [j for j in range(2, model.njoints)
                 if model.parents[j] == 1 and model.frames[_parent_body_frame(model, j)].name
                 == arm_name + SENSOR_SUFFIX]
        if len(first) != 1:
            raise DescriptionError(f"{name}: arm {arm_name!r} must have exactly one joint under its sensor")
        chain = [first[0]]
        while True:
            children = [j for j in range(2, model.njoints) if model.parents[j] == chain[-1]]
            if not children:
                break
            if len(children) > 1:
                raise DescriptionError(f"{name}: arm {arm_name!r} branches; each arm must be a serial chain")
            chain.append(children[0])
        for j in chain:
            if not model.joints[j].shortname().startswith("JointModelR") or model.joints[j].nq != 1:
                raise DescriptionError(f"{name}: joint {model.names[j]!r} is not a revolute joint")
        ee = _frame(model, arm_name + EE_SUFFIX)
        if ee is None or model.frames[ee].parentJoint != chain[-1]:
            raise DescriptionError(f"{name}: arm {arm_name!r} needs a '{arm_name}{EE_SUFFIX}' link on its last link")
        arms.append(Arm(
            name=arm_name, sensor_frame=sensor, ee_frame=ee, joints=tuple(chain),
            joint_names=tuple(model.names[j].removeprefix(arm_name + "_") for j in chain),
            iq=tuple(model.joints[j].idx_q for j in chain), iv=tuple(model.joints[j].idx_v for j in chain),
            r_sc=np.array(M.translation), R_sc=np.array(M.rotation),
        ))
    n_arm_joints = sum(a.n for a in arms)
    if n_arm_joints != model.nv - 6:
        raise DescriptionError(f"{name}: {model.nv - 6 - n_arm_joints} joint(s) belong to no arm")
    # v order = arms in name order, proximal first: the gateway's vectors rely on it
    order = [i for a in arms for i in a.iv]
    if order != list(range(6, model.nv)):
        raise DescriptionError(f"{name}: joints must be declared arm by arm, proximal first")
    return Robot(name=name, urdf=text, model=model, arms=tuple(arms), imu_frame=imu,
                 r_imu=np.array(imu_M.translation), R_imu=np.array(imu_M.rotation))


def _parent_body_frame(model: pin.Model, joint: int) -> int:
    """The BODY frame of the link a joint hangs from (its URDF parent link)."""
    f = model.frames[model.getFrameId(model.names[joint], pin.FrameType.JOINT)]
    return f.parentFrame if model.frames[f.parentFrame].type == pin.FrameType.BODY else \
        model.frames[f.parentFrame].parentFrame


def perturbed(robot: Robot, rel: float, seed: int = 0) -> Robot:
    """The same robot with every mass and inertia scaled by a random factor within +-``rel``.

    For robustness studies: the gateway believes this model while the simulator runs the truth.
    CoM positions are kept; inertia tensors are scaled as a whole so they stay physical.
    """
    rng = np.random.default_rng(seed)
    model = robot.model.copy()
    for j in range(1, model.njoints):
        Y = model.inertias[j]
        s = 1.0 + rel * rng.choice([-1.0, 1.0])
        model.inertias[j] = pin.Inertia(Y.mass * s, Y.lever, Y.inertia * s)
    return Robot(name=robot.name + f"~{rel:g}", urdf=robot.urdf, model=model, arms=robot.arms,
                 imu_frame=robot.imu_frame, r_imu=robot.r_imu, R_imu=robot.R_imu)
