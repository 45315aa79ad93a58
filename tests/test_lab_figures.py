"""The report's assembly on a small lab: what the data allow is drawn, what they do not is listed with why."""

from __future__ import annotations

from analysis.lab_figures import all_figures, lab_report
from pipeline.grid import run_grid


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
    run_grid(lab, grid)
    res = all_figures(lab, tmp_path / "figures")
    assert {"error_heatmaps", "learning_curves", "clock_fits"} <= set(res.figures)
    assert all(p.is_file() and p.with_suffix(".pdf").is_file() for p in res.figures.values())
    assert (tmp_path / "figures" / "error_heatmaps.json").is_file()  # which versions it was made from
    assert {"dataset experiment1", "dataset experiment2"} <= set(res.missing)  # named, with the reason
    table = res.tables["forward model: test error (mm), campaign, random split"]
    assert table.loc["forward-small-residual", "mean"] < 0.5 * table.loc["rigid model", "mean"]
    assert res.versions["dataset campaign"] == version
    page = lab_report(lab, res).read_text()
    assert "error_heatmaps" in page and "not made (and why)" in page and "dataset experiment1" in page
