"""Algorithms 1–2, Experiment 1's trajectories (seed 000) and the velocity law eq. (3) (seed 001)."""

import numpy as np
import pytest

from models.kinematics import ArmLengths, vsl_fk, vsl_jacobian
from models.trajectories import (
    EXPERIMENT1_NAMES,
    circular,
    distance_to_path,
    experiment1,
    linear,
    velocity_law,
)

L = ArmLengths(0.100, 0.250, 0.250)


def _consistent(plan, speed):
    """FK(q) = x, and the FK velocity J q̇ has the commanded speed."""
    np.testing.assert_allclose(vsl_fk(plan.q, L), plan.x, atol=1e-9)
    xdot = np.einsum("nij,nj->ni", vsl_jacobian(plan.q, L), plan.qd)
    np.testing.assert_allclose(np.linalg.norm(xdot, axis=-1), speed, rtol=1e-9)
    return xdot


def test_linear_is_algorithm1():
    x0, xg = np.array([0.3, 0, 0.05]), np.array([0.3, 0, 0.35])
    plan = linear(x0, xg, speed=0.02, n=30, lengths=L)
    assert len(plan) == 31
    np.testing.assert_allclose(plan.x[[0, -1]], [x0, xg], atol=1e-15)
    steps = np.diff(plan.x, axis=0)
    np.testing.assert_allclose(steps, np.broadcast_to(steps[0], steps.shape), atol=1e-15)  # evenly, collinear
    np.testing.assert_allclose(np.diff(plan.t), 0.3 / 0.02 / 30, rtol=1e-12)
    assert plan.t[0] == 0 and plan.t[-1] == pytest.approx(0.3 / 0.02)
    xdot = np.broadcast_to(0.02 * (xg - x0) / 0.3, (31, 3))
    np.testing.assert_allclose(_consistent(plan, 0.02), xdot, atol=1e-12)  # J q̇ = ẋ
    np.testing.assert_allclose(plan.qd, np.linalg.solve(vsl_jacobian(plan.q, L), xdot[..., None])[..., 0])


def test_linear_off_the_xz_plane_and_elbow_down():
    x0, xg = np.array([0.2, 0.1, 0.15]), np.array([0.1, -0.25, 0.3])
    plan = linear(x0, xg, speed=0.05, n=20, lengths=L, elbow=-1)
    assert np.all(plan.q[:, 2] >= 0)  # elbow down
    direction = np.cross(plan.x - x0, xg - x0)
    np.testing.assert_allclose(direction, 0, atol=1e-15)
    _consistent(plan, 0.05)


def test_concat_continues_the_clock():
    a = linear([0.3, 0, 0.05], [0.3, 0, 0.15], 0.02, 4, L)
    b = linear([0.3, 0, 0.15], [0.2, 0, 0.15], 0.02, 5, L)
    ab = a.concat(b)
    assert len(ab) == len(a) + len(b) == 11
    np.testing.assert_allclose(ab.t[5:], a.t[-1] + (b.t[1] - b.t[0]) + b.t)
    np.testing.assert_array_equal(ab.x, np.concatenate([a.x, b.x]))


def test_circular_reproduces_the_papers_loop():
    n, speed = 40, 0.02
    x0, xg, xc = np.array([0.3, 0, 0.05]), np.array([0.4, 0, 0.15]), np.array([0.3, 0, 0.15])
    plan = circular(x0, xg, xc, speed, n, L)
    r, alpha, k = np.linalg.norm(xc - x0), np.pi / (2 * n), np.arange(n + 1)  # Algorithm 2's r and α
    paper = np.stack([xc[0] + r * np.sin(alpha * k), np.zeros(n + 1), xc[2] - r * np.cos(alpha * k)], -1)
    np.testing.assert_array_equal(plan.x, paper)  # bit for bit
    np.testing.assert_allclose(np.linalg.norm(plan.x - xc, axis=-1), r, atol=1e-15)
    _consistent(plan, speed)
    # Algorithm 2's velocity: [V cos(αk), 0, V sin(αk)]
    xdot = np.einsum("nij,nj->ni", vsl_jacobian(plan.q, L), plan.qd)
    np.testing.assert_allclose(xdot[:, [0, 2]], speed * np.stack([np.cos(alpha * k), np.sin(alpha * k)], -1),
                               atol=1e-12)  # fmt: skip


def test_circular_general_arc_endpoints_and_direction():
    xc = np.array([0.3, 0, 0.2])
    x0, xg = xc + 0.08 * np.array([np.cos(0.3), 0, np.sin(0.3)]), xc + 0.08 * np.array([0, 0, -1.0])
    plan = circular(x0, xg, xc, 0.03, 33, L)
    np.testing.assert_allclose(plan.x[[0, -1]], [x0, xg], atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(plan.x - xc, axis=-1), 0.08, atol=1e-15)
    xdot = _consistent(plan, 0.03)
    np.testing.assert_allclose(np.einsum("ni,ni->n", xdot, plan.x - xc), 0, atol=1e-12)  # tangent
    assert xdot[0] @ (xg - x0) > 0  # heading towards the goal the short way
    arc = np.linalg.norm(np.diff(plan.x, axis=0), axis=-1)
    np.testing.assert_allclose(arc, arc[0], rtol=1e-9)  # evenly spaced


def test_circular_rejects_bad_input():
    with pytest.raises(ValueError, match="not on one circle"):
        circular([0.3, 0, 0.05], [0.45, 0, 0.15], [0.3, 0, 0.15], 0.02, 10, L)
    with pytest.raises(ValueError, match="y must be 0"):
        circular([0.3, 0.01, 0.05], [0.4, 0.01, 0.15], [0.3, 0.01, 0.15], 0.02, 10, L)
    with pytest.raises(ValueError, match="x0 ≠ xg"):
        circular([0.3, 0, 0.05], [0.3, 0, 0.05], [0.3, 0, 0.15], 0.02, 10, L)


def test_curve_is_two_arcs_back_to_the_start():
    plan = experiment1("curve", L, n_per_segment=25)
    np.testing.assert_allclose(plan.x[0], [0.3, 0, 0.05], atol=1e-15)
    np.testing.assert_allclose(plan.x[25], [0.4, 0, 0.15], atol=1e-15)
    np.testing.assert_allclose(plan.x[-1], plan.x[0], atol=1e-15)
    assert np.all(np.diff(plan.t) > 0)
    _consistent(plan, 0.02)


def test_square_visits_the_papers_corners_in_order():
    plan = experiment1("square", L, n_per_segment=10)
    corners = np.array([[350, 0, 50], [250, 0, 50], [250, 0, 150], [350, 0, 150], [350, 0, 50]]) * 1e-3
    np.testing.assert_allclose(plan.x[::10], corners, atol=1e-15)
    assert np.all(np.diff(plan.t) > 0)


def test_every_experiment1_trajectory_is_reachable_and_unknown_names_fail():
    for name in EXPERIMENT1_NAMES:
        assert len(experiment1(name, L)) > 50
    with pytest.raises(ValueError, match="linear, curve, square"):
        experiment1("zigzag", L)


def test_velocity_law():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(500, 3))
    t = rng.uniform(0, 10, 500)
    v0, a0 = 0.1, 0.05
    v = velocity_law(d, t, v0, a0)
    speed = np.linalg.norm(v, axis=-1)
    assert np.all(speed <= v0 + 1e-15)
    assert np.all(speed <= np.sqrt(2 * a0 * np.linalg.norm(d, axis=-1)) + 1e-15)
    np.testing.assert_allclose(np.cross(v, d), 0, atol=1e-15)
    assert np.all(np.einsum("ni,ni->n", v, d) >= 0)
    np.testing.assert_array_equal(velocity_law(d, np.zeros(500), v0, a0), 0)
    np.testing.assert_array_equal(velocity_law(np.zeros(3), 1.0, v0, a0), 0)


def test_distance_to_path_is_point_to_segment():
    path = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    points = np.array([[0.5, 0.2, 0.0], [1.3, 0.5, 0.0], [-1.0, 0.0, 0.0], [1.0, 2.0, 0.1], [0.7, 0.0, 0.0]])
    np.testing.assert_allclose(
        distance_to_path(points, path), [0.2, 0.3, 1.0, np.hypot(1.0, 0.1), 0.0], atol=1e-12
    )
    many = np.random.default_rng(0).uniform(-1, 2, size=(10_000, 3))
    np.testing.assert_allclose(distance_to_path(many, path, chunk=333), distance_to_path(many, path))


def _every_segment(points: np.ndarray, path: np.ndarray) -> np.ndarray:
    """The distance measured against every segment (what :func:`distance_to_path` prunes), as it was."""
    a, seg = path[:-1], path[1:] - path[:-1]
    length2 = np.maximum((seg**2).sum(axis=1), 1e-300)
    rel = points[:, None, :] - a[None]
    s = np.clip((rel * seg[None]).sum(axis=2) / length2, 0.0, 1.0)
    return np.sqrt(((rel - s[..., None] * seg[None]) ** 2).sum(axis=2)).min(axis=1)


@pytest.mark.parametrize("trajectory", ["linear", "curve", "square"])
def test_distance_to_path_measures_only_the_segments_that_can_be_nearest_and_agrees_bit_for_bit(trajectory):
    """Measured tips scattered about the desired path (near it, far from it, beyond its ends, on a vertex):
    the pruned distances are the all-segments distances exactly."""
    from analysis.vsl_paths import desired_path

    path = desired_path(trajectory)
    rng = np.random.default_rng(3)
    on = path[rng.integers(0, len(path), 3000)]
    points = np.concatenate([
        on + rng.normal(scale=1e-3, size=on.shape),   # a good tracking error
        on + rng.normal(scale=3e-2, size=on.shape),   # a bad one
        rng.uniform(-0.5, 0.5, size=(500, 3)),        # anywhere
        path[:50], path[-1:] + 0.1,                   # on the vertices, beyond the end
    ])  # fmt: skip
    np.testing.assert_array_equal(distance_to_path(points, path, chunk=700), _every_segment(points, path))
