"""Segment: a synced timeline → settled static points (seed 000's rows of D) and labelled repetitions.

The plans mark what to cut: a SETTLED event (index = point number, value = hold window in s) starts the window
that one static point averages; REPETITION_START/END (index = repetition, label = trajectory) bracket a
repetition; PAYLOAD (value = kg) says what hangs at the end-effector from then on. Events carry host log
times (ns); the timeline counts ``t`` in seconds from ``t0_ns``.

A window is kept only if the bench really was still in it: the least-squares drift over the window of every
joint, of the tip and of every link pressure stays below a threshold. A window that fails is counted by reason
(``points.attrs["rejected"]``, the stage report if one is given, a log line), never silently averaged.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pandas as pd

from acquisition.schemas.events import EventKind
from pipeline.tables import StageReport

log = logging.getLogger(__name__)

TIP = [f"tracker_position_{k}" for k in range(3)]
STREAM = "static_points"  # the name rejected windows are counted under in the stage report


@dataclass(frozen=True)
class Stillness:
    """Largest drift over one hold window that still counts as settled (least-squares slope × window)."""

    joint_rad: float = 2e-3  # ≈ 1 mm at the 0.5 m reach; encoder quantum 1.5 mrad averages out in the fit
    tip_m: float = 1e-3  # |drift| of the 3-D tip; tracker noise alone gives ≈ 0.3 mm over 20 frames
    pressure_pa: float = 2e3  # 0.02 bar; the valve leak alone is ≈ 50 Pa over 0.5 s
    min_samples: int = 5  # valid tracker frames in the window


def _event_times(events: pd.DataFrame, kind: EventKind, t0_ns: int) -> pd.DataFrame:
    """The events of one kind, sorted, with ``t`` (s since ``t0_ns``)."""
    sel = events[events["kind"].to_numpy() == int(kind)].sort_values("log_time", kind="stable")
    return sel.assign(t=(sel["log_time"].to_numpy(np.int64) - int(t0_ns)) * 1e-9)


def _window_of(t: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Per sample, the window [start, end) it lies in, or −1 (windows sorted and not overlapping)."""
    if not len(starts):
        return np.full(len(t), -1)
    k = np.searchsorted(starts, t, side="right") - 1
    inside = (k >= 0) & (t < ends[np.clip(k, 0, None)])
    return np.where(inside, k, -1)


def _group_mean(group: np.ndarray, y: np.ndarray, n_groups: int) -> np.ndarray:
    """Mean of every column of ``y`` (n, k) within each group, NaN samples left out (NaN if none)."""
    w = np.isfinite(y)
    y0 = np.where(w, y, 0.0)
    count = np.stack([np.bincount(group, w[:, j], n_groups) for j in range(y.shape[1])], axis=1)
    total = np.stack([np.bincount(group, y0[:, j], n_groups) for j in range(y.shape[1])], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (total / count).reshape(n_groups, y.shape[1])


def _group_slopes(group: np.ndarray, t: np.ndarray, y: np.ndarray, n_groups: int) -> np.ndarray:
    """Least-squares slope dy/dt of every column of ``y`` (n, k) within each group, NaN samples left out;
    NaN where a group has fewer than two samples of a column."""
    w = np.isfinite(y)
    y0 = np.where(w, y, 0.0)
    tw = np.where(w, t[:, None], 0.0)

    def gsum(v: np.ndarray) -> np.ndarray:
        return np.stack([np.bincount(group, v[:, j], n_groups) for j in range(v.shape[1])], axis=1)

    n, st, sy = gsum(w.astype(float)), gsum(tw), gsum(y0)
    stt, sty = gsum(tw * tw), gsum(tw * y0)
    with np.errstate(invalid="ignore", divide="ignore"):
        var = stt - st * st / n
        slope = (sty - st * sy / n) / var
    return np.where((n >= 2) & (var > 0), slope, np.nan)


def static_points(
    timeline: pd.DataFrame,
    events: pd.DataFrame,
    t0_ns: int,
    stillness: Stillness | None = None,
    report: StageReport | None = None,
) -> pd.DataFrame:
    """One row per settled static point: the mean of every timeline column over the SETTLED hold window,
    ``n_samples`` (valid tracker frames), ``tracker_position_std_0..2`` (m), ``point``, ``payload_kg`` (latest
    PAYLOAD event before the window; NaN if none), ``t_start``/``window_s`` (s). Rows ordered by window start.

    Windows that fail the stillness test are left out and counted by reason in ``attrs["rejected"]``
    ({reason: count}), ``attrs["rejected_points"]`` ({point: reason}) and ``report`` (if given)."""
    still = stillness or Stillness()
    settled = _event_times(events, EventKind.SETTLED, t0_ns)
    settled = settled[~(settled["value"] <= 0)]  # a SETTLED mark without a hold window measures nothing
    starts = settled["t"].to_numpy(float)
    lengths = settled["value"].to_numpy(float)
    ends = starts + np.nan_to_num(lengths, nan=0.0)
    m = len(starts)
    t = timeline["t"].to_numpy(float)
    group = _window_of(t, starts, ends)
    inside = group >= 0
    rows, g = timeline[inside], group[inside]
    numeric = rows.select_dtypes(include=["number", "bool"]).astype(float)
    tip = rows[TIP].to_numpy(float) if set(TIP) <= set(rows.columns) else np.full((len(rows), 3), np.nan)
    tip_ok = np.isfinite(tip).all(axis=1)
    n_tip = np.bincount(g[tip_ok], minlength=m)

    mean = _group_mean(g, numeric.to_numpy(), m)
    tip_mean = _group_mean(g[tip_ok], tip[tip_ok], m)
    dev2 = (tip[tip_ok] - tip_mean[g[tip_ok]]) ** 2
    tip_std = np.sqrt(_group_mean(g[tip_ok], dev2, m) * (n_tip / np.maximum(n_tip - 1, 1))[:, None])

    def drift(prefixes: tuple[str, ...]) -> np.ndarray:  # |least-squares slope| × window length, (m, k)
        cols = [c for c in rows.columns if c.startswith(prefixes)]
        slope = _group_slopes(g, t[inside], rows[cols].to_numpy(float), m) if cols else np.zeros((m, 0))
        return np.abs(np.nan_to_num(slope, nan=0.0)) * lengths[:, None]

    reason = np.full(m, "", dtype=object)
    checks = [  # the last failed check names the reason: the sample count first
        ("tip motion", np.linalg.norm(drift(("tracker_position_",)), axis=1) > still.tip_m),
        ("pressure change", (drift(("pressure_",)) > still.pressure_pa).any(axis=1)),
        ("joint motion", (drift(("servo_position_", "stepper_position_")) > still.joint_rad).any(axis=1)),
        ("too few tracker samples", n_tip < still.min_samples),
    ]
    for name, failed in checks:
        reason[failed] = name
    keep = reason == ""

    payload = _event_times(events, EventKind.PAYLOAD, t0_ns)
    k = np.searchsorted(payload["t"].to_numpy(float), starts, side="right") - 1
    payload_kg = np.where(
        k >= 0, payload["value"].to_numpy(float)[np.clip(k, 0, None)] if len(payload) else 0, np.nan
    )

    out = pd.DataFrame(mean, columns=numeric.columns)
    out = out.assign(
        **{f"tracker_position_std_{k}": tip_std[:, k] for k in range(3)},
        n_samples=n_tip,
        point=settled["index"].to_numpy(np.int64),
        payload_kg=payload_kg,
        t_start=starts,
        window_s=lengths,
    )
    out = out[keep].reset_index(drop=True)
    rejected = pd.Series(reason[~keep]).value_counts().to_dict()
    out.attrs["rejected"] = {str(r): int(n) for r, n in rejected.items()}
    out.attrs["rejected_points"] = dict(
        zip(settled["index"].to_numpy(np.int64)[~keep].tolist(), reason[~keep].tolist(), strict=True)
    )
    if report is not None:
        for r, n in out.attrs["rejected"].items():
            report.remove(STREAM, r, n)
        report.values["segment/static_points"] = {"settled": m, "kept": int(keep.sum())}
    if not keep.all():
        log.info("%d of %d settled windows rejected: %s", (~keep).sum(), m, out.attrs["rejected"])
    return out


def repetition_table(events: pd.DataFrame, t0_ns: int) -> pd.DataFrame:
    """The complete repetitions: ``repetition``, ``label`` (trajectory), ``t_start``, ``t_end`` (s). A START
    without its END (a stopped session) is left out with a warning."""
    start = _event_times(events, EventKind.REPETITION_START, t0_ns)
    end = _event_times(events, EventKind.REPETITION_END, t0_ns)
    key = ["index", "label"]
    both = start[[*key, "t"]].merge(end[[*key, "t"]], on=key, how="left", suffixes=("_start", "_end"))
    both = both[both["t_end"] >= both["t_start"]] if len(both) else both
    if len(both) < len(start):
        log.warning("%d repetition(s) started but never ended: left out", len(start) - len(both))
    both = both.rename(columns={"index": "repetition"}).sort_values("t_start", kind="stable")
    return both[["repetition", "label", "t_start", "t_end"]].reset_index(drop=True)


def repetitions(timeline: pd.DataFrame, events: pd.DataFrame, t0_ns: int) -> pd.Series:
    """Per timeline row, the repetition it lies in (START ≤ t ≤ END), or −1 outside any."""
    reps = repetition_table(events, t0_ns)
    t = timeline["t"].to_numpy(float)
    k = _window_of(t, reps["t_start"].to_numpy(float), np.nextafter(reps["t_end"].to_numpy(float), np.inf))
    labels = np.where(
        k >= 0, reps["repetition"].to_numpy(np.int64)[np.clip(k, 0, None)] if len(reps) else -1, -1
    )
    return pd.Series(labels.astype(np.int64), index=timeline.index, name="repetition")


def move_windows(
    timeline: pd.DataFrame, events: pd.DataFrame, t0_ns: int, goal_t: np.ndarray
) -> pd.DataFrame:
    """The timeline's rows while the arm moves into each settled point and rings after the move: from the
    last servo goal commanded before the point's SETTLED window (``goal_t``: the goal stream's times, s) to
    that window's start, tagged ``point`` and ``t_command`` (the goal's time, s) and ``payload_kg`` (the
    latest PAYLOAD event before the row). The links' swings after a move are what their damping shapes
    (``pipeline.damping_fit``); settled points hold none of it. A point with no goal since the window
    before it (a hold without a move) has no rows."""
    settled = _event_times(events, EventKind.SETTLED, t0_ns)
    settled = settled[~(settled["value"] <= 0)]
    starts = settled["t"].to_numpy(float)
    ends = starts + np.nan_to_num(settled["value"].to_numpy(float), nan=0.0)
    goal_t = np.sort(np.asarray(goal_t, float))
    k = np.searchsorted(goal_t, starts, side="left") - 1  # the last goal before each window
    command = np.where(k >= 0, goal_t[np.clip(k, 0, None)] if len(goal_t) else np.nan, np.nan)
    previous_end = np.concatenate([[-np.inf], ends[:-1]])
    moved = np.isfinite(command) & (command >= previous_end)
    t = timeline["t"].to_numpy(float)
    group = _window_of(t, command[moved], starts[moved])  # goals in time order: the windows do not overlap
    inside = group >= 0
    g = group[inside]
    payload = _event_times(events, EventKind.PAYLOAD, t0_ns)
    pt, pv = payload["t"].to_numpy(float), payload["value"].to_numpy(float)
    at = np.searchsorted(pt, t[inside], side="right") - 1
    return (
        timeline[inside]
        .assign(
            point=settled["index"].to_numpy(np.int64)[moved][g],
            t_command=command[moved][g],
            payload_kg=np.where(at >= 0, pv[np.clip(at, 0, None)] if len(pv) else np.nan, np.nan),
        )
        .reset_index(drop=True)
    )
