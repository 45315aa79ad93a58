"""The unmodelled-effects study (issue 19): the twin with its unmodelled effects (``vsl_unmodelled``), every
model beside the floor on it, and Experiment 2 on it with the learned commands.

It works in a lab of its own inside the main job's (``lab.study("unmodelled")``):
- ``drawn/``, ``shuffled/``: the campaign and its repeat from other histories (each bench shuffled), their
  sessions and datasets; the networks of the comparison saved in ``drawn/``'s models, their cards
  carrying the table beside the floor;
- ``experiment1/``: Experiment 1 on that twin (the paths the history-aware hybrid learns from);
- ``experiment2/``: Experiment 2 on it (both built in ``drawn/``, borrowing its campaign's registration).
The table and the path errors go to the main lab's comparison ``UNMODELLED``.

Scoring Experiment 2 (the distance to the desired path) is analysis: the caller gives it (``score``).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

import pandas as pd

from pipeline.simulated import simulated_dataset

if TYPE_CHECKING:
    from pipeline.lab import Lab

log = logging.getLogger(__name__)

UNMODELLED_ROBOT = "vsl_unmodelled"  # the twin with its unmodelled effects (issue 19)
STUDY_LAB = "unmodelled"  # the lab inside the main job's where the study works: lab.study(STUDY_LAB)
# the campaign on that twin and its repeat; --quick: fewer points, shorter training and Experiment 1 on the
# same twin (the paths the history-aware hybrid learns from)
STUDY = {"points": 3000, "train": {}, "paths": {"repetitions": 2}}
STUDY_QUICK = {"points": 600, "train": {"max_epochs": 30},
               "paths": {"repetitions": 1, "payloads_g": [25, 75], "pressures_bar": [0.5, 1.5]}}  # fmt: skip
Score = Callable[[pd.DataFrame], pd.DataFrame]  # Experiment 2's rows → path errors per session


def unmodelled_study(lab: Lab, seed: int, points: int, train: dict, paths: dict, score: Score) -> None:
    """The campaign on the twin with its unmodelled effects on and the same campaign again from other
    histories (each bench shuffled), built in ``lab.study("unmodelled")``'s ``drawn`` and ``shuffled``; the
    comparison of every model with the floor on them (grouped split) is written to ``lab``'s comparison
    ``UNMODELLED`` unless it was made from these datasets already."""
    from acquisition.plans.experiments import arm_lengths
    from models.robot import load_robot
    from pipeline.comparison import (
        UNMODELLED,
        compare_models,
        load_comparison,
        save_compared,
        save_comparison,
    )
    from twin.runner import Simulation, simulate_side_by_side

    robot = UNMODELLED_ROBOT
    study = lab.study(STUDY_LAB)
    versions = {"training": json.dumps(train, sort_keys=True), "paths": json.dumps(paths, sort_keys=True)}
    orders = ("drawn", "shuffled")  # not reversed: creep would make a point's two visits anti-correlated
    campaigns = {order: {"points": points, "robot": robot, "visit_order": order} for order in orders}
    simulate_side_by_side(  # both campaigns and the paths of Experiment 1 (path_rows), two at a time
        [Simulation("campaign", study.study(order).sessions, campaigns[order]) for order in orders]
        + [Simulation("experiment1", study.study("experiment1").sessions, _paths_overrides(paths))],
        seed=seed,
    )
    data = {}
    for order in orders:
        part = study.study(order)
        report = simulated_dataset(part, "campaign", seed=seed, overrides=campaigns[order])
        versions[f"campaign ({order})"] = report.version
        data[order] = part.datasets.load("campaign", report.version)[0]
    path = lab.comparisons.path(UNMODELLED)
    if path.exists() and load_comparison(path)[1]["made_from"] == versions:
        return
    lengths = arm_lengths(load_robot(robot))
    nets = {}
    table = compare_models(data["drawn"], lengths, data["shuffled"], train=train, seed=seed, nets=nets)
    campaign = {"name": "campaign", "version": versions["campaign (drawn)"]}
    models = study.study("drawn").models  # their cards carry the table beside the floor
    saved = save_compared(models, data["drawn"], campaign, table, nets, versions)
    errors = _experiment2(study, seed, data["drawn"], versions["campaign (drawn)"], train, paths, score)
    made = [{"name": p.parent.name, "version": p.name} for p in saved]
    save_comparison(path, table, versions, "split_group", {"experiment2": errors.to_dict("records"),
                                                           "models": made})  # fmt: skip


def _experiment2(study: Lab, seed: int, campaign: pd.DataFrame, campaign_version: str, train: dict,
                 paths: dict, score: Score) -> pd.DataFrame:  # fmt: skip
    """Experiment 2 on the twin with its unmodelled effects: model-based IK, the grey box's static
    compensation, the hybrid (a small residual inverse net trained on that twin's campaign) and the
    history-aware hybrid (``pipeline.history.HistoryModel`` over ``PATHS``, trained on :func:`path_rows`)
    on the paper's two cases, two repetitions; the path errors per session (``score``)."""
    from models.hybrid import preset
    from pipeline.history import PATHS, HistoryModel
    from pipeline.train import TrainConfig
    from pipeline.train import train as train_net

    rows = path_rows(study, seed, campaign_version, paths)
    history = HistoryModel("inverse", PATHS, random_state=seed).fit(rows)
    config = TrainConfig(preset("inverse", "small-residual"), seed=seed, **train)
    models = {"hybrid": train_net(campaign, config).model, "history": history}
    made = f"campaign@{campaign_version}, seed {seed}"  # the models are a function of these (and the code)
    identities = {"hybrid": f"small-residual inverse net of {train} on {made}",
                  "history": f"history-aware hybrid on the paths of {paths}, {made}"}  # fmt: skip
    commands = ["ik", "static", "hybrid", "history"]
    rows = experiment2_rows(study, "experiment2", seed, campaign_version, commands, models, identities)
    return score(rows)


def path_rows(study: Lab, seed: int, campaign_version: str, paths: dict) -> pd.DataFrame:
    """What a history-aware inverse model of the twin with its unmodelled effects learns from: Experiment 1
    run on that twin (``paths``: its overrides) into ``study.study("experiment1")``, built in
    ``study.study("drawn")`` (the tracker registered as the campaign ``campaign_version`` there), every cell
    but the ones Experiment 2 follows, with the ``PATHS`` history of every frame, at each set-point's end
    (``pipeline.history.set_point_ends``)."""
    from acquisition.plans.experiments import expand_experiment
    from pipeline.history import PATHS, set_point_ends, with_history

    _, plans, _ = expand_experiment("experiment2", {"robot": UNMODELLED_ROBOT, "rigid_arm": False})
    followed = {"experiment1/" + p.name.removeprefix("experiment2/").rsplit("/", 1)[0] for p in plans}
    sessions = study.study("experiment1").sessions
    drawn = study.study("drawn")
    overrides = _paths_overrides(paths)
    report = simulated_dataset(drawn, "experiment1", seed=seed, overrides=overrides, sessions=sessions,
                               registration_from=f"campaign@{campaign_version}")  # fmt: skip
    rows = drawn.datasets.load("experiment1", report.version)[0]
    rows = rows[~rows["plan"].isin(followed)]  # not the cells Experiment 2 is scored on
    return set_point_ends(with_history(rows, PATHS))


def _paths_overrides(paths: dict) -> dict:
    """Experiment 1's overrides for the paths the history-aware model learns from (``paths``: the study's)."""
    return paths | {"robot": UNMODELLED_ROBOT, "rigid_arm": False}


def experiment2_rows(study: Lab, name: str, seed: int, campaign_version: str, commands: list[str],
                     models: dict, identities: dict | None = None) -> pd.DataFrame:  # fmt: skip
    """Experiment 2 on the twin with its unmodelled effects with ``commands``, two repetitions per case,
    into ``study.study(name)`` (built in ``study.study("drawn")``); ``models``: the inverse model of each
    learned command ("hybrid", "history"); the dataset's rows (``analysis.vsl_paths.path_errors`` scores
    them)."""
    from models.robot import load_robot
    from pipeline.in_loop import learned_compensators

    compensator = learned_compensators(models, load_robot(UNMODELLED_ROBOT), identities)
    overrides = {"robot": UNMODELLED_ROBOT, "rigid_arm": False, "commands": commands, "repetitions": 2}
    sessions = study.study(name).sessions
    drawn = study.study("drawn")
    report = simulated_dataset(drawn, "experiment2", seed=seed, overrides=overrides, name=name,
                               inverse_model=compensator, sessions=sessions,
                               registration_from=f"campaign@{campaign_version}")  # fmt: skip
    return drawn.datasets.load(name, report.version)[0]
