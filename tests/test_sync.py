"""The sync stage on twin sessions: clock fits against the twin's true clocks, counter resets, and the
tracker-frame timeline against a noise-free twin run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from mcap.reader import make_reader

from acquisition.devices.kinds import stamp_fields
from acquisition.plans.plan import PlanBuilder
from acquisition.schemas import topics as T
from acquisition.schemas.fast_read import read_fixed_topics
from pipeline.clock import ClockFitter, unwrap_stamps
from pipeline.sync import interpolate, sync
from pipeline.tables import EVENT_COLUMNS, SessionTables
from twin.clocks import unwrap_ticks
from twin.runner import TWIN_TRUTH, session_id, simulate

SEED = 46  # the benches of _plans, seed 46: stepper boards at ≈ +3175, +4690 ppm, a pressure board −2150
SECONDS = 60.0
DEVICES = {T.SERVO_STATE: "servo_bus", T.PRESSURE: "pressure_board", T.STEPPER: "stepper_board",
           T.TRACKER: "tracker"}  # fmt: skip


def _plans(robot, seconds: float = SECONDS):
    """Two benches: pressure steps and slow joint moves, so the streams change while the clocks run."""
    plans = []
    for k, sign in enumerate((1.0, -1.0)):
        b = PlanBuilder(f"sync/p{k}", robot.name, 3, robot.pneumatics.channels, {"experiment": "sync"})
        b.goto([0.0, 0.3, -0.6]).pressure(1.0e5).payload(0.0).wait(2.0)
        b.goto([0.3 * sign, 0.5, -0.3], speed=0.5).pressure(1.5e5).wait(seconds / 2)
        b.goto([-0.2 * sign, 0.1, -0.8], speed=0.5).pressure(0.8e5).wait(seconds / 2 - 2.0)
        plans.append(b.build())
    return plans


def _table(data) -> pd.DataFrame:
    """A topic as the pipeline's stream table: log/publish time, fields flattened to ``<field>_<i>``."""
    cols = {"log_time": data.log_time.astype(np.int64), "publish_time": data.publish_time.astype(np.int64)}
    for name in data.rows.dtype.names:
        if name.startswith("_"):
            continue
        x = data.rows[name]
        cols.update({name: x} if x.ndim == 1 else {f"{name}_{i}": x[:, i] for i in range(x.shape[1])})
    return pd.DataFrame(cols)


def _load(directory: Path, plan, robot) -> tuple[SessionTables, dict]:
    (part,) = sorted((directory / session_id(plan)).glob("*.mcap"))
    with open(part, "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}["vslab.session"]
    streams = {topic: _table(d) for topic, d in read_fixed_topics(part).items() if len(d)}
    events = pd.DataFrame({c: [] for c in EVENT_COLUMNS})
    session = SessionTables(session_id(plan), robot, {}, streams, events)
    return session, json.loads(meta[TWIN_TRUTH])


@pytest.fixture(scope="module")
def synced(vsl, tmp_path_factory):
    directory = tmp_path_factory.mktemp("sync")
    plans = _plans(vsl)
    simulate(plans, vsl, directory, seed=SEED)
    return [(*sync(session), truth, session) for session, truth in (_load(directory, p, vsl) for p in plans)]


def _true_offset(clock: dict, ref_ns: int, epoch_ns: int) -> float:
    """The twin's device clock (s) at host time ``ref_ns``: (1 + ε)·t + b with t = ref − epoch."""
    return (1.0 + clock["drift_ppm"] * 1e-6) * (ref_ns - epoch_ns) * 1e-9 + clock["offset_s"]


def _true_times(raw: np.ndarray, host_ns: np.ndarray, clock: dict, epoch_ns: int) -> np.ndarray:
    """True sampling times (s since the twin's epoch) of wrapped stamps: t = (t_dev − b)/(1 + ε), the wrap
    count chosen to land closest to the host's receive time minus latency (stamps floor: ≤ 1 tick early)."""
    rate = 1.0 + clock["drift_ppm"] * 1e-6
    t = (raw.astype(np.int64) * clock["tick_s"] - clock["offset_s"]) / rate
    turn = clock["wrap"] * clock["tick_s"] / rate
    seen = (host_ns.astype(np.int64) - epoch_ns) * 1e-9 - clock["latency_s"]
    return t + np.round((seen - t) / turn) * turn


def _time_tolerance(clock: dict, field: str) -> float:
    """How far a fitted sampling time may be from :func:`_true_times`: 0.1 ms, plus for a floored counter
    read at any instant (servo tick, micros) 1.5 ticks: the sample lies somewhere in its tick (the fit puts it
    mid-tick) and a slowly walking phase can hide the tick's start from the envelope."""
    return 1e-4 + (0.0 if field == "frame" else 1.5 * clock["tick_s"])


def test_clock_fits_match_the_twin(synced):
    """Every device, both benches: drift within 20 ppm and offset (device s at the session's t0) within 1 ms
    of the twin's; among them ceramic resonators with |ε| ≥ 1500 ppm."""
    big = 0
    for out, _, truth, session in synced:
        epoch = truth["host_epoch_ns"]
        for topic, device in DEVICES.items():
            fit, clock = out.report.values[f"clock/{device}"], truth["clocks"][device]
            assert fit["resets"] == 0 and fit["n"] == len(session.streams[topic])
            assert abs(fit["drift_ppm"] - clock["drift_ppm"]) < 20.0, device
            period = clock["wrap"] * clock["tick_s"]  # the unwrapped counter starts from a wrapped reading
            error = (fit["offset_s"] - _true_offset(clock, session.t0_ns, epoch) + period / 2) % period
            assert abs(error - period / 2) < 1e-3, device
            assert fit["jitter_p95_s"] <= clock["jitter_s"] + clock["tick_s"] + 1e-4
            big += abs(clock["drift_ppm"]) >= 1500.0
    assert big >= 2


def test_fitted_sample_times_are_the_true_ones(synced):
    """Each stream's ``t`` is its samples' true sampling time (see :func:`_time_tolerance`), increasing."""
    for out, _, truth, session in synced:
        for topic, device in DEVICES.items():
            df, clock = out.streams[topic], truth["clocks"][device]
            stamp = stamp_fields(session.robot)[topic][1]
            true_t = _true_times(df[stamp].to_numpy(), df["log_time"].to_numpy(), clock,
                                 truth["host_epoch_ns"])  # fmt: skip
            got = df["t"].to_numpy() + (session.t0_ns - truth["host_epoch_ns"]) * 1e-9
            assert np.abs(got - true_t).max() < _time_tolerance(clock, stamp), device
            assert np.all(np.diff(df["t"].to_numpy()) > 0), device


@pytest.mark.parametrize("device", ["pressure_board", "servo_bus"])
def test_counter_reset_mid_session_is_split_and_fitted(synced, device):
    """The board reboots halfway: its counter restarts at 0. micros() steps back (not a wrap); the servo tick,
    unwrapped the naive way (``unwrap_ticks``), reads the reset as a wrap forward. Both are found (device
    steps the host does not see), and both segments map onto the true sampling times."""
    out, _, truth, session = synced[0]
    topic = next(t for t, d in DEVICES.items() if d == device)
    clock, df = truth["clocks"][device], session.streams[topic]
    field = stamp_fields(session.robot)[topic][1]
    raw, host = df[field].to_numpy().astype(np.int64), df["log_time"].to_numpy()
    true_t = _true_times(raw, host, clock, truth["host_epoch_ns"])
    half = len(raw) // 2
    after = unwrap_stamps(raw, host, clock["tick_s"], clock["wrap"])[half:]
    raw[half:] = (after - after[0] + 1234) % clock["wrap"]  # boot, then the first sample 1234 ticks in
    ticks = unwrap_ticks(raw, clock["wrap"])
    fit = ClockFitter(clock["tick_s"], clock["latency_s"], ref_ns=session.t0_ns).fit(ticks, host).clock_
    assert fit.resets == 1 and fit.segments[1].start == half
    for segment in fit.segments:
        assert abs(segment.drift_ppm - clock["drift_ppm"]) < 20.0
    got = (fit.to_host_ns(ticks, fit.labels()) - truth["host_epoch_ns"]) * 1e-9
    assert np.abs(got - true_t).max() < _time_tolerance(clock, field)
    assert out.report.values[f"clock/{device}"]["resets"] == 0  # the untouched session had none


def test_interpolate_leaves_gaps_and_edges_empty():
    t = np.array([0.0, 1.0, 2.0, 10.0, 11.0])
    values = np.column_stack([10 * t, -t])
    got = interpolate(t, values, np.array([-0.5, 0.5, 2.0, 5.0, 10.5, 11.0, 12.0]), max_gap_s=3.0)
    np.testing.assert_allclose(got[:, 0], [np.nan, 5.0, 20.0, np.nan, 105.0, 110.0, np.nan])
    np.testing.assert_allclose(got[:, 1], -got[:, 0] / 10)


def _quiet(robot):
    """The same robot with (almost) noise-free pressure and current readings. The noise draws still happen
    (σ > 0), so the twin's random stream, hence clocks, jitter and tracker noise, stays the same."""
    sensors = robot.sensors
    return robot.model_copy(update={"sensors": sensors.model_copy(update={
        "servo": sensors.servo.model_copy(update={"current_noise_counts": 1e-9}),
        "pressure": sensors.pressure.model_copy(update={"adc_noise_v": 1e-12})})})  # fmt: skip


def test_timeline_matches_noise_free_truth_within_sensor_noise(synced, vsl, tmp_path):
    """Resampled pressure and servo current at the tracker frames vs the twin's truth: the same plan and seed
    run again with noise-free sensors (only quantisation left), its samples placed at their *true* times
    (twin clocks) and interpolated at the frames' *true* times. What differs is the sensor noise (and any
    timing error of the fit, which would show on the pressure steps): the RMS difference stays below the
    per-sample noise σ (measured on the raw streams), and no frame is off by more than the worst sample's
    noise and what one tick of the device's stamp is worth where the truth moves (a servo sample is placed
    within its 1 ms tick: on a current step of 0.47 A in 2 ms that is up to ~0.2 A)."""
    quiet = _quiet(vsl)
    plans = _plans(vsl)
    simulate(plans, quiet, tmp_path, seed=SEED)
    for (out, timeline, truth, _), plan in zip(synced, plans, strict=True):
        clean, _ = _load(tmp_path, plan, quiet)
        epoch, clocks = truth["host_epoch_ns"], truth["clocks"]
        tracker = clean.streams[T.TRACKER]
        frame_t = _true_times(tracker["frame"].to_numpy(), tracker["log_time"].to_numpy(), clocks["tracker"],
                              epoch)  # fmt: skip
        assert len(timeline) == len(tracker)
        inside = np.isfinite(timeline["pressure_0"].to_numpy())
        assert inside.mean() > 0.99
        for topic, field in ((T.PRESSURE, "pressure"), (T.SERVO_STATE, "current")):
            noisy, ref = out.streams[topic], clean.streams[topic]
            np.testing.assert_array_equal(noisy["log_time"], ref["log_time"])  # same draws, same instants
            stamp = stamp_fields(vsl)[topic][1]
            sample_t = _true_times(ref[stamp].to_numpy(), ref["log_time"].to_numpy(), clocks[DEVICES[topic]],
                                   epoch)  # fmt: skip
            for col in (c for c in timeline.columns if c.endswith(field + "_0") or c.endswith(field + "_1")):
                name = col.removeprefix("servo_")
                sigma = np.std(noisy[name].to_numpy() - ref[name].to_numpy())
                truth_at_frames = np.interp(frame_t, sample_t, ref[name].to_numpy())
                diff = (timeline[col].to_numpy() - truth_at_frames)[inside]
                worst = np.abs(noisy[name].to_numpy() - ref[name].to_numpy()).max()
                rate = np.abs(np.diff(ref[name].to_numpy()) / np.diff(sample_t))  # per sample interval
                k = np.searchsorted(sample_t, frame_t) - 1  # the interval holding each frame
                steep = np.max([rate[np.clip(k + d, 0, len(rate) - 1)] for d in (-1, 0, 1)], axis=0)[inside]
                tick_s = clocks[DEVICES[topic]]["tick_s"]
                assert np.sqrt(np.mean(diff**2)) < sigma, col
                assert np.all(np.abs(diff) <= worst + 0.1 * sigma + steep * tick_s), col


def test_fit_on_arrays_with_exponential_jitter_a_wrap_and_a_short_segment():
    """Synthetic micros() at 200 Hz, ε = −2000 ppm, starting just before the 2³² µs wrap, exponential
    jitter (mean 5 ms) and a USB stall (every sample of a second 80 ms late); the board reboots 3 s before
    the end: the short last segment keeps the long one's rate and fits only its offset."""
    rng = np.random.default_rng(7)
    eps, b, tick, wrap, latency = -2000e-6, 4294.9, 1e-6, 2**32, 0.002
    t = np.arange(0.0, 90.0, 0.005)
    device = (1 + eps) * t + b
    boot = t >= 87.0
    device[boot] = (1 + eps) * (t[boot] - 87.0) + 0.01
    raw = np.floor(device / tick).astype(np.int64) % wrap
    delay = latency + rng.exponential(0.005, t.size) + np.where((t > 40.0) & (t < 41.0), 0.08, 0.0)
    host = 10**18 + np.round((t + delay) * 1e9).astype(np.int64)
    ticks = unwrap_stamps(raw, host, tick, wrap)
    fit = ClockFitter(tick, latency, ref_ns=10**18).fit(ticks, host).clock_
    assert fit.resets == 1 and fit.segments[1].start == int(np.argmax(boot))
    assert abs(fit.drift_ppm - eps * 1e6) < 1.0 and abs(fit.segments[1].drift_ppm - eps * 1e6) < 1.0
    assert abs(fit.offset_s - b) < 1e-4
    got = (fit.to_host_ns(ticks, fit.labels()) - 10**18) * 1e-9
    assert np.abs(got - t).max() < 2e-4
    assert 0.002 < fit.jitter_p50_s < 0.005 < fit.jitter_p95_s
