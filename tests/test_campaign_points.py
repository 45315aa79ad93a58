"""The campaign's points and its repeats (acquisition.plans.experiments): the visit orders of the floor's
repeat, checked on the plans themselves (no simulation)."""

from __future__ import annotations

import numpy as np

from acquisition.plans.experiments import expand_experiment, visit_order
from acquisition.schemas.events import EventKind


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
