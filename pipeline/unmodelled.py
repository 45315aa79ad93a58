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

from pipeline.simulated import TwinExperiment, simulated_dataset, simulated_datasets

if TYPE_CHECKING:
    from acquisition.recorder.sessions import SessionStore
    from pipeline.lab import Lab, LabPath

log = logging.getLogger(__name__)

UNMODELLED_ROBOT = "vsl_unmodelled"  # the twin with its unmodelled effects (issue 19)
STUDY_LAB = "unmodelled"  # the lab inside the main job's where the study works: lab.study(STUDY_LAB)
# the campaign on that twin and its repeat; --quick: fewer points, shorter training and Experiment 1 on the
# same twin (the paths the history-aware hybrid learns from)
STUDY = {"points": 3000, "train": {}, "paths": {"repetitions": 2}}
STUDY_QUICK = {"points": 600, "train": {"max_epochs": 30},
               "paths": {"repetitions": 1, "payloads_g": [25, 75], "pressures_bar": [0.5, 1.5]}}  # fmt: skip
Score = Callable[[pd.DataFrame], pd.DataFrame]  # Experiment 2's rows → path errors per session


def unmodelled_study(study: Lab, comparison: LabPath, seed: int, points: int, train: dict, paths: dict,
                     score: Score) -> None:  # fmt: skip
    """The campaign on the twin with its unmodelled effects on and the same campaign again from other
    histories (each bench shuffled), built in ``study`` (the main job's ``lab.study(STUDY_LAB)``)'s ``drawn``
    and ``shuffled``; the comparison of every model with the floor on them (grouped split), with Experiment 2
    on that twin, is written to ``comparison`` (the main job's ``lab.comparisons.path(UNMODELLED)``) unless
    it was made from these datasets already."""
    from acquisition.plans.experiments import arm_lengths
    from models.robot import load_robot
    from pipeline.comparison import compare_models, load_comparison, save_compared

    versions = {"training": json.dumps(train, sort_keys=True), "paths": json.dumps(paths, sort_keys=True)}
    experiments = study_experiments(study, points, paths)
    drawn = experiments[0].lab  # the networks compared are saved there, their cards carrying the table
    *built, experiment1 = simulated_datasets(study, experiments, seed=seed)  # two at a time
    data = {}
    for order, experiment, report in zip(ORDERS, experiments, built, strict=False):
        versions[f"campaign ({order})"] = report.version
        data[order] = experiment.lab.datasets.load("campaign", report.version)[0]
    if comparison.exists() and load_comparison(comparison)[1]["made_from"] == versions:
        return
    lengths = arm_lengths(load_robot(UNMODELLED_ROBOT))
    nets = {}
    table = compare_models(data["drawn"], lengths, data["shuffled"], train=train, seed=seed, nets=nets)
    rows = path_rows(drawn, experiment1.version)
    errors = _experiment2(drawn, study.study("experiment2").sessions, seed, data["drawn"],
                          versions["campaign (drawn)"], rows, train, paths, score)  # fmt: skip
    campaign = {"name": "campaign", "version": versions["campaign (drawn)"]}
    save_compared(comparison, drawn.models, data["drawn"], campaign, table, nets, versions, "split_group",
                  {"experiment2": errors.to_dict("records")})  # fmt: skip


def _experiment2(drawn: Lab, sessions: SessionStore, seed: int, campaign: pd.DataFrame,
                 campaign_version: str, history_rows: pd.DataFrame, train: dict, paths: dict,
                 score: Score) -> pd.DataFrame:  # fmt: skip
    """Experiment 2 on the twin with its unmodelled effects: model-based IK, the grey box's static
    compensation, the hybrid (a small residual inverse net trained on that twin's campaign) and the
    history-aware hybrid (``pipeline.history.HistoryModel`` over ``PATHS``, trained on ``history_rows``: the
    rows of :func:`path_rows`, Experiment 1 with the study's ``paths``) on the paper's two cases, two
    repetitions, into ``sessions`` (built in ``drawn``); the path errors per session (``score``)."""
    from models.hybrid import preset
    from pipeline.history import PATHS, HistoryModel
    from pipeline.train import TrainConfig
    from pipeline.train import train as train_net

    history = HistoryModel("inverse", PATHS, random_state=seed).fit(history_rows)
    config = TrainConfig(preset("inverse", "small-residual"), seed=seed, **train)
    models = {"hybrid": train_net(campaign, config).model, "history": history}
    made = f"campaign@{campaign_version}, seed {seed}"  # the models are a function of these (and the code)
    identities = {"hybrid": f"small-residual inverse net of {train} on {made}",
                  "history": f"history-aware hybrid on the paths of {paths}, {made}"}  # fmt: skip
    commands = ["ik", "static", "hybrid", "history"]
    rows = experiment2_rows(
        drawn, sessions, "experiment2", seed, campaign_version, commands, models, identities
    )
    return score(rows)


def path_rows(drawn: Lab, version: str) -> pd.DataFrame:
    """What a history-aware inverse model of the twin with its unmodelled effects learns from: Experiment 1
    run on that twin (:func:`study_experiments`), built in ``drawn`` (the study's ``study("drawn")``) as
    ``experiment1@version``, every cell but the ones Experiment 2 follows, with the ``PATHS`` history of
    every frame, at each set-point's end (``pipeline.history.set_point_ends``)."""
    from acquisition.plans.experiments import expand_experiment
    from pipeline.history import PATHS, set_point_ends, with_history

    _, plans, _ = expand_experiment("experiment2", {"robot": UNMODELLED_ROBOT, "rigid_arm": False})
    followed = {"experiment1/" + p.name.removeprefix("experiment2/").rsplit("/", 1)[0] for p in plans}
    rows = drawn.datasets.load("experiment1", version)[0]
    rows = rows[~rows["plan"].isin(followed)]  # not the cells Experiment 2 is scored on
    return set_point_ends(with_history(rows, PATHS))


ORDERS = ("drawn", "shuffled")  # not reversed: creep would make a point's two visits anti-correlated


def study_experiments(study: Lab, points: int, paths: dict) -> list[TwinExperiment]:
    """What the study simulates first: the campaign of ``points`` on the twin with its unmodelled effects,
    each bench in its drawn order and shuffled (``ORDERS``), each in its own lab of ``study`` (the repeat
    from other histories), and Experiment 1 on that twin (``paths``: the study's overrides) simulated into
    ``study.study("experiment1")`` and built in ``study.study("drawn")``, the tracker registered as the
    campaign there: the paths the history-aware hybrid learns from (:func:`path_rows`)."""
    campaigns = [
        TwinExperiment("campaign", {"points": points, "robot": UNMODELLED_ROBOT, "visit_order": order},
                       dataset="campaign", lab=study.study(order))
        for order in ORDERS
    ]  # fmt: skip
    overrides = paths | {"robot": UNMODELLED_ROBOT, "rigid_arm": False}
    return [*campaigns, TwinExperiment("experiment1", overrides, dataset="experiment1", lab=campaigns[0].lab,
                                       sessions=study.study("experiment1").sessions,
                                       registration_from="campaign")]  # fmt: skip


def experiment2_rows(drawn: Lab, sessions: SessionStore, name: str, seed: int, campaign_version: str,
                     commands: list[str], models: dict,
                     identities: dict | None = None) -> pd.DataFrame:  # fmt: skip
    """Experiment 2 on the twin with its unmodelled effects with ``commands``, two repetitions per case,
    into ``sessions``, built in ``drawn`` (the study's ``study("drawn")``) as ``name``; ``models``: the
    inverse model of each learned command ("hybrid", "history"); the dataset's rows
    (``analysis.vsl_paths.path_errors`` scores them)."""
    from models.robot import load_robot
    from pipeline.in_loop import learned_compensators

    compensator = learned_compensators(models, load_robot(UNMODELLED_ROBOT), identities)
    overrides = {"robot": UNMODELLED_ROBOT, "rigid_arm": False, "commands": commands, "repetitions": 2}
    report = simulated_dataset(drawn, TwinExperiment(
        "experiment2", overrides, dataset=name, inverse_model=compensator, sessions=sessions,
        registration_from=f"campaign@{campaign_version}"), seed=seed)  # fmt: skip
    return drawn.datasets.load(name, report.version)[0]
