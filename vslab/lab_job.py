"""The main job: the whole lab on the twin, end to end (`make demo` / `vslab demo`).

1. a short real-time session through the rig (the twin behind its devices' emulators, recorded live);
2. the POPUP link tests, the campaign and Experiment 1 simulated (the batched twin, in simulated time; two
   experiments at a time), and the campaign's dataset and Experiment 1's (borrowing the campaign's
   registration) built of the simulated sessions (``pipeline.simulated.simulated_datasets``): the rig's
   single real-time repetition is reported on its own, not pooled with the five simulated ones of its
   cell, whose spread Fig. 5 shows;
3. `vslab train`: the forward and inverse networks of the grid (existing versions skipped);
4. Experiment 2 with the model-based, grey-box and hybrid (trained inverse) commands, and its dataset;
5. the twin with its unmodelled effects (``vsl_unmodelled``): a campaign and its repeat in a lab of their own
   (``lab.study("unmodelled")``), every model beside the floor on them (the networks registered there, their
   cards carrying the table), Experiment 1 on that twin (the paths the history-aware hybrid learns from) and
   Experiment 2 on it (the lab's comparison ``unmodelled``): ``pipeline.unmodelled``;
6. the figures and the report.
Every step reuses what an earlier run left (complete sessions, cached stages, existing versions), so a second
run is quick. Each step is timed; the report page says where everything came from.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

from pipeline.comparison import UNMODELLED
from pipeline.lab import Lab
from pipeline.model_store import INVERSE
from pipeline.unmodelled import STUDY, STUDY_LAB, STUDY_QUICK
from vslab.app import CommandLineError

# --quick: a smaller lab, its networks trained as long as the study's quick ones (the paper's network ran
# 148 epochs, 34 s, of the quick job's 42 s of training; a quick lab's figures need them made, not converged)
QUICK = {"campaign": {"points": 4000}, "experiment1": {"repetitions": 3}, "train": STUDY_QUICK["train"]}
LAB_GRID = Path(__file__).resolve().parents[1] / "configs" / "train" / "lab.yaml"  # the networks it trains
SIMULATIONS = "the POPUP tests, the campaign and Experiment 1 simulated"  # side by side: one step


def run(lab: Lab, seed: int = 0, quick: bool = False, say: Callable[[str], None] = print,
        batch_priority: bool = False) -> Path:  # fmt: skip
    """Run every step into ``lab``; returns the report's path. ``batch_priority``: this process runs the
    steps after the real-time session at a batch priority (the CLI's choice; a caller that goes on with other
    work, a test run, keeps its own)."""
    from analysis.lab_figures import FIGURE_INPUTS, all_figures, figure_inputs
    from analysis.lab_report import lab_report
    from analysis.vsl_paths import path_errors
    from pipeline.grid import load_grid, run_grid
    from pipeline.in_loop import learned_compensators
    from pipeline.simulated import TwinExperiment, simulated_datasets
    from pipeline.unmodelled import unmodelled_study

    timings: dict[str, float] = {}
    under_way: list[tuple[str, float]] = []  # the step being timed, when it started

    def step(name: str | None) -> None:  # the step under way ends (its time said and kept); ``name`` starts
        if under_way:
            what, start = under_way.pop()
            timings[what] = time.perf_counter() - start
            say(f"  {what}: {timings[what]:.1f} s")
        if name is not None:
            say(f"▶ {name}")
            under_way.append((name, time.perf_counter()))

    step("real-time session on the rig")
    _rig_session(lab)
    step(None)
    if batch_priority:  # the rest is batch work, lowered after the rig session (it cannot be raised back)
        from acquisition.processes import lower_priority

        lower_priority()

    def sized(what: str) -> dict:  # an experiment's overrides, or the training's
        return QUICK.get(what, {}) if quick else {}

    # simulated two at a time, the longest first (complete sessions are kept), then the datasets built (each
    # a step): the campaign, and Experiment 1 of its simulated sessions only (the rig's repetition is
    # reported on its own), borrowing the campaign's registration; the POPUP tests' sessions are read as
    # they are
    built = {"campaign": "campaign", "experiment1": "Experiment 1"}  # dataset → its step
    simulated = (*built, "popup_static", "popup_impact", "popup_deploy")
    campaign, *_ = simulated_datasets(lab, [
        TwinExperiment(e, sized(e), dataset=e if e in built else None,
                       registration_from="campaign" if e == "experiment1" else None)
        for e in simulated], seed=seed, phase=lambda what: step(built.get(what, SIMULATIONS)))  # fmt: skip
    registration = f"campaign@{campaign.version}"  # Experiment 2 borrows it too

    step("training")  # the grid's forward and inverse networks on the campaign (existing versions skipped)
    grid = load_grid(LAB_GRID, {"datasets": [registration], **sized("train")})
    run_grid(lab, grid)  # its networks tagged: the figures and Experiment 2 find them by LAB_TAGS

    step("Experiment 2 with the trained inverse model")
    model, identity = lab.models.inverse_onnx(INVERSE)  # the tagged network, recorded by its full version id
    learned = learned_compensators({"hybrid": model}, identities={"hybrid": identity})
    simulated_datasets(lab, [TwinExperiment("experiment2", dataset="experiment2", inverse_model=learned,
                                            registration_from=registration)], seed=seed)  # fmt: skip

    step("unmodelled effects: every model beside the floor")
    unmodelled_study(lab.study(STUDY_LAB), lab.comparisons.path(UNMODELLED), seed,
                     **(STUDY_QUICK if quick else STUDY), score=path_errors)  # fmt: skip

    step("figures and report")
    inputs, stamp = figure_inputs(lab), lab.report / FIGURE_INPUTS
    if inputs is not None and stamp.exists() and json.loads(stamp.read_text()) == inputs:
        say("  nothing they read has changed since they were made: the figures and the report stay")
        step(None)
        return lab.report / "index.html"
    results = all_figures(lab)
    step(None)
    report = lab_report(lab, results, timings)
    (lab.report / "timings.json").write_text(json.dumps(timings, indent=1))
    if inputs is not None:
        stamp.write_text(json.dumps(inputs))
    for what, why in results.missing.items():
        say(f"  not made: {what}: {why}")
    return report


class MainJobError(CommandLineError):
    """A step of the main job did not do its work (the rig session stopped early)."""


def _rig_session(lab: Lab) -> None:
    """One Experiment 1 curve run in real time on the rig, recorded into ``lab`` (skipped when already
    recorded): the library calls behind `vslab run experiment1 --plan … --rig`, the whole plan or a
    MainJobError (a ``PlanRunError``, ``RigError``, ``SetupError`` or ``RecorderError`` where it cannot
    start)."""
    if any(lab.sessions.root.glob("rig-*/session.json")):
        return
    from acquisition.plans.plan_run import choose_plan, plan_session, ready_plan, record_plan
    from acquisition.recorder.recorder import Recorder
    from acquisition.recorder.setup import recording_failure
    from twin.rig_process import rig_controls, session_devices

    overrides = {"repetitions": 1, "rest_s": 0.5, "settle_s": 1.0}
    plan, desc = choose_plan("experiment1", "experiment1/curve/vsl-1bar/25g", overrides)
    compensator, session = ready_plan(plan, desc), "rig-experiment1-curve"
    with session_devices(desc, rig_dir=lab.rigs / session, plan=plan) as (port_map, rig_dir):
        rec = Recorder(
            desc, port_map, lab.sessions.root / session, session, **plan_session(plan, "experiment1")
        )
        report = record_plan(plan, rec, compensator, rig_controls(rig_dir))
    if failure := recording_failure(rec):
        raise MainJobError(f"the rig session {plan.name}: {failure}")
    if report.status != "complete":
        raise MainJobError(f"the rig session {plan.name} stopped ({report.status}) after "
                           f"{report.elapsed_s:.1f} s: {report.reason}")  # fmt: skip
