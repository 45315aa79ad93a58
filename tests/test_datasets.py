"""The matrix D, its splits, dataset versions, and the stage cache."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from acquisition.plans import experiments
from models import kinematics
from pipeline import datasets
from pipeline.cache import StageCache, stage_key
from pipeline.dataset_store import DatasetStore


def _rows(vsl, n=200, seed=0):
    """Timeline-like rows: joint columns as the sync stage names them, x already in the base frame."""
    rng = np.random.default_rng(seed)
    lengths = experiments.arm_lengths(vsl)
    x = rng.uniform([0.22, -0.08, 0.02], [0.38, 0.08, 0.18], size=(n, 3))
    q = kinematics.vsl_ik(x, lengths, 1)
    return pd.DataFrame(
        {
            "stepper_position_0": q[:, 0], "servo_position_0": q[:, 1], "servo_position_1": q[:, 2],
            "servo_current_0": rng.normal(0.3, 0.05, n), "servo_current_1": rng.normal(0.1, 0.05, n),
            "pressure_0": rng.uniform(5e4, 2e5, n), "pressure_1": rng.uniform(5e4, 2e5, n),
            "x_0": x[:, 0], "x_1": x[:, 1], "x_2": x[:, 2] - 0.005,  # a 5 mm sag below the rigid model
            "payload_kg": rng.choice([0.0, 0.05], n), "session": rng.choice(["a", "b", "c", "d", "e"], n),
            "point": np.arange(n),
        }
    )  # fmt: skip


def test_assemble_has_the_papers_columns_and_the_model_based_ones(vsl):
    rows = _rows(vsl)
    d = datasets.assemble(rows, vsl)
    lengths = experiments.arm_lengths(vsl)
    q = d[["q_0", "q_1", "q_2"]].to_numpy()
    np.testing.assert_allclose(q[:, 1:], rows[["servo_position_0", "servo_position_1"]].to_numpy())
    np.testing.assert_allclose(d[["fk_0", "fk_1", "fk_2"]].to_numpy(), kinematics.vsl_fk(q, lengths))
    x = d[["x_0", "x_1", "x_2"]].to_numpy()
    np.testing.assert_allclose(
        kinematics.vsl_fk(d[["ik_0", "ik_1", "ik_2"]].to_numpy(), lengths), x, atol=1e-9
    )
    assert np.abs(d["fk_2"] - d["x_2"]).mean() == pytest.approx(0.005)
    assert set(d.columns) >= {"p_0", "p_1", "i_0", "i_1", "payload_kg", "robot", "session", "point"}
    far = rows.assign(x_0=2.0)  # out of reach: no IK, no exception
    assert datasets.assemble(far, vsl)[["ik_0", "ik_1", "ik_2"]].isna().all().all()


def test_splits_random_and_grouped(vsl):
    d = datasets.add_splits(datasets.assemble(_rows(vsl, 1000), vsl), seed=3)
    counts = d["split_random"].value_counts(normalize=True)
    assert counts["train"] == pytest.approx(0.70, abs=0.005) and counts["test"] == pytest.approx(
        0.15, abs=0.005
    )
    per_session = d.groupby("session")["split_group"].nunique()
    assert (per_session == 1).all()  # no session in two splits: no leakage
    assert set(d["split_group"]) <= {"train", "val", "test"}
    again = datasets.add_splits(datasets.assemble(_rows(vsl, 1000), vsl), seed=3)
    pd.testing.assert_frame_equal(d, again)


def test_versions_are_content_addressed(tmp_path, vsl):
    sources = {"s1": "aa", "s2": "bb"}
    v = datasets.dataset_version(sources, {"clean": {"k": 1}})
    assert v == datasets.dataset_version(dict(reversed(sources.items())), {"clean": {"k": 1}})
    assert v != datasets.dataset_version(sources, {"clean": {"k": 2}})
    assert v != datasets.dataset_version({**sources, "s2": "bc"}, {"clean": {"k": 1}})
    data = datasets.add_splits(datasets.assemble(_rows(vsl), vsl))
    path = DatasetStore(tmp_path).write("d", v, {"data": data}, {"made_from": sources})
    mtime = (path / "data.parquet").stat().st_mtime_ns
    assert DatasetStore(tmp_path).write("d", v, {"data": data.head(3)}, {}) == path  # exists: untouched
    assert (path / "data.parquet").stat().st_mtime_ns == mtime
    loaded, card = DatasetStore(tmp_path).load("d")
    pd.testing.assert_frame_equal(loaded, data)
    assert card["version"] == v and card["counts"]["rows"] == len(data)
    assert not [p for p in (tmp_path / "d").iterdir() if p.name.startswith(".")]  # no temporary left


def test_stage_cache_round_trip(tmp_path):
    cache = StageCache(tmp_path)
    key = stage_key("session", ["abc"], {"clean": {"hampel_window": 7}})
    assert key != stage_key("session", ["abc"], {"clean": {"hampel_window": 9}})
    assert not cache.has("session", key)
    df = pd.DataFrame({"a": [1, 2], "b": [0.5, 1.5]})
    cache.store("session", key, {"static": df}, {"session": "s"})
    tables, record = cache.load("session", key)
    pd.testing.assert_frame_equal(tables["static"], df)
    assert record["session"] == "s" and cache.has("session", key)
