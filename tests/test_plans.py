"""Plans as data: the builder, Plan.at, protocol loading and the Experiment 1 / campaign expansions."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.plans import experiments
from acquisition.plans.plan import Plan, PlanBuilder
from acquisition.schemas.events import Event, EventKind
from models import kinematics, trajectories

BAR, GRAM = 1e5, 1e-3


def _builder(name: str = "test/plan") -> PlanBuilder:
    return PlanBuilder(name, "vsl", joints=3, channels=2, parameters={"experiment": "test"})


def _simple_plan() -> Plan:
    b = _builder()
    b.goto([0.0, 0.1, 0.2], speed=0.5).pressure(1.0 * BAR).payload(0.0)
    b.wait(1.0).goto([0.3, 0.4, 0.5]).mark(EventKind.NOTE, text="moved")
    b.wait(0.5).pressure([1.5 * BAR, 2.0 * BAR], valve_open=[True, False])
    b.settle(2.0, index=7, hold_s=0.25)
    b.payload(0.05)
    return b.build()


# ------------------------------------------------------------------------------ PlanBuilder / Plan
def test_builder_places_actions_at_the_cursor():
    plan = _simple_plan()
    assert plan.name == "test/plan" and plan.robot == "vsl"
    assert plan.parameters == {"experiment": "test"}
    assert plan.duration_s == pytest.approx(3.75)
    np.testing.assert_allclose(plan.goal_t, [0.0, 1.0])
    np.testing.assert_allclose(plan.goal_q, [[0.0, 0.1, 0.2], [0.3, 0.4, 0.5]])
    np.testing.assert_allclose(plan.goal_speed, [[0.5, 0.5, 0.5], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(plan.pressure_t, [0.0, 1.5])
    np.testing.assert_allclose(plan.pressure_pa, [[1e5, 1e5], [1.5e5, 2e5]])
    assert plan.valve_open.dtype == bool
    np.testing.assert_array_equal(plan.valve_open, [[True, True], [True, False]])
    np.testing.assert_allclose(plan.payload_t, [0.0, 3.75])
    np.testing.assert_allclose(plan.payload_kg, [0.0, 0.05])
    kinds = [(t, e.kind) for t, e in plan.events]
    assert kinds == [
        (0.0, EventKind.PAYLOAD),
        (1.0, EventKind.NOTE),
        (3.5, EventKind.SETTLED),
        (3.75, EventKind.PAYLOAD),
    ]
    settled = plan.events[2][1]
    assert settled.index == 7 and settled.value == pytest.approx(0.25)
    assert plan.events[0][1].value == 0.0 and plan.events[3][1].value == pytest.approx(0.05)
    assert plan.events[3][1].text == "payload 50 g"


def test_plan_at_returns_the_latest_action_at_or_before_t():
    plan = _simple_plan()
    t = np.array([0.0, 0.5, 0.999, 1.0, 1.2, 1.5, 3.0, 3.75, 3.8])
    now = plan.at(t)
    np.testing.assert_array_equal(now["goal_index"], [0, 0, 0, 1, 1, 1, 1, 1, 1])
    np.testing.assert_array_equal(now["pressure_index"], [0, 0, 0, 0, 0, 1, 1, 1, 1])
    np.testing.assert_allclose(now["goal_q"][2], [0.0, 0.1, 0.2])
    np.testing.assert_allclose(now["goal_q"][3], [0.3, 0.4, 0.5])
    np.testing.assert_allclose(now["goal_speed"][0], [0.5] * 3)
    np.testing.assert_allclose(now["pressure_pa"][5], [1.5e5, 2e5])
    np.testing.assert_array_equal(now["valve_open"][4], [True, True])
    np.testing.assert_array_equal(now["valve_open"][5], [True, False])
    np.testing.assert_allclose(now["payload_kg"], [0, 0, 0, 0, 0, 0, 0, 0.05, 0.05])
    assert now["goal_q"].shape == (len(t), 3) and now["pressure_pa"].shape == (len(t), 2)


def test_follow_shifts_setpoint_times_to_the_cursor():
    t = np.array([10.0, 10.5, 11.25])  # absolute times of the trajectory: only the spacing counts
    q = np.array([[0.0, 0.1, 0.2], [0.1, 0.2, 0.3], [0.2, 0.3, 0.4]])
    qd = np.array([[-0.1, 0.2, 0.0], [0.3, -0.4, 0.5], [0.0, 0.0, 0.0]])
    b = _builder().goto(q[0]).pressure(1e5).payload(0.0).wait(2.0)
    b.follow(t, q, qd)
    assert b.t == pytest.approx(3.25)  # the cursor ends at the last set-point
    b.wait(0.5)
    plan = b.build()
    np.testing.assert_allclose(plan.goal_t, [0.0, 2.0, 2.5, 3.25])
    np.testing.assert_allclose(plan.goal_q[1:], q)
    np.testing.assert_allclose(plan.goal_speed[1:], np.abs(qd))  # speeds are magnitudes
    assert plan.duration_s == pytest.approx(3.75)
    now = plan.at(np.array([2.4, 2.5, 3.0, 3.3]))
    np.testing.assert_array_equal(now["goal_index"], [1, 2, 2, 3])


def test_follow_accepts_lists():
    b = _builder().goto([0, 0, 0]).pressure(1e5).payload(0.0).wait(1.0)
    b.follow([5.0, 6.0], [[0, 0, 0], [1, 1, 1]], [[0, 0, 0], [1, 1, 1]])
    np.testing.assert_allclose(b.build().goal_t, [0.0, 1.0, 2.0])


@pytest.mark.parametrize("missing", ["goal", "pressure", "payload"])
def test_build_without_an_action_raises(missing):
    b = _builder()
    if missing != "goal":
        b.goto([0, 0, 0])
    if missing != "pressure":
        b.pressure(1e5)
    if missing != "payload":
        b.payload(0.0)
    b.wait(1.0)
    with pytest.raises(ValueError, match=f"no {missing} action"):
        b.build()


def test_first_action_must_be_at_zero():
    b = _builder().pressure(1e5).payload(0.0).wait(1.0).goto([0, 0, 0])
    with pytest.raises(ValueError, match="goal times must start at 0"):
        b.build()


def test_times_going_back_raise():
    good = _simple_plan()
    with pytest.raises(ValueError, match="goal times must start at 0 and never go back"):
        Plan(
            "bad", "vsl", 3.0, np.array([0.0, 2.0, 1.0]), np.zeros((3, 3)), np.zeros((3, 3)),
            good.pressure_t, good.pressure_pa, good.valve_open, good.payload_t, good.payload_kg, (),
        )  # fmt: skip
    # a follow() whose set-point times run backwards moves goals back in time: refused at build
    b = _builder().goto([0, 0, 0]).pressure(1e5).payload(0.0).wait(5.0)
    b.follow([3.0, 1.0], [[0, 0, 0], [1, 1, 1]], [[0, 0, 0], [0, 0, 0]])
    with pytest.raises(ValueError, match="never go back"):
        b.build()


def test_action_after_the_end_raises():
    good = _simple_plan()
    with pytest.raises(ValueError, match="after the plan's end"):
        Plan(
            "late", "vsl", 1.0, good.goal_t, good.goal_q, good.goal_speed, good.pressure_t,
            good.pressure_pa, good.valve_open, good.payload_t, good.payload_kg, (),
        )  # fmt: skip


def test_negative_wait_raises():
    b = _builder()
    with pytest.raises(ValueError, match="negative"):
        b.wait(-0.1)
    with pytest.raises(ValueError, match="negative"):
        b.settle(-1.0)
    assert b.t == 0.0


def test_events_are_sorted_and_keep_their_order_at_equal_times():
    b = _builder().goto([0, 0, 0]).pressure(1e5).payload(0.0)
    b.mark(EventKind.NOTE, text="a").mark(EventKind.PLAN_STEP, index=1, label="b")
    b.wait(1.0).mark(EventKind.REPETITION_START, 0, "rep").wait(2.0).mark(EventKind.REPETITION_END, 0, "rep")
    plan = b.build()
    times = [t for t, _ in plan.events]
    assert times == sorted(times)
    assert [e.kind for _, e in plan.events] == [
        EventKind.PAYLOAD,
        EventKind.NOTE,
        EventKind.PLAN_STEP,
        EventKind.REPETITION_START,
        EventKind.REPETITION_END,
    ]
    step = plan.events[2][1]
    assert (step.index, step.label, step.text) == (1, "b", "")
    assert plan.events[1][1] == Event(EventKind.NOTE, -1, plan.events[1][1].value, "", "a")
    assert times == [0.0, 0.0, 0.0, 1.0, 3.0]


def test_builder_checks_shapes():
    b = _builder()
    with pytest.raises(ValueError):
        b.goto([0.0, 1.0])  # two values for three joints
    b.pressure(2e5)  # a scalar is broadcast to every channel
    b.pressure([1e5, 2e5], valve_open=False)
    with pytest.raises(ValueError):
        b.pressure([1e5, 2e5, 3e5])


# ------------------------------------------------------------------------------ load_experiment
def test_load_protocol_reads_the_yaml():
    p = experiments.load_experiment("experiment1")
    assert p["trajectories"] == ["linear", "curve", "square"]
    assert p["repetitions"] == 5 and p["rigid_arm"] is True
    c = experiments.load_experiment("campaign")
    assert c["points"] == 17568 and c["robot"] == "vsl"


def test_load_protocol_applies_overrides():
    p = experiments.load_experiment("experiment1", repetitions=2, payloads_g=[0, 50], rigid_arm=False)
    assert p["repetitions"] == 2 and p["payloads_g"] == [0, 50] and p["rigid_arm"] is False
    assert p["pressures_bar"] == [0.5, 1.0, 1.5, 2.0]  # untouched keys stay
    # the overrides do not leak into the next load
    assert experiments.load_experiment("experiment1")["repetitions"] == 5


def test_load_protocol_by_path(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text("points: 3\nrobot: vsl\n")
    assert experiments.load_experiment(path, points=4) == {"points": 4, "robot": "vsl"}


def test_misspelt_override_raises():
    with pytest.raises(ValueError, match="repetition"):
        experiments.load_experiment("experiment1", repetition=3)


def test_unknown_protocol_lists_the_known_ones():
    with pytest.raises(FileNotFoundError, match="no experiment 'experiment9'") as err:
        experiments.load_experiment("experiment9")
    assert "campaign" in str(err.value) and "experiment1" in str(err.value)


# ------------------------------------------------------------------------------ experiment1
@pytest.fixture(scope="module")
def e1_params():
    return experiments.load_experiment(
        "experiment1",
        trajectories=["linear", "curve"],
        payloads_g=[0, 50, 100],
        pressures_bar=[0.5, 2.0],
        repetitions=3,
        points_per_segment=10,
    )


@pytest.fixture(scope="module")
def e1_plans(vsl, rigid, e1_params):
    return experiments.experiment1(vsl, rigid, e1_params)


def test_experiment1_plan_count(vsl, rigid, e1_params, e1_plans):
    n_traj, n_pay, n_p = (len(e1_params[k]) for k in ("trajectories", "payloads_g", "pressures_bar"))
    assert len(e1_plans) == n_traj * n_pay * (n_p + 1)
    assert len({p.name for p in e1_plans}) == len(e1_plans)
    assert sum(p.robot == "vsl_rigid" for p in e1_plans) == n_traj * n_pay
    without_rigid = experiments.experiment1(vsl, rigid, e1_params | {"rigid_arm": False})
    assert len(without_rigid) == n_traj * n_pay * n_p
    assert all(p.robot == "vsl" for p in without_rigid)
    assert len(experiments.experiment1(vsl, None, e1_params)) == n_traj * n_pay * n_p


def test_experiment1_full_protocol_count(vsl, rigid):
    params = experiments.load_experiment("experiment1", points_per_segment=5, repetitions=1)
    plans = experiments.experiment1(vsl, rigid, params)
    assert len(plans) == 3 * 5 * (4 + 1)


def test_experiment1_repetitions_are_bracketed_in_order(e1_plans, e1_params):
    reps = e1_params["repetitions"]
    for plan in e1_plans:
        marks = [
            (t, e) for t, e in plan.events if e.kind in (EventKind.REPETITION_START, EventKind.REPETITION_END)
        ]
        assert len(marks) == 2 * reps, plan.name
        expected = [
            (k, i) for i in range(reps) for k in (EventKind.REPETITION_START, EventKind.REPETITION_END)
        ]
        assert [(e.kind, e.index) for _, e in marks] == expected
        times = [t for t, _ in marks]
        assert np.all(np.diff(times) > 0)
        trajectory = plan.parameters["trajectory"]
        assert all(e.label == trajectory for _, e in marks)
        assert times[-1] < plan.duration_s


def test_experiment1_cells_set_payload_and_pressure(e1_plans):
    for plan in e1_plans:
        cell = plan.parameters
        assert cell["experiment"] == "experiment1"
        grams = round(cell["payload_kg"] / GRAM)
        assert plan.name == f"experiment1/{cell['trajectory']}/{cell['arm']}/{grams:g}g"
        np.testing.assert_allclose(plan.payload_kg, [cell["payload_kg"]])
        np.testing.assert_allclose(plan.payload_t, [0.0])
        np.testing.assert_allclose(plan.pressure_pa, cell["pressure_pa"])
        assert plan.valve_open.all()
        payload_events = [e for _, e in plan.events if e.kind == EventKind.PAYLOAD]
        assert len(payload_events) == 1 and payload_events[0].value == pytest.approx(cell["payload_kg"])
        if plan.robot == "vsl_rigid":
            assert cell["arm"] == "vsl_rigid" and cell["pressure_pa"] == 0.0
        else:
            bar = cell["pressure_pa"] / BAR
            assert bar in (0.5, 2.0) and cell["arm"] == f"vsl-{bar:g}bar"
    cells = {(p.parameters["trajectory"], p.parameters["arm"], p.parameters["payload_kg"]) for p in e1_plans}
    assert len(cells) == len(e1_plans)


def test_experiment1_follows_the_trajectory(vsl, rigid, e1_plans, e1_params):
    for plan in e1_plans:
        robot = rigid if plan.robot == "vsl_rigid" else vsl
        path = trajectories.experiment1(
            plan.parameters["trajectory"],
            experiments.arm_lengths(robot),
            speed=e1_params["speed_m_s"],
            n_per_segment=e1_params["points_per_segment"],
        )
        n = len(path)
        starts = [t for t, e in plan.events if e.kind == EventKind.REPETITION_START]
        for t_start in starts:
            k = int(np.searchsorted(plan.goal_t, t_start, side="left"))
            np.testing.assert_allclose(plan.goal_q[k : k + n], path.q)
            np.testing.assert_allclose(plan.goal_t[k : k + n] - t_start, path.t - path.t[0], atol=1e-9)
            np.testing.assert_allclose(plan.goal_speed[k : k + n], np.abs(path.qd))
            # then a slow return to the start point
            np.testing.assert_allclose(plan.goal_q[k + n], path.q[0])
            np.testing.assert_allclose(plan.goal_speed[k + n], e1_params["return_speed_rad_s"])
        np.testing.assert_allclose(plan.goal_q[0], path.q[0])  # the plan starts at the path's start
        assert len(plan.goal_t) == 1 + len(starts) * (n + 1)
        # before the first repetition: settle_s of settling
        assert starts[0] == pytest.approx(e1_params["settle_s"])


# ------------------------------------------------------------------------------ campaign
@pytest.fixture(scope="module")
def campaign_params():
    return experiments.load_experiment("campaign", points=200)


def test_campaign_deals_every_point_once(vsl, campaign_params):
    plans = experiments.campaign(vsl, campaign_params, benches=7, seed=3)
    assert len(plans) == 7
    assert sum(p.parameters["points"] for p in plans) == 200
    sizes = [p.parameters["points"] for p in plans]
    assert max(sizes) - min(sizes) <= 1
    indexes = []
    for plan in plans:
        settled = [(t, e) for t, e in plan.events if e.kind == EventKind.SETTLED]
        assert len(settled) == plan.parameters["points"]
        assert all(e.value == pytest.approx(campaign_params["hold_s"]) for _, e in settled)
        indexes += [e.index for _, e in settled]
        assert plan.parameters["experiment"] == "campaign" and plan.parameters["seed"] == 3
    assert indexes == list(range(200))


def test_campaign_point_timing_and_values(vsl, campaign_params):
    (plan,) = experiments.campaign(vsl, campaign_params, benches=1, seed=0)
    # each point: travel (the largest joint move at the move speed), settle, hold
    travel = np.abs(np.diff(plan.goal_q, axis=0, prepend=plan.goal_q[:1])).max(axis=1)
    p = campaign_params
    step = travel / p["move_speed_rad_s"] + p["settle_s"] + p["hold_s"]
    starts = np.concatenate([[0.0], np.cumsum(step)[:-1]])
    assert plan.duration_s == pytest.approx(step.sum())
    np.testing.assert_allclose(plan.goal_t, starts, atol=1e-9)
    np.testing.assert_allclose(plan.pressure_t, starts, atol=1e-9)
    np.testing.assert_allclose(plan.payload_t, starts, atol=1e-9)
    settled_t = np.array([t for t, e in plan.events if e.kind == EventKind.SETTLED])
    np.testing.assert_allclose(settled_t, starts + step - campaign_params["hold_s"], atol=1e-9)
    lo, hi = (v * BAR for v in campaign_params["pressure_bar"])
    assert np.all((plan.pressure_pa >= lo) & (plan.pressure_pa <= hi))
    assert np.all(plan.pressure_pa[:, 0] == plan.pressure_pa[:, 1])
    assert plan.pressure_pa.std() > 0.2 * (hi - lo) / np.sqrt(12)  # spread over the range, not constant
    allowed = np.array(campaign_params["payloads_g"], float) * GRAM
    assert np.all(np.isclose(plan.payload_kg[:, None], allowed[None]).any(axis=1))
    assert len(np.unique(plan.payload_kg)) == len(allowed)  # 200 draws hit all five masses
    assert np.all(np.isfinite(plan.goal_q))
    # the fastest drive at the move speed, the others slower so that every joint arrives at once (a drive no
    # slower than SLOWEST of the move speed, which arrives early by a step that small)
    speed = p["move_speed_rad_s"]
    np.testing.assert_allclose(plan.goal_speed.max(axis=1), speed)
    steps = np.abs(np.diff(plan.goal_q, axis=0, prepend=plan.goal_q[:1]))
    arrive = steps / plan.goal_speed
    together = steps >= experiments.SLOWEST * travel[:, None]
    expected = np.where(together, travel[:, None] / speed, 0.0)
    np.testing.assert_allclose(np.where(together, arrive, 0.0), expected)
    assert np.all(plan.goal_speed >= experiments.SLOWEST * speed - 1e-12)
    # the joint targets reach tip targets inside the workspace box (rigid FK)
    tips = kinematics.vsl_fk(plan.goal_q, experiments.arm_lengths(vsl))
    lo_box = np.array(campaign_params["workspace_mm"]["min"]) * 1e-3
    hi_box = np.array(campaign_params["workspace_mm"]["max"]) * 1e-3
    assert np.all((tips >= lo_box - 1e-6) & (tips <= hi_box + 1e-6))


def test_campaign_is_reproducible(vsl, campaign_params):
    a = experiments.campaign(vsl, campaign_params, benches=2, seed=11)
    b = experiments.campaign(vsl, campaign_params, benches=2, seed=11)
    c = experiments.campaign(vsl, campaign_params, benches=2, seed=12)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.goal_q, y.goal_q)
        np.testing.assert_array_equal(x.pressure_pa, y.pressure_pa)
        np.testing.assert_array_equal(x.payload_kg, y.payload_kg)
        assert x.events == y.events
    assert not np.allclose(a[0].goal_q, c[0].goal_q)
    assert not np.allclose(a[0].pressure_pa, c[0].pressure_pa)


def test_campaign_with_more_benches_than_points(vsl):
    params = experiments.load_experiment("campaign", points=3)
    plans = experiments.campaign(vsl, params, benches=5, seed=0)
    assert sum(p.parameters["points"] for p in plans) == 3
