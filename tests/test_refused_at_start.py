"""A simulated plan refused at t = 0 (finding 11 of the issue "Nothing silently stale, nothing hung, nothing
torn"): its session held no COMMAND_REFUSED / SAFETY_STOP event, said ``complete``, and a rerun skipped it."""

from __future__ import annotations

import numpy as np

from acquisition.plans.experiments import expand_experiment
from acquisition.recorder.sessions import read_card
from acquisition.schemas.events import EventKind
from acquisition.schemas.fast_read import read_events
from acquisition.schemas.session_card import STATUSES
from twin.runner import session_id, simulate


def past_the_limits(q_ik, pressure_pa, current_a, t_s=0.0):
    """A compensator that commands every joint 10 rad past its goal: the command guard refuses it."""
    return np.asarray(q_ik, float) + 10.0


def test_a_plan_refused_at_its_start_leaves_its_events_and_a_refused_status(tmp_path):
    robots, plans, _ = expand_experiment("campaign", {"points": 2})
    robot = robots["vsl"]
    for attempt in range(2):  # a rerun runs it again: a refused session is not complete
        report = simulate(plans, robot, tmp_path, compensators=[past_the_limits])
        assert report.sessions == [session_id(plans[0])] and not report.skipped, attempt
        assert session_id(plans[0]) in report.stopped
        directory = tmp_path / session_id(plans[0])
        card = read_card(directory)
        assert card["status"] == "refused" and card["status"] in STATUSES
        kinds = [e.kind for part in sorted(directory.glob("*.mcap")) for _, e in read_events(part)]
        assert EventKind.COMMAND_REFUSED in kinds and EventKind.SAFETY_STOP in kinds, kinds
