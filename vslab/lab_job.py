"""The main job: the whole lab on the twin, end to end (`make demo` / `vslab demo`).

1. a short real-time session through the rig (the twin behind its devices' emulators, recorded live);
2. the simulated campaign, Experiment 1 and the POPUP link tests (the batched twin, in simulated time);
3. `vslab build`: the campaign dataset, then Experiment 1's (borrowing the campaign's registration) from the
   simulated sessions: the rig's single real-time repetition is reported on its own, not pooled with the
   five simulated ones of its cell, whose spread Fig. 5 shows;
4. `vslab train`: the forward and inverse networks of the grid (existing versions skipped);
5. Experiment 2 with the model-based, grey-box and hybrid (trained inverse) commands, and its dataset;
6. the twin with its unmodelled effects (``vsl_unmodelled``): a campaign and its repeat in a lab of their own
   (``<lab>/unmodelled``), every model beside the floor on them (the networks registered there, their cards
   carrying the table), Experiment 1 on that twin (the paths the history-aware hybrid learns from) and
   Experiment 2 on it (``<lab>/comparisons/unmodelled.json``);
7. the figures and the report.
Every step reuses what an earlier run left (complete sessions, cached stages, existing versions), so a second
run is quick. Each step is timed; the report page says where everything came from.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from pathlib import Path

from pipeline.registry import INVERSE
from vslab.app import CommandLineError

log = logging.getLogger(__name__)

UNMODELLED_ROBOT = "vsl_unmodelled"  # the twin with its unmodelled effects (issue 19)
QUICK = {"campaign": {"points": 4000}, "experiment1": {"repetitions": 3}}  # --quick: a smaller lab
# the campaign on the twin with its unmodelled effects and its repeat; --quick: fewer points, shorter training
# and Experiment 1 on the same twin (the paths the history-aware hybrid learns from)
STUDY = {"points": 3000, "train": {}, "paths": {"repetitions": 2}}
STUDY_QUICK = {"points": 600, "train": {"max_epochs": 30},
               "paths": {"repetitions": 1, "payloads_g": [25, 75], "pressures_bar": [0.5, 1.5]}}  # fmt: skip


def run(lab: Path, seed: int = 0, quick: bool = False, say: Callable[[str], None] = print,
        batch_priority: bool = False) -> Path:  # fmt: skip
    """Run every step into ``lab``; returns the report's path. ``batch_priority``: this process runs the
    steps after the real-time session at a batch priority (the CLI's choice; a caller that goes on with other
    work, a test run, keeps its own)."""
    from pipeline.build import build
    from twin.runner import simulate_experiment

    lab = Path(lab)
    timings: dict[str, float] = {}
    sessions = lab / "sessions"

    def step(name: str):
        say(f"▶ {name}")
        timings[name] = time.perf_counter()

    def done(name: str) -> None:
        timings[name] = time.perf_counter() - timings[name]
        say(f"  {name}: {timings[name]:.1f} s")

    step("real-time session on the rig")
    _rig_session(lab)
    done("real-time session on the rig")
    if batch_priority:  # the rest is batch work, lowered after the rig session (it cannot be raised back)
        from acquisition.processes import lower_priority

        lower_priority()

    step("simulated campaign, Experiment 1, POPUP tests")
    for experiment in ("campaign", "experiment1", "popup_static", "popup_impact", "popup_deploy"):
        overrides = QUICK.get(experiment, {}) if quick else {}
        simulate_experiment(experiment, sessions, seed=seed, overrides=overrides)
    done("simulated campaign, Experiment 1, POPUP tests")

    step("datasets")
    campaign = build(sessions_of(sessions, "campaign"), lab, "campaign")
    borrowed = {"register": {"from_dataset": f"campaign@{campaign.version}"}}
    build(sessions_of(sessions, "experiment1", runner="simulated"), lab, "experiment1", borrowed)
    done("datasets")

    step("training")
    models = _train(lab, campaign.version)
    done("training")

    step("Experiment 2 with the trained inverse model")
    _experiment2(lab, sessions, models[INVERSE], seed, borrowed)
    done("Experiment 2 with the trained inverse model")

    step("unmodelled effects: every model beside the floor")
    _unmodelled(lab, seed, **(STUDY_QUICK if quick else STUDY))
    done("unmodelled effects: every model beside the floor")

    step("figures and report")
    from analysis.lab_figures import all_figures, lab_report

    results = all_figures(lab)
    done("figures and report")
    report = lab_report(lab, results, timings)
    (lab / "report" / "timings.json").write_text(json.dumps(timings, indent=1))
    for what, why in results.missing.items():
        say(f"  not made: {what}: {why}")
    return report


def sessions_of(sessions: Path, experiment: str, runner: str | None = None) -> list[Path]:
    """The session directories of one experiment, of one runner ("simulated", "real-time") if given; a
    damaged folder is named in the log and never joins a dataset."""
    from pipeline.session_index import experiment_sessions

    selected, bad = experiment_sessions(sessions, experiment, runner)
    for why in bad.values():
        log.warning("skipped %s", why)
    return selected


class MainJobError(CommandLineError):
    """A step of the main job did not do its work (the rig session stopped early)."""


def _rig_session(lab: Path) -> None:
    """One Experiment 1 curve run in real time on the rig, recorded (skipped when already recorded): the
    library calls behind `vslab run experiment1 --plan … --rig`, the whole plan or a MainJobError (a
    ``PlanRunError``, ``RigError`` or ``SetupError`` where it cannot start)."""
    if any((lab / "sessions").glob("rig-*/session.json")):
        return
    from acquisition.plans.plan_run import choose_plan, ready_plan, record_plan
    from acquisition.recorder.setup import recording_failure
    from twin.rig_process import rig_controls, session_devices

    overrides = {"repetitions": 1, "rest_s": 0.5, "settle_s": 1.0}
    plan, desc = choose_plan("experiment1", "experiment1/curve/vsl-1bar/25g", overrides)
    compensator, session = ready_plan(plan, desc), "rig-experiment1-curve"
    with session_devices(desc, rig_dir=lab / "rig" / session, plan=plan) as (port_map, rig_dir):
        report, rec = record_plan(plan, desc, port_map, lab / "sessions", session, compensator,
                                  rig_controls(rig_dir), "experiment1")  # fmt: skip
    if failure := recording_failure(rec):
        raise MainJobError(f"the rig session {plan.name}: {failure}")
    if report.status != "complete":
        raise MainJobError(f"the rig session {plan.name} stopped ({report.status}) after "
                           f"{report.elapsed_s:.1f} s: {report.reason}")  # fmt: skip


def _train(lab: Path, dataset_version: str) -> dict[str, str]:
    """The grid's forward and inverse networks on the campaign; returns the versions the figures use."""
    from pipeline import registry
    from pipeline.grid import load_grid, run_grid

    grid = load_grid(
        Path(__file__).resolve().parents[1] / "configs" / "train" / "lab.yaml",
        {"datasets": [f"campaign@{dataset_version}"]},
    )
    results = run_grid(lab, grid)
    by_name = {r["name"]: r["version"] for r in results}
    for name, model in registry.LAB_TAGS.items():  # the figures and Experiment 2 find them by these tags
        registry.tag(lab / "models", name, by_name[model])
    return {name: by_name[model] for name, model in registry.LAB_TAGS.items()}


def _experiment2(lab: Path, sessions: Path, inverse_version: str, seed: int, borrowed: dict):
    from pipeline.build import build
    from twin.runner import simulate_experiment
    from vslab.app import inverse_compensators

    learned = inverse_compensators(inverse_version, lab)
    simulate_experiment("experiment2", sessions, seed=seed, inverse_model=learned)
    return build(sessions_of(sessions, "experiment2"), lab, "experiment2", borrowed)


def _unmodelled(lab: Path, seed: int, points: int, train: dict, paths: dict) -> None:
    """Issue 19: the campaign on the twin with its unmodelled effects on and the same campaign again from
    other histories (each bench shuffled), built in ``<lab>/unmodelled/{drawn,shuffled}``; the comparison
    of every model with the floor on them (grouped split) is written unless one of these datasets has it."""
    from acquisition.plans.experiments import arm_lengths
    from models.robot import load_robot
    from pipeline.build import build
    from pipeline.comparison import (
        UNMODELLED,
        compare_models,
        load_comparison,
        register_compared,
        save_comparison,
    )
    from pipeline.datasets import load_dataset
    from twin.runner import simulate_experiment

    robot = UNMODELLED_ROBOT
    versions = {"training": json.dumps(train, sort_keys=True), "paths": json.dumps(paths, sort_keys=True)}
    data = {}
    for order in ("drawn", "shuffled"):  # not reversed: creep would make a point's two visits anti-correlated
        study = lab / "unmodelled" / order
        overrides = {"points": points, "robot": robot, "visit_order": order}
        simulate_experiment("campaign", study / "sessions", seed=seed, overrides=overrides)
        report = build(sessions_of(study / "sessions", "campaign"), study, "campaign")
        versions[f"campaign ({order})"] = report.version
        data[order] = load_dataset(study / "datasets", "campaign", report.version)[0]
    path = lab / UNMODELLED
    if path.exists() and load_comparison(path)[1]["sources"] == versions:
        return
    lengths = arm_lengths(load_robot(robot))
    nets = {}
    table = compare_models(data["drawn"], lengths, data["shuffled"], train=train, seed=seed, nets=nets)
    campaign = {"name": "campaign", "version": versions["campaign (drawn)"]}
    registry = lab / "unmodelled" / "drawn" / "models"  # their cards carry the table beside the floor
    registered = register_compared(registry, data["drawn"], campaign, table, nets, versions)
    errors = _unmodelled_experiment2(
        lab / "unmodelled", seed, data["drawn"], versions["campaign (drawn)"], train, paths
    )
    models = [{"name": p.parent.name, "version": p.name} for p in registered]
    save_comparison(
        path, table, versions, "split_group", {"experiment2": errors.to_dict("records"), "models": models}
    )


def _unmodelled_experiment2(study: Path, seed: int, campaign, campaign_version: str, train: dict,
                            paths: dict):  # fmt: skip
    """Experiment 2 on the twin with its unmodelled effects: model-based IK, the grey box's static
    compensation, the hybrid (a small residual inverse net trained on that twin's campaign) and the
    history-aware hybrid (``pipeline.history.HistoryModel`` over ``PATHS``, trained on :func:`path_rows`)
    on the paper's two cases, two repetitions; the path errors per session (``analysis.vsl_paths``)."""
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
    return experiment2_path_errors(study, "experiment2", seed, campaign_version, commands, models, identities)


def path_rows(study: Path, seed: int, campaign_version: str, paths: dict):
    """What a history-aware inverse model of the twin with its unmodelled effects learns from: Experiment 1
    run on that twin (``paths``: its overrides) into ``<study>/experiment1``, built in ``<study>/drawn``
    (the tracker registered as the campaign ``campaign_version`` there), every cell but the ones Experiment
    2 follows, with the ``PATHS`` history of every frame, at each set-point's end
    (``pipeline.history.set_point_ends``)."""
    from acquisition.plans.experiments import expand_experiment
    from pipeline.build import build
    from pipeline.datasets import load_dataset
    from pipeline.history import PATHS, set_point_ends, with_history
    from twin.runner import simulate_experiment

    _, plans, _ = expand_experiment("experiment2", {"robot": UNMODELLED_ROBOT, "rigid_arm": False})
    followed = {"experiment1/" + p.name.removeprefix("experiment2/").rsplit("/", 1)[0] for p in plans}
    sessions = study / "experiment1" / "sessions"
    overrides = paths | {"robot": UNMODELLED_ROBOT, "rigid_arm": False}
    simulate_experiment("experiment1", sessions, seed=seed, overrides=overrides)
    borrowed = {"register": {"from_dataset": f"campaign@{campaign_version}"}}
    report = build(sessions_of(sessions, "experiment1"), study / "drawn", "experiment1", borrowed)
    rows = load_dataset(study / "drawn" / "datasets", "experiment1", report.version)[0]
    rows = rows[~rows["plan"].isin(followed)]  # not the cells Experiment 2 is scored on
    return set_point_ends(with_history(rows, PATHS))


def experiment2_path_errors(study: Path, name: str, seed: int, campaign_version: str, commands: list[str],
                            models: dict, identities: dict | None = None):  # fmt: skip
    """Experiment 2 on the twin with its unmodelled effects with ``commands``, two repetitions per case,
    into ``<study>/<name>`` (built in ``<study>/drawn``); ``models``: the inverse model of each learned
    command ("hybrid", "history"); the path errors per session (``analysis.vsl_paths.path_errors``)."""
    from analysis.vsl_paths import path_errors
    from models.robot import load_robot
    from pipeline.build import build
    from pipeline.datasets import load_dataset
    from pipeline.in_loop import learned_compensators
    from twin.runner import simulate_experiment

    # one per session: the history-aware one starts each with no history
    compensator = learned_compensators(models, load_robot(UNMODELLED_ROBOT), identities)
    overrides = {"robot": UNMODELLED_ROBOT, "rigid_arm": False, "commands": commands, "repetitions": 2}
    sessions = study / name / "sessions"
    simulate_experiment("experiment2", sessions, seed=seed, overrides=overrides, inverse_model=compensator)
    borrowed = {"register": {"from_dataset": f"campaign@{campaign_version}"}}
    report = build(sessions_of(sessions, "experiment2"), study / "drawn", name, borrowed)
    return path_errors(load_dataset(study / "drawn" / "datasets", name, report.version)[0])
