"""The sync stage: every device's stamps → host time of sampling, then every stream on one timeline.

Each stamped stream's device clock is fitted (``pipeline.clock.ClockFitter``, lower envelope, resets split)
and the stream gets ``t``: its samples' fitted sampling times in s since the session's ``t0_ns``. Streams the
host stamps itself (commands) get ``t`` from their log time. The timeline is the tracker's frames at their
fitted times, with the other streams linearly interpolated there, NaN outside a stream's span and across its
gaps, so nothing is invented.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import numpy as np
import pandas as pd

from acquisition.devices.kinds import polled_topics, stamp_fields, timeline_fields
from acquisition.schemas import topics as T
from pipeline.clean import DEVICE_TICKS, device_ticks, stamp_clock
from pipeline.clock import ClockFitter
from pipeline.errors import PipelineError
from pipeline.tables import SessionTables, columns

log = logging.getLogger(__name__)


class SyncError(PipelineError, ValueError):
    """A session that cannot be put on a timeline (no tracker frames)."""


def interpolate(t_src: np.ndarray, values: np.ndarray, t_query: np.ndarray, max_gap_s: float) -> np.ndarray:
    """Linear interpolation of ``values`` (n, k) sampled at increasing ``t_src`` at ``t_query`` (m,) → (m, k);
    NaN outside [t_src[0], t_src[-1]] and between samples more than ``max_gap_s`` apart."""
    t_src, t_query = np.asarray(t_src, dtype=float), np.asarray(t_query, dtype=float)
    values = np.asarray(values, dtype=float).reshape(len(t_src), -1)
    return _interpolated(values, t_query.size, _brackets(t_src, t_query, max_gap_s))


def _brackets(t_src: np.ndarray, t_query: np.ndarray, max_gap_s: float):
    """Where each query falls among the samples (left, right, weight, usable): shared by every column
    sampled at ``t_src`` (None: fewer than 2 samples)."""
    if t_src.size < 2:
        return None
    right = np.clip(np.searchsorted(t_src, t_query, side="right"), 1, t_src.size - 1)
    left = right - 1
    span = t_src[right] - t_src[left]
    weight = np.divide(t_query - t_src[left], span, out=np.zeros_like(span), where=span > 0)
    ok = (t_query >= t_src[0]) & (t_query <= t_src[-1]) & ((span <= max_gap_s) | (t_query == t_src[left]))
    return left[ok], right[ok], weight[ok, None], ok


def _interpolated(values: np.ndarray, m: int, brackets) -> np.ndarray:
    out = np.full((m, values.shape[1]), np.nan)
    if brackets is not None:
        left, right, weight, ok = brackets
        out[ok] = values[left] * (1.0 - weight) + values[right] * weight
    return out


def resample(t_query: np.ndarray, series: Mapping[str, tuple[np.ndarray, np.ndarray]],
             gap_periods: float = 3.0) -> pd.DataFrame:  # fmt: skip
    """Columns ``series[name] = (t, values (n,) or (n, k))`` interpolated at ``t_query``: one column
    ``name`` (k = 1) or ``name_<i>``. A gap is longer than ``gap_periods`` median sample periods. Series
    given the same ``t`` array (one stream's fields) share its ordering and interpolation weights."""
    t_query = np.asarray(t_query, dtype=float)
    out: dict[str, np.ndarray] = {"t": t_query}
    shared: dict[int, tuple] = {}  # id(t) → (order, brackets), for the series sampled at that t
    for name, (t, values) in series.items():
        if id(t) not in shared:
            times = np.asarray(t, dtype=float)
            order = np.argsort(times, kind="stable")
            times = times[order]
            period = float(np.median(np.diff(times))) if times.size > 1 else 0.0
            shared[id(t)] = order, _brackets(times, t_query, gap_periods * period)
        order, brackets = shared[id(t)]
        values = np.asarray(values, dtype=float)
        scalar = values.ndim == 1
        got = _interpolated(values.reshape(len(order), -1)[order], t_query.size, brackets)
        if scalar:
            out[name] = got[:, 0]
        else:
            out.update({f"{name}_{i}": got[:, i] for i in range(got.shape[1])})
    return pd.DataFrame(out)


def fit_stream(
    session: SessionTables, topic: str, **fit_options
) -> tuple[str, ClockFitter, np.ndarray] | None:
    """Fit the clock of the device that stamps ``topic``: (device, fitted :class:`ClockFitter`, unwrapped
    ticks), or None (not stamped, or fewer than 2 rows). The ticks are clean's ``device_ticks``, or the stamps
    unwrapped the same way for a stream that was not cleaned."""
    stamped = stamp_clock(session.robot, topic)
    df = session.streams[topic]
    if stamped is None or len(df) < 2 or not {stamped[1], DEVICE_TICKS} & set(df.columns):
        return None
    device, field = stamped
    spec = session.robot.devices[device]
    host = df["log_time"].to_numpy(dtype=np.int64)
    if DEVICE_TICKS in df.columns:
        ticks = df[DEVICE_TICKS].to_numpy(dtype=np.int64)
    else:
        ticks = device_ticks(df, field, spec.clock)
    phase = 0.0 if field == "frame" else 0.5  # a frame number is the sampling event; a counter is floored
    options = {"polled": topic in polled_topics(session.robot), **fit_options}
    model = ClockFitter(spec.clock.tick_s, spec.host_link.latency_s, ref_ns=session.t0_ns, stamp_phase=phase,
                       **options)  # fmt: skip
    return device, model.fit(ticks, host), ticks


def hold_last(t_src: np.ndarray, values: np.ndarray, t_query: np.ndarray) -> np.ndarray:
    """Zero-order hold: at each ``t_query`` the latest ``values`` row (n, k) at or before it (NaN before)."""
    order = np.argsort(t_src, kind="stable")
    idx = np.searchsorted(t_src[order], t_query, side="right") - 1
    out = np.full((len(t_query), values.shape[1]), np.nan)
    out[idx >= 0] = values[order][idx[idx >= 0]]
    return out


def timeline(session: SessionTables, gap_periods: float = 3.0) -> pd.DataFrame:
    """The tracker's frames at their fitted times (``t``, ``tracker_position_<i>``) with the other streams
    (their devices' kinds' ``timeline`` fields) interpolated there and the servo goals in force
    (``goal_position_<i>``). Streams must already have ``t`` (see :func:`sync`)."""
    tracker = session.streams.get(T.TRACKER)
    if tracker is None or "t" not in tracker.columns:
        raise ValueError(f"session {session.session_id}: no synced tracker stream to put the timeline on")
    series: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for topic, (prefix, fields) in timeline_fields(session.robot).items():
        df = session.streams.get(topic)
        if df is None or "t" not in df.columns or not len(df):
            continue
        t = df["t"].to_numpy()  # one array for the stream's fields: resample orders and brackets it once
        for name in fields:
            try:
                series[prefix + name] = (t, columns(df, name))
            except KeyError:
                continue
    frame_t = tracker["t"].to_numpy(dtype=float)
    out = resample(frame_t, series, gap_periods)
    goals = session.streams.get(T.SERVO_GOAL)
    if goals is not None and len(goals) and "t" in goals.columns:  # commands hold until the next one
        held = hold_last(goals["t"].to_numpy(float), columns(goals, "position"), frame_t)
        out = out.assign(**{f"goal_position_{k}": held[:, k] for k in range(held.shape[1])})
    position = pd.DataFrame(columns(tracker, "position"), index=out.index).add_prefix("tracker_position_")
    frame = {"frame": tracker["frame"].to_numpy()} if "frame" in tracker.columns else {}
    return pd.concat([out[["t"]], pd.DataFrame(frame, index=out.index), position, out.drop(columns="t")],
                     axis=1)  # fmt: skip


def sync(
    session: SessionTables, gap_periods: float = 3.0, **fit_options
) -> tuple[SessionTables, pd.DataFrame]:
    """Fit every stamped device clock, add ``t`` (s since ``t0_ns``) to every stream, record each fit in
    ``report.values["clock/<device>"]`` and return the synced session with its tracker-frame timeline.
    A session without tracker frames has no ground truth to put on a timeline: :class:`SyncError`."""
    tracker = session.streams.get(T.TRACKER)
    if tracker is None or not len(tracker):
        raise SyncError(
            f"session {session.session_id}: no {T.TRACKER} samples, so no ground truth and no timeline"
        )
    out = session.replace()
    t0 = session.t0_ns
    stamped = stamp_fields(session.robot)
    for topic, df in session.streams.items():
        fitted = fit_stream(session, topic, **fit_options)
        df = df.copy(deep=False)  # a new column on a shallow copy: the session's own table is left as it was
        if fitted is None:
            if topic in stamped and len(df):
                out.report.warnings.append(f"{topic}: no device stamps to fit; t is the host log time")
            df["t"] = (df["log_time"].to_numpy(dtype=np.int64) - t0) * 1e-9
        else:
            device, model, ticks = fitted
            fit = model.clock_
            df["t"] = (model.predict(ticks, fit.labels()) - t0) * 1e-9
            out.report.values[f"clock/{device}"] = fit.as_dict()
            if fit.resets:
                out.report.warnings.append(f"{device}: {fit.resets} counter reset(s), segments fitted apart")
            if not fit.drift_fitted:
                span = np.ptp(ticks) * fit.tick_s
                out.report.warnings.append(
                    f"{device}: session too short to fit clock drift ({span:.1f} s: its polled counter "
                    f"slipped phase under twice); drift {fit.drift_ppm:+.1f} ppm, the middle of what its "
                    "stamps allow (0 without a slip: the device's nominal rate)"
                )
            log.debug("%s: drift %.1f ppm, jitter p95 %.2f ms", device, fit.drift_ppm, 1e3 * fit.jitter_p95_s)
        out.streams[topic] = df
    return out, timeline(out, gap_periods)
