"""Clean: each kind of bad sample injected into tables is removed and counted; clean data passes untouched."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from numpy.lib.stride_tricks import sliding_window_view

from acquisition.schemas import topics as T
from models.robot import load_robot
from pipeline.clean import (
    DUPLICATE,
    MISSING,
    OUTLIER,
    PORT_STATUS,
    clean,
    clean_stream,
    hampel_outliers,
    unwrap_ticks,
    window_medians,
)
from pipeline.tables import EVENT_COLUMNS, SessionTables, StageReport

N = 400
OK_STATUS = 0x31  # occupied, initialized, enabled


def _tracker(n: int = N, frame0: int = 1000) -> pd.DataFrame:
    """A smooth tip path at 40 Hz (no noise: a Hampel filter must leave it alone)."""
    t = np.arange(n) * 25_000_000
    s = np.arange(n) / 40.0
    df = pd.DataFrame({"log_time": t + 10**18, "publish_time": t + 10**18})
    df["frame"] = (frame0 + np.arange(n)).astype(np.uint32)
    df["port_handle"] = np.full(n, 10, np.uint16)
    df["port_status"] = np.full(n, OK_STATUS, np.uint16)
    df["missing"] = np.zeros(n, bool)
    for i, p in enumerate([0.1 * np.sin(s), 0.05 * np.cos(0.7 * s), 0.2 + 0.01 * s]):
        df[f"position_{i}"] = p
    for i in range(4):
        df[f"quaternion_{i}"] = 0.5
    df["rms_error"] = 2e-4
    return df


def _pressure(n: int = N, channels: int = 3) -> pd.DataFrame:
    t = np.arange(n) * 10_000_000 + 10**18
    df = pd.DataFrame({"log_time": t, "publish_time": t, "seq": np.arange(n, dtype=np.uint32)})
    df["micros"] = ((np.arange(n) * 10_000 + 2**32 - 1_000_000) % 2**32).astype(np.uint32)  # wraps
    for i in range(channels):
        counts = np.round(8000 + 2000 * np.sin(np.arange(n) / 50 + i))  # quantised, no noise
        df[f"counts_{i}"] = counts.astype(np.int16)
        df[f"pressure_{i}"] = counts * 12.5
    return df


def _session(streams: dict[str, pd.DataFrame]) -> SessionTables:
    events = pd.DataFrame({c: [] for c in EVENT_COLUMNS})
    return SessionTables("s", load_robot("vsl"), {}, streams, events)


def test_clean_data_passes_untouched():
    tracker, pressure = _tracker(), _pressure()
    session = _session({T.TRACKER: tracker, T.PRESSURE: pressure})
    out = clean(session)
    assert out.report.removed_total() == 0 and session.report.removed_total() == 0
    for topic, df in session.streams.items():
        got = out.streams[topic]
        pd.testing.assert_frame_equal(got.drop(columns="device_ticks"), df)
        assert out.report.values[f"clean/{topic}"]["out_of_order"] == 0
    assert out.streams[T.TRACKER] is not tracker and "device_ticks" not in tracker.columns  # input untouched


def test_tracker_faults_are_removed_and_counted():
    df = _tracker()
    df.loc[[10, 11, 12], "missing"] = True
    df.loc[[10, 11, 12], ["position_0", "position_1", "position_2"]] = np.nan
    df.loc[50, "position_1"] = np.nan  # NaN position without the flag
    df.loc[[80, 81], "port_status"] = OK_STATUS | 0x40  # out of volume
    df.loc[90, "port_status"] = 0x11  # port not enabled
    df.loc[[200, 300], "position_0"] += 0.05  # 5 cm spikes
    df.loc[250, "position_2"] -= 0.02
    out = clean(_session({T.TRACKER: df}))
    assert out.report.removed[T.TRACKER] == {MISSING: 4, PORT_STATUS: 3, OUTLIER: 3}
    kept = out.streams[T.TRACKER]
    assert len(kept) == N - 10
    assert not set(kept["frame"]) & {1010, 1011, 1012, 1050, 1080, 1081, 1090, 1200, 1250, 1300}


def test_duplicates_and_out_of_order_samples():
    df = _pressure()
    shuffled = df.copy()
    shuffled.iloc[[20, 21]] = df.iloc[[21, 20]].to_numpy()  # two swapped in arrival order
    shuffled.iloc[[100, 101]] = df.iloc[[101, 100]].to_numpy()
    dup = df.iloc[[5, 6, 7]].copy()
    dup["log_time"] += 1234  # received twice: same seq and payload, another host time
    resent = df.iloc[[8]].copy()
    resent["pressure_0"] += 1.0  # same seq, other payload: not a duplicate
    mixed = pd.concat([shuffled, dup, resent], ignore_index=True)
    report = StageReport()
    out = clean_stream(T.PRESSURE, mixed, report, load_robot("vsl"))
    assert report.removed == {T.PRESSURE: {DUPLICATE: 3}}
    assert report.values[f"clean/{T.PRESSURE}"]["out_of_order"] == 3  # 20, 100 and the resent 8 came late
    assert len(out) == N + 1 and np.all(np.diff(out["seq"].to_numpy().astype(np.int64)) >= 0)
    assert set(np.diff(out["device_ticks"].to_numpy())) == {0, 10_000}  # the resent sample: same stamp


def test_pressure_spikes_are_outliers():
    df = _pressure()
    df.loc[150, "pressure_1"] += 5e4
    df.loc[[300], "pressure_2"] -= 3e4
    out = clean(_session({T.PRESSURE: df}))
    assert out.report.removed == {T.PRESSURE: {OUTLIER: 2}}
    assert 150 not in set(out.streams[T.PRESSURE]["seq"]) and "counts_0" in out.streams[T.PRESSURE]


def test_device_ticks_unwrap_across_wraps():
    df = _pressure()
    micros = df["micros"].to_numpy()
    assert np.any(np.diff(micros.astype(np.int64)) < 0)  # the fixture wraps
    out = clean_stream(T.PRESSURE, df, StageReport(), load_robot("vsl"))
    ticks = out["device_ticks"].to_numpy()
    assert ticks.dtype == np.int64 and np.all(np.diff(ticks) == 10_000) and ticks[0] == micros[0]
    np.testing.assert_array_equal(out["micros"].to_numpy(), micros)  # raw stamps stay
    servo = np.array([32760, 32767, 5, 10000, 20000, 32700, 3], dtype=np.uint16)  # tick_ms wraps at 32768
    np.testing.assert_array_equal(
        unwrap_ticks(servo, 1 << 15), [32760, 32767, 32773, 42768, 52768, 65468, 65539]
    )
    assert unwrap_ticks(np.array([], np.uint16), 1 << 15).size == 0


def test_hampel_flags_spikes_not_noise():
    rng = np.random.default_rng(0)
    x = rng.normal(0, 1e-3, 20_000)
    spikes = rng.choice(20_000, 40, replace=False)
    x[spikes] += 0.02
    flagged = hampel_outliers(x, 7, 4.0)
    assert set(spikes) <= set(np.flatnonzero(flagged))
    assert flagged.sum() - len(spikes) < 0.002 * len(x)  # few false alarms on Gaussian noise
    quantised = np.repeat([0.0, 1.0, 0.0, 2.0], 50)
    assert not hampel_outliers(quantised).any()
    assert not hampel_outliers(np.ones(5)).any()  # shorter than a window


@pytest.mark.parametrize("window", [3, 4, 5, 6, 7, 8, 9, 15, 16, 21])
def test_window_medians_are_numpys_medians(window):
    """The sorting network gives np.median's values bit for bit: noise, ties, steps, signed zeros."""
    rng = np.random.default_rng(window)
    for x in (rng.normal(size=3000), np.round(rng.normal(size=3000), 1), rng.integers(-1, 2, 3000) * 0.0,
              np.repeat(rng.normal(size=300), 10)):  # fmt: skip
        windows = sliding_window_view(x, window)
        want = np.median(windows, axis=1)
        got = window_medians(list(windows.T))
        assert got.dtype == np.float64 and got.shape == want.shape
        np.testing.assert_array_equal(got, want)


def _hampel_by_numpy(x: np.ndarray, window: int, sigmas: float) -> np.ndarray:
    """The Hampel filter written with np.median over every window (the definition the fast one must match)."""
    n = len(x)
    windows = sliding_window_view(x, window)
    median = np.median(windows, axis=1)
    mad = np.median(np.abs(windows - median[:, None]), axis=1)
    at = np.clip(np.arange(n) - window // 2, 0, n - window)
    residual = np.abs(x - median[at])
    steps = np.abs(np.diff(x))
    steps = steps[steps > 0]
    finite = residual[np.isfinite(residual)]
    noise = 1.4826 * float(np.median(finite)) if finite.size else 0.0
    scale = np.maximum(1.4826 * mad[at], max(noise, float(steps.min()) if steps.size else 0.0))
    with np.errstate(invalid="ignore"):
        return residual > sigmas * scale


@pytest.mark.parametrize("window", [5, 7, 8, 31])
def test_hampel_equals_its_definition_with_nans(window):
    rng = np.random.default_rng(1)
    x = rng.normal(0, 1e-3, 5000)
    x[rng.choice(5000, 30, replace=False)] += 0.02
    x[rng.choice(5000, 12, replace=False)] = np.nan  # a NaN makes its windows' medians NaN
    x[100], x[102] = np.nan, 0.05  # a spike beside a NaN: its window has no median, so no verdict
    np.testing.assert_array_equal(hampel_outliers(x, window, 4.0), _hampel_by_numpy(x, window, 4.0))


@pytest.mark.parametrize("wrap_at", [3, 390])
def test_tracker_frames_wrap(wrap_at):
    df = _tracker(frame0=2**32 - wrap_at)
    out = clean(_session({T.TRACKER: df}))
    assert out.report.removed_total() == 0
    assert np.all(np.diff(out.streams[T.TRACKER]["device_ticks"].to_numpy()) == 1)


def test_duplicates_found_through_the_sequence_are_pandas_duplicates():
    """Rows are compared only where their sequence number recurs: the same rows as pandas' ``duplicated``
    over every payload column (a resent frame, a wrapped counter, a number reused with other values)."""
    from pipeline.clean import _duplicated

    rng = np.random.default_rng(7)
    for _ in range(20):
        n = int(rng.integers(1, 400))
        df = pd.DataFrame({"seq": rng.integers(0, n, n), "value": rng.integers(0, 3, n).astype(float),
                           "log_time": np.arange(n)})  # fmt: skip
        payload = ["seq", "value"]
        want = df.duplicated(subset=payload).to_numpy()
        assert np.array_equal(_duplicated(df, payload, "seq"), want)
        assert np.array_equal(_duplicated(df, payload, None), want)
