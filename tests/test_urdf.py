"""The robots' URDFs, read by a URDF library (yourdfpy), move as ``models.kinematics`` does."""

from __future__ import annotations

import io
import subprocess
import sys

import numpy as np
import pytest
import yourdfpy

from models.robot import load_robot
from models.urdf import BASE, TOOL, frame_names, joint_origins, joint_transforms, link_name, robot_urdf

ROBOTS = ["vsl", "popup", "vsl_rigid"]


def _load(robot) -> yourdfpy.URDF:
    return yourdfpy.URDF.load(
        io.StringIO(robot_urdf(robot)), load_meshes=False, build_collision_scene_graph=False
    )


@pytest.mark.parametrize("name", ROBOTS)
def test_the_urdf_forward_kinematics_equals_the_chain_at_random_joints(name):
    robot = load_robot(name)
    urdf = _load(robot)
    chain = robot.chain()
    assert urdf.robot.name == robot.name
    assert [j.name for j in urdf.robot.joints] == [*(r.joint for r in robot.dh_rows()), TOOL]
    assert {lk.name for lk in urdf.robot.links} == set(frame_names(robot))
    rng = np.random.default_rng(7)
    limits = robot.joint_limits()
    for _ in range(50):
        q = rng.uniform(limits[:, 0], limits[:, 1])
        delta = rng.uniform(-0.2, 0.2, len(chain.virtual))
        urdf.update_cfg(dict(zip([*chain.actuated, *chain.virtual], [*q, *delta], strict=True)))
        frames = chain.frames(q, delta)
        np.testing.assert_allclose(urdf.get_transform(TOOL, BASE), frames[-1], atol=1e-9, rtol=0)
        for i, row in enumerate(robot.dh_rows()):  # every link: frame i turned by its joint
            turned = urdf.get_transform(link_name(row.joint), BASE)
            np.testing.assert_allclose(turned[:3, 3], frames[i][:3, 3], atol=1e-9, rtol=0)


@pytest.mark.parametrize("name", ["vsl", "popup"])
def test_the_joint_transforms_compose_to_the_chain(name):
    """What /tf carries: each joint's child in its parent; composed from the base they give every frame."""
    robot = load_robot(name)
    chain = robot.chain()
    rng = np.random.default_rng(3)
    q = rng.uniform(-1, 1, (5, len(chain.actuated)))
    delta = rng.uniform(-0.1, 0.1, (5, len(chain.virtual)))
    local = joint_transforms(robot, q, delta)
    composed = np.broadcast_to(np.eye(4), (5, 4, 4))
    for i in range(local.shape[1]):
        composed = composed @ local[:, i]
    composed = composed @ joint_origins(robot)[-1]  # the tool's fixed joint (/tf_static)
    np.testing.assert_allclose(composed, chain.fk(q, delta), atol=1e-12)


@pytest.mark.slow
def test_a_robot_of_anyone_s_file_becomes_a_urdf_on_the_command_line(tmp_path):
    out = tmp_path / "vsl.urdf"
    cli = [sys.executable, "-m", "vslab.cli", "--lab", str(tmp_path / "lab")]
    done = subprocess.run([*cli, "robots", "urdf", "vsl", "--out", str(out)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert out.read_text() == robot_urdf(load_robot("vsl"))
    printed = subprocess.run([*cli, "robots", "urdf", "popup"], capture_output=True, text=True)
    assert printed.returncode == 0 and printed.stdout == robot_urdf(load_robot("popup"))
    bad = subprocess.run([*cli, "robots", "urdf", "nope"], capture_output=True, text=True)
    said = (bad.stdout + bad.stderr).strip().splitlines()
    assert bad.returncode == 2 and len(said) == 1 and said[0].startswith("error:"), said
