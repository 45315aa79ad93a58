"""Safety limits: static moments against the twin's kernel, and each limit caught on plans and on samples."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.plans import experiments
from acquisition.plans.plan import PlanBuilder
from acquisition.safety import SafetyChecker, SafetyError
from models.prbm import collapse_moment, wrinkling_moment
from models.robot import load_robot
from models.statics import gravity_moments, static_deflection
from twin.world import World

BAR, KPA = 1e5, 1e3


@pytest.mark.parametrize(
    ("name", "q0", "pressure"), [("vsl", [0.0, 0.9, -1.6], 1.0 * BAR), ("popup", [0.3, 0.8, -1.2], 40 * KPA)]
)
def test_static_moments_match_the_twin_kernel(name, q0, pressure):
    """The virtual joints' gravity moments (numpy, models.statics) equal the kernel's at rest, and the static
    deflection δ = M/k(p) matches the settled twin within the hysteresis offset δ_h."""
    robot = load_robot(name)
    world = World(robot, batch=1, seed=0, q0=np.array(q0), pressure_pa=pressure, payload_kg=0.05)
    world.settle(5.0)
    trace = world.step(1)
    rows = [i for i, r in enumerate(robot.dh_rows()) if not r.joint.startswith("q")]
    moments = gravity_moments(robot, trace.q[0, -1], trace.delta[0, -1], 0.05)[rows]
    np.testing.assert_allclose(moments, world.state.vj_torque[0], rtol=1e-4, atol=1e-5)  # one step apart
    delta, _ = static_deflection(robot, trace.q[0, -1], pressure, 0.05)
    delta_h = max(link.hysteresis.delta_h_rad for link in robot.links)
    assert np.abs(delta - trace.delta[0, -1]).max() <= delta_h * 1.05


@pytest.mark.slow
def test_the_seed_protocols_are_safe(vsl):
    rigid = load_robot("vsl_rigid")
    plans = experiments.experiment1(
        vsl, rigid, experiments.load_experiment("experiment1", payloads_g=[0, 100])
    )
    plans += experiments.campaign(vsl, experiments.load_experiment("campaign", points=400), benches=4)
    for plan in plans:
        SafetyChecker(vsl if plan.robot == "vsl" else rigid).require_safe(plan)


def _vsl_plan(q_end, pressure_pa=1.0 * BAR, valve=True):
    b = PlanBuilder("test/safety", "vsl", joints=3, channels=2)
    b.goto([0.0, 0.9, -1.6], 0.5).pressure(1.0 * BAR).payload(0.0).wait(2.0)
    b.pressure(pressure_pa, valve).goto(q_end, 0.5).wait(3.0)
    return b.build()


def test_joint_pressure_and_workspace_limits(vsl):
    check = SafetyChecker(vsl)
    assert check.check_plan(_vsl_plan([0.0, 1.0, -1.7])) == []
    # q3 beyond its +170° limit
    v = check.check_plan(_vsl_plan([0.0, 1.0, 3.0]))[0]  # (the tip also leaves the box on the way)
    assert v.limit == "joint" and "q3" in v.detail and v.t_s == pytest.approx(2.0)
    # 2.5 bar is above the VSL's 2 bar; 0.2 bar with the valve open is below its 0.5 bar
    assert {x.limit for x in check.check_plan(_vsl_plan([0.0, 1.0, -1.7], 2.5 * BAR))} == {"pressure"}
    assert {x.limit for x in check.check_plan(_vsl_plan([0.0, 1.0, -1.7], 0.2 * BAR))} == {"pressure"}
    # the tip under the base plate (shoulder pitched down), caught when commanded
    violations = check.check_plan(_vsl_plan([0.0, -0.15, -1.0]))
    assert {x.limit for x in violations} == {"workspace"} and violations[0].t_s == pytest.approx(2.0)
    with pytest.raises(SafetyError, match="workspace"):
        check.require_safe(_vsl_plan([0.0, -0.15, -1.0]))


def _popup_plan(pressure_pa, payload_kg, allow_wrinkling=False, stowed=False):
    """Link 2 horizontal (q2 = 0, q3 = 90°: link 1 up, link 2 out), a tip payload."""
    b = PlanBuilder(
        "test/popup", "popup", joints=3, channels=2, parameters={"allow_wrinkling": allow_wrinkling}
    )
    b.goto([0.0, np.pi / 2, -np.pi / 2], 0.3).pressure(pressure_pa, valve_open=not stowed).payload(0.0).wait(
        5.0
    )
    b.payload(payload_kg).wait(2.0)
    if stowed:
        b.goto([0.2, np.pi / 2, -np.pi / 2], 0.3).wait(2.0)
    return b.build()


def test_wrinkling_and_collapse_limits_of_inflatable_links(popup):
    check = SafetyChecker(popup)
    q = np.array([0.0, np.pi / 2, -np.pi / 2])
    p = np.array([50 * KPA, 50 * KPA])
    _, moments = static_deflection(popup, q, p, 2.0)
    bending = np.hypot(moments[2], moments[3])  # link 2's two virtual joints
    m_w, m_c = wrinkling_moment(50 * KPA, 0.055), collapse_moment(50 * KPA, 0.055)
    assert m_w < bending < 0.9 * m_c  # 2 kg (seed 001's task payload) wrinkles link 2 at 50 kPa
    assert check.check_plan(_popup_plan(50 * KPA, 0.0)) == []
    assert {v.limit for v in check.check_plan(_popup_plan(50 * KPA, 2.0))} == {"wrinkling"}
    # a protocol studying the non-linear range is held below collapse instead
    assert check.check_plan(_popup_plan(50 * KPA, 2.0, allow_wrinkling=True)) == []
    assert {v.limit for v in check.check_plan(_popup_plan(50 * KPA, 3.0, allow_wrinkling=True))} == {
        "collapse"
    }
    # deflated (stowed) links carry no wrinkling limit, but nothing may move while one is stowed
    assert {v.limit for v in check.check_plan(_popup_plan(0.0, 0.0, stowed=True))} == {"stowed-motion"}


def test_measured_state_checks(popup):
    check = SafetyChecker(popup)
    t = np.array([0.0, 0.1, 0.2])
    q = np.tile([0.0, np.pi / 2, -np.pi / 2], (3, 1))
    p = np.array([[50, 50], [50, 50], [96, 50]]) * KPA  # 96 kPa > 90 kPa + 5 kPa tolerance
    violations = check.check_state(t, q, p, payload_kg=[0.0, 2.0, 0.0])
    assert [(v.t_s, v.limit) for v in violations] == [(0.1, "wrinkling"), (0.2, "pressure")]


def _deployment(popup, move_after: bool = False):
    """Stowed at 0 kPa in an upright pose; both links inflated at 1 s, their valves closed at 3 s; optionally
    a move at 4 s."""
    b = PlanBuilder("test/deploy", "popup", joints=3, channels=2)
    b.goto([0.0, np.pi / 2, 0.0]).pressure(0.0, False).payload(0.0).wait(1.0)
    b.pressure(50 * KPA, True).wait(2.0).pressure(50 * KPA, False).wait(1.0)
    if move_after:
        b.goto([0.0, np.pi / 2 - 0.2, 0.0]).wait(1.0)
    return b.build()


def test_a_link_filling_from_stowed_bears_no_load_until_the_arm_moves(popup):
    """A link inflated from stowed counts as stowed below the operating minimum (at 0 kPa M_w is 0: any
    moment would break it), but only until a joint moves: a link that loses its pressure later is wrinkled."""
    check = SafetyChecker(popup)
    plan = _deployment(popup)
    assert check.check_plan(plan) == []
    t = np.array([0.5, 1.5, 3.5, 10.0])
    np.testing.assert_array_equal(check.stowed(plan, t), [[1, 1], [1, 1], [1, 1], [1, 1]])
    moved = _deployment(popup, move_after=True)
    assert check.check_plan(moved) == []
    np.testing.assert_array_equal(check.stowed(moved, np.array([3.5, 4.5])), [[1, 1], [0, 0]])
    q = np.tile([0.0, np.pi / 2 - 0.05, 0.0], (2, 1))  # tilted a little: a small moment on both links
    p = np.array([[2 * KPA, 0.0], [2 * KPA, 0.0]])  # both filling (or deflated again)
    filling = check.stowed(plan, np.array([1.5, 1.6]))
    assert check.check_state(np.array([1.5, 1.6]), q, p, 0.0, stowed=filling) == []
    assert check.check_state(np.array([1.5, 1.6]), q, p, 0.0) != []  # the same state, not stowed: wrinkling
    late = check.check_state(np.array([4.5]), q[:1], p[:1], 0.0, stowed=check.stowed(moved, np.array([4.5])))
    assert {v.limit for v in late} == {"wrinkling"}
    # stowed by the plan but measured inflated: load-bearing, checked (2 kg wrinkles link 2 at 50 kPa)
    horizontal, high = np.array([[0.0, np.pi / 2, -np.pi / 2]]), np.array([[50 * KPA, 50 * KPA]])
    wrinkled = check.check_state(np.array([0.5]), horizontal, high, 2.0, stowed=check.stowed(plan, [0.5]))
    assert {v.limit for v in wrinkled} == {"wrinkling"}


def test_a_plan_that_starts_stowed_needs_the_bench_set_up_as_it_starts(popup):
    check = SafetyChecker(popup)
    plan = _deployment(popup)
    assert check.check_start(plan, np.array([0.0, np.pi / 2, 0.0]), np.array([0.0, 5 * KPA])) == []
    problems = check.check_start(plan, np.deg2rad([0.0, 30.0, -60.0]), np.array([90 * KPA, 5 * KPA]))
    assert [v.detail for v in problems] == [
        "q2 at 30.0°, q3 at -60.0° (the plan starts at 90.0°, 0.0° and moves no joint while a link is "
        "deflated)",
        "link1 at 90.0 kPa (the plan starts with it deflated, below 10 kPa)",
    ]
    inflated = _popup_plan(50 * KPA, 0.0)  # a plan that starts inflated moves the arm to its start itself
    assert check.check_start(inflated, np.deg2rad([0.0, 30.0, -60.0]), np.array([90 * KPA] * 2)) == []
