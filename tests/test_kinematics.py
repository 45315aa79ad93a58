"""Rigid kinematics of the VSL arm (seed 000 eqs. 1–8) and the POPUP D-H chain with virtual joints."""

import numpy as np
import pytest

from models.kinematics import (
    BATCHED_POINTS,
    POPUP_TABLE2_MM,
    ArmLengths,
    DHChain,
    DHRow,
    SingularityError,
    UnreachableError,
    dh_chain_from_table,
    inverse_jacobian_velocity,
    vsl_fk,
    vsl_fk_transform,
    vsl_ik,
    vsl_jacobian,
)

L = ArmLengths(0.100, 0.250, 0.250)


def _reachable_points(rng, n):
    """Points strictly inside the reachable shell, all around the arm (off the XZ plane too)."""
    r3 = rng.uniform(0.02, 0.49, n)  # distance from the J2 axis (|L2 − L3| = 0, L2 + L3 = 0.5)
    elev = rng.uniform(-np.pi / 2 + 0.05, np.pi / 2 - 0.05, n)
    azim = rng.uniform(-np.pi, np.pi, n)
    r1 = r3 * np.cos(elev)
    return np.stack([r1 * np.cos(azim), r1 * np.sin(azim), L.l1 + r3 * np.sin(elev)], -1)


@pytest.mark.parametrize("elbow", [1, -1])
def test_fk_of_ik_returns_the_target(elbow):
    x = _reachable_points(np.random.default_rng(0), 10_000)
    q = vsl_ik(x, L, elbow)
    assert np.abs(vsl_fk(q, L) - x).max() < 1e-9
    assert np.all((q[:, 2] > -np.pi) & (q[:, 2] <= np.pi))


@pytest.mark.parametrize("elbow", [1, -1])
def test_ik_of_fk_recovers_the_branch(elbow):
    rng = np.random.default_rng(1)
    q = np.stack([rng.uniform(-3, 3, 2000), rng.uniform(-1.4, 1.4, 2000), rng.uniform(0.1, 3.0, 2000)], -1)
    q[:, 2] *= -elbow  # elbow up bends J3 negative
    # eqs. (2)–(7) give the front solution (r1 = √(X² + Y²) ≥ 0): keep poses that reach forward
    q = q[L.l2 * np.cos(q[:, 1]) + L.l3 * np.cos(q[:, 1] + q[:, 2]) > 0.01]
    assert len(q) > 500
    back = vsl_ik(vsl_fk(q, L), L, elbow)
    np.testing.assert_allclose(back, q, atol=1e-7)


def test_transform_position_matches_fk_and_rotation_is_orthonormal():
    q = np.random.default_rng(2).uniform(-2, 2, (100, 3))
    t = vsl_fk_transform(q, L)
    np.testing.assert_allclose(t[:, :3, 3], vsl_fk(q, L), atol=1e-15)
    rot = t[:, :3, :3]
    np.testing.assert_allclose(
        rot @ np.swapaxes(rot, 1, 2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12
    )


def test_jacobian_matches_central_differences():
    q = np.random.default_rng(3).uniform(-3, 3, (500, 3))
    h = 1e-6
    numeric = np.stack([(vsl_fk(q + h * e, L) - vsl_fk(q - h * e, L)) / (2 * h) for e in np.eye(3)], -1)
    assert np.abs(vsl_jacobian(q, L) - numeric).max() < 1e-6


@pytest.mark.parametrize("elbow", [1, -1])
def test_ik_on_the_workspace_boundaries(elbow):
    azim = np.linspace(-np.pi, np.pi, 7)
    stretched = np.stack([0.5 * np.cos(azim), 0.5 * np.sin(azim), np.full(7, L.l1)], -1)  # r3 = L2 + L3
    on_axis = np.array([[0.0, 0.0, 0.3], [0.0, 0.0, -0.2]])  # r1 = 0: θ1 = 0
    folded = np.array([0.0, 0.0, L.l1])  # r3 = 0 = |L2 − L3|: any θ2 works
    for x in (stretched, on_axis, folded):
        q = vsl_ik(x, L, elbow)
        assert np.all(np.isfinite(q))
        assert np.abs(vsl_fk(q, L) - x).max() < 1e-9
    np.testing.assert_array_equal(vsl_ik(on_axis, L, elbow)[:, 0], 0.0)


def test_unreachable_target_raises_a_clear_error():
    with pytest.raises(
        UnreachableError,
        match=r"2 target\(s\) unreachable, first at \[700\.0, 0\.0, 100\.0\] mm \(flat index 1\).*"
        r"\[0\.0, 500\.0\] mm",
    ):
        vsl_ik(np.array([[0.3, 0, 0.2], [0.7, 0, 0.1], [0, 0.6, 0.1]]), L)
    with pytest.raises(UnreachableError, match="1 target"):
        vsl_ik(np.array([np.nan, 0, 0.2]), L)
    with pytest.raises(UnreachableError, match=r"\[100\.0, 400\.0\] mm"):  # the annulus of unequal links
        vsl_ik(np.array([0.05, 0, L.l1]), ArmLengths(0.1, 0.25, 0.15))
    with pytest.raises(ValueError, match="elbow"):
        vsl_ik(np.array([0.3, 0, 0.2]), L, elbow=0)


def test_inverse_jacobian_velocity_and_singularity():
    q = np.array([0.1, 0.5, -1.0])
    xdot = np.array([0.01, 0.0, -0.02])
    qd = inverse_jacobian_velocity(vsl_jacobian(q, L), xdot)
    np.testing.assert_allclose(vsl_jacobian(q, L) @ qd, xdot, atol=1e-12)
    batch = vsl_jacobian(np.array([q, [0.0, 0.3, 0.0]]), L)  # the second: arm stretched out
    with pytest.raises(SingularityError, match=r"1 of 2 configuration.*flat index 1"):
        inverse_jacobian_velocity(batch, xdot)


def test_vsl_as_a_dh_chain_equals_eq1():
    chain = DHChain(
        [DHRow(0.0, np.pi / 2, L.l1, "q1"), DHRow(L.l2, 0.0, 0.0, "q2"), DHRow(L.l3, 0.0, 0.0, "q3")]
    )
    q = np.random.default_rng(4).uniform(-3, 3, (300, 3))
    np.testing.assert_allclose(chain.fk(q), vsl_fk_transform(q, L), atol=1e-14)
    np.testing.assert_allclose(chain.jacobian(q), vsl_jacobian(q, L), atol=1e-14)


def test_popup_chain_with_zero_deflection_matches_the_rigid_model():
    chain = dh_chain_from_table(POPUP_TABLE2_MM)
    assert chain.actuated == ("q1", "q2", "q3")
    assert chain.virtual == ("d11", "d12", "d21", "d22")
    q = np.random.default_rng(5).uniform(-3, 3, (1000, 3))
    np.testing.assert_allclose(chain.fk(q), chain.rigid().fk(q), atol=1e-12)
    np.testing.assert_allclose(chain.fk(q, np.zeros(4)), chain.fk(q), atol=0)
    assert np.abs(chain.fk(q, np.full(4, 0.01)) - chain.fk(q)).max() > 1e-3  # δ does change the pose


@pytest.mark.parametrize("batch", [(BATCHED_POINTS,), (3, BATCHED_POINTS), (BATCHED_POINTS - 1,)])
def test_a_batch_of_frames_is_each_point_s_frames(batch):
    """Many points' frames (composed column by column from ``BATCHED_POINTS`` on, 4 × 4 products below) are
    each point's own, alone, to a few bits, with the rows' lengths given per point too."""
    chain = dh_chain_from_table(POPUP_TABLE2_MM)
    rng = np.random.default_rng(7)
    q, delta = rng.uniform(-3, 3, (*batch, 3)), rng.normal(0, 0.2, (*batch, 4))
    lengths = np.array([row.a for row in chain.rows]) * rng.uniform(0.9, 1.1, (*batch, len(chain.rows)))
    frames = chain.frames(q, delta, lengths)
    assert frames.shape == (*batch, len(chain.rows) + 1, 4, 4)
    alone = np.array([chain.frames(q[i], delta[i], lengths[i]) for i in np.ndindex(batch)])
    np.testing.assert_allclose(frames.reshape(alone.shape), alone, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(
        frames[..., 3, :], np.broadcast_to([0.0, 0.0, 0.0, 1.0], frames[..., 3, :].shape)
    )
    rotations = frames[..., :3, :3]  # orthonormal
    np.testing.assert_allclose(
        rotations @ np.swapaxes(rotations, -1, -2), np.broadcast_to(np.eye(3), rotations.shape), atol=1e-14
    )


def test_dh_chain_rejects_bad_shapes():
    chain = dh_chain_from_table(POPUP_TABLE2_MM)
    with pytest.raises(ValueError, match=r"q has shape \(4,\).*q1"):
        chain.fk(np.zeros(4))
    with pytest.raises(ValueError, match="delta has shape"):
        chain.fk(np.zeros((5, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="unique"):
        DHChain([DHRow(0.1, 0, 0, "q1"), DHRow(0.1, 0, 0, "q1")])


def test_popup_virtual_joints_move_the_end_effector_as_expected():
    chain = dh_chain_from_table(POPUP_TABLE2_MM)
    q = np.deg2rad([0.0, 60.0, -120.0])
    frames = chain.frames(q)
    tip = frames[-1, :3, 3]
    eps = 1e-4
    for name in chain.virtual:
        delta = np.zeros(4)
        delta[chain.virtual.index(name)] = eps
        moved = chain.position(q, delta) - tip
        row = [r.joint for r in chain.rows].index(name)
        axis, origin = frames[row, :3, 2], frames[row, :3, 3]
        expected = eps * np.cross(axis, tip - origin)  # small rotation about the virtual axis
        np.testing.assert_allclose(moved, expected, atol=eps**2)  # up to second order
        assert np.linalg.norm(moved) > 0
    # δ22 bends the last 590 mm body: the tip moves ≈ 0.590 m × δ, perpendicular to that body, towards
    # the side that rotation about the frame's z axis by +δ turns it (z × body direction)
    body = tip - frames[-2, :3, 3]
    assert np.linalg.norm(body) == pytest.approx(0.590, abs=1e-12)
    moved = chain.position(q, [0, 0, 0, eps]) - tip
    assert np.linalg.norm(moved) == pytest.approx(0.590 * eps, rel=1e-3)
    assert abs(moved @ body) < 1e-3 * np.linalg.norm(moved) * np.linalg.norm(body)
    side = np.cross(frames[-2, :3, 2], body / np.linalg.norm(body))
    assert moved @ side == pytest.approx(0.590 * eps, rel=1e-3)
    # δ12 (link 1's hinge): the tip moves by its distance from that hinge's axis × δ
    i12 = [r.joint for r in chain.rows].index("d12")
    axis, origin = frames[i12, :3, 2], frames[i12, :3, 3]
    lever = np.linalg.norm(np.cross(axis, tip - origin))
    assert lever > 0.5
    moved = chain.position(q, [0, eps, 0, 0]) - tip
    assert np.linalg.norm(moved) == pytest.approx(lever * eps, rel=1e-3)


def test_dh_chain_jacobian_matches_central_differences():
    chain = dh_chain_from_table(POPUP_TABLE2_MM)
    rng = np.random.default_rng(6)
    q, delta = rng.uniform(-2, 2, (200, 3)), rng.uniform(-0.05, 0.05, (200, 4))
    h = 1e-6
    numeric = np.stack(
        [(chain.position(q + h * e, delta) - chain.position(q - h * e, delta)) / (2 * h) for e in np.eye(3)],
        -1,
    )
    assert np.abs(chain.jacobian(q, delta) - numeric).max() < 1e-6


def test_ik_where_reachable_is_nan_exactly_where_the_ik_refuses():
    """The dataset's rigid IK column: the closed form where it answers, NaN (not an error) elsewhere."""
    from models.kinematics import vsl_ik_where_reachable

    x = np.array([[0.3, 0, 0.2], [0.7, 0, 0.1], [np.nan, 0, 0.2], [0, 0.3, 0.25]])
    out = vsl_ik_where_reachable(x, L)
    assert np.isnan(out[[1, 2]]).all()
    np.testing.assert_array_equal(out[[0, 3]], vsl_ik(x[[0, 3]], L))


def test_joint_offsets_are_the_encoders_zero_errors_in_every_kinematic_function():
    """A description's joint offsets (true angle − encoder reading) enter eq. (1), its IK, its Jacobian and
    the D-H chain the twin and the statics use, the same way: the functions take and give encoder angles."""
    from models.robot import load_robot

    nominal = load_robot("vsl")
    offsets = (0.004, 0.005236, -0.005236)
    kin = nominal.kinematics.model_copy(update={"joint_offsets_rad": offsets})
    arm = nominal.model_copy(update={"kinematics": kin})
    rng = np.random.default_rng(2)
    q = np.column_stack([rng.uniform(-1, 1, 50), rng.uniform(0.1, 1.4, 50), rng.uniform(-2, -0.3, 50)])
    lengths = kin.arm()
    np.testing.assert_allclose(vsl_fk(q, lengths), arm.chain().position(q), atol=1e-12)
    np.testing.assert_allclose(vsl_fk(q, lengths), vsl_fk(q + offsets, nominal.kinematics.arm()), atol=1e-15)
    np.testing.assert_allclose(vsl_ik(vsl_fk(q, lengths), lengths, 1), q, atol=1e-9)
    np.testing.assert_allclose(vsl_jacobian(q, lengths), vsl_jacobian(q + offsets, nominal.kinematics.arm()))
    np.testing.assert_allclose(vsl_fk_transform(q, lengths)[:, :3, 3], vsl_fk(q, lengths), atol=1e-15)
    assert nominal.kinematics.arm().offsets == (0.0, 0.0, 0.0)  # the papers' arm: none
