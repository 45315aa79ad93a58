"""Datasets of the twin's sessions: experiments simulated into a lab, side by side, then built like any other.

The main job, the unmodelled-effects study and pretraining make every dataset of theirs this way; a lab's own
sessions go through ``vslab build`` (``pipeline.build``) alone.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from acquisition.recorder.sessions import SessionStore
    from pipeline.build import BuildReport
    from pipeline.lab import Lab


@dataclass(frozen=True)
class TwinExperiment:
    """One experiment for :func:`simulated_datasets`: ``configs/experiments/<experiment>.yaml`` with
    ``overrides`` (as ``vslab simulate --set`` takes them), simulated into ``sessions`` (the lab's unless
    named) and, where ``dataset`` names one, built as that dataset in ``lab`` (the call's unless named) of
    exactly the sessions of its plans: none of another runner, another seed or other overrides that the store
    may also hold. ``registration_from``: the dataset (``name`` or ``name@version``) whose tracker
    registration it borrows (Experiments 1 and 2 have few or no static points of their own); a dataset of that
    name built earlier by the same call, in the same lab, is taken at the version it built. ``inverse_model``:
    Experiment 2's learned commands (``twin.runner.simulate_experiment``); such an experiment is simulated in
    this process."""

    experiment: str
    overrides: dict | None = None
    dataset: str | None = None
    lab: Lab | None = None
    sessions: SessionStore | None = None
    registration_from: str | None = None
    inverse_model: Callable | None = None


def simulated_datasets(lab: Lab, experiments: list[TwinExperiment], *, seed: int = 0,
                       phase: Callable[[str], None] | None = None) -> list[BuildReport | None]:  # fmt: skip
    """Simulate ``experiments`` side by side (``twin.runner.simulate_side_by_side``: put the longest first;
    sessions already complete are kept), then build each that names a dataset, in the order given. Returns
    each experiment's build, in the order given (None for one that names no dataset). ``phase(what)``: called
    as the simulations start ("simulated") and as each build starts (its dataset's name)."""
    from pipeline.build import build
    from twin.runner import Simulation, simulate_side_by_side

    stores = [e.sessions or (e.lab or lab).sessions for e in experiments]
    if phase:
        phase("simulated")
    runs = [Simulation(e.experiment, store, e.overrides, e.inverse_model)
            for e, store in zip(experiments, stores, strict=True)]  # fmt: skip
    reports = simulate_side_by_side(runs, seed=seed)
    built: dict[tuple[str, str], BuildReport] = {}  # (lab, dataset) → its build
    made: list[BuildReport | None] = []
    for e, store, report in zip(experiments, stores, reports, strict=True):
        if e.dataset is None:
            made.append(None)
            continue
        if phase:
            phase(e.dataset)
        into = e.lab or lab
        source = e.registration_from
        if (into.root, source) in built:
            source = f"{source}@{built[into.root, source].version}"
        parameters = {"registration": {"from_dataset": source}} if source else None
        sessions = sorted({s for r in report for s in (*r.sessions, *r.skipped)})
        built[into.root, e.dataset] = build([store.path(s) for s in sessions], into, e.dataset, parameters)
        made.append(built[into.root, e.dataset])
    return made


def simulated_dataset(lab: Lab, experiment: TwinExperiment, *, seed: int = 0) -> BuildReport:
    """One experiment of :func:`simulated_datasets` simulated and built (it must name its dataset)."""
    if experiment.dataset is None:
        raise ValueError(f"simulated_dataset: {experiment.experiment} names no dataset to build")
    return simulated_datasets(lab, [experiment], seed=seed)[0]
