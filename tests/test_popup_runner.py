"""POPUP's plans in real time on the rig: the runner commands the CiA 402 drives and the main board over the
CAN bus and watches the joint states the drives answer; a drive's fault (EMCY) or a drive gone silent stops
the plan safely, with the reason, and the session stays whole."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.plans.experiments import load_experiment
from acquisition.plans.plan import PlanBuilder
from acquisition.plans.popup_experiments import deployment
from acquisition.plans.rt_runner import RealTimeRunner, RunnerError
from acquisition.recorder.recorder import Recorder
from acquisition.recorder.sessions import session_info
from acquisition.schemas import topics as T
from acquisition.schemas.events import EventKind
from acquisition.schemas.fast_read import read_events, read_fixed_topics
from twin.ptyhost import send_control

RIG = {"module": "twin.rig", "extra": ("--robot", "popup")}
KPA = 1e3
START = [0.0, 0.6, -0.9]  # near where the rig starts ([0, 0.52, -1.05]): reached in the first second


def _plan(name: str = "test/popup-rt"):
    """Inflated links, a start pose, three set-points, a payload change at ≈ 2.5 s, a hold: ≈ 5 s."""
    b = PlanBuilder(name, "popup", joints=3, channels=2, parameters={"experiment": "test"})
    b.pressure(40 * KPA).payload(0.0).goto(START, 0.5).wait(1.0)
    t = np.array([0.0, 0.5, 1.0])
    q = np.array([START, [0.1, 0.65, -0.85], [0.2, 0.7, -0.8]])
    b.follow(t, q, np.full((3, 3), 0.3)).payload(0.0).wait(2.0)
    return b.build()


def _run(host_factory, tmp_path, popup, at_payload=None):
    """Run the plan on a fresh rig; ``at_payload(rig_dir)`` is what happens at the second payload step."""
    plan = _plan()
    steps = []

    def payload_step(kg):
        steps.append(kg)
        if len(steps) == 2 and at_payload is not None:
            at_payload(rig_dir)

    with host_factory(**RIG) as ports:
        rig_dir = tmp_path / "run"
        with Recorder(popup, {"can_bus": ports["can_bus"]}, tmp_path / "s", "s") as rec:
            report = RealTimeRunner(rec, plan, on_payload=payload_step).run()
            truth = send_control(rig_dir, {"op": "state"})
    (part,) = sorted((tmp_path / "s").glob("*.mcap"))
    return plan, report, truth, part


@pytest.mark.slow
def test_a_popup_plan_runs_on_the_rig_through_the_can_bus(host_factory, tmp_path, popup):
    plan, report, truth, part = _run(host_factory, tmp_path, popup)
    assert report.status == "complete", report.reason
    data = read_fixed_topics(part)
    goals = data[T.SERVO_GOAL].rows
    np.testing.assert_allclose(goals["position"], plan.goal_q)  # drive node order q1, q2, q3
    joints = data[T.JOINT_STATE].rows
    assert len(joints) > 300  # 100 Hz over ≈ 5 s
    # the drives interpolate toward each goal and get there: measured, and in the twin's truth
    np.testing.assert_allclose(joints["position"][-20:].mean(axis=0), plan.goal_q[-1], atol=0.02)
    np.testing.assert_allclose(truth["q"], plan.goal_q[-1], atol=0.03)
    np.testing.assert_allclose(data[T.PRESSURE].rows["pressure"][-50:].mean(axis=0), 40 * KPA, rtol=0.05)
    assert EventKind.SAFETY_STOP not in [e.kind for _, e in read_events(part)]


@pytest.mark.slow
@pytest.mark.parametrize(
    ("fault", "why"),
    [({"op": "can", "node": 2, "fault": 0x2310}, "q2 faulted: EMCY 0x2310 (over-current)"),
     ({"op": "can", "node": 3, "power": False}, "no fresh samples")],
)  # fmt: skip
def test_a_drive_fault_or_a_silent_drive_stops_a_popup_plan(host_factory, tmp_path, popup, fault, why):
    plan, report, _, part = _run(host_factory, tmp_path, popup, lambda rig_dir: send_control(rig_dir, fault))
    assert report.status == "stopped" and report.reason.startswith("device") and why in report.reason, report
    assert report.elapsed_s < plan.duration_s - 1.0
    stops = [e for _, e in read_events(part) if e.kind == EventKind.SAFETY_STOP]
    assert len(stops) == 1 and stops[0].label == "device"
    if "fault" in fault:
        faults = [e for _, e in read_events(part) if e.kind == EventKind.DEVICE_FAULT]
        assert faults and faults[0].label == "can_bus" and "over-current" in faults[0].text
    assert session_info(tmp_path / "s").status == "complete"


@pytest.mark.slow
def test_a_deployment_refuses_to_start_on_an_arm_that_is_not_set_up_for_it(host_factory, tmp_path, popup):
    """A deployment begins with its links stowed and moves no joint before they are inflated: on the rig as
    it boots (home pose, links at 90 kPa) it refuses to start, says what differs, and sends nothing."""
    (plan,) = deployment(popup, load_experiment("popup_deploy"))
    with host_factory(**RIG) as ports:
        with Recorder(popup, {"can_bus": ports["can_bus"]}, tmp_path / "s", "s") as rec:
            with pytest.raises(RunnerError) as refused:
                RealTimeRunner(rec, plan).run()
    assert f"plan {plan.name} cannot start on the bench as it is: q2 at 29." in str(refused.value)  # drooped
    assert "link1 at 89.9 kPa, link2 at 89.9 kPa (the plan starts with them deflated" in str(refused.value)
    (part,) = sorted((tmp_path / "s").glob("*.mcap"))
    data = read_fixed_topics(part)
    assert len(data[T.SERVO_GOAL]) == len(data[T.PRESSURE_COMMAND]) == 0
