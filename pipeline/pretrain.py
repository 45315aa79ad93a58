"""Pretraining on the lab's twin (issue 33): a network first learns a campaign simulated on a description of
the lab's own arm (the one ``vslab twin fit`` writes), then the lab's measured rows fine-tune it.

The twin's campaign is simulated into a study of its own per description, size and seed,
``<lab>/twin/<name>-<digest>[-<points>pts]-seed<seed>/`` (a description fitted again is another twin: its
sessions are never taken for the old one's), and built into the lab's datasets as ``twin-<name>``, beside
the measured ones. :func:`learning_curve` measures what the twin saves: the test error on the measured data
of a net trained on 1 … 100 % of the measured rows alone, beside
the same net pretrained on the twin and fine-tuned on those rows.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from models.robot import AnthropomorphicKinematics, RobotDescription, load_robot
from pipeline.errors import PipelineError
from pipeline.train import HybridRegressor, TrainConfig, evaluate

if TYPE_CHECKING:
    from pipeline.build import BuildReport
    from pipeline.lab import Lab

FRACTIONS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0)  # of the measured train and val rows (issue 33)


class PretrainError(PipelineError, ValueError):
    """A description the hybrid nets cannot be pretrained on, or data too small to fine-tune on."""


def twin_robot(robot: str | RobotDescription) -> RobotDescription:
    """The description (a name or a file) if the hybrid nets can learn its arm; :class:`PretrainError`
    otherwise (they are the VSL arm's: anthropomorphic, three joints)."""
    description = robot if isinstance(robot, RobotDescription) else load_robot(robot)
    if not isinstance(description.kinematics, AnthropomorphicKinematics):
        raise PretrainError(f"robot {description.name!r}: the hybrid nets are the anthropomorphic VSL arm's; "
                            "its twin cannot pretrain them")  # fmt: skip
    return description


def twin_campaign(lab: Lab, robot: str, *, points: int | None = None, seed: int = 0) -> BuildReport:
    """The campaign experiment (``configs/experiments/campaign.yaml``, ``points`` of it if given) simulated on
    description ``robot`` (a name or a file) into its own study of ``lab`` and built into ``lab``'s datasets
    as ``twin-<name>``. Sessions already simulated for the same description are kept."""
    from pipeline.simulated import TwinExperiment, simulated_dataset

    description = twin_robot(robot)
    digest = hashlib.sha256(description.model_dump_json().encode()).hexdigest()[:10]
    size = f"-{int(points)}pts" if points else ""  # another size or seed: other plans, their own sessions
    study = lab.twin.campaigns(f"{description.name}-{digest}{size}-seed{seed}")
    overrides = {"robot": str(robot)} | ({"points": int(points)} if points else {})
    name = f"twin-{description.name}"
    experiment = TwinExperiment("campaign", overrides, dataset=name, sessions=study.sessions)
    return simulated_dataset(lab, experiment, seed=seed)


def measured_subset(data: pd.DataFrame, fraction: float, split: str, seed: int = 0) -> pd.DataFrame:
    """The rows of ``data`` a lab with ``fraction`` of its measurements would have: the test part of
    ``split`` whole (every fraction is scored on the same rows), ``fraction`` of its train and of its val
    part (at least 2 train rows and 1 val row), drawn at random by ``seed``; whole sessions for
    ``split_group`` (which deals sessions), rows for ``split_random``. A smaller fraction's rows are a part
    of a larger's."""
    if not 0 < fraction <= 1:
        raise PretrainError(f"a fraction of the measured rows is in (0, 1], got {fraction}")
    rng = np.random.default_rng(seed)
    units = data["session"].astype(str).to_numpy() if split == "split_group" else np.arange(len(data))
    keep = data[split].eq("test").to_numpy().copy()
    for part in ("train", "val"):
        drawn = rng.permutation(pd.unique(units[data[split].eq(part).to_numpy()]))
        n = max(1, round(fraction * len(drawn)))
        while n < len(drawn) and np.isin(units, drawn[:n]).sum() < (2 if part == "train" else 1):
            n += 1
        keep |= np.isin(units, drawn[:n])
    return data[keep]


def _scores(net, data: pd.DataFrame, split: str, prefix: str) -> dict[str, float]:
    m = evaluate(net, data, split, "test")
    return {f"{prefix}_{k}": m[k] for k in ("tip_mean_mm", "joint_mean_mrad") if k in m}


def learning_curve(
    measured: pd.DataFrame,
    twin: pd.DataFrame,
    config: TrainConfig,
    *,
    fractions: tuple[float, ...] = FRACTIONS,
    robot: str | RobotDescription | None = None,
    threads: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> pd.DataFrame:
    """Test error on ``measured`` (its ``config.split`` test part) against the measured rows used: one row
    per fraction (``fraction``, ``train_rows``, ``val_rows``, ``measured_only_*`` and ``fine_tuned_*``: the
    mean tip error in mm and, for inverse nets, the joint error in mrad), and a first row of fraction 0: the
    net pretrained on ``twin`` alone (the twin's campaign; ``robot``: its description, which scores the
    pretraining's validation tip error). Every net has ``config``'s seed; on CPU."""
    say = progress or (lambda _: None)
    say(f"pretraining on the twin's {len(twin):,} rows")
    pretrained = HybridRegressor(config, threads, "cpu", robot=robot).fit(twin).net_
    records = [{"fraction": 0.0, "train_rows": 0, "val_rows": 0,
                **_scores(pretrained, measured, config.split, "fine_tuned")}]  # fmt: skip
    for fraction in fractions:
        rows = measured_subset(measured, fraction, config.split, config.seed)
        counts = rows[config.split].value_counts()
        record = {"fraction": fraction, "train_rows": int(counts.get("train", 0)),
                  "val_rows": int(counts.get("val", 0))}  # fmt: skip
        if record["train_rows"] < 2 or record["val_rows"] < 1:
            raise PretrainError(f"{fraction:.0%} of the measured rows is {record['train_rows']} train and "
                                f"{record['val_rows']} val rows: too few to train on")  # fmt: skip
        train, val = record["train_rows"], record["val_rows"]
        say(f"{fraction:.0%} of the measured rows ({train:,} train, {val:,} val)")
        alone = HybridRegressor(config, threads, "cpu").fit(rows).net_
        tuned = HybridRegressor(config, threads, "cpu", pretrained).fit(rows).net_
        record |= _scores(alone, measured, config.split, "measured_only")
        record |= _scores(tuned, measured, config.split, "fine_tuned")
        records.append(record)
    return pd.DataFrame(records)


def curve_verdict(curve: pd.DataFrame, fraction: float = 0.1, metric: str = "tip_mean_mm") -> dict:
    """Issue 33's question of a curve: is the net pretrained on the twin and fine-tuned on ``fraction`` of the
    measured rows as good as the net trained on all of them alone? ``fine_tuned``, ``all_measured``, their
    ``ratio`` and the rows each used."""
    at = curve[np.isclose(curve["fraction"], fraction)].iloc[0]
    full = curve[np.isclose(curve["fraction"], 1.0)].iloc[0]
    tuned, alone = float(at[f"fine_tuned_{metric}"]), float(full[f"measured_only_{metric}"])
    return {"fraction": fraction, "metric": metric, "fine_tuned": tuned, "all_measured": alone,
            "ratio": tuned / alone, "rows": int(at["train_rows"] + at["val_rows"]),
            "all_rows": int(full["train_rows"] + full["val_rows"])}  # fmt: skip
