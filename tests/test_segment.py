"""pipeline.segment: static points from SETTLED windows, stillness checks, repetition labels."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from twin_timeline import sessions, timeline

from acquisition.plans.experiments import expand_experiment
from acquisition.schemas.events import EventKind
from pipeline.segment import Stillness, repetition_table, repetitions, static_points
from pipeline.tables import EVENT_COLUMNS, StageReport, columns
from twin.runner import SIM_EPOCH_NS, session_id, simulate

N_POINTS, BENCHES, SEED = 120, 12, 7


def _events(rows: list[tuple[float, EventKind, int, float, str]], t0_ns: int = 0) -> pd.DataFrame:
    data = [(t0_ns + round(t * 1e9), int(k), i, v, label, "") for t, k, i, v, label in rows]
    return pd.DataFrame(data, columns=list(EVENT_COLUMNS))


def _noise_free(robot):
    tracker = robot.sensors.tracker.model_copy(update={"noise_m": 0.0})
    return robot.model_copy(update={"sensors": robot.sensors.model_copy(update={"tracker": tracker})})


@pytest.fixture(scope="module")
def twin_pair(tmp_path_factory):
    """The same campaign run twice on the twin with the same seed: as recorded, and with a noise-free
    tracker. The sensor model draws the tracker noise even at σ = 0, so every other reading (clocks, host
    times, servo and pressure noise) is the same in both; the noise-free run's tracker is the true tip."""
    root = tmp_path_factory.mktemp("segment")
    robots, plans, params = expand_experiment("campaign", {"points": N_POINTS}, benches=BENCHES, seed=SEED)
    robot = robots[params["robot"]]
    simulate(plans, robot, root / "noisy", seed=SEED)
    simulate(plans, _noise_free(robot), root / "true", seed=SEED)
    return plans, params, root, robot


@pytest.mark.slow
def test_static_points_average_to_the_true_tip(twin_pair):
    """Each averaged tip lies within 4 σ/√n of the true tip, where the truth is the mean of the noise-free
    tracker over the plan's own hold window (plan time, not the events or this module's windowing): a wrong
    window, a point mixed with motion or a bad average would show. The payload is the plan's at that time."""
    plans, params, root, robot = twin_pair
    sigma = robot.sensors.tracker.noise_m
    noisy = {s.session_id: s for s in sessions(root / "noisy")}
    true = {s.session_id: s for s in sessions(root / "true")}
    z, total = [], 0
    for plan in plans:
        s = noisy[session_id(plan)]
        points = static_points(timeline(s), s.events, s.t0_ns)
        assert points.attrs["rejected"] == {}
        settled = [(t, e.index, e.value) for t, e in plan.events if e.kind == EventKind.SETTLED]
        assert points["point"].tolist() == [i for _, i, _ in settled]
        pd.testing.assert_frame_equal(s.streams["/servo/state"], true[s.session_id].streams["/servo/state"])
        pose = true[s.session_id].streams["/tracker/pose"]
        t_true = (pose["log_time"].to_numpy(np.int64) - SIM_EPOCH_NS) * 1e-9
        true_pos = columns(pose, "position")
        for row, (t, _, hold) in zip(points.itertuples(), settled, strict=True):
            sel = (t_true >= t) & (t_true < t + hold)
            truth = np.nanmean(true_pos[sel], axis=0)
            est = np.array([row.tracker_position_0, row.tracker_position_1, row.tracker_position_2])
            z.append((est - truth) / (sigma / np.sqrt(row.n_samples)))
            assert row.payload_kg == pytest.approx(plan.at(np.array([t]))["payload_kg"][0])
        assert np.all(points["n_samples"] >= params["hold_s"] * robot.sensors.tracker.frame_rate_hz - 2)
        total += len(points)
    z = np.asarray(z)
    assert total == N_POINTS
    assert np.abs(z).max() < 4.0
    assert 0.8 < np.sqrt(np.mean(z**2)) < 1.2  # the window's noise is averaged, not more, not less


def test_unsettled_windows_are_rejected_and_counted(tmp_path):
    """Too short a settle time: windows that start while the arm moves are left out, counted by reason."""
    fast = {"points": 40, "settle_s": 0.1, "move_speed_rad_s": 20.0}  # plans a move faster than the servos go
    robots, plans, params = expand_experiment("campaign", fast, benches=4, seed=3)
    simulate(plans, robots[params["robot"]], tmp_path, seed=3)
    kept, rejected, report = 0, 0, StageReport()
    for s in sessions(tmp_path):
        points = static_points(timeline(s), s.events, s.t0_ns, report=report)
        kept += len(points)
        rejected += sum(points.attrs["rejected"].values())
        assert set(points.attrs["rejected_points"]).isdisjoint(points["point"])
    assert kept + rejected == 40
    assert rejected > 10
    assert report.removed_total() == rejected
    assert set(report.removed["static_points"]) <= {"joint motion", "tip motion", "pressure change"}


def test_stillness_reasons_on_a_synthetic_timeline():
    t = np.arange(0, 3, 0.025)
    tip = np.zeros((len(t), 3))
    tip[(t >= 1) & (t < 1.5), 0] = 0.01 * (t[(t >= 1) & (t < 1.5)] - 1)  # 5 mm drift in window 1
    tip[(t >= 2) & (t < 2.45)] = np.nan  # window 2: only 2 tracker frames
    tl = pd.DataFrame({"t": t, **{f"tracker_position_{k}": tip[:, k] for k in range(3)},
                       "servo_position_0": 0.5, "pressure_0": 1e5})  # fmt: skip
    settled = [(t, EventKind.SETTLED, i, 0.5, "") for i, t in enumerate((0.2, 1.0, 2.0))]
    ev = _events([(0.0, EventKind.PAYLOAD, -1, 0.05, ""), *settled], 10**9)
    points = static_points(tl, ev, 10**9, Stillness(min_samples=5))
    assert points["point"].tolist() == [0]
    assert points.attrs["rejected_points"] == {1: "tip motion", 2: "too few tracker samples"}
    assert points.loc[0, "n_samples"] == 20 and points.loc[0, "payload_kg"] == 0.05
    assert points.loc[0, "servo_position_0"] == 0.5 and points.loc[0, "t"] == pytest.approx(0.4375)


def test_repetitions_label_rows_inside_complete_repetitions():
    t = np.arange(0, 10, 0.5)
    ev = _events([(1.0, EventKind.REPETITION_START, 0, np.nan, "curve"),
                  (3.0, EventKind.REPETITION_END, 0, np.nan, "curve"),
                  (5.0, EventKind.REPETITION_START, 1, np.nan, "curve"),
                  (6.0, EventKind.REPETITION_END, 1, np.nan, "curve"),
                  (8.0, EventKind.REPETITION_START, 2, np.nan, "curve")], 5)  # fmt: skip
    tl = pd.DataFrame({"t": t}, index=np.arange(100, 100 + len(t)))
    labels = repetitions(tl, ev, 5)
    expected = np.where((t >= 1) & (t <= 3), 0, np.where((t >= 5) & (t <= 6), 1, -1))
    assert labels.tolist() == expected.tolist() and labels.index.equals(tl.index)
    table = repetition_table(ev, 5)
    assert table["repetition"].tolist() == [0, 1] and set(table["label"]) == {"curve"}


def test_move_windows_run_from_each_goal_to_its_settled_window():
    """The rows of each move: from the last goal before a SETTLED window (and after the window before) to
    that window's start, tagged with the point, the goal's time and the payload hung then; a hold without a
    goal since the last window has none."""
    from pipeline.segment import move_windows

    t = np.arange(0.0, 10.0, 0.025)  # a 40 Hz timeline
    line = pd.DataFrame({"t": t, "tracker_position_0": np.sin(t)})
    events = _events([
        (0.5, EventKind.PAYLOAD, 0, 0.025, ""),
        (2.0, EventKind.SETTLED, 4, 0.5, ""),  # point 4: its goal at 1.0
        (4.0, EventKind.PAYLOAD, 0, 0.05, ""),
        (5.0, EventKind.SETTLED, 9, 0.5, ""),  # point 9: goals at 3.0 and 4.5, the last counts
        (8.0, EventKind.SETTLED, 2, 0.5, ""),  # point 2: no goal since 5.5, a hold without a move
    ])  # fmt: skip
    moves = move_windows(line, events, 0, np.array([1.0, 3.0, 4.5]))
    assert sorted(set(moves["point"])) == [4, 9]
    four, nine = moves[moves["point"] == 4], moves[moves["point"] == 9]
    assert four["t"].min() >= 1.0 and four["t"].max() < 2.0 and len(four) == 40
    assert (four["t_command"] == 1.0).all() and (four["payload_kg"] == 0.025).all()
    assert nine["t"].min() >= 4.5 and nine["t"].max() < 5.0 and (nine["t_command"] == 4.5).all()
    assert (nine["payload_kg"] == 0.05).all()
    assert move_windows(line, events, 0, np.array([])).empty  # no goals recorded: no moves
