"""Write URDF files that follow the bsc robot convention (see docs/robot-convention.md).

    python -m robot_description.generate            # rewrites the shipped URDFs
    python -m robot_description.generate --print three_arm

The shipped files in ``robot_description/urdf/`` are this module's output; any hand-written URDF
that follows the convention works just as well.
"""
from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, field
from pathlib import Path

URDF_DIR = Path(__file__).parent / "urdf"


@dataclass(frozen=True)
class LinkSpec:
    length_m: float
    mass_kg: float
    inertia_kgm2: float          # about the CoM, perpendicular to the link (both transverse axes)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)   # joint axis in the joint frame
    effort_nm: float = 500.0     # actuator torque limit
    velocity_rad_s: float = 1.0


@dataclass(frozen=True)
class ArmSpec:
    name: str
    mount_deg: float             # azimuth of the mount point on the spacecraft rim
    links: tuple[LinkSpec, ...]
    sensor_to_joint_m: float = 0.15   # the F/T sensor sits between the rim and joint 1


@dataclass(frozen=True)
class RobotSpec:
    name: str
    mass_kg: float
    inertia_kgm2: tuple[float, float, float]   # principal, about the CoM (body x, y, z)
    radius_m: float
    arms: tuple[ArmSpec, ...]
    imu_xyz_m: tuple[float, float, float] = (0.4, -0.3, 0.2)
    imu_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    height_m: float = 2.0        # the body's height along z (its <visual> box only)
    notes: list[str] = field(default_factory=list)


def _paper_arm(name: str, mount_deg: float) -> ArmSpec:
    # Boning & Dubowsky, Table I: link 1 4 m 200 kg 345 kg m^2; link 2 3 m 100 kg 106 kg m^2.
    return ArmSpec(name, mount_deg, (
        LinkSpec(4.0, 200.0, 345.0, effort_nm=600.0),
        LinkSpec(3.0, 100.0, 106.0, effort_nm=300.0),
    ))


# Spacecraft: 4.2 m diameter, 2400 kg, Izz 5808 kg m^2 (paper). The paper is planar; the
# transverse inertia is ours: a 2 m tall cylinder, m (3 r^2 + h^2) / 12 = 3446 kg m^2.
PAPER = RobotSpec(
    name="paper_robot", mass_kg=2400.0, inertia_kgm2=(3446.0, 3446.0, 5808.0), radius_m=2.1,
    arms=(_paper_arm("arm0", 45.0), _paper_arm("arm1", -45.0)),
)


def _spatial_arm(name: str, mount_deg: float) -> ArmSpec:
    return ArmSpec(name, mount_deg, (
        LinkSpec(2.0, 80.0, 30.0, axis=(0.0, 0.0, 1.0), effort_nm=400.0),
        LinkSpec(1.8, 60.0, 18.0, axis=(0.0, 1.0, 0.0), effort_nm=250.0),
        LinkSpec(1.2, 30.0, 4.0, axis=(0.0, 1.0, 0.0), effort_nm=120.0),
    ))


# A robot that is not the paper's: three spatial arms of three joints each, so that no code can
# get away with "two planar arms of two joints".
THREE_ARM = RobotSpec(
    name="three_arm", mass_kg=1500.0, inertia_kgm2=(1800.0, 2100.0, 2600.0), radius_m=1.6,
    arms=(_spatial_arm("left", 50.0), _spatial_arm("right", -50.0), _spatial_arm("center", 0.0)),
    imu_xyz_m=(-0.2, 0.5, -0.3), imu_rpy=(0.0, 0.0, math.pi / 2), height_m=1.6,
)

SPECS = {s.name: s for s in (PAPER, THREE_ARM)}


def random_spec(seed: int) -> RobotSpec:
    """A plausible free-flyer the tests have never seen: 2-3 arms of 2-4 revolute joints, mounted
    within +-60 degrees of the +x side (where the scenarios put their target); two joints both
    about z (planar), else the first about z, the second about y, the others about y or z; arms
    4.2-5.5 m long in links of uneven length, 5-90 kg each (lighter outwards); a spacecraft of
    800-2500 kg. For robustness studies (benchmarks/bench_accuracy.py --random)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    n_arms = int(rng.integers(2, 4))
    mounts = np.sort(rng.uniform(-60.0, 60.0, n_arms))
    while n_arms > 1 and np.diff(mounts).min() < 25.0:      # room between the mounts
        mounts = np.sort(rng.uniform(-60.0, 60.0, n_arms))
    arms = []
    for k, mount in enumerate(mounts):
        n = int(rng.integers(2, 5))
        lengths = rng.uniform(0.6, 2.2, n)
        lengths *= rng.uniform(4.2, 5.5) / lengths.sum()
        mass = 90.0 * rng.uniform(0.5, 1.0)
        links = []
        for i, length in enumerate(lengths):
            if i == 0 or n == 2:               # two joints: a planar arm (a yaw and a pitch reach no plane)
                axis = (0.0, 0.0, 1.0)
            elif i == 1 or rng.random() < 0.7:
                axis = (0.0, 1.0, 0.0)
            else:                              # (not x: a roll about the link itself moves no point of it)
                axis = (0.0, 0.0, 1.0)
            m = max(5.0, mass)
            links.append(LinkSpec(round(float(length), 3), round(m, 1), round(m * length ** 2 / 12.0, 2), axis=axis,
                                  effort_nm=round(float(150.0 + 60.0 * m * length / 10.0), 0)))
            mass *= rng.uniform(0.4, 0.8)
        arms.append(ArmSpec(f"arm{k}", float(round(mount, 1)), tuple(links)))
    m_s = float(rng.uniform(800.0, 2500.0))
    r = float(rng.uniform(1.3, 2.0))
    i_xy = m_s * (3 * r ** 2 + 1.6 ** 2) / 12.0
    inertia = (round(i_xy * rng.uniform(0.8, 1.2), 1), round(i_xy * rng.uniform(0.8, 1.2), 1),
               round(m_s * r ** 2 / 2, 1))
    return RobotSpec(name=f"random{seed}", mass_kg=round(m_s, 1), inertia_kgm2=inertia, radius_m=round(r, 2),
                     arms=tuple(arms), imu_xyz_m=(0.3, -0.2, 0.1))


def _f(x: float) -> str:
    return f"{x:.9g}"


def _xyz(v) -> str:
    return " ".join(_f(c) for c in v)


# Visual geometry: for viewers (Foxglove's 3D panel, RViz) only; the dynamics read <inertial>.
# Along x (a link's direction from its joint) a URDF cylinder, which lies along z, is turned by
# pitch pi/2.
_ALONG_X = f"0 {math.pi / 2:.9g} 0"
_MATERIALS = (("body", "0.78 0.78 0.8 1"), ("link", "0.2 0.45 0.85 1"), ("sensor", "0.95 0.6 0.1 1"),
              ("tool", "0.85 0.2 0.2 1"))


def _visual(geometry: str, material: str, xyz: str = "0 0 0", rpy: str = "0 0 0") -> list[str]:
    return ["    <visual>", f'      <origin xyz="{xyz}" rpy="{rpy}"/>', f"      <geometry>{geometry}</geometry>",
            f'      <material name="{material}"/>', "    </visual>"]


def link_radius_m(length_m: float) -> float:
    """The radius of a link's visual cylinder: thicker for longer links."""
    return 0.04 + 0.03 * length_m


def urdf_text(spec: RobotSpec) -> str:
    ixx, iyy, izz = spec.inertia_kgm2
    # the body as a box inscribed in the rim (its corners on the rim circle)
    side = spec.radius_m * math.sqrt(2.0)
    out = [
        '<?xml version="1.0"?>',
        "<!-- Generated by robot_description/generate.py; convention: docs/robot-convention.md -->",
        f'<robot name="{spec.name}">',
        *(f'  <material name="{name}"><color rgba="{rgba}"/></material>' for name, rgba in _MATERIALS),
        '  <link name="spacecraft">',
        "    <inertial>",
        '      <origin xyz="0 0 0" rpy="0 0 0"/>',
        f'      <mass value="{_f(spec.mass_kg)}"/>',
        f'      <inertia ixx="{_f(ixx)}" ixy="0" ixz="0" iyy="{_f(iyy)}" iyz="0" izz="{_f(izz)}"/>',
        "    </inertial>",
        *_visual(f'<box size="{_xyz((side, side, spec.height_m))}"/>', "body"),
        "  </link>",
        '  <link name="imu">',
        *_visual('<box size="0.2 0.15 0.1"/>', "sensor"),
        "  </link>",
        '  <joint name="imu_mount" type="fixed">',
        '    <parent link="spacecraft"/><child link="imu"/>',
        f'    <origin xyz="{_xyz(spec.imu_xyz_m)}" rpy="{_xyz(spec.imu_rpy)}"/>',
        "  </joint>",
    ]
    for arm in spec.arms:
        a = math.radians(arm.mount_deg)
        rim = (spec.radius_m * math.cos(a), spec.radius_m * math.sin(a), 0.0)
        out += [
            f'  <link name="{arm.name}_ft_sensor">',
            # the sensor puck, from the rim to joint 1
            *_visual(f'<cylinder radius="0.15" length="{_f(arm.sensor_to_joint_m)}"/>', "sensor",
                     xyz=f"{_f(arm.sensor_to_joint_m / 2)} 0 0", rpy=_ALONG_X),
            "  </link>",
            f'  <joint name="{arm.name}_ft_mount" type="fixed">',
            f'    <parent link="spacecraft"/><child link="{arm.name}_ft_sensor"/>',
            f'    <origin xyz="{_xyz(rim)}" rpy="0 0 {_f(a)}"/>',
            "  </joint>",
        ]
        parent, offset = f"{arm.name}_ft_sensor", arm.sensor_to_joint_m
        for k, link in enumerate(arm.links, start=1):
            child = f"{arm.name}_link{k}"
            out += [
                f'  <link name="{child}">',
                "    <inertial>",
                f'      <origin xyz="{_f(link.length_m / 2)} 0 0" rpy="0 0 0"/>',
                f'      <mass value="{_f(link.mass_kg)}"/>',
                f'      <inertia ixx="{_f(link.inertia_kgm2 / 20)}" ixy="0" ixz="0" '
                f'iyy="{_f(link.inertia_kgm2)}" iyz="0" izz="{_f(link.inertia_kgm2)}"/>',
                "    </inertial>",
                # the link from its joint to the next: a cylinder, and a sphere for the joint
                *_visual(f'<cylinder radius="{_f(link_radius_m(link.length_m))}" length="{_f(link.length_m)}"/>',
                         "link", xyz=f"{_f(link.length_m / 2)} 0 0", rpy=_ALONG_X),
                *_visual(f'<sphere radius="{_f(1.3 * link_radius_m(link.length_m))}"/>', "link"),
                "  </link>",
                f'  <joint name="{arm.name}_j{k}" type="revolute">',
                f'    <parent link="{parent}"/><child link="{child}"/>',
                f'    <origin xyz="{_f(offset)} 0 0" rpy="0 0 0"/>',
                f'    <axis xyz="{_xyz(link.axis)}"/>',
                f'    <limit lower="-3.1" upper="3.1" effort="{_f(link.effort_nm)}" '
                f'velocity="{_f(link.velocity_rad_s)}"/>',
                "  </joint>",
            ]
            parent, offset = child, link.length_m
        out += [
            f'  <link name="{arm.name}_ee">',
            *_visual('<sphere radius="0.12"/>', "tool"),
            "  </link>",
            f'  <joint name="{arm.name}_ee_mount" type="fixed">',
            f'    <parent link="{parent}"/><child link="{arm.name}_ee"/>',
            f'    <origin xyz="{_f(offset)} 0 0" rpy="0 0 0"/>',
            "  </joint>",
        ]
    out.append("</robot>")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--print", dest="show", choices=sorted(SPECS), help="print one URDF to stdout")
    args = ap.parse_args(argv)
    if args.show:
        print(urdf_text(SPECS[args.show]), end="")
        return 0
    URDF_DIR.mkdir(exist_ok=True)
    for name, spec in SPECS.items():
        (URDF_DIR / f"{name}.urdf").write_text(urdf_text(spec))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
