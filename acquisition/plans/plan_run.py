"""One plan of an experiment run in real time on devices while it is recorded: the library form of
`vslab run` (the main job's rig session calls it too).

Three steps, each refusing what it cannot do with a :class:`PlanRunError` before anything starts:
:func:`choose_plan` (the experiment expanded, one plan picked by name or number), :func:`ready_plan` (the
plan held to the robot's safety limits, its compensator chosen) and :func:`record_plan` (the session
recorded while the :class:`~acquisition.plans.rt_runner.RealTimeRunner` runs the plan on the recorder's
devices). Where the devices come from (ports, a rig), where the session goes (the caller makes the
:class:`Recorder`, with :func:`plan_session`'s words) and who hangs payloads is the caller's: the rig is
the twin's (``twin.rig_process``), a prompt is the command line's.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping
from contextlib import AbstractContextManager

from acquisition.errors import AcquisitionError
from acquisition.plans.compensation import CompensationError, Compensator, compensator_for
from acquisition.plans.plan import Plan
from acquisition.plans.rt_runner import RealTimeRunner, RunnerError, RunReport
from acquisition.recorder.recorder import Recorder
from acquisition.recorder.setup import recording
from acquisition.safety import SafetyChecker, SafetyError
from models.robot import RobotDescription

Action = Callable[[float], object] | None
Controls = tuple[Action, Action]  # (hang a payload of kg, tap the link with N·m·s)


class PlanRunError(AcquisitionError, ValueError):
    """A plan that cannot be run as asked (unknown plan, unsafe, no model for learned commands, a runner's
    stop on an error): nothing was started, or the session was stopped safely and kept."""


def choose_plan(
    experiment: str, plan: str = "0", overrides: dict | None = None
) -> tuple[Plan, RobotDescription]:
    """Plan ``plan`` (its name, or its number from 0) of ``experiment`` with ``overrides``, and the robot
    description it runs on (the experiment's variant of the robot, as its plans expect)."""
    from acquisition.plans.experiments import expand_experiment

    try:
        robots, plans, _ = expand_experiment(experiment, overrides)
    except (ValueError, OSError) as exc:  # ExperimentError, RobotDescriptionError, an unreachable path
        raise PlanRunError(str(exc)) from None
    chosen = [p for k, p in enumerate(plans) if plan in (p.name, str(k))]
    if not chosen:
        more = " …" if len(plans) > 10 else ""
        raise PlanRunError(f"{experiment} has no plan {plan!r}; its plans (or their numbers, from 0): "
                           + ", ".join(p.name for p in plans[:10]) + more)  # fmt: skip
    return chosen[0], robots[chosen[0].robot]


def ready_plan(
    plan: Plan,
    desc: RobotDescription,
    learned: Callable[[Plan], Compensator] | None = None,
    refused: Mapping[str, str] | None = None,
) -> Compensator | None:
    """``plan``'s compensator once the plan keeps to ``desc``'s safety limits, checked before any device is
    opened, a rig started or a session folder made. ``learned``: the learned compensators
    (``pipeline.in_loop.learned_compensators``); ``refused``: commands the caller cannot give, with why."""
    try:
        SafetyChecker(desc).require_safe(plan)
    except SafetyError as exc:
        first, _, details = str(exc).partition("\n")
        raise PlanRunError(f"{first.rstrip(':')}: refused, nothing was started:\n{details}") from None
    commands = plan.parameters.get("commands", "ik")
    if commands in (refused or {}):
        raise PlanRunError(refused[commands])
    try:
        return compensator_for(plan, desc, learned)
    except CompensationError as exc:
        raise PlanRunError(str(exc)) from None


def operator_prompts(ask: Callable[[str], object]) -> Controls:
    """(hang a payload, tap the link) done by an operator: ``ask`` shows what to do and returns once done
    (the plan's clock waits for it)."""
    return (lambda kg: ask(f"hang {kg * 1e3:g} g at the end-effector, then press Enter"),
            lambda nms: ask(f"tap the link (≈ {nms * 1e3:g} mN·m·s), then press Enter"))  # fmt: skip


def plan_session(plan: Plan, experiment: str = "") -> dict:
    """What the session of ``plan`` says of it: its :class:`Recorder`'s ``experiment`` (the plan's own,
    else ``experiment``) and ``metadata`` (the plan, its parameters, the real-time runner)."""
    metadata = {"plan": plan.name, "runner": "real-time", "parameters": plan.parameters}
    return {"experiment": plan.parameters.get("experiment", experiment), "metadata": metadata}


def record_plan(
    plan: Plan,
    rec: Recorder,
    compensator: Compensator | None = None,
    controls: Controls = (None, None),
    live: Callable[[], AbstractContextManager] | None = None,
) -> RunReport:
    """Run ``plan`` on ``rec``'s devices while ``rec`` records them (made with :func:`plan_session`'s
    words; the caller reports its account once stopped): the runner's report. ``live``: a started live view
    for the recorder to serve (a context); a runner's stop on an error is a :class:`PlanRunError`, the
    session stopped safely and kept."""
    with live() if live is not None else contextlib.nullcontext() as live_server:
        rec.live = live_server
        with recording(rec):
            try:
                return RealTimeRunner(rec, plan, compensator, *controls).run()
            except (SafetyError, RunnerError) as exc:
                raise PlanRunError(str(exc)) from None
