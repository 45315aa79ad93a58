"""The arm's own moves between settled points (``pipeline.move_paths``): the twin fit follows each link's
hysteresis through them instead of through straight joint-space lines."""

from __future__ import annotations

import numpy as np

from acquisition.plans.experiments import together
from models.robot import load_robot
from models.statics import gravity_moments
from pipeline.arm_history import hysteresis_states, path_parts, path_torques, session_order
from pipeline.move_paths import _turning_points, move_speed, simulated_moves
from twin.world import World

LAB_ARM = "bench/lab_arm.yaml"


def test_the_turning_points_of_a_load_are_its_reversals_then_its_end():
    load = np.array([0.0, 0.5, 1.0, 0.8, 0.9, 0.90005, 0.2, 0.2, 0.6, 0.6])[None, :, None]
    out = np.empty((1, 6, 1), np.int64)
    _turning_points(load, 1e-3, out)
    # up to 1.0 (index 2), back to 0.8 (3), up to 0.90005 (5; 0.9 → 0.90005 is the same way), down to 0.2 (6),
    # up to the end; the rest padded with the last sample
    assert out[0, :, 0].tolist() == [2, 3, 5, 6, 9, 9]
    few = np.empty((1, 3, 1), np.int64)
    _turning_points(load, 1e-3, few)
    assert few[0, :, 0].tolist() == [2, 3, 9]  # no room for more: the end still last
    still = np.empty((1, 3, 1), np.int64)
    _turning_points(np.zeros((1, 5, 1)), 1e-3, still)
    assert still[0, :, 0].tolist() == [4, 4, 4]


def test_the_move_speed_is_read_from_the_points_times(campaign_dataset):
    data = campaign_dataset[2]  # the campaign moves its largest joint step at 1 rad/s
    t, goals = data["t"].to_numpy(float), data[["qc_0", "qc_1", "qc_2"]].to_numpy(float)
    order = session_order(data["session"].to_numpy(), t)
    assert abs(move_speed(t, goals, order) - 1.0) < 0.02
    assert move_speed(np.arange(len(t), dtype=float), goals, order) is None  # a point a second: no speed
    assert move_speed(t[:5], goals[:5], session_order(np.zeros(5), t[:5])) is None  # too few moves


def test_the_simulated_moves_give_the_links_the_twin_s_own_hysteresis_states():
    """The lab arm (its links 0.8× and 1.25× as stiff, masses 1.15×) moved between random points of the
    campaign's box at 1 rad/s, settled 1.5 s as the campaign does, its true Bouc–Wen states read from the
    twin:
    the states followed through the moves ``simulated_moves`` makes agree with them 20× better than along
    straight lines (measured: 0.0019 and 0.0026 rms against 0.049 and 0.034; the states are 0.50 and 0.16 in
    size); along straight lines the states come out larger than the twin's (the ring's swings relax each loop
    toward its middle: the bias that took the fitted loops 13–15 % low)."""
    from models import kinematics
    from twin.survey import arm_lengths

    robot = load_robot(LAB_ARM)
    benches, points = 6, 40
    rng = np.random.default_rng(1)
    targets = rng.uniform([0.22, -0.08, 0.02], [0.42, 0.08, 0.18], size=(benches * points, 3))
    goals = kinematics.vsl_ik(targets, arm_lengths(robot), 1).reshape(benches, points, 3)
    bar = rng.uniform(0.5e5, 2e5, (benches, points))
    kg = rng.choice([0.0, 0.025, 0.05, 0.075, 0.1], (benches, points))
    world = World(robot, batch=benches, q0=goals[:, 0], pressure_pa=np.repeat(bar[:, :1], 2, 1),
                  payload_kg=kg[:, 0])  # fmt: skip
    world.settle(2.0)
    true_z = np.zeros((benches, points, 2))
    for k in range(points):  # as the campaign commands them
        step = goals[:, k] - world.commands.goal
        world.command_pressure(np.repeat(bar[:, k : k + 1], 2, 1))
        world.set_payload(kg[:, k])
        world.command_joints(goals[:, k], profile_vel=np.stack([together(s, 1.0) for s in step]))
        world.run_for(float(np.abs(step).max()) + 1.5)
        true_z[:, k] = world.state.hyst_z
    q, m = goals.reshape(-1, 3), kg.reshape(-1)
    order = session_order(np.repeat(np.arange(benches), points), np.tile(np.arange(points), benches))
    tau_y = np.array([link.hysteresis.tau_y_nm for link in robot.links])
    moves = simulated_moves(robot, q, np.repeat(bar.reshape(-1, 1), 2, 1), m, order, 1.0)
    assert moves[0].shape == (benches * points, 16, 2, 3) and moves[1].shape == (benches * points, 16, 2, 2)

    def states(parts):
        return hysteresis_states(path_torques(parts, {}), tau_y, order).reshape(benches, points, 2)

    simulated = states(path_parts(robot, robot.links, q, m, order, 0, moves))
    straight = states(path_parts(robot, robot.links, q, m, order, 8))
    later = slice(5, None)  # past each session's first points (the twin starts settled where they start)
    off = np.sqrt(((simulated - true_z)[:, later] ** 2).mean(axis=(0, 1)))
    straight_off = np.sqrt(((straight - true_z)[:, later] ** 2).mean(axis=(0, 1)))
    assert (off < 0.005).all() and (off * 10 < straight_off).all(), (off, straight_off)
    for link in range(2):  # along straight lines the states overshoot the twin's (measured: by 3–4 %)
        z, true = straight[:, later, link].ravel(), true_z[:, later, link].ravel()
        assert (z * true).sum() / (z * z).sum() < 0.985
    # the moves' last samples are where the arm came to rest: its gravity moments there are the settled ones
    end = gravity_moments(robot, moves[0][:, -1, 0], moves[1][:, -1, 0], m)
    rest = gravity_moments(robot, q, None, m)
    assert np.abs(end - rest).max() < 0.05 * np.abs(rest).max()
