"""Static loads of a robot description: the gravity moment about every joint of the chain.

The moment about a joint is what its drive (actuated joint) or its link's spring (virtual joint) must hold;
on an inflatable link it is compared with the wrinkling moment M_w(p) (``models.prbm.wrinkling_moment``).
Vectorised over any leading batch shape of ``q``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from models.robot import TIP_FRAME, RobotDescription

Array = NDArray[np.float64]


def _mass_table(robot: RobotDescription) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row index of each point mass's frame (−1 = the tool point), positions in that frame, masses."""
    rows = [r.joint for r in robot.dh_rows()]
    frame = np.array([-1 if m.frame == TIP_FRAME else rows.index(m.frame) for m in robot.masses], dtype=int)
    tool = np.asarray(robot.tool_offset_m, float)
    pos = np.array(
        [np.add(m.position_m, tool) if m.frame == TIP_FRAME else m.position_m for m in robot.masses], float
    ).reshape(-1, 3)
    return frame, pos, np.array([m.mass_kg for m in robot.masses], float)


def gravity_moments(robot: RobotDescription, q: ArrayLike, delta: ArrayLike | None = None,
                    payload_kg: ArrayLike = 0.0, a: ArrayLike | None = None) -> Array:  # fmt: skip
    """Gravity moment (N·m) about every row's joint axis, (..., R) in chain order: (r × m g) · z summed over
    the masses distal to the joint, the payload hanging at the tool point. Same convention as the twin's
    kernel: positive = gravity turns the joint in its positive direction. ``a``: the rows' lengths (..., R)
    of links that lengthen with pressure (``RobotDescription.row_lengths``)."""
    chain = robot.chain()
    q = np.asarray(q, float)
    frames = chain.frames(q, delta, a)  # (..., R + 1, 4, 4); frames[..., i] is the frame before row i
    n_rows = frames.shape[-3] - 1
    mass_row, mass_pos, mass_kg = _mass_table(robot)
    tip = frames[..., -1, :, :]
    tool = tip[..., :3, :3] @ np.asarray(robot.tool_offset_m, float) + tip[..., :3, 3]
    # base-frame positions of the masses (..., M, 3)
    owner = np.where(mass_row < 0, n_rows, mass_row + 1)
    f = frames[..., owner, :, :]
    world = (f[..., :3, :3] @ mass_pos[:, :, None])[..., 0] + f[..., :3, 3]
    payload = np.broadcast_to(np.asarray(payload_kg, float), q.shape[:-1])
    gravity = np.asarray(robot.gravity_m_s2, float)
    # The masses distal to row i (a mass is when its row ≥ i; the tool's are distal to every row) and the
    # payload pull with Σ m g from their centre: M_i = (Σ m x − (Σ m) o_i) × g, projected on the row's axis.
    # One sum per row of what the masses weigh, not one cross product per mass and row (the twin fit asks for
    # these moments at every point hundreds of times).
    distal_of = np.where(mass_row < 0, n_rows, mass_row)
    distal = (distal_of[None, :] >= np.arange(n_rows)[:, None]).astype(float)  # (R, M)
    points = int(np.prod(world.shape[:-2], dtype=int)) * 3
    first = mass_kg[:, None] * np.moveaxis(world, -2, 0).reshape(len(mass_kg), points)  # (M, … · 3)
    weighed = np.moveaxis((distal @ first).reshape(n_rows, *world.shape[:-2], 3), 0, -2)  # (..., R, 3)
    weighed = weighed + payload[..., None, None] * tool[..., None, :]
    weight = distal @ mass_kg + payload[..., None]  # (..., R)
    origin, z = frames[..., :n_rows, :3, 3], frames[..., :n_rows, :3, 2]
    arm = weighed - weight[..., None] * origin  # Σ m (x − o_i), payload included
    return np.einsum("...k,...k->...", _cross(arm, np.broadcast_to(gravity, arm.shape)), z)


def _cross(a: Array, b: Array) -> Array:
    """``np.cross`` of 3-vectors on the last axis: the same products in the same order (bit-identical).
    numpy's moves axes and checks shapes on every call: half of a compensated command's time went there."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def static_deflection(robot: RobotDescription, q: ArrayLike, pressure_pa: ArrayLike,
                      payload_kg: ArrayLike = 0.0, iterations: int = 3) -> tuple[Array, Array]:  # fmt: skip
    """Virtual-joint angles δ = M(q, δ)/k(p) at rest (fixed-point iterations, hysteresis ignored) and the
    moments about the virtual joints there: ((..., V), (..., V))."""
    q = np.asarray(q, float)
    rows = robot.dh_rows()
    virtual = [i for i, r in enumerate(rows) if not r.joint.startswith("q")]
    stiffness = _virtual_stiffness(robot, q.shape[:-1], pressure_pa)
    delta = np.zeros((*q.shape[:-1], len(virtual)))
    for _ in range(iterations):
        moments = gravity_moments(robot, q, delta, payload_kg)[..., virtual]
        delta = moments / stiffness
    return delta, gravity_moments(robot, q, delta, payload_kg)[..., virtual]


def _virtual_stiffness(robot: RobotDescription, batch: tuple[int, ...], pressure_pa: ArrayLike) -> Array:
    """k(p) of every virtual joint's link at the link's channel pressure, (..., V)."""
    from models.prbm import interp_table

    pressure = np.broadcast_to(np.asarray(pressure_pa, float), (*batch, robot.pneumatics.channels))
    out = np.empty((*batch, len(robot.virtual_joints)))
    for v, name in enumerate(robot.virtual_joints):
        link = robot.link_of(name)
        table = robot.link_table(link.name)
        p = pressure[..., link.pressure_channel] if link.pressure_channel is not None else np.zeros(batch)
        out[..., v] = interp_table(p, table.pressure_pa, table.stiffness_nm_per_rad)
    return out


def servo_current_a(servo, torque: ArrayLike, qd: ArrayLike, direction: ArrayLike | None = None) -> Array:
    """The drive current (A, no noise) of servos (a ``ServoSpec``) holding ``torque`` (N·m) at speed ``qd``
    (rad/s): torque / K_t + idle · sign(torque) + friction · sign(speed) (smoothed). The twin's current
    registers read it; the twin fit weighs the arm with it. ``direction``: the sign the idle current takes
    where it is held fixed, not the torque's (a fit's solve: sign(τ) jumps at τ = 0, and a finite difference
    across the jump is no derivative)."""
    torque = np.asarray(torque, float)
    return (
        torque / servo.torque_constant_nm_per_a
        + servo.idle_current_a * (np.sign(torque) if direction is None else direction)
        + servo.friction_current_a * np.tanh(np.asarray(qd, float) / 0.02)
    )


def servo_droop(robot: RobotDescription, q: ArrayLike, payload_kg: ArrayLike = 0.0) -> Array:
    """How far the position-controlled drives sit from their goals under the static load, (..., A) rad:
    output = goal + M/K (M the gravity moment about the joint, K the position loop's stiffness); steppers land
    on their step (0)."""
    rows = [r.joint for r in robot.dh_rows()]
    actuated = [rows.index(j) for j in robot.actuated_joints]
    moments = gravity_moments(robot, q, None, payload_kg)[..., actuated]
    servo = np.array([j.drive != "stepper" for j in robot.joints])
    return np.where(servo, moments / robot.servo.stiffness_nm_per_rad, 0.0)
