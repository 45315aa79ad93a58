"""Pretraining on the lab's twin (issue 33): ``pipeline.pretrain``, `vslab train --pretrain` and
`vslab twin curve`.

A net fine-tuned from a pretrained one starts from its weights and scaling and leaves it unchanged; the rows
of a fraction of the measured data keep the test part whole and nest; the grid pretrains each net once on the
twin's campaign, saves both, and fine-tunes a version of its own; what the commands cannot use is one
`error:` line. Whether pretraining pays is `bench/pretrain.py`'s question (its figures are in the stop notes).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from typer.testing import CliRunner

from models.hybrid import preset
from pipeline.datasets import SPLIT_COLUMNS
from pipeline.pretrain import PretrainError, curve_verdict, measured_subset
from pipeline.train import HybridRegressor, TrainConfig
from vslab.cli import app

runner = CliRunner()


@pytest.mark.parametrize("split", SPLIT_COLUMNS)
def test_a_fraction_of_the_measured_rows_keeps_the_test_part_and_nests(campaign_dataset, split):
    data = campaign_dataset[2]
    test = set(data.index[data[split] == "test"])
    subsets = {f: measured_subset(data, f, split, seed=3) for f in (0.1, 0.2, 0.5, 1.0)}
    for fraction, rows in subsets.items():
        assert set(rows.index[rows[split] == "test"]) == test  # every fraction scored on the same rows
        for part in ("train", "val"):
            unit = (lambda d: d["session"].nunique()) if split == "split_group" else len  # sessions or rows
            drawn, there = unit(rows[rows[split] == part]), unit(data[data[split] == part])
            assert drawn == max(1, round(fraction * there)), (part, drawn, there)
    assert set(subsets[0.1].index) <= set(subsets[0.2].index) <= set(subsets[0.5].index)  # nested
    assert len(subsets[0.1]) < len(subsets[0.5]) < len(subsets[1.0])
    assert len(subsets[1.0]) == len(data)
    if split == "split_group":  # whole sessions, so the twin fitted on them sees no test row
        kept = subsets[0.2]
        for session, rows in kept.groupby("session"):
            assert len(rows) == (data["session"] == session).sum()
    for wrong in (0, -0.1, 1.5):
        with pytest.raises(PretrainError, match=r"in \(0, 1\]"):
            measured_subset(data, wrong, split)


def test_fine_tuning_starts_from_the_pretrained_net_and_leaves_it_as_it_was(campaign_dataset):
    data = campaign_dataset[2]
    config = TrainConfig(preset("inverse", "small-residual"), max_epochs=2, seed=1)
    pretrained = HybridRegressor(config, threads=1).fit(data).net_
    before = {k: v.clone() for k, v in pretrained.state_dict().items()}
    still = TrainConfig(preset("inverse", "small-residual"), max_epochs=1, lr=1e-12, seed=5)
    tuned = HybridRegressor(still, threads=1, pretrained=pretrained).fit(data.iloc[::4]).net_
    fresh = HybridRegressor(still, threads=1).fit(data.iloc[::4]).net_
    for name, tensor in pretrained.state_dict().items():
        assert torch.equal(tensor, before[name])  # copied, never changed
        assert torch.allclose(tuned.state_dict()[name], tensor, atol=1e-9)  # its weights and scaling
    assert not torch.allclose(fresh.in_mean, tuned.in_mean)  # a fresh net scales by its own rows
    with pytest.raises(ValueError, match="same shape"):
        HybridRegressor(TrainConfig(preset("inverse", "paper")), pretrained=pretrained).fit(data)


def test_fine_tuning_that_only_makes_val_worse_keeps_the_pretrained_weights(campaign_dataset):
    """The weights fine-tuning starts from are a candidate for early stopping (the curves' first entry, no
    step taken): a step far too large makes every epoch worse, and the pretrained net comes back as it was.
    A net trained from scratch has no such entry."""
    data = campaign_dataset[2]
    config = TrainConfig(preset("inverse", "small-residual"), max_epochs=20, seed=1)
    pretrained = HybridRegressor(config, threads=1).fit(data).net_
    wild = TrainConfig(preset("inverse", "small-residual"), max_epochs=4, patience=2, lr=10.0, seed=5)
    tuned = HybridRegressor(wild, threads=1, pretrained=pretrained).fit(data)
    history = tuned.history_
    assert history.best_epoch == 0 and len(history.val_loss) == 1 + wild.patience  # the start, then 2 worse
    assert min(history.val_loss[1:]) > history.val_loss[0]
    for name, tensor in pretrained.state_dict().items():
        assert torch.equal(tuned.net_.state_dict()[name], tensor)
    fresh = HybridRegressor(wild, threads=1).fit(data).history_
    assert len(fresh.val_loss) == len(fresh.train_loss) <= wild.max_epochs  # an entry an epoch, none before


def test_the_verdict_reads_ten_percent_against_all():
    import pandas as pd

    curve = pd.DataFrame({
        "fraction": [0.0, 0.1, 1.0], "train_rows": [0, 70, 700], "val_rows": [0, 15, 150],
        "measured_only_tip_mean_mm": [np.nan, 2.0, 0.8], "fine_tuned_tip_mean_mm": [1.0, 0.72, 0.7],
    })  # fmt: skip
    verdict = curve_verdict(curve)
    assert verdict["ratio"] == pytest.approx(0.9) and verdict["rows"] == 85 and verdict["all_rows"] == 850


def _measured_lab(campaign_dataset, tmp_path_factory) -> Path:
    copy = tmp_path_factory.mktemp("pretrain-lab") / "lab"
    shutil.copytree(campaign_dataset[0] / "datasets", copy / "datasets")
    return copy


@pytest.fixture(scope="module")
def measured_lab(campaign_dataset, tmp_path_factory):
    """A copy of the small campaign's lab: what a lab has measured, its twin not fitted."""
    return _measured_lab(campaign_dataset, tmp_path_factory)


@pytest.fixture(scope="module")
def lab(campaign_dataset, tmp_path_factory):
    """A copy of the small campaign's lab with its twin fitted (`vslab twin fit`)."""
    copy = _measured_lab(campaign_dataset, tmp_path_factory)
    result = runner.invoke(app, ["--lab", str(copy), "twin", "fit", "--dataset", "campaign"])
    assert result.exit_code == 0, result.output
    return copy


TINY_GRID = {
    "models": [{"direction": "inverse", "preset": "small-residual"}],
    "datasets": ["campaign"], "splits": ["split_group"], "seeds": [0],
    "train": {"max_epochs": 3, "patience": 2},
}  # fmt: skip


@pytest.mark.slow
def test_train_pretrains_each_net_on_the_twin_then_fine_tunes_it(lab, tmp_path):
    grid = tmp_path / "grid.yaml"
    grid.write_text(yaml.safe_dump(TINY_GRID))
    fitted = lab / "twin" / "vsl_fitted.yaml"
    args = ["--lab", str(lab), "train", "--grid", str(grid), "--workers", "1", "--pretrain", str(fitted),
            "--pretrain-points", "300"]  # fmt: skip
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "1 trained, 0 existing" in result.output
    twin = [p.name for p in (lab / "datasets").iterdir()]
    assert "twin-vsl_fitted" in twin  # the twin's campaign, beside the measured dataset
    cards = [json.loads(p.read_text()) for p in (lab / "models").glob("*/*/card.json")]
    by_dataset = {c["dataset"]["name"]: c for c in cards}
    assert set(by_dataset) == {"campaign", "twin-vsl_fitted"}  # the pretrained net is kept too
    tuned, first = by_dataset["campaign"], by_dataset["twin-vsl_fitted"]
    assert tuned["pretrained"]["model"] == first["version"] and tuned["pretrained"]["robot"] == str(fitted)
    assert tuned["pretrained"]["dataset"] == f"twin-vsl_fitted@{first['dataset']['version']}"
    plain = runner.invoke(app, ["--lab", str(lab), "train", "--grid", str(grid), "--workers", "1"])
    assert plain.exit_code == 0 and "1 trained" in plain.output  # without pretraining: another version
    again = runner.invoke(app, args)
    assert again.exit_code == 0 and "0 trained, 1 existing" in again.output, again.output


@pytest.mark.slow
def test_twin_curve_prints_and_draws_the_learning_curve(lab):
    fitted = lab / "twin" / "vsl_fitted.yaml"
    result = runner.invoke(app, ["--lab", str(lab), "twin", "curve", "--robot", str(fitted), "--dataset",
                                 "campaign", "--points", "300", "--max-epochs", "3"])  # fmt: skip
    assert result.exit_code == 0, result.output
    for row in ("none (twin", "1%", "10%", "100%"):
        assert f"│ {row}" in result.output
    assert "fine-tuned on 10 %" in result.output
    record = json.loads((lab / "figures" / "pretraining_curve.json").read_text())
    assert record["made_from"]["measured"].startswith("campaign@")
    assert (lab / "figures" / "pretraining_curve.png").stat().st_size > 10_000


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["train", "--pretrain", "popup"], "anthropomorphic VSL arm"),
        (["train", "--pretrain", "no_such_robot"], "no such robot description"),
        (["train", "--pretrain-points", "100"], "--pretrain-points"),
        (["train", "--pretrain", "vsl", "--pretrain-points", "3"], "--pretrain-points"),
        (["twin", "curve", "--robot", "popup", "--dataset", "campaign"], "anthropomorphic VSL arm"),
        (["twin", "curve", "--robot", "vsl", "--dataset", "nothing"], "--dataset nothing"),
        (["twin", "curve", "--robot", "vsl", "--dataset", "campaign", "--preset", "huge"], "--preset huge"),
        (["twin", "curve", "--robot", "vsl", "--dataset", "campaign", "--split", "x"], "--split x"),
    ],
)
def test_what_pretraining_cannot_use_is_one_error_line(measured_lab, args, says):
    result = runner.invoke(app, ["--lab", str(measured_lab), *args])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert lines[0].startswith("error:") and says in result.output and "Traceback" not in result.output


@pytest.mark.slow
def test_the_report_has_a_section_the_twin_against_your_robot(lab, tmp_path):
    """What `twin fit`, `twin check` and `twin curve` kept in the lab's twin folder is the report's section:
    the fitted values beside the nominal ones, the check per cell, the curve drawn again with its table."""
    from analysis.lab_figures import Results
    from analysis.lab_report import lab_report
    from analysis.twin_report import twin_against_robot
    from pipeline.lab import Lab

    fitted = lab / "twin" / "vsl_fitted.yaml"
    if not (lab / "twin" / "pretraining_curve.json").exists():
        test_twin_curve_prints_and_draws_the_learning_curve(lab)
    checked = runner.invoke(app, ["--lab", str(lab), "twin", "check", "--robot", str(fitted), "--dataset",
                                  "campaign"])  # fmt: skip
    assert checked.exit_code == 0 and (lab / "twin" / "check-vsl_fitted.json").is_file(), checked.output
    res = Results()
    twin_against_robot(Lab(lab), res, tmp_path / "figures")
    assert res.missing == {}
    values = res.tables["your twin: vsl_fitted, fitted beside nominal"]
    assert {"l2_m", "upper_vsl.k@1bar"} <= set(values.index)
    assert list(values.columns) == ["nominal", "fitted", "standard error", "change (%)", "change (SE)"]
    assert "l1_m" in res.texts["your twin: vsl_fitted, fitted beside nominal"]  # not identifiable, and why
    check = next(v for k, v in res.tables.items() if "checked on campaign@" in k)
    assert ("all", "all") in check.index
    assert (tmp_path / "figures" / "pretraining_curve.png").is_file()
    page = lab_report(Lab(tmp_path / "report-lab"), res).read_text()
    assert "The twin against your robot" in page and "pretrained, fine-tuned (mm)" in page


def test_twin_campaigns_of_other_sizes_or_descriptions_keep_their_own_sessions(tmp_path):
    """A second campaign of the same twin at another size (or of a description fitted again) is simulated
    beside the first, not refused as the first's sessions made otherwise, nor taken for them."""
    from pipeline.lab import Lab
    from pipeline.pretrain import twin_campaign

    lab = Lab(tmp_path / "lab")
    (tmp_path / "arm.yaml").write_text("extends: vsl\nname: vsl_fitted\ndescription: a fitted arm\n")
    small = twin_campaign(lab, str(tmp_path / "arm.yaml"), points=12)
    larger = twin_campaign(lab, str(tmp_path / "arm.yaml"), points=16)
    assert (small.rows, larger.rows) == (12, 16) and small.version != larger.version
    (tmp_path / "arm.yaml").write_text("extends: vsl\nname: vsl_fitted\ndescription: fitted again\n"
                                       "kinematics: {l2_m: 0.251}\n")  # fmt: skip
    again = twin_campaign(lab, str(tmp_path / "arm.yaml"), points=12)
    assert again.version not in (small.version, larger.version)
    assert len(list((tmp_path / "lab" / "twin").iterdir())) == 3
