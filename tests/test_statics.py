"""The statics' gravity moments (``models.statics``) against their definition, mass by mass."""

import numpy as np
import pytest

from models.robot import load_robot
from models.statics import _mass_table, gravity_moments


def _by_definition(robot, q, delta, payload_kg):
    """Σ over the masses distal to each row (and the payload at the tool point) of ((x − o) × m g) · z, one
    point, one mass at a time."""
    frames = robot.chain().frames(q, delta)
    rows, pos, kg = _mass_table(robot)
    n_rows, g = len(frames) - 1, np.asarray(robot.gravity_m_s2)
    tip = frames[-1]
    tool = tip[:3, :3] @ np.asarray(robot.tool_offset_m) + tip[:3, 3]
    out = np.zeros(n_rows)
    for i in range(n_rows):
        origin, z = frames[i][:3, 3], frames[i][:3, 2]
        total = np.cross(tool - origin, payload_kg * g)
        for row, p, m in zip(rows, pos, kg, strict=True):
            if row < 0 or row >= i:  # on the tool, or on a frame at or past this row's
                frame = frames[n_rows if row < 0 else row + 1]
                total = total + np.cross(frame[:3, :3] @ p + frame[:3, 3] - origin, m * g)
        out[i] = total @ z
    return out


@pytest.mark.parametrize("name", ["vsl", "popup", "vsl_unmodelled"])
def test_gravity_moments_are_their_definition_for_a_batch_and_for_one_point(name):
    robot = load_robot(name)
    chain = robot.chain()
    rng = np.random.default_rng(11)
    n = 300  # past models.kinematics.BATCHED_POINTS: the batch's frames are composed column by column
    q = rng.uniform(-2, 2, (n, len(chain.actuated)))
    delta = rng.normal(0, 0.1, (n, len(chain.virtual)))
    payload = rng.uniform(0, 0.2, n)
    batch = gravity_moments(robot, q, delta, payload)
    assert batch.shape == (n, len(chain.rows))
    for i in range(0, n, 37):
        want = _by_definition(robot, q[i], delta[i], payload[i])
        np.testing.assert_allclose(batch[i], want, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(
            gravity_moments(robot, q[i], delta[i], payload[i]), want, rtol=1e-12, atol=1e-14
        )


def test_an_arm_without_masses_feels_only_its_payload():
    robot = load_robot("vsl").model_copy(update={"masses": []})
    q = np.random.default_rng(2).uniform(-1, 1, (200, 3))
    moments = gravity_moments(robot, q, None, 0.1)
    assert moments.shape == (200, len(robot.dh_rows()))
    for i in (0, 99, 199):
        np.testing.assert_allclose(moments[i], _by_definition(robot, q[i], None, 0.1), rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(gravity_moments(robot, q, None, 0.0), 0.0)


def test_a_held_idle_direction_makes_the_current_continuous_through_zero_torque():
    """The twin's servo current jumps by twice the idle current where the torque changes sign; with the
    direction held (a fit's solve, from the measured currents) it is a straight line through τ = 0."""
    from models.statics import servo_current_a

    servo = load_robot("vsl").servo
    torque = np.array([-1e-9, 0.0, 1e-9])
    free = servo_current_a(servo, torque, 0.0)
    assert free[2] - free[0] == pytest.approx(2 * servo.idle_current_a)
    held = servo_current_a(servo, torque, 0.0, direction=np.ones(3))
    np.testing.assert_allclose(np.diff(held), 1e-9 / servo.torque_constant_nm_per_a, rtol=1e-6)
    assert held[1] == pytest.approx(servo.idle_current_a)
