"""Plans run on the batched twin and written as sessions: files, rates, physics trends, events, commands,
skipping finished sessions, determinism and the pressure board's clock drift."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from acquisition.plans import experiments
from acquisition.plans.plan import PlanBuilder
from acquisition.recorder.sessions import SessionStore, list_sessions, session_info
from acquisition.schemas import topics as T
from acquisition.schemas.events import Event, EventKind
from acquisition.schemas.fast_read import read_events, read_fixed_topics
from models import trajectories
from models.robot import load_robot
from twin.runner import (
    SIM_EPOCH_NS,
    Simulation,
    session_id,
    simulate,
    simulate_experiment,
    simulate_side_by_side,
)
from twin.streams import tracker_spec
from twin.world import World

SEED = 1
BLOCK_S = 0.01  # simulate()'s default command block


def _part(directory: Path) -> Path:
    (part,) = sorted(directory.glob("*.mcap"))
    return part


def _events(directory: Path) -> list[tuple[int, Event]]:
    return read_events(_part(directory))


def _seconds(log_time: np.ndarray) -> np.ndarray:
    return (log_time.astype(np.int64) - SIM_EPOCH_NS) / 1e9


def _same_event(a: Event, b: Event) -> bool:
    same_value = (math.isnan(a.value) and math.isnan(b.value)) or a.value == b.value
    return (a.kind, a.index, a.label, a.text) == (b.kind, b.index, b.label, b.text) and same_value


@pytest.fixture(scope="module")
def e1(vsl, tmp_path_factory):
    """Experiment 1, curve only, 0 g and 100 g at 1 bar, one repetition: two ~21 s sessions."""
    params = experiments.load_experiment(
        "experiment1",
        trajectories=["curve"],
        payloads_g=[0, 100],
        pressures_bar=[1.0],
        repetitions=1,
        rigid_arm=False,
    )
    plans = experiments.experiment1(vsl, None, params)
    directory = tmp_path_factory.mktemp("sessions")
    report = simulate(plans, vsl, directory, seed=SEED)
    data = [read_fixed_topics(_part(directory / session_id(p))) for p in plans]
    events = [_events(directory / session_id(p)) for p in plans]
    path = trajectories.experiment1(
        "curve",
        experiments.arm_lengths(vsl),
        speed=params["speed_m_s"],
        n_per_segment=params["points_per_segment"],
    )
    return {
        "params": params,
        "plans": plans,
        "dir": directory,
        "report": report,
        "data": data,
        "events": events,
        "path": path,
    }


def _repetition_window(plan) -> tuple[float, float]:
    (start,) = [t for t, e in plan.events if e.kind == EventKind.REPETITION_START]
    (end,) = [t for t, e in plan.events if e.kind == EventKind.REPETITION_END]
    return start, end


# ------------------------------------------------------------------------------ sessions on disk
def test_sessions_are_written_complete(e1, vsl):
    plans, directory, report = e1["plans"], e1["dir"], e1["report"]
    ids = [session_id(p) for p in plans]
    assert ids == ["sim-experiment1-curve-vsl-1bar-0g", "sim-experiment1-curve-vsl-1bar-100g"]
    assert report.sessions == ids and report.skipped == []
    assert report.simulated_s == pytest.approx(sum(p.duration_s for p in plans))
    assert report.messages > 0 and report.speedup > 1
    infos = list_sessions(directory)
    assert [i.id for i in infos] == ids
    for info in infos:
        assert info.status == "complete"
        assert info.robot == vsl.name and info.experiment == "experiment1"
        assert info.torn == [] and len(info.parts) == 1
        assert info.streams[T.SERVO_STATE].messages > 0
    total = sum(s.messages for i in infos for s in i.streams.values())
    assert total == report.messages + 2 * len(plans)  # + SESSION_START/END of each session


def test_topic_rates(e1, vsl):
    for plan, data in zip(e1["plans"], e1["data"], strict=True):
        duration = plan.duration_s
        for topic, hz, tol in (
            (T.SERVO_STATE, 500.0, 0.03),
            (T.TRACKER, vsl.sensors.tracker.frame_rate_hz, 0.03),
            (T.PRESSURE, vsl.sensors.pressure.sample_rate_hz, 0.03),  # clock drift σ 2000 ppm
            (T.STEPPER, vsl.stepper.report_rate_hz, 0.03),
        ):
            d = data[topic]
            assert len(d) / duration == pytest.approx(hz, rel=tol), topic
            t = _seconds(d.log_time)
            assert (len(d) - 1) / (t[-1] - t[0]) == pytest.approx(hz, rel=0.01), topic
            assert t[0] >= 0.0 and t[0] < 2.0 / hz + 0.01, topic  # streams start with the session
        assert vsl.sensors.tracker.frame_rate_hz == 40.0
        info = session_info(e1["dir"] / session_id(plan))
        assert info.streams[T.SERVO_STATE].rate_hz == pytest.approx(500.0, rel=0.01)
        assert info.streams[T.TRACKER].rate_hz == pytest.approx(40.0, rel=0.01)
        assert info.streams[T.PRESSURE].rate_hz == pytest.approx(250.0, rel=0.02)


def test_tracker_follows_the_commanded_path(e1, vsl):
    transform = tracker_spec(vsl).base_to_tracker
    rot, trans = transform[:3, :3], transform[:3, 3]
    path_x = e1["path"].x
    for plan, data in zip(e1["plans"], e1["data"], strict=True):
        tracker = data[T.TRACKER]
        assert not tracker.rows["missing"].any()
        base = (tracker.rows["position"] - trans) @ rot  # back to the robot base frame
        t = _seconds(tracker.log_time)
        start, end = _repetition_window(plan)
        during = (t > start) & (t < end)
        assert during.sum() > 0.9 * (end - start) * 40
        dist = np.linalg.norm(base[during][:, None, :] - path_x[None], axis=-1).min(axis=1)
        assert dist.mean() < 8e-3, plan.name
        assert dist.max() < 15e-3, plan.name
        # it goes round the whole path, not just near its start
        nearest = np.linalg.norm(base[during][:, None, :] - path_x[None], axis=-1).argmin(axis=1)
        assert len(np.unique(nearest)) > 0.8 * len(path_x)
        # before the repetition it rests at the start point
        before = (t > 2.0) & (t < start)
        assert np.linalg.norm(base[before].mean(axis=0) - path_x[0]) < 10e-3


def test_payload_makes_the_arm_sag(e1, vsl):
    transform = tracker_spec(vsl).base_to_tracker
    rot, trans = transform[:3, :3], transform[:3, 3]
    z = {}
    for plan, data in zip(e1["plans"], e1["data"], strict=True):
        tracker = data[T.TRACKER]
        t = _seconds(tracker.log_time)
        start, end = _repetition_window(plan)
        z[round(plan.parameters["payload_kg"] * 1e3)] = ((tracker.rows["position"] - trans) @ rot)[
            (t > start) & (t < end), 2
        ].mean()
    assert z[100] < z[0] - 1e-3  # 100 g: the tip is lower on average (by millimetres)
    assert z[0] - z[100] < 20e-3


def test_pressure_readings_near_the_setpoint(e1):
    for plan, data in zip(e1["plans"], e1["data"], strict=True):
        pressure = data[T.PRESSURE]
        t = _seconds(pressure.log_time)
        settled = pressure.rows["pressure"][t > 1.0]
        setpoint = plan.pressure_pa[0]
        np.testing.assert_allclose(setpoint, 1e5)
        np.testing.assert_allclose(settled.mean(axis=0), setpoint, rtol=1e-3)
        assert np.all(np.abs(settled - setpoint) < 0.02 * setpoint)
        assert pressure.rows["valve_open"].all()
        command = data[T.PRESSURE_COMMAND]
        assert len(command) == len(plan.pressure_t)
        np.testing.assert_allclose(command.rows["setpoint"], plan.pressure_pa)
        np.testing.assert_array_equal(command.rows["valve_open"], plan.valve_open)


def test_events_in_the_file_are_the_plans(e1):
    for plan, events in zip(e1["plans"], e1["events"], strict=True):
        (t0, first), *middle, (t_end, last) = events
        assert first.kind == EventKind.SESSION_START and first.label == plan.name and t0 == SIM_EPOCH_NS
        assert last.kind == EventKind.SESSION_END and last.label == plan.name
        assert t_end == SIM_EPOCH_NS + round(plan.duration_s * 1e9)
        assert len(middle) == len(plan.events)
        for (log_time, got), (t, want) in zip(middle, plan.events, strict=True):
            assert _same_event(got, want), (got, want)
            assert log_time == SIM_EPOCH_NS + round(t * 1e9)
        kinds = [e.kind for _, e in middle]
        assert kinds == [
            EventKind.PAYLOAD,
            EventKind.SETTLED,
            EventKind.REPETITION_START,
            EventKind.REPETITION_END,
        ]


def test_servo_goal_topic_is_the_plans_servo_goals(e1, vsl):
    servo = [i for i, j in enumerate(vsl.joints) if j.drive != "stepper"]
    assert servo == [1, 2]
    for plan, data in zip(e1["plans"], e1["data"], strict=True):
        goal = data[T.SERVO_GOAL]
        assert len(goal) == len(plan.goal_t)
        np.testing.assert_array_equal(goal.rows["seq"], np.arange(len(plan.goal_t)))
        np.testing.assert_allclose(goal.rows["position"], plan.goal_q[:, servo])
        np.testing.assert_allclose(goal.rows["profile_velocity"], plan.goal_speed[:, servo])
        lag = _seconds(goal.log_time) - plan.goal_t  # applied at the next command block
        assert np.all(lag > -1e-9) and np.all(lag < BLOCK_S + 1e-6)


def test_servo_positions_track_the_goals(e1):
    for plan, data in zip(e1["plans"], e1["data"], strict=True):
        state = data[T.SERVO_STATE]
        t = _seconds(state.log_time)
        start, end = _repetition_window(plan)
        during = (t > start + 0.5) & (t < end - 0.5)
        commanded = plan.at(t[during])["goal_q"][:, 1:]
        assert np.abs(state.rows["position"][during] - commanded).max() < 0.1  # rad


def test_second_run_skips_complete_sessions(e1, vsl):
    directory = e1["dir"]
    before = {p: p.stat().st_mtime_ns for p in directory.rglob("*") if p.is_file()}
    report = simulate(e1["plans"], vsl, directory, seed=SEED)
    assert report.sessions == [] and report.messages == 0
    assert report.skipped == [session_id(p) for p in e1["plans"]]
    after = {p: p.stat().st_mtime_ns for p in directory.rglob("*") if p.is_file()}
    assert after == before


def test_pressure_board_clock_drifts(e1, vsl):
    sigma_ppm = vsl.devices["pressure_board"].clock.drift_ppm_sigma
    assert sigma_ppm == 2000.0
    # the drifts the runner's World drew (same robot, seed and benches, named by their sessions: same draws)
    benches = [session_id(p) for p in e1["plans"]]
    drawn = World(vsl, batch=len(benches), seed=SEED, benches=benches).clocks["pressure_board"].drift_ppm
    fitted = []
    for data in e1["data"]:
        pressure = data[T.PRESSURE]
        micros = np.unwrap(pressure.rows["micros"].astype(float), period=2.0**32)
        host_us = (pressure.log_time.astype(np.int64) - SIM_EPOCH_NS) / 1e3
        x = host_us - host_us.mean()
        slope, intercept = np.polyfit(x, micros, 1)
        resid = micros - (slope * x + intercept)
        stderr = np.sqrt(resid.var(ddof=2) / (x**2).sum())
        drift = slope - 1.0
        assert abs(drift) > 10 * stderr  # the board's clock runs off the host's, well beyond the jitter
        assert abs(drift) < 5 * sigma_ppm * 1e-6  # and by a plausible amount for σ = 2000 ppm
        fitted.append(drift * 1e6)
    np.testing.assert_allclose(fitted, drawn, atol=20.0)
    assert abs(fitted[0] - fitted[1]) > 50.0  # each bench has its own clock


def test_no_data_after_the_session_end(e1):
    for plan, data, events in zip(e1["plans"], e1["data"], e1["events"], strict=True):
        end_ns = events[-1][0]
        assert end_ns == SIM_EPOCH_NS + round(plan.duration_s * 1e9)
        last = max(int(d.log_time.max()) for d in data.values() if len(d))
        assert last <= end_ns + 20_000_000  # allow for the host link's latency (a few ms)


# ------------------------------------------------------------------------------ determinism
def _short_plans(robot, seconds: float = 1.5):
    plans = []
    for k, (q2, grams) in enumerate([(0.2, 0.0), (-0.2, 50.0)]):
        b = PlanBuilder(f"short/p{k}", robot.name, 3, robot.pneumatics.channels, {"experiment": "short"})
        b.goto([0.0, 0.3, -0.6]).pressure(1.2e5).payload(grams * 1e-3).wait(0.5)
        b.goto([0.1, 0.3 + q2, -0.5], speed=1.0).mark(EventKind.NOTE, text="moved").wait(seconds - 0.5)
        plans.append(b.build())
    return plans


def _read_all(directory: Path, plans) -> list[dict]:
    return [read_fixed_topics(_part(directory / session_id(p))) for p in plans]


def test_same_seed_gives_identical_sessions(vsl, tmp_path):
    plans = _short_plans(vsl)
    a = simulate(plans, vsl, tmp_path / "a", seed=5)
    b = simulate(plans, vsl, tmp_path / "b", seed=5)
    simulate(plans, vsl, tmp_path / "c", seed=6)
    assert a.messages == b.messages
    runs = [_read_all(tmp_path / name, plans) for name in "abc"]
    differs = False
    for sa, sb, sc in zip(*runs, strict=True):
        assert sa.keys() == sb.keys()
        for topic in sa:
            np.testing.assert_array_equal(sa[topic].log_time, sb[topic].log_time, err_msg=topic)
            np.testing.assert_array_equal(sa[topic].publish_time, sb[topic].publish_time, err_msg=topic)
            assert sa[topic].rows.tobytes() == sb[topic].rows.tobytes(), topic
        tracker_a, tracker_c = sa[T.TRACKER].rows["position"], sc[T.TRACKER].rows["position"]
        differs |= tracker_a.shape != tracker_c.shape or not np.array_equal(tracker_a, tracker_c)
        differs |= not np.array_equal(sa[T.PRESSURE].log_time, sc[T.PRESSURE].log_time)
    assert differs  # another seed: other noise and clocks
    for p in plans:
        events_a = _events(tmp_path / "a" / session_id(p))
        events_b = _events(tmp_path / "b" / session_id(p))
        assert [t for t, _ in events_a] == [t for t, _ in events_b]
        assert all(_same_event(x, y) for (_, x), (_, y) in zip(events_a, events_b, strict=True))


def test_a_plans_session_is_the_same_in_any_batch(vsl, tmp_path):
    """Each bench draws its clocks and noise from generators of its own (its session's name spawned from the
    seed): a plan simulated alone, in a batch with longer and shorter plans, or in another order writes the
    same bytes, so an experiment may be split over batches and processes without changing its data."""
    plans = []
    for k, seconds in enumerate((1.5, 2.7, 0.9)):
        b = PlanBuilder(f"batched/p{k}", vsl.name, 3, vsl.pneumatics.channels, {"experiment": "batched"})
        b.goto([0.0, 0.3, -0.6]).pressure(1.2e5).payload(0.02 * k).wait(0.4)
        b.goto([0.1, 0.1 * k, -0.5], speed=1.0).wait(seconds - 0.4)
        plans.append(b.build())
    simulate(plans, vsl, tmp_path / "batch", seed=5)
    simulate(plans[1:2], vsl, tmp_path / "alone", seed=5)
    simulate([plans[2], plans[0]], vsl, tmp_path / "reordered", seed=5)
    for where, plan in (("alone", plans[1]), ("reordered", plans[0]), ("reordered", plans[2])):
        a, b = (sorted((tmp_path / n / session_id(plan)).iterdir()) for n in ("batch", where))
        assert [f.name for f in a] == [f.name for f in b] and len(a) >= 2
        assert [f.read_bytes() for f in a] == [f.read_bytes() for f in b], (where, session_id(plan))


def test_incomplete_session_is_simulated_again(vsl, tmp_path):
    plans = _short_plans(vsl, seconds=1.0)
    stale = tmp_path / session_id(plans[0])
    stale.mkdir()
    (stale / "junk_000.mcap").write_bytes(b"torn")
    report = simulate(plans, vsl, tmp_path, seed=0)
    assert report.sessions == [session_id(p) for p in plans]
    assert not (stale / "junk_000.mcap").exists()
    assert session_info(stale).status == "complete" and session_info(stale).torn == []


def test_batch_of_other_robots_plans_raises(vsl, tmp_path):
    rigid = load_robot("vsl_rigid")
    with pytest.raises(ValueError, match="every plan of a batch"):
        simulate(_short_plans(rigid), vsl, tmp_path)


# ------------------------------------------------------------------------------ simulate_experiment
def test_simulate_protocol_runs_both_arms(tmp_path):
    overrides = {
        "trajectories": ["linear"],
        "payloads_g": [25],
        "pressures_bar": [2.0],
        "repetitions": 1,
        "rigid_arm": True,
        "points_per_segment": 10,
        "settle_s": 0.5,
        "rest_s": 0.2,
    }
    reports = simulate_experiment("experiment1", SessionStore(tmp_path), seed=3, overrides=overrides)
    assert len(reports) == 2  # one batch per robot
    infos = {i.id: i for i in list_sessions(tmp_path)}
    assert set(infos) == {"sim-experiment1-linear-vsl-2bar-25g", "sim-experiment1-linear-vsl_rigid-25g"}
    assert infos["sim-experiment1-linear-vsl-2bar-25g"].robot == "vsl"
    assert infos["sim-experiment1-linear-vsl_rigid-25g"].robot == "vsl_rigid"
    assert all(i.status == "complete" for i in infos.values())
    again = simulate_experiment("experiment1", SessionStore(tmp_path), seed=3, overrides=overrides)
    assert all(r.sessions == [] for r in again) and sum(len(r.skipped) for r in again) == 2


def test_simulate_protocol_unknown_kind(tmp_path):
    path = tmp_path / "other.yaml"
    path.write_text("robot: vsl\n")
    with pytest.raises(ValueError, match="no plans for experiment"):
        simulate_experiment(str(path), SessionStore(tmp_path / "sessions"))
    with pytest.raises(FileNotFoundError, match="known: campaign, experiment1"):
        simulate_experiment("nonesuch", SessionStore(tmp_path / "sessions"))


def test_simulate_protocol_campaign(tmp_path):
    overrides = {"points": 6, "settle_s": 0.3, "hold_s": 0.2}
    (report,) = simulate_experiment(
        "campaign", SessionStore(tmp_path), seed=4, benches=2, overrides=overrides
    )
    assert report.sessions == ["sim-campaign-bench000", "sim-campaign-bench001"]
    settled = []
    for sid in report.sessions:
        settled += [e.index for _, e in _events(tmp_path / sid) if e.kind == EventKind.SETTLED]
    assert sorted(settled) == list(range(6))


@pytest.mark.slow
def test_campaign_runs_to_the_end_within_the_safety_limits(tmp_path):
    """Every random point of the campaign (commanded targets down to 20 mm, links sagging below them) stays
    inside the robot's limits: no bench is stopped, all the bench-seconds are simulated."""
    overrides = {"points": 240}
    (report,) = simulate_experiment(
        "campaign", SessionStore(tmp_path), seed=5, benches=8, overrides=overrides
    )
    plans = experiments.campaign(
        load_robot("vsl"), experiments.load_experiment("campaign", **overrides), 8, seed=5
    )
    assert report.simulated_s == pytest.approx(sum(p.duration_s for p in plans))
    for sid in report.sessions:
        assert not [e for _, e in _events(tmp_path / sid) if e.kind == EventKind.SAFETY_STOP]


def test_same_seed_gives_the_same_bytes_however_fast_the_machine_ran(vsl, tmp_path, monkeypatch):
    """A dataset's version is a hash of its sessions' bytes, so the writer's chunks must not depend on
    wall time (under load the runs flushed at other points, and the same campaign gave another version)."""
    from twin import session_writers as sim_runner

    writers = []

    class Spy(sim_runner.SessionWriter):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            writers.append(self)

    monkeypatch.setattr(sim_runner, "SessionWriter", Spy)
    plans = _short_plans(vsl)
    simulate(plans, vsl, tmp_path / "a", seed=5)
    end = max(p.duration_s for p in plans)
    window_s = 1.0  # the runner's default: the clock stops at the end of the window holding the plan's end
    clocks = [w.clock() for w in writers]
    assert clocks and all(end - 0.02 <= c <= end + window_s for c in clocks), clocks  # simulated seconds
    simulate(plans, vsl, tmp_path / "b", seed=5)
    for p in plans:  # every file, the MCAP parts and session.json, byte for byte
        a, b = (sorted((tmp_path / n / session_id(p)).iterdir()) for n in "ab")
        assert [f.name for f in a] == [f.name for f in b] and len(a) >= 2
        assert [f.read_bytes() for f in a] == [f.read_bytes() for f in b], session_id(p)


def test_writes_gathered_over_seconds_are_the_same_messages(vsl, tmp_path):
    """The runner gathers ``write_s`` of a session's rows before it writes them (fewer, larger writes):
    every topic, the standard ones included (/tf holds the stepper's angle from reports that may come in a
    later write), has the same messages as when each window is written at once."""
    from mcap.reader import make_reader

    def messages(directory: Path) -> dict[str, list[tuple[int, int, bytes]]]:
        with open(_part(directory), "rb") as f:
            out: dict[str, list] = {}
            for _, channel, m in make_reader(f).iter_messages(log_time_order=False):
                out.setdefault(channel.topic, []).append((m.log_time, m.sequence, m.data))
        return {topic: sorted(ms) for topic, ms in out.items()}

    plans = _short_plans(vsl, seconds=24.5)  # a write holds more stepper reports than a live view keeps
    simulate(plans, vsl, tmp_path / "window", seed=3, write_s=1.0)
    simulate(plans, vsl, tmp_path / "gathered", seed=3, write_s=12.0)
    for p in plans:
        each, gathered = (messages(tmp_path / n / session_id(p)) for n in ("window", "gathered"))
        assert {"/tf", "/joint_states", T.SERVO_STATE, T.TRACKER} <= each.keys()
        assert len(each["/tf"]) > 1200  # 50 Hz over the plan
        assert gathered == each


def test_an_interrupted_batch_leaves_no_session_complete(vsl, tmp_path):
    """A run stopped part-way (Ctrl-C, a failed write) closes its sessions readable but not complete, so the
    next run simulates them again instead of taking a cut-short session for the plan's."""
    from acquisition.recorder.sessions import read_card

    plans = _short_plans(vsl, seconds=3.5)

    def stop(fraction: float) -> None:
        if fraction < 1.0:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        simulate(plans, vsl, tmp_path, seed=2, progress=stop)
    for p in plans:
        card = read_card(tmp_path / session_id(p))
        assert card["status"] == "interrupted"
        assert session_info(tmp_path / session_id(p)).torn == []  # its part is whole, as far as it went
    again = simulate(plans, vsl, tmp_path, seed=2)
    assert again.sessions == [session_id(p) for p in plans] and again.skipped == []
    assert all(read_card(tmp_path / session_id(p))["status"] == "complete" for p in plans)


def test_experiments_side_by_side_write_what_one_after_another_writes(tmp_path):
    """Two experiments simulated at once in two worker processes (each kernel on one thread) write every
    session byte for byte as one experiment after the other in this process (two kernel threads) does."""
    runs = [("campaign", {"points": 24}), ("popup_impact", {"pressures_kpa": [10, 50], "taps": 1})]
    for name, overrides in runs:
        simulate_experiment(name, SessionStore(tmp_path / "a"), seed=3, overrides=overrides)
    store = SessionStore(tmp_path / "b")
    reports = simulate_side_by_side([Simulation(name, store, overrides) for name, overrides in runs], seed=3)
    written = sorted(s for r in reports for batch in r for s in batch.sessions)
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert written == names and len(names) >= 3
    for name in names:  # every file, the MCAP parts and session.json
        a, b = (sorted((tmp_path / store_name / name).iterdir()) for store_name in "ab")
        assert [f.name for f in a] == [f.name for f in b] and len(a) >= 2
        assert [f.read_bytes() for f in a] == [f.read_bytes() for f in b], name


def test_an_experiment_spread_over_processes_writes_what_one_process_writes(tmp_path, monkeypatch):
    """``processes=2``: the batch's plans cut in two parts, each in a worker process, write every session
    byte for byte as the whole batch in this process does; a second run finds them complete."""
    from twin import runner

    monkeypatch.setattr(runner, "PART_MIN_S", 1.0)  # this small campaign is cut too (it is not, otherwise)
    simulate_experiment("campaign", SessionStore(tmp_path / "a"), seed=3, overrides={"points": 24})
    reports = simulate_experiment("campaign", SessionStore(tmp_path / "b"), seed=3, overrides={"points": 24},
                                  processes=2)  # fmt: skip
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert len(reports) == 2 and sorted(s for r in reports for s in r.sessions) == names and len(names) >= 2
    for name in names:  # every file, the MCAP parts and session.json
        a, b = (sorted((tmp_path / store_name / name).iterdir()) for store_name in "ab")
        assert [f.name for f in a] == [f.name for f in b] and len(a) >= 2
        assert [f.read_bytes() for f in a] == [f.read_bytes() for f in b], name
    again = simulate_experiment("campaign", SessionStore(tmp_path / "b"), seed=3, overrides={"points": 24},
                                processes=2)  # fmt: skip
    assert sorted(s for r in again for s in r.skipped) == names and not any(r.sessions for r in again)


def test_an_unknown_experiment_side_by_side_is_refused_before_any_is_simulated(tmp_path):
    runs = [
        Simulation("popup_deploy", SessionStore(tmp_path / "a")),
        Simulation("no_such_experiment", SessionStore(tmp_path / "b")),
    ]
    with pytest.raises(FileNotFoundError, match="no experiment 'no_such_experiment'"):
        simulate_side_by_side(runs)
    assert not list(tmp_path.glob("*/*/session.json"))


def test_experiments_side_by_side_already_simulated_start_no_worker(tmp_path, monkeypatch):
    """A second run (every session complete) checks them here, as simulate_experiment does, and starts no
    process; the sessions stay as they were."""
    import concurrent.futures as cf

    store = SessionStore(tmp_path / "s")
    runs = [
        Simulation("popup_deploy", store),
        Simulation("popup_impact", store, {"pressures_kpa": [10], "taps": 1}),
    ]
    first = simulate_side_by_side(runs)
    cards = {p: p.read_bytes() for p in (tmp_path / "s").glob("*/session.json")}

    def no_pool(*args, **kwargs):
        raise AssertionError("a worker was started for sessions already complete")

    monkeypatch.setattr(cf, "ProcessPoolExecutor", no_pool)
    again = simulate_side_by_side(runs)
    assert [s for r in first for b in r for s in b.sessions] == [
        s for r in again for b in r for s in b.skipped
    ]
    assert {p: p.read_bytes() for p in (tmp_path / "s").glob("*/session.json")} == cards and len(cards) == 2


def test_plans_whose_sessions_are_complete_are_not_checked_against_the_limits_again(tmp_path, monkeypatch):
    """A second run's check is the sessions' identity, not the limits again (~7 s of a second main job)."""
    from acquisition.safety import SafetyChecker
    from twin.runner import prepare_experiment

    overrides = {"pressures_kpa": [10, 50], "taps": 1}
    simulate_experiment("popup_impact", SessionStore(tmp_path / "s"), overrides=overrides)
    checked = []
    monkeypatch.setattr(SafetyChecker, "require_safe", lambda self, plan: checked.append(plan.name))
    _, plans, _ = prepare_experiment("popup_impact", overrides, sessions_dir=tmp_path / "s")
    assert len(plans) == 2 and checked == []
    (tmp_path / "s" / session_id(plans[1]) / "session.json").unlink()  # as an interrupted one: run again
    prepare_experiment("popup_impact", overrides, sessions_dir=tmp_path / "s")
    assert checked == [plans[1].name]
    prepare_experiment("popup_impact", overrides)  # no sessions named: every plan, as `vslab simulate` does
    assert checked == [plans[1].name, *(p.name for p in plans)]
