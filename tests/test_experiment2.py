"""Experiment 2 on the twin: the compensation hook in the simulated-time runner, and its watchdog."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.plans import experiments
from acquisition.plans.compensation import StaticModelCompensator
from acquisition.plans.plan import PlanBuilder
from acquisition.recorder.sessions import SessionStore
from acquisition.safety import SafetyChecker, SafetyError
from acquisition.schemas import topics as T
from acquisition.schemas.events import Event, EventKind
from acquisition.schemas.fast_read import read_events, read_fixed_topics
from models import kinematics, trajectories
from twin.runner import SIM_EPOCH_NS, session_id, simulate, simulate_experiment
from twin.world import World

BAR, GRAM = 1e5, 1e-3


def test_static_compensation_lands_the_settled_tip_on_target(vsl):
    """Servo droop and link bending under a payload, inverted from the description: the twin's settled tip
    lands within 1 mm of the target (model-based IK alone: several mm at 0.5 bar and 75 g)."""
    lengths = experiments.arm_lengths(vsl)
    targets = np.random.default_rng(3).uniform([0.22, -0.08, 0.02], [0.38, 0.08, 0.18], size=(8, 3))
    q_ik = kinematics.vsl_ik(targets, lengths, 1)
    comp = StaticModelCompensator(vsl, payload_kg=0.075)
    q_cmd = comp(q_ik, np.full((8, 2), 0.5 * BAR), np.zeros((8, 3)))
    errors = {}
    for name, q in (("ik", q_ik), ("static", q_cmd)):
        world = World(vsl, batch=8, seed=0, q0=q, pressure_pa=0.5 * BAR, payload_kg=0.075)
        world.settle(3.0)
        errors[name] = np.linalg.norm(world.step(1).tip_pos[:, -1] - targets, axis=1)
    assert errors["ik"].mean() > 4e-3
    assert errors["static"].max() < 1e-3


def _base_frame_tip(robot, path):
    """Tracker poses of a session in the robot's base frame (the twin's configured placement: the test knows
    the truth the pipeline has to estimate) and the times of its repetition markers."""
    data = read_fixed_topics(path)
    tr = data[T.TRACKER]
    spec = robot.sensors.tracker
    r, p, y = spec.base_to_tracker_rpy_rad
    rot = _rpy(r, p, y)
    ok = ~tr.rows["missing"]
    tip = (tr.rows["position"][ok] - np.asarray(spec.base_to_tracker_translation_m)) @ rot
    return tr.log_time[ok], tip, data


def _rpy(r, p, y):
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array(
        [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
         [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
         [-sp, cp * sr, cp * cr]]
    )  # fmt: skip


def _path_error(tip: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Distance from each measured point to the densely sampled desired path."""
    return np.sqrt(((tip[:, None, :] - path[None]) ** 2).sum(-1)).min(axis=1)


@pytest.mark.slow
def test_experiment2_static_compensation_beats_model_based_ik(vsl, tmp_path):
    """Experiment 2's 0.5 bar / 75 g case, one repetition, on the twin: the sent goals are the compensator's,
    and the compensated path error is a fraction of the model-based one."""
    params = experiments.load_experiment(
        "experiment2", cases=[{"payload_g": 75, "pressure_bar": 0.5}], commands=["ik", "static"],
        rigid_arm=False, repetitions=1, points_per_segment=25, settle_s=1.0, rest_s=0.5,
    )  # fmt: skip
    (report,) = simulate_experiment("experiment2", SessionStore(tmp_path), seed=1, overrides=params)
    assert len(report.sessions) == 2
    plans = {p.parameters["commands"]: p for p in experiments.experiment2(vsl, None, params)}
    lengths = experiments.arm_lengths(vsl)
    desired = trajectories.experiment1("curve", lengths, speed=0.02, n_per_segment=400).x
    errors = {}
    for mode, plan in plans.items():
        session = tmp_path / session_id(plan)
        part = next(session.glob("*.mcap"))
        t, tip, data = _base_frame_tip(vsl, part)
        events = read_events(part)
        ((t0, _),) = [(t, e) for t, e in events if e.kind == EventKind.REPETITION_START]
        ((t1, _),) = [(t, e) for t, e in events if e.kind == EventKind.REPETITION_END]
        inside = (t >= t0 + 0.5e9) & (t <= t1 - 0.5e9)  # skip the start transient and the final hold
        errors[mode] = _path_error(tip[inside], desired)
        goals = data[T.SERVO_GOAL].rows["position"]
        if mode == "ik":
            np.testing.assert_allclose(goals, plan.goal_q[:, 1:], atol=1e-12)  # q1 is the stepper
        else:
            assert np.abs(goals[1:] - plan.goal_q[1:, 1:]).max() > 5e-3  # compensated
    assert errors["ik"].mean() > 3e-3
    assert errors["static"].mean() < 0.35 * errors["ik"].mean()


def test_hybrid_commands_need_an_inverse_model(tmp_path):
    with pytest.raises(ValueError, match="inverse model"):
        simulate_experiment("experiment2", SessionStore(tmp_path), overrides={"repetitions": 1})
    with pytest.raises(ValueError, match="history commands need a trained inverse model"):
        simulate_experiment(
            "experiment2", SessionStore(tmp_path), overrides={"repetitions": 1, "commands": ["ik", "history"]}
        )
    assert not any(tmp_path.iterdir())


def test_unsafe_plans_do_not_run_and_the_watchdog_stops_a_bench(vsl, tmp_path, monkeypatch):
    """A plan over the pressure limit is refused before anything runs; with the pre-check bypassed, the
    in-run watchdog ends that bench's session with a SAFETY_STOP event while the other bench goes on."""

    def plan(name, bar):
        b = PlanBuilder(name, "vsl", joints=3, channels=2)
        b.goto([0.0, 0.9, -1.6], 0.5).pressure(1.0 * BAR).payload(0.0).wait(1.0)
        return b.pressure(bar * BAR).wait(3.0).build()

    plans = [plan("test/ok", 1.5), plan("test/over", 2.6)]
    with pytest.raises(SafetyError, match="2600"):
        simulate(plans, vsl, tmp_path, seed=0)
    assert not any(tmp_path.iterdir())
    monkeypatch.setattr(SafetyChecker, "require_safe", lambda self, plan: None)
    simulate(plans, vsl, tmp_path, seed=0)
    ok_part, over_part = (next((tmp_path / session_id(p)).glob("*.mcap")) for p in plans)
    ok, over = read_fixed_topics(ok_part), read_fixed_topics(over_part)
    assert not [e for _, e in read_events(ok_part) if e.kind == EventKind.SAFETY_STOP]
    stops = [(t, e) for t, e in read_events(over_part) if e.kind == EventKind.SAFETY_STOP]
    assert len(stops) == 1 and stops[0][1].label == "pressure"
    t_stop = (stops[0][0] - SIM_EPOCH_NS) / 1e9
    assert 1.0 < t_stop < 1.5  # the regulator passes 2.05 bar within a few time constants of the step
    assert over[T.PRESSURE].log_time.max() <= stops[0][0] + 50e6
    assert ok[T.PRESSURE].log_time.max() > SIM_EPOCH_NS + 3.9e9
    assert isinstance(stops[0][1], Event)
