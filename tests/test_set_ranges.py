"""Experiment parameters that pass the kind checks but would break the run (findings 3 and 12 of the issue
"Nothing silently stale, nothing hung, nothing torn"): values past their physical range, plans too large to
build or too long to run, and batch commands that lowered their priority before checking their arguments."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from acquisition.plans.experiments import ExperimentError, expand_experiment

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(
    ("experiment", "overrides", "says"),
    [
        ("campaign", {"points": 20, "settle_s": 1e308}, "settle_s: 1e+308: expected a number up to 3600"),
        ("experiment1", {"speed_m_s": 1e-300}, "--set speed_m_s: 1e-300: expected a number from 0.001 to 1"),
        ("campaign", {"points": 100_000, "settle_s": 3600.0}, "days of bench time (at most 7"),
        ("experiment1", {"repetitions": 1000, "points_per_segment": 10_000}, "set-points (at most 100,000"),
        ("popup_static", {"load_steps": 1000, "repetitions": 1000}, "set-points (at most 100,000"),
        ("experiment2", {"cases": [{"payload_g": 1e300, "pressure_bar": 1.0}]}, "cases.payload_g: 1e+300"),
        ("popup_reach", {"target_mm": [1e308, 0.0, 0.0]}, "expected a number from -10000 to 10000"),
        ("popup_static", {"pressures_kpa": list(range(101))}, "at most 100 values"),
    ],
)
@pytest.mark.slow
def test_values_that_would_never_end_are_refused(experiment, overrides, says):
    """Before the fix: an OverflowError, a plan of 1e300 s, or minutes of building."""
    with pytest.raises(ExperimentError) as refused:
        expand_experiment(experiment, overrides)
    assert says in str(refused.value)


def test_the_shipped_experiments_are_within_range():
    shipped = ("experiment1", "experiment2", "campaign", "popup_static", "popup_impact", "popup_deploy",
               "popup_reach", "popup_survey")  # fmt: skip
    for experiment in shipped:
        _, plans, _ = expand_experiment(experiment, {"points": 5} if "campaign" in experiment else {})
        assert plans


# Runs the CLI in a session of its own (no fork in lower_priority) and says its nice value as it exits.
NICE_AT_EXIT = (
    "import atexit, os, runpy, sys\n"
    "atexit.register(lambda: print('nice at exit', os.getpriority(os.PRIO_PROCESS, 0), file=sys.stderr))\n"
    "sys.argv = ['vslab', *sys.argv[1:]]\n"
    "runpy.run_module('vslab.cli', run_name='__main__')\n"
)


@pytest.mark.parametrize(
    "args",
    [
        ["simulate", "campaign", "--set", "pointz=3"],
        ["build", "--set", "nostage.key=1"],
        ["train", "--set", "no_such_field=1"],
    ],
    ids=["simulate", "build", "train"],
)
@pytest.mark.slow
def test_batch_commands_check_their_arguments_before_lowering_their_priority(tmp_path, args):
    """A typo is refused at the caller's priority (at nice 19 on a busy machine it took minutes)."""
    env = {**os.environ, "VSLAB_BATCH_NICE": "19", "PYTHONPATH": str(ROOT)}
    nice = os.getpriority(os.PRIO_PROCESS, 0)
    run = subprocess.run([sys.executable, "-c", NICE_AT_EXIT, "--lab", str(tmp_path / "lab"), *args], env=env,
                         capture_output=True, text=True, timeout=300, start_new_session=True)  # fmt: skip
    out = run.stdout + run.stderr
    assert run.returncode == 2, out
    assert sum(line.startswith("error:") for line in out.splitlines()) == 1, out
    assert f"nice at exit {nice}" in out, out
