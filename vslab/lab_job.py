"""The main job: the whole lab on the twin, end to end (`make demo` / `vslab demo`).

1. a short real-time session through the rig (the twin behind its devices' emulators, recorded live);
2. the POPUP link tests, the campaign and Experiment 1 simulated (the batched twin, in simulated time; two
   experiments at a time, ``twin.runner.simulate_side_by_side``), and the campaign's dataset and
   Experiment 1's (borrowing the campaign's registration) built of the simulated sessions
   (``pipeline.simulated``): the rig's single real-time repetition is reported on its own, not pooled with
   the five simulated ones of its cell, whose spread Fig. 5 shows;
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

from pipeline.lab import Lab
from pipeline.model_store import INVERSE
from pipeline.unmodelled import STUDY, STUDY_QUICK
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
    from pipeline.in_loop import stored_compensators
    from pipeline.simulated import simulated_dataset
    from pipeline.unmodelled import unmodelled_study
    from twin.runner import Simulation, simulate_side_by_side

    timings: dict[str, float] = {}

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

    def sized(what: str) -> dict:  # an experiment's overrides, or the training's
        return QUICK.get(what, {}) if quick else {}

    step(SIMULATIONS)  # two at a time, the longest first (sessions already complete are kept)
    simulated = ("campaign", "experiment1", "popup_static", "popup_impact", "popup_deploy")
    simulate_side_by_side([Simulation(e, lab.sessions, sized(e)) for e in simulated], seed=seed)
    done(SIMULATIONS)

    step("campaign")
    campaign = simulated_dataset(lab, "campaign", seed=seed, overrides=sized("campaign"))
    registration = f"campaign@{campaign.version}"  # Experiments 1 and 2 borrow the campaign's
    done("campaign")

    step("Experiment 1")  # its simulated sessions only: the rig's repetition is reported on its own
    simulated_dataset(lab, "experiment1", seed=seed, overrides=sized("experiment1"),
                      registration_from=registration)  # fmt: skip
    done("Experiment 1")

    step("training")  # the grid's forward and inverse networks on the campaign (existing versions skipped)
    grid = load_grid(LAB_GRID, {"datasets": [registration], **sized("train")})
    run_grid(lab, grid)  # its networks tagged: the figures and Experiment 2 find them by LAB_TAGS
    done("training")

    step("Experiment 2 with the trained inverse model")
    learned = stored_compensators(lab.models, INVERSE)
    simulated_dataset(lab, "experiment2", seed=seed, inverse_model=learned, registration_from=registration)
    done("Experiment 2 with the trained inverse model")

    step("unmodelled effects: every model beside the floor")
    unmodelled_study(lab, seed, **(STUDY_QUICK if quick else STUDY), score=path_errors)
    done("unmodelled effects: every model beside the floor")

    step("figures and report")
    inputs, stamp = figure_inputs(lab), lab.report / FIGURE_INPUTS
    if inputs is not None and stamp.exists() and json.loads(stamp.read_text()) == inputs:
        say("  nothing they read has changed since they were made: the figures and the report stay")
        done("figures and report")
        return lab.report / "index.html"
    results = all_figures(lab)
    done("figures and report")
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
    MainJobError (a ``PlanRunError``, ``RigError`` or ``SetupError`` where it cannot start)."""
    if any(lab.sessions.root.glob("rig-*/session.json")):
        return
    from acquisition.plans.plan_run import choose_plan, ready_plan, record_plan
    from acquisition.recorder.setup import recording_failure
    from twin.rig_process import rig_controls, session_devices

    overrides = {"repetitions": 1, "rest_s": 0.5, "settle_s": 1.0}
    plan, desc = choose_plan("experiment1", "experiment1/curve/vsl-1bar/25g", overrides)
    compensator, session = ready_plan(plan, desc), "rig-experiment1-curve"
    with session_devices(desc, rig_dir=lab.rigs / session, plan=plan) as (port_map, rig_dir):
        report, rec = record_plan(plan, desc, port_map, lab.sessions.root, session, compensator,
                                  rig_controls(rig_dir), "experiment1")  # fmt: skip
    if failure := recording_failure(rec):
        raise MainJobError(f"the rig session {plan.name}: {failure}")
    if report.status != "complete":
        raise MainJobError(f"the rig session {plan.name} stopped ({report.status}) after "
                           f"{report.elapsed_s:.1f} s: {report.reason}")  # fmt: skip
