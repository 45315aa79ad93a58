"""`vslab build` end to end on twin sessions: the dataset, its cache, and bad inputs beside good ones."""

from __future__ import annotations

import shutil
import time

import numpy as np
import pytest

from acquisition.plans.plan import PlanBuilder
from acquisition.recorder.sessions import SessionStore
from models.robot import load_robot
from pipeline.build import build
from pipeline.dataset_store import DatasetStore
from pipeline.lab import Lab
from twin.runner import simulate, simulate_experiment

POINTS = 96


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """A small campaign (4 benches → 4 sessions of 24 settled points)."""
    lab = tmp_path_factory.mktemp("lab")
    simulate_experiment(
        "campaign", SessionStore(lab / "sessions"), seed=2, benches=4, overrides={"points": POINTS}
    )
    return lab


@pytest.mark.slow
def test_campaign_builds_once(lab):
    sessions = sorted((lab / "sessions").iterdir())
    report = build(sessions, Lab(lab), "campaign")
    assert report.built and not report.failed and report.cached == 0
    d, card = DatasetStore(lab / "datasets").load("campaign", report.version)
    assert abs(len(d) - POINTS) <= 2  # ± settled windows that failed (reported in the card)
    assert card["counts"]["rows"] == len(d) and set(card["made_from"]) == {s.name for s in sessions}
    # the measured tip is in the base frame: near the model's FK, sagging below it (payloads, soft links)
    sag = d["fk_2"] - d["x_2"]
    assert 0 < sag.mean() < 0.03 and np.hypot(d["fk_0"] - d["x_0"], d["fk_1"] - d["x_1"]).mean() < 0.01
    unfitted = 0
    for session in card["sessions"].values():
        assert {"clock/servo_bus", "clock/pressure_board", "clock/tracker"} <= set(session["values"])
        for key, fit in session["values"].items():  # a drift the session was too short to fit says so
            if key.startswith("clock/") and not fit["drift_fitted"]:
                device = key.removeprefix("clock/")
                assert any(w.startswith(f"{device}: session too short to fit") for w in session["warnings"])
                unfitted += 1
    assert unfitted >= 1  # ≈ 45 s sessions: a polled servo's phase mostly slips under twice
    # nothing changed: the same version, found without running a stage
    start = time.perf_counter()
    again = build(sessions, Lab(lab), "campaign")
    assert again.version == report.version and not again.built and again.rows == len(d)
    assert time.perf_counter() - start < 5.0
    # a changed parameter: a new version; the per-session stages it does not touch are reused
    other = build(sessions, Lab(lab), "campaign", {"splits": {"seed": 1}})
    assert other.version != report.version and other.built and other.cached == len(sessions)


@pytest.mark.slow
def test_bad_sessions_are_reported_and_the_others_build(lab, tmp_path):
    good = sorted((lab / "sessions").iterdir())[:2]
    bad = tmp_path / "bad"
    for name in ("truncated", "not-mcap", "empty"):
        (bad / name).mkdir(parents=True)
    part = next(good[0].glob("*.mcap"))
    data = part.read_bytes()
    (bad / "truncated" / part.name).write_bytes(data[: len(data) // 3])  # a killed recorder's torn file
    (bad / "not-mcap" / "x_000.mcap").write_text("this is not an MCAP file\n")
    vsl = load_robot("vsl")  # a session recorded without the tracker: no ground truth
    blind = vsl.model_copy(update={"devices": {k: v for k, v in vsl.devices.items() if k != "tracker"}})
    plan = (
        PlanBuilder("no/tracker", "vsl", 3, 2)
        .goto([0, 0.9, -1.6])
        .pressure(1e5)
        .payload(0)
        .settle(1.0, 0, 0.5)
    )
    simulate([plan.build()], blind, bad)
    report = build([*good, *(sorted(bad.iterdir()))], Lab(tmp_path / "lab"), "mixed")
    assert "tracker" in report.failed["sim-no-tracker"]
    assert set(report.sessions) >= {g.name for g in good}
    assert "not-mcap" in report.failed and "MCAP" in report.failed["not-mcap"]
    assert "empty" in report.failed and "no MCAP parts" in report.failed["empty"]
    # the torn file is read up to the tear (with a warning in its card), or reported — never silently lost
    _, card = DatasetStore(tmp_path / "lab" / "datasets").load("mixed", report.version)
    if "truncated" in report.sessions:
        assert any("torn" in w or "tear" in w for w in card["sessions"]["truncated"]["warnings"])
    else:
        assert "truncated" in report.failed
    shutil.rmtree(bad)


@pytest.mark.slow
def test_trajectory_sessions_borrow_the_campaigns_registration(lab):
    """Experiment 2 sessions have no settled points: their dataset takes the tracker registration of the
    campaign of the same setup; its rows are the trajectory samples, in the base frame, by repetition."""
    from acquisition.plans import experiments
    from models import trajectories

    campaign = build(sorted((lab / "sessions").iterdir()), Lab(lab), "campaign")
    case = {
        "cases": [{"payload_g": 75, "pressure_bar": 0.5}],
        "commands": ["ik", "static"],
        "rigid_arm": False,
    }
    overrides = case | {"repetitions": 1, "points_per_segment": 25, "settle_s": 1.0, "rest_s": 0.5}
    simulate_experiment("experiment2", SessionStore(lab / "e2"), seed=3, overrides=overrides)
    sessions = sorted((lab / "e2").iterdir())
    with pytest.raises(ValueError, match=r"registration\.from_dataset"):
        build(sessions, Lab(lab), "experiment2")
    borrowed = {"registration": {"from_dataset": f"campaign@{campaign.version}"}}
    assert (
        build(sessions, Lab(lab), "experiment2", borrowed).version
        == build(sessions, Lab(lab), "experiment2", borrowed).version
    )
    report = build(sessions, Lab(lab), "experiment2", borrowed)
    d, card = DatasetStore(lab / "datasets").load("experiment2", report.version)
    assert card["parameters"]["registration"]["from_dataset"] == f"campaign@{campaign.version}"
    assert set(d["repetition"]) == {0} and set(d["session"]) == {s.name for s in sessions}
    path = trajectories.experiment1("curve", experiments.arm_lengths(load_robot("vsl")), 0.02, 400).x
    error = {s: trajectories.distance_to_path(g[["x_0", "x_1", "x_2"]].to_numpy(), path).mean()
             for s, g in d.groupby("session")}  # fmt: skip
    ik, static = (error[s.name] for s in sessions)
    assert static < 0.5 * ik and static < 2e-3  # the registered tip shows the compensation working


def _flip_a_byte(path) -> None:
    """Change one bit in the middle of ``path`` (inside a column's pages), as a failing disk would."""
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x10
    path.write_bytes(bytes(data))


@pytest.mark.slow
def test_a_damaged_cache_entry_is_made_again_and_a_damaged_dataset_is_refused(lab, caplog):
    """Every page of a cache entry's or a dataset's Parquet carries its CRC: a flipped bit is found on read.
    A session's damaged stages are made again from the session (saying so), giving the same rows; a damaged
    dataset is an error naming the check, never other numbers."""
    sessions = sorted((lab / "sessions").iterdir())
    first = build(sessions, Lab(lab), "campaign", {"splits": {"seed": 3}})
    entries = [p for p in (Lab(lab).cache.root / "session").iterdir() if (p / "record.json").is_file()]
    damaged = max(entries[0].glob("*.parquet"), key=lambda p: p.stat().st_size)
    _flip_a_byte(damaged)
    again = build(sessions, Lab(lab), "campaign", {"splits": {"seed": 4}})
    assert again.built and not again.failed
    assert any("cached stages cannot be read" in r.message and "making them again" in r.message
               for r in caplog.records)  # fmt: skip
    store = DatasetStore(lab / "datasets")
    d1, d2 = store.load("campaign", first.version)[0], store.load("campaign", again.version)[0]
    columns = [c for c in d1.columns if not c.startswith("split")]
    assert d1[columns].equals(d2[columns])  # the stages made again are the same numbers
    _flip_a_byte(store.path("campaign", again.version) / "data.parquet")
    with pytest.raises(OSError, match="checksum"):
        store.load("campaign", again.version)
