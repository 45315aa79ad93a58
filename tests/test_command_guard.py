"""The command guard: nothing outside the robot's limits, and nothing that is not a number, reaches a device —
from a plan, a compensator (NaN, ±1e35, out-of-range angles) or the Python API; the events say why."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from acquisition.command_guard import CommandGuard, CommandRefused
from acquisition.plans.plan import PlanBuilder
from acquisition.plans.rt_runner import RealTimeRunner
from acquisition.recorder.recorder import Recorder
from acquisition.schemas import topics as T
from acquisition.schemas.events import EventKind
from acquisition.schemas.fast_read import read_events, read_fixed_topics
from twin.ptyhost import send_control
from twin.runner import simulate

RIG = {"module": "twin.rig", "extra": ("--robot", "vsl")}
BAR = 1e5
BAD_GOALS = {
    "nan": [0.2, math.nan, -1.6],
    "huge": [0.2, 2e35, -1.6],
    "minus-huge": [-1e35, 0.9, -1.6],
    "out of range": [0.2, 0.9, -3.5],  # q3's range is ±170°
    "inf": [0.2, 0.9, math.inf],
}


# ------------------------------------------------------------------------------------------- the guard
def test_goals_inside_the_limits_pass_unchanged(vsl):
    guard = CommandGuard(vsl)
    q = guard.joint_goals([0.2, 0.9, -1.6])
    np.testing.assert_array_equal(q, [0.2, 0.9, -1.6])
    lo, hi = vsl.joint_limits().T
    np.testing.assert_array_equal(guard.joint_goals(lo), lo)  # the limits themselves are inside
    np.testing.assert_array_equal(guard.joint_goals(hi), hi)


@pytest.mark.parametrize("case", sorted(BAD_GOALS))
def test_bad_joint_goals_are_refused_with_the_reason(vsl, case):
    with pytest.raises(CommandRefused, match=r"not a finite number|outside its range"):
        CommandGuard(vsl).joint_goals(BAD_GOALS[case])


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda g: g.joint_goals([0.1, 0.2]), "2 values where 3"),
        (lambda g: g.joint_goals(["a", 0.2, 0.3]), "not numbers"),
        (lambda g: g.servo_goals(["q2", "q3"], [0.9, -1.6], [0.3, -0.1]), "profile velocity of q3"),
        (lambda g: g.servo_goals(["q2", "q3"], [0.9, -1.6], [0.3, 1e9]), "profile velocity of q3"),
        (lambda g: g.pressures([1e5, 3.5e5], [True, True]), r"channel 1 .* outside"),
        (lambda g: g.pressures([-1.0, 1e5], [True, True]), r"channel 0 .* outside"),
        (lambda g: g.pressures([1e5, math.nan], [True, True]), "not a finite number"),
        (lambda g: g.pressures([1e5, 1e5], [True, 7]), "valve states"),
        (lambda g: g.pressures([1e5, 1e5], [True]), "valve states"),
        (lambda g: g.stepper_move("q1", 10.5, 100.0, 100.0), "whole number"),
        (lambda g: g.stepper_move("q1", 10**9, 100.0, 100.0), "outside the range of q1"),
        (lambda g: g.stepper_move("q1", 0, 0.0, 100.0), "speed"),
        (lambda g: g.stepper_move("q1", 0, 100.0, math.nan), "not a finite number"),
        (lambda g: g.stepper_move("q1", 0, 100.0, 1e12), "acceleration"),
    ],
)
def test_each_kind_of_bad_command_is_refused(vsl, call, match):
    with pytest.raises(CommandRefused, match=match):
        call(CommandGuard(vsl))


@settings(max_examples=300, derandomize=True, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=3, max_size=3))
def test_any_goal_either_passes_inside_the_limits_or_is_refused(vsl, q):
    lo, hi = vsl.joint_limits().T
    try:
        out = CommandGuard(vsl).joint_goals(q)
    except CommandRefused:
        return
    assert np.all(np.isfinite(out)) and np.all(out >= lo) and np.all(out <= hi)


@settings(max_examples=200, derandomize=True, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=2, max_size=2))
def test_any_setpoint_either_passes_inside_the_range_or_is_refused(vsl, p):
    try:
        out, _ = CommandGuard(vsl).pressures(p, [True, False])
    except CommandRefused:
        return
    assert np.all(out >= 0) and np.all(out <= vsl.pneumatics.max_operating_pa)


# ------------------------------------------------------------------------------------ on the rig
def _plan(name="test/guard"):
    b = PlanBuilder(name, "vsl", joints=3, channels=2, parameters={"experiment": "test"})
    b.goto([0.2, 0.9, -1.6], 0.6).pressure(1.0 * BAR).payload(0.0).wait(0.4)
    b.goto([0.25, 0.95, -1.65], 0.5).wait(0.5)
    return b.build()


class _Network:
    """A compensator that is right for the first set-point and then goes wrong."""

    def __init__(self, bad):
        self.bad, self.calls = bad, 0

    def __call__(self, q_ik, pressure_pa, current_a, t_s=None):
        self.calls += 1
        return q_ik if self.calls == 1 else np.asarray([self.bad], float)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["nan", "huge", "out of range"])
def test_a_compensator_gone_wrong_stops_the_plan_and_nothing_reaches_the_servos(host_factory, tmp_path, vsl,
                                                                                case):  # fmt: skip
    plan = _plan()
    with host_factory(**RIG) as ports:
        with Recorder(vsl, ports, tmp_path / "s", "s") as rec:
            report = RealTimeRunner(rec, plan, compensator=_Network(BAD_GOALS[case])).run()
            state = send_control(tmp_path / "run", {"op": "state"})
    assert report.status == "stopped" and report.reason.startswith("command: refused")
    took = np.asarray(state["goal_q"])  # what the servos were given (the first goal, or the hold)
    lo, hi = vsl.joint_limits().T
    assert np.all(np.isfinite(took)) and np.all(took >= lo) and np.all(took <= hi)
    (part,) = sorted((tmp_path / "s").glob("*.mcap"))
    sent = read_fixed_topics(part)[T.SERVO_GOAL].rows["position"]
    np.testing.assert_allclose(sent, plan.goal_q[:1, 1:])  # only the good goal went out
    events = [e for _, e in read_events(part)]
    refused = [e for e in events if e.kind == EventKind.COMMAND_REFUSED]
    assert len(refused) == 1 and ("finite" in refused[0].text or "outside" in refused[0].text)
    assert any(e.kind == EventKind.SAFETY_STOP and e.label == "command" for e in events)


@pytest.mark.slow
def test_the_daemon_refuses_what_the_python_api_sends_and_the_runner_would_stop(host_factory, tmp_path, vsl):
    with host_factory(**RIG) as ports:
        with Recorder(vsl, ports, tmp_path / "s", "s") as rec:
            while rec.latest(T.SERVO_STATE) is None:
                time.sleep(0.01)
            assert rec.command(T.SERVO_GOAL, {"op": "torque", "on": True})
            assert rec.command(
                T.SERVO_GOAL, {"op": "goals", "position": [0.9, -1.6], "profile_velocity": [0.5, 0.5]}
            )
            assert rec.command(T.SERVO_GOAL, {"op": "goals", "position": [math.nan, -1.6],
                                              "profile_velocity": [0.5, 0.5]})  # fmt: skip
            assert rec.command(T.PRESSURE_COMMAND, {"op": "pressures", "setpoint": [1e5, 9e5],
                                                    "valve_open": [True, True]})  # fmt: skip
            assert rec.command(T.STEPPER, {"op": "move", "steps": 10**9, "speed": 100.0, "accel": 100.0})
            deadline = time.monotonic() + 5
            while rec.refusals()[0] < 3 and time.monotonic() < deadline:
                time.sleep(0.02)
            count, last = rec.refusals()
            state = send_control(tmp_path / "run", {"op": "state"})
    assert count == 3 and "outside" in last
    np.testing.assert_allclose(state["goal_q"][1:], [0.9, -1.6], atol=2e-3)  # the good goal, not the NaN
    assert max(state["pressure_set_pa"]) <= vsl.pneumatics.max_operating_pa  # not the 9 bar sent
    assert abs(state["goal_q"][0]) < 1.6  # the stepper never went for 10⁹ steps
    (part,) = sorted((tmp_path / "s").glob("*.mcap"))
    refused = [e for _, e in read_events(part) if e.kind == EventKind.COMMAND_REFUSED]
    assert sorted(e.label for e in refused) == [
        "pressure_board",
        "servo_bus",
        "stepper_board",
    ]  # daemons run apart


# ------------------------------------------------------------------------------- in simulated time
def test_simulated_benches_hold_when_their_compensator_goes_wrong(tmp_path, vsl):
    plans = [_plan(f"test/guard-{k}") for k in range(3)]
    compensators = [None, _Network(BAD_GOALS["huge"]), _Network(BAD_GOALS["nan"])]
    report = simulate(plans, vsl, tmp_path, compensators=compensators)
    assert sorted(report.stopped) == ["sim-test-guard-1", "sim-test-guard-2"]
    assert all(why.startswith("command: refused") for why in report.stopped.values())
    for k in range(3):
        (part,) = sorted((tmp_path / f"sim-test-guard-{k}").glob("*.mcap"))
        goals = read_fixed_topics(part)[T.SERVO_GOAL].rows["position"]
        lo, hi = vsl.joint_limits()[1:].T
        assert np.all(np.isfinite(goals)) and np.all(goals >= lo) and np.all(goals <= hi)
        kinds = [e.kind for _, e in read_events(part)]
        assert (EventKind.COMMAND_REFUSED in kinds) == (k > 0)
