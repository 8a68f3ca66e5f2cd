"""The mobile manipulator as one URDF: planar x/y/yaw joints, a box base and the Panda on top."""

from __future__ import annotations

import copy
import xml.etree.ElementTree as ET
from pathlib import Path

import pybullet_data

from schemas.world import RobotSpec

BASE_X_JOINT = "base_x"
BASE_Y_JOINT = "base_y"
BASE_YAW_JOINT = "base_yaw"
BASE_LINK = "base_link"
ARM_ROOT_LINK = "panda_link0"
BASE_MASS = 40.0


def _link(name: str, mass: float, inertia: float) -> ET.Element:
    link = ET.Element("link", name=name)
    inertial = ET.SubElement(link, "inertial")
    ET.SubElement(inertial, "origin", xyz="0 0 0", rpy="0 0 0")
    ET.SubElement(inertial, "mass", value=f"{mass}")
    ET.SubElement(inertial, "inertia", ixx=f"{inertia}", iyy=f"{inertia}", izz=f"{inertia}", ixy="0", ixz="0", iyz="0")
    return link


def _joint(name: str, kind: str, parent: str, child: str, axis: str = "0 0 0", xyz: str = "0 0 0") -> ET.Element:
    joint = ET.Element("joint", name=name, type=kind)
    ET.SubElement(joint, "parent", link=parent)
    ET.SubElement(joint, "child", link=child)
    ET.SubElement(joint, "origin", xyz=xyz, rpy="0 0 0")
    ET.SubElement(joint, "axis", xyz=axis)
    if kind == "prismatic":
        # A flat far larger than any world; the velocity controller does the limiting.
        ET.SubElement(joint, "limit", lower="-1000", upper="1000", effort="100000", velocity="10")
    return joint


def _base_box(robot: RobotSpec) -> ET.Element:
    size = robot.base_size
    link = _link(BASE_LINK, BASE_MASS, BASE_MASS * (size.x**2 + size.y**2) / 12)
    # A sliver of clearance under the box: the base glides on its joints, not on floor friction.
    clearance = 0.01
    height = size.z - clearance
    centre = f"0 0 {clearance + height / 2}"
    for tag in ("visual", "collision"):
        element = ET.SubElement(link, tag)
        ET.SubElement(element, "origin", xyz=centre, rpy="0 0 0")
        geometry = ET.SubElement(element, "geometry")
        ET.SubElement(geometry, "box", size=f"{size.x} {size.y} {height}")
        if tag == "visual":
            material = ET.SubElement(element, "material", name="base_grey")
            ET.SubElement(material, "color", rgba="0.3 0.3 0.35 1")
    return link


def mobile_manipulator_urdf(robot: RobotSpec) -> str:
    """URDF text: world -> x -> y -> yaw -> base box -> (fixed at arm_mount) -> the Panda's links."""
    arm_path = Path(pybullet_data.getDataPath()) / robot.arm_urdf
    arm = ET.parse(arm_path).getroot()
    root = ET.Element("robot", name="tether_mobile_panda")
    root.append(_link("world", 0.0, 0.0))
    root.append(_link("base_x_link", 0.5, 0.01))
    root.append(_link("base_y_link", 0.5, 0.01))
    root.append(_base_box(robot))
    root.append(_joint(BASE_X_JOINT, "prismatic", "world", "base_x_link", axis="1 0 0"))
    root.append(_joint(BASE_Y_JOINT, "prismatic", "base_x_link", "base_y_link", axis="0 1 0"))
    root.append(_joint(BASE_YAW_JOINT, "continuous", "base_y_link", BASE_LINK, axis="0 0 1"))
    mount = robot.arm_mount
    root.append(_joint("arm_mount", "fixed", BASE_LINK, ARM_ROOT_LINK, xyz=f"{mount.x} {mount.y} {mount.z}"))
    mesh_dir = arm_path.parent
    for element in arm:
        element = copy.deepcopy(element)
        for mesh in element.iter("mesh"):
            filename = mesh.get("filename", "")
            if filename.startswith("package://"):
                mesh.set("filename", str(mesh_dir / filename.removeprefix("package://")))
        root.append(element)
    return ET.tostring(root, encoding="unicode")
