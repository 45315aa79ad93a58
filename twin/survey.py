"""Quick twin surveys: Experiment 1's error trends and POPUP's static deflection, all robots in one batch.

These answer "does the twin behave like the lab?" without recording anything: the tip error (true tip vs the
rigid forward kinematics of the encoder readings) per pressure × payload, as in seed 000's Experiment 1.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from models import kinematics, trajectories
from models.robot import AnthropomorphicKinematics, RobotDescription
from twin import sensors
from twin.world import World

PRESSURES_BAR = (0.5, 1.0, 1.5, 2.0)  # SEED: Experiment 1
PAYLOADS_G = (0, 25, 50, 75, 100)  # SEED: Experiment 1
TRAJECTORY_SPEED_M_S = 0.02  # ASSUMED: the paper gives no speed


def arm_lengths(robot: RobotDescription) -> kinematics.ArmLengths:
    """The rigid model's link lengths of an anthropomorphic arm."""
    kin = robot.kinematics
    if not isinstance(kin, AnthropomorphicKinematics):
        raise ValueError(f"robot {robot.name!r} is not the anthropomorphic VSL arm")
    return kin.arm()


def follow(world: World, plan: trajectories.SetPoints) -> list:
    """Drive every robot of ``world`` through the set-points as the paper's Move(q, q̇) does: each goal
    with its joint speed as profile velocity, held until the next set-point's time. Returns the traces."""
    traces = []
    default_vel = world.commands.profile_vel.copy()
    for k in range(len(plan)):
        speed = np.abs(plan.qd[k])
        world.command_joints(plan.q[k], profile_vel=np.where(speed > 1e-6, speed, default_vel))
        hold = plan.t[k + 1] - plan.t[k] if k + 1 < len(plan) else 0.5
        traces.append(world.step(max(1, round(hold / world.dt))))
    return traces


def encoder_tip_error_mm(robot: RobotDescription, trace) -> np.ndarray:
    """(B, n) distance between the true tip and the rigid FK of the quantised encoder angles, in mm."""
    zero = robot.servo.zero_count if robot.servo else 0
    q_enc = sensors.encoder_angle(sensors.encoder_counts(trace.q, zero), zero)
    rigid = kinematics.vsl_fk(q_enc, arm_lengths(robot))
    return np.linalg.norm(trace.tip_pos - rigid, axis=-1) * 1e3


def experiment1_survey(
    robot: RobotDescription,
    trajectory: str = "curve",
    pressures_bar: tuple[float, ...] = PRESSURES_BAR,
    payloads_g: tuple[float, ...] = PAYLOADS_G,
    seed: int = 0,
    speed_m_s: float = TRAJECTORY_SPEED_M_S,
) -> pd.DataFrame:
    """Mean tip error (mm) over one run of an Experiment 1 trajectory: pressures (rows) × payloads."""
    lengths = arm_lengths(robot)
    plan = trajectories.experiment1(trajectory, lengths, speed=speed_m_s)
    p_grid, m_grid = np.meshgrid(
        np.asarray(pressures_bar) * 1e5, np.asarray(payloads_g) * 1e-3, indexing="ij"
    )
    world = World(robot, batch=p_grid.size, seed=seed, q0=plan.q[0], pressure_pa=p_grid.reshape(-1, 1),
                  payload_kg=m_grid.reshape(-1))  # fmt: skip
    world.settle(2.0)
    traces = follow(world, plan)
    total = sum(encoder_tip_error_mm(robot, tr).sum(axis=1) for tr in traces)
    mean = total / sum(tr.t.size for tr in traces)
    return pd.DataFrame(
        mean.reshape(p_grid.shape),
        index=pd.Index([f"{p:g} bar" for p in pressures_bar], name="pressure"),
        columns=pd.Index([f"{m:g} g" for m in payloads_g], name="payload"),
    )


def popup_reach_check(robot: RobotDescription, seed: int = 0, payload_kg: float = 2.0,
                      pressure_pa: float = 60e3) -> dict:  # fmt: skip
    """Static tip deflection of POPUP at seed 001's start pose q0 = [0, 60, −120]° (PRBM vs RBM)."""
    q0 = np.deg2rad([0.0, 60.0, -120.0])
    world = World(robot, batch=1, seed=seed, q0=q0, pressure_pa=pressure_pa, payload_kg=payload_kg)
    world.settle(3.0)
    trace = world.step(1)
    rigid = robot.chain().position(trace.q[0, -1])
    deflection = float(np.linalg.norm(trace.tip_pos[0, -1] - rigid) * 1e3)
    return {"deflection_mm": deflection, "delta_rad": trace.delta[0, -1].tolist()}
