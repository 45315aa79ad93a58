"""The robot as a URDF: what Foxglove's 3D panel (and any ROS tool) draws the arm from.

Generated from the robot description's D-H chain, virtual joints included, so a URDF tool's forward kinematics
equals :meth:`models.kinematics.DHChain.fk`. Standard D-H row i is ``Rz(θᵢ + qᵢ) · Cᵢ`` with
``Cᵢ = Tz(dᵢ) Tx(aᵢ) Rx(αᵢ)``; URDF moves a child by ``origin · R(axis, q)``. So joint i is revolute about z,
its origin ``Cᵢ₋₁ · Rz(offsetᵢ)`` (C₀ = I), and a fixed ``tool`` joint carries the last ``Cₙ``. Link i is the
frame that turns with joint i; it draws the row's d (along z) and a (along x) as cylinders.

The link and joint names are the frame ids the session's ``/tf`` uses (:func:`frame_names`).
"""

from __future__ import annotations

import math
from xml.etree import ElementTree as ET

import numpy as np
from scipy.spatial.transform import Rotation

from models.robot import DHRowSpec, RobotDescription

BASE = "base_link"
TOOL = "tool"
VIRTUAL_RANGE_RAD = math.pi / 2  # a virtual joint's URDF limits: display only, the PRBM bends far less
DEFAULT_RADIUS_M = 0.02  # a link drawn without a radius in its description (ASSUMED: display only)


def link_name(joint: str) -> str:
    """The URDF link (and tf frame) that turns with ``joint``."""
    return f"{joint}_link"


def frame_names(robot: RobotDescription) -> list[str]:
    """Every frame of the chain in order: the base, one per D-H row, the tool."""
    return [BASE, *(link_name(r.joint) for r in robot.dh_rows()), TOOL]


def _row_transform(row: DHRowSpec) -> np.ndarray:
    """Cᵢ = Tz(d) Tx(a) Rx(α): the fixed part of a D-H row after its joint's rotation."""
    ca, sa = math.cos(row.alpha_rad), math.sin(row.alpha_rad)
    return np.array([[1, 0, 0, row.a_m], [0, ca, -sa, 0], [0, sa, ca, row.d_m], [0, 0, 0, 1]], dtype=float)


def _rz(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=float)


def joint_origins(robot: RobotDescription) -> list[np.ndarray]:
    """Each row's joint origin in its parent link (``Cᵢ₋₁ · Rz(offsetᵢ)``), then the tool's (``Cₙ``): the
    transforms ``/tf`` composes with each joint's rotation."""
    rows = robot.dh_rows()
    previous = np.eye(4)
    origins = []
    for row in rows:
        origins.append(previous @ _rz(row.offset_rad))
        previous = _row_transform(row)
    return [*origins, previous]


def _origin(parent: ET.Element, transform: np.ndarray) -> None:
    rpy = Rotation.from_matrix(transform[:3, :3]).as_euler("xyz")  # URDF's fixed-axis roll, pitch, yaw
    ET.SubElement(parent, "origin", xyz=" ".join(f"{v:.17g}" for v in transform[:3, 3]),
                  rpy=" ".join(f"{v:.17g}" for v in rpy))  # fmt: skip


def _cylinder(link: ET.Element, name: str, length: float, radius: float, centre, rpy: str) -> None:
    if abs(length) < 1e-9:
        return
    visual = ET.SubElement(link, "visual", name=name)
    ET.SubElement(visual, "origin", xyz=" ".join(f"{v:.17g}" for v in centre), rpy=rpy)
    ET.SubElement(
        ET.SubElement(visual, "geometry"), "cylinder", radius=f"{radius:g}", length=f"{abs(length):.17g}"
    )
    ET.SubElement(visual, "material", name="link")


def robot_urdf(robot: RobotDescription) -> str:
    """The robot's URDF (XML text): its D-H chain, virtual joints included, joint limits from the
    description (virtual joints ±90°, for display), cylinders along each row's d and a."""
    rows = robot.dh_rows()
    limits = {j.name: (j.lower_rad, j.upper_rad) for j in robot.joints}
    radius = {v: link.radius_m or DEFAULT_RADIUS_M for link in robot.links for v in link.virtual_joints}
    root = ET.Element("robot", name=robot.name)
    material = ET.SubElement(root, "material", name="link")
    ET.SubElement(material, "color", rgba="0.55 0.7 0.9 1")
    ET.SubElement(root, "link", name=BASE)
    origins = joint_origins(robot)
    parent = BASE
    for i, row in enumerate(rows):
        child = link_name(row.joint)
        joint = ET.SubElement(root, "joint", name=row.joint, type="revolute")
        ET.SubElement(joint, "parent", link=parent)
        ET.SubElement(joint, "child", link=child)
        _origin(joint, origins[i])
        ET.SubElement(joint, "axis", xyz="0 0 1")
        lower, upper = limits.get(row.joint, (-VIRTUAL_RANGE_RAD, VIRTUAL_RANGE_RAD))
        ET.SubElement(joint, "limit", lower=f"{lower:.17g}", upper=f"{upper:.17g}", effort="0", velocity="0")
        link = ET.SubElement(root, "link", name=child)
        r = radius.get(row.joint, DEFAULT_RADIUS_M)
        _cylinder(link, f"{child}_d", row.d_m, r, (0.0, 0.0, row.d_m / 2), "0 0 0")
        _cylinder(link, f"{child}_a", row.a_m, r, (row.a_m / 2, 0.0, row.d_m), f"0 {math.pi / 2:.17g} 0")
        parent = child
    tool = ET.SubElement(root, "joint", name=TOOL, type="fixed")
    ET.SubElement(tool, "parent", link=parent)
    ET.SubElement(tool, "child", link=TOOL)
    _origin(tool, origins[-1])
    ET.SubElement(root, "link", name=TOOL)
    ET.indent(root)
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


class JointTransforms:
    """Each movable joint's child link in its parent (..., R, 4, 4), as ``/tf`` carries them: the joint's
    origin times its rotation by q (actuated rows) or δ (virtual rows; 0 where ``delta`` is None). The
    robot's constant transforms are worked out once (a recording calls it at every batch)."""

    def __init__(self, robot: RobotDescription) -> None:
        self.chain = robot.chain()
        self.offsets = np.array([r.offset_rad for r in robot.dh_rows()])
        self.origins = np.stack(joint_origins(robot)[:-1])

    def __call__(self, q: np.ndarray, delta: np.ndarray | None = None) -> np.ndarray:
        value = self.chain.theta(np.asarray(q, dtype=float), delta) - self.offsets  # offsets: in the origins
        c, s = np.cos(value), np.sin(value)
        rz = np.zeros((*value.shape, 4, 4))
        rz[..., 0, 0], rz[..., 0, 1], rz[..., 1, 0], rz[..., 1, 1] = c, -s, s, c
        rz[..., 2, 2] = rz[..., 3, 3] = 1.0
        return self.origins @ rz


def joint_transforms(robot: RobotDescription, q: np.ndarray, delta: np.ndarray | None = None) -> np.ndarray:
    """:class:`JointTransforms` of ``robot`` at q (and δ)."""
    return JointTransforms(robot)(q, delta)
