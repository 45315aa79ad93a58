"""The campaign's points and its repeats (acquisition.plans.experiments): the visit orders of the floor's
repeat, and the default campaign's moves inside the safety box (on the plans; one short simulation)."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pandas as pd
import pytest

from acquisition.plans.experiments import expand_experiment, together, visit_order
from acquisition.plans.plan import Plan, PlanBuilder
from acquisition.recorder.sessions import SessionStore
from acquisition.safety import SafetyChecker, SafetyError
from acquisition.schemas.events import EventKind
from pipeline.lab import Lab
from twin.runner import session_id, simulate, simulate_experiment


def _settle_points(plan) -> list[int]:
    """The campaign points a plan visits, in its order (each SETTLED event's index)."""
    return [e.index for _, e in plan.events if e.kind == EventKind.SETTLED]


def _settle_times(plan) -> list[float]:
    return [t for t, e in plan.events if e.kind == EventKind.SETTLED]


def _campaign(order: str, seed: int = 3) -> list:
    overrides = {"points": 240, "visit_order": order}
    return expand_experiment("campaign", overrides, benches=4, seed=seed)[1]


def test_shuffled_repeat_visits_the_same_points_in_another_order_from_its_seed():
    """Each bench of the shuffled repeat visits the drawn bench's points, with the same commands, in another
    order, the same for the same seed (deterministic) and another for another seed; reversed stays
    backwards. The repeats' sessions are named apart."""
    drawn, shuffled, again, reverse = (_campaign(o) for o in ("drawn", "shuffled", "shuffled", "reversed"))
    for a, s, s2, r in zip(drawn, shuffled, again, reverse, strict=True):
        first, other = _settle_points(a), _settle_points(s)
        assert sorted(first) == sorted(other) and first != other
        assert other == _settle_points(s2)  # from its own seed: the same order again
        assert _settle_points(r) == first[::-1]
        assert s.name.startswith("campaign/shuffled/bench") and r.name.startswith("campaign/reversed/bench")
        assert a.name.startswith("campaign/bench")
        # the same command at each point: goal joints, pressure and payload where it settles
        ta, ts = (p.at(np.array(_settle_times(p))) for p in (a, s))
        order = np.argsort(first), np.argsort(other)
        for key in ("goal_q", "pressure_pa", "payload_kg"):
            np.testing.assert_array_equal(ta[key][order[0]], ts[key][order[1]])
    other_seed = _campaign("shuffled", seed=4)
    assert [_settle_points(p) for p in other_seed] != [_settle_points(p) for p in _campaign("drawn", seed=4)]


def test_visit_order_never_returns_the_drawn_order():
    """Two points have one other order: a shuffle that drew the drawn order again draws once more."""
    for seed in range(20):
        assert visit_order(np.array([5, 9]), "shuffled", seed, 0).tolist() == [9, 5]
    points = np.arange(10)
    assert visit_order(points, "shuffled", 1, 2).tolist() == visit_order(points, "shuffled", 1, 2).tolist()
    assert visit_order(points, "shuffled", 1, 2).tolist() != visit_order(points, "shuffled", 1, 3).tolist()


# ------------------------------------------------------------------ the default campaign inside the box
def _default_campaign():
    """The documented `vslab simulate campaign` (docs/how-to/record.md): the defaults on 128 benches."""
    robots, plans, _ = expand_experiment("campaign", benches=128)
    return robots["vsl"], plans


@pytest.mark.slow
def test_default_campaign_stays_inside_the_box_under_predicted_sag():
    """Every plan of the default campaign passes the safety check: the tip, sagging under payload and
    pressure as the twin's statics predict, stays inside the box at every point and on every move."""
    robot, plans = _default_campaign()
    checker = SafetyChecker(robot)
    assert [v for p in plans for v in checker.check_plan(p)] == []


def _drives_in_turn(plan: Plan) -> Plan:
    """``plan`` with every drive at the move speed (each joint arriving at its own time), as the campaign
    was drawn before its moves were synchronised."""
    return dataclasses.replace(plan, goal_speed=np.where(plan.goal_speed > 0, 1.0, plan.goal_speed))


@pytest.mark.slow
def test_a_plan_whose_move_leaves_the_box_is_refused_naming_the_point():
    """With its drives arriving one by one, a default campaign bench passes through a corner below the box
    (z ≈ −52 mm predicted; the twin went to −51 to −58 mm): refused before it runs, the violation's line
    naming the point it was going to."""
    robot, plans = _default_campaign()
    checker = SafetyChecker(robot)
    refused = [(p, checker.check_plan(_drives_in_turn(p))) for p in plans]
    refused = [(p, v) for p, v in refused if v]
    assert refused, "no bench of the default campaign dips out of the box with its drives in turn"
    plan, violations = refused[0]
    assert violations[0].limit == "workspace"
    point = int(re.search(r"point (\d+)\)", str(violations[0])).group(1))
    assert point in _settle_points(plan)
    with pytest.raises(SafetyError, match=rf"workspace: tip at .* \(on the way to or at point {point}\)"):
        checker.require_safe(_drives_in_turn(plan))


@pytest.mark.slow
def test_the_worst_move_of_the_default_campaign_completes_on_the_twin(tmp_path):
    """The move that dipped out of the box (drives in turn) runs to the end on the twin with the campaign's
    synchronised drives: no safety stop, the tip's lowest point inside the box."""
    robot, plans = _default_campaign()
    checker = SafetyChecker(robot)
    plan, violations = next((p, v) for p in plans if (v := checker.check_plan(_drives_in_turn(p))))
    point = int(re.search(r"point (\d+)\)", str(violations[0])).group(1))
    points = _settle_points(plan)
    k = points.index(point)
    at = plan.at(np.array(_settle_times(plan)))
    b = PlanBuilder("campaign/worst", robot.name, len(robot.actuated_joints), robot.pneumatics.channels,
                    {"experiment": "campaign"})  # fmt: skip
    for i in (k - 1, k):  # the point before, settled, then the move that dipped
        previous = at["goal_q"][max(i - 1, 0)] if i == k else at["goal_q"][i]
        b.pressure(at["pressure_pa"][i]).payload(at["payload_kg"][i])
        b.goto(at["goal_q"][i], together(at["goal_q"][i] - previous, 1.0))
        b.wait(float(np.abs(at["goal_q"][i] - previous).max())).settle(1.0, index=points[i], hold_s=0.5)
    worst = b.build()
    assert checker.check_plan(worst) == [] and checker.check_plan(_drives_in_turn(worst)) != []
    report = simulate([worst], robot, tmp_path / "sessions", seed=0)
    assert report.stopped == {} and report.sessions == [session_id(worst)]


def test_the_report_says_what_the_inverse_models_read(tmp_path):
    """The report's comparison section says the inverse models' currents are measured after the move has
    landed (a payload sensor), from the comparison's card."""
    from analysis.lab_figures import Results, _unmodelled
    from analysis.lab_report import lab_report
    from pipeline.comparison import UNMODELLED, save_comparison

    table = pd.DataFrame([{"direction": d, "model": m, "cell": "all", "n": 10, "tip_mm_mean": 0.5}
                          for d in ("forward", "inverse") for m in ("gbr", "floor")])  # fmt: skip
    save_comparison(
        Lab(tmp_path).comparisons.path(UNMODELLED), table, {"campaign (drawn)": "v1"}, "split_group"
    )
    res = Results()
    _unmodelled(Lab(tmp_path), res)
    page = lab_report(Lab(tmp_path), res).read_text()
    assert "The inverse models read the tip wanted" in page and "measured after the move has landed" in page


@pytest.mark.slow
def test_the_default_campaign_completes_on_the_twin(tmp_path):
    """The documented `vslab simulate campaign` in full (17,568 points on 128 benches; minutes): no bench
    stops early."""
    reports = simulate_experiment("campaign", SessionStore(tmp_path / "sessions"), seed=0, benches=128)
    assert [r.stopped for r in reports] == [{}] and sum(len(r.sessions) for r in reports) == 128
