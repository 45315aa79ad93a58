"""Datasets of the twin's sessions: an experiment simulated into a lab, then built like any other.

The main job and the unmodelled-effects study make every dataset of theirs this way; a lab's own sessions go
through ``vslab build`` (``pipeline.build``) alone.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from acquisition.recorder.sessions import SessionStore
    from pipeline.build import BuildReport
    from pipeline.lab import Lab


def simulated_dataset(
    lab: Lab,
    experiment: str,
    *,
    seed: int = 0,
    overrides: dict | None = None,
    inverse_model: Callable | None = None,
    name: str | None = None,
    registration_from: str | None = None,
    sessions: SessionStore | None = None,
) -> BuildReport:
    """Simulate ``experiment`` (``configs/experiments/<name>.yaml`` + ``overrides``) on the twin into
    ``sessions`` (``lab.sessions`` unless named; sessions already complete there are kept) and build dataset
    ``name`` (the experiment's by default) in ``lab`` of exactly the sessions of those plans: none of
    another runner, another seed or other overrides that the store may also hold. ``registration_from``:
    ``name@version`` of the dataset whose tracker registration this one borrows (Experiments 1 and 2 have
    few or no static points of their own); ``inverse_model``: Experiment 2's learned commands
    (``twin.runner.simulate_experiment``)."""
    from pipeline.build import build
    from twin.runner import simulate_experiment

    store = sessions or lab.sessions
    reports = simulate_experiment(experiment, store, seed=seed, overrides=overrides,
                                  inverse_model=inverse_model)  # fmt: skip
    made = sorted({s for r in reports for s in (*r.sessions, *r.skipped)})
    parameters = {"registration": {"from_dataset": registration_from}} if registration_from else None
    return build([store.path(s) for s in made], lab, name or experiment, parameters)
