"""The report's assembly on a small lab: what the data allow is drawn, what they do not is listed with why."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.recorder.sessions import SessionStore
from acquisition.recorder.writer import SessionWriter
from acquisition.schemas.events import Event, EventKind
from analysis.lab_figures import all_figures, realtime_sessions
from analysis.lab_report import lab_report
from models.robot import load_robot
from pipeline import model_store
from pipeline.grid import run_grid
from pipeline.lab import Lab
from pipeline.session_index import sessions_of


@pytest.mark.slow
def test_figures_and_report_of_a_lab_with_only_a_campaign(campaign_dataset, tmp_path):
    shared, version, _ = campaign_dataset
    lab = tmp_path / "lab"  # its own models; the shared fixture's datasets (read only)
    lab.mkdir()
    (lab / "datasets").symlink_to(shared / "datasets")
    grid = {
        "models": [{"direction": "forward", "preset": "small-residual"}],
        "datasets": [f"campaign@{version}"],
        "splits": ["split_random"],
        "seeds": [0],
        "train": {"max_epochs": 15, "patience": 5},
    }
    (trained,) = run_grid(Lab(lab), grid)
    res = all_figures(Lab(lab), tmp_path / "figures")
    assert (
        "forward-small-residual" not in res.tables["forward model: test error, campaign, random split"].index
    )
    model_store.tag(
        lab / "models", model_store.FORWARD, trained["version"]
    )  # figures take models by tag only
    res = all_figures(Lab(lab), tmp_path / "figures")
    assert {"error_heatmaps", "learning_curves", "clock_fits", "registration_vsl"} <= set(res.figures)
    assert all(p.is_file() and p.with_suffix(".pdf").is_file() for p in res.figures.values())
    assert (tmp_path / "figures" / "error_heatmaps.json").is_file()  # which versions it was made from
    assert {"dataset experiment1", "dataset experiment2"} <= set(res.missing)  # named, with the reason
    table = res.tables["forward model: test error, campaign, random split"]
    assert table.loc["forward-small-residual", "mean (mm)"] < 0.5 * table.loc["rigid model", "mean (mm)"]
    assert res.versions["dataset campaign"] == version
    reg = res.tables["registration (tracker → base), campaign"].loc["vsl"]
    assert 0 < reg["rms, selected (mm)"] < 1.0 and reg["selected points"] <= reg["static points"]
    page = lab_report(Lab(lab), res).read_text()
    assert "error_heatmaps" in page and "not made (and why)" in page and "dataset experiment1" in page


def _session(sessions, name, runner, n_events):
    meta = {"runner": runner, "plan": "experiment1/curve/vsl-1bar/25g"}
    with SessionWriter(
        sessions / name, load_robot("vsl"), name, experiment="experiment1", metadata=meta
    ) as w:
        for i in range(n_events):
            w.event(Event(EventKind.PLAN_STEP, index=i, label="step"), int(i * 1e8))


def test_real_time_sessions_are_reported_apart_from_the_simulated_ones(tmp_path):
    sessions = tmp_path / "sessions"
    _session(sessions, "rig-a", "real-time", 11)
    _session(sessions, "sim-b", "simulated", 3)
    table = realtime_sessions(Lab(tmp_path))
    assert table.index.get_level_values("session").unique().tolist() == ["rig-a"]
    row = table.loc[("rig-a", "/events")]
    assert row["messages"] == 11 and np.isclose(row["rate (Hz)"], 10.0) and row["status"] == "complete"
    # the main job builds Experiment 1's dataset from the simulated sessions only
    assert [d.name for d in sessions_of(SessionStore(sessions), "experiment1", runner="simulated")] == [
        "sim-b"
    ]
    assert [d.name for d in sessions_of(SessionStore(sessions), "experiment1")] == ["rig-a", "sim-b"]
    assert realtime_sessions(Lab(tmp_path / "empty")).empty
