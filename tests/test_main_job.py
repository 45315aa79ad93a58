"""The main job end to end on the twin (`vslab demo --quick`): every figure of issue 7 is made, nothing is
listed as missing, and the report page embeds them all (≈ 2.5 min on 2 cores). The run is the twin
tutorial's (the ``tutorial_run`` fixture: docs/tutorials/twin-end-to-end.md runs
`vslab --lab lab demo --quick`), so the suite runs the main job once for both."""

from __future__ import annotations

import json

import pytest

from acquisition.recorder.sessions import SessionStore
from analysis import lab_figures
from pipeline.lab import Lab
from pipeline.session_index import sessions_of
from vslab import lab_job

FIGURES = [
    "fig5", "fig6", "fig7a", "fig7b",  # seed 000
    "fig7_popup_hysteresis", "fig12_popup_reach_paths", "fig13_popup_reach_difference",  # seed 001
    "fig15_popup_visual_servoing_paths", "fig16_popup_visual_servoing_joints",
    "error_heatmaps", "learning_curves", "clock_fits", "registration_vsl",  # ours
]  # fmt: skip


@pytest.mark.slow
def test_quick_main_job_makes_every_figure_and_the_report(tutorial_run):
    assert tutorial_run.failure() is None, tutorial_run.failure()
    tmp_path = tutorial_run.workdir  # the tutorials' working directory: `lab` is the main job's lab
    said = " ".join(tutorial_run.output_of(" demo").split())  # the CLI's lines, as rich wrapped them
    assert "main job done" in said, "the twin tutorial must run `vslab --lab lab demo --quick`"
    report = Lab(tmp_path / "lab").report / "index.html"
    assert report.is_file()
    assert "not made" not in said, said
    figures = tmp_path / "lab" / "figures"
    for name in FIGURES:
        assert (figures / f"{name}.png").stat().st_size > 10_000, name
        assert (figures / f"{name}.pdf").is_file(), name
    page = report.read_text()
    assert all(f'alt="{name}"' in page for name in FIGURES)
    assert "POPUP Table 1" in page and "Real-time sessions" in page
    timings = json.loads((report.parent / "timings.json").read_text())
    assert set(timings) == {
        "real-time session on the rig", lab_job.SIMULATIONS, "campaign", "Experiment 1", "training",
        "Experiment 2 with the trained inverse model", "figures and report",
        "unmodelled effects: every model beside the floor",
    }  # fmt: skip
    assert "unmodelled effects: forward models" in page and "unmodelled effects: inverse models" in page
    assert "unmodelled effects: Experiment 2" in page
    # on that twin: IK, static, the hybrid and the history-aware hybrid along the paper's two cases, and the
    # networks of the comparison saved with the table in their cards
    from pipeline.comparison import UNMODELLED, load_comparison
    from pipeline.model_store import load_card

    _, card = load_comparison(Lab(tmp_path / "lab").comparisons.path(UNMODELLED))
    paths = {(r["mode"], r["pressure_bar"]): r["mean_mm"] for r in card["experiment2"]}
    assert set(paths) == {(m, b) for m in ("ik", "static", "hybrid", "history") for b in (0.5, 1.5)}
    assert all(0 < e < 20 for e in paths.values()), paths
    assert all(paths["history", b] < paths["ik", b] for b in (0.5, 1.5)), paths
    assert len(card["models"]) == 6
    models = tmp_path / "lab" / "unmodelled" / "drawn" / "models"
    assert all("comparison" in load_card(models / m["name"] / m["version"]) for m in card["models"])
    # the rig's real-time session is in the lab, but not in Experiment 1's dataset
    sessions = tmp_path / "lab" / "sessions"
    rig = [d for d in sessions_of(SessionStore(sessions), "experiment1") if d.name.startswith("rig-")]
    assert len(rig) == 1 and rig[0] not in sessions_of(
        SessionStore(sessions), "experiment1", runner="simulated"
    )
    # a second run reuses every step's work; the figures read nothing new, so they stay as they were drawn
    drawn = (figures / "fig5.png").stat().st_mtime_ns
    again: list[str] = []
    assert lab_job.run(Lab(tmp_path / "lab"), quick=True, say=again.append) == report
    assert any("the figures and the report stay" in line for line in again), again
    assert (figures / "fig5.png").stat().st_mtime_ns == drawn
    inputs = lab_figures.figure_inputs(Lab(tmp_path / "lab"))
    assert inputs == json.loads((report.parent / lab_figures.FIGURE_INPUTS).read_text())
    assert any(path.startswith("models/") for path, *_ in inputs["files"])  # what a retrained model changes
