"""Clean: drop what no later stage should see, count every removal, and unwrap the device counters.

Per stream: duplicated samples (same sequence number and payload) go, samples are put in device order (by
the unwrapped sequence / frame number; late arrivals are counted, kept), and the wrapping device stamp gets an
unwrapped int64 twin, ``device_ticks``, unwrapped with the host's clock as a guide (``clock.unwrap_stamps``:
a gap longer than half a wrap still unwraps right) by the tick and wrap of the robot description's clock of
the device that stamps it (the clock sync fits). Tracker frames that are MISSING (flag or NaN position)
or carry an NDI port-status fault go, then Hampel outliers on position; pressure rows with a Hampel outlier
on any channel go.

Units: the recorder already writes SI (m, rad, rad/s, A, Pa); only the raw ADC ``counts`` are not, and they
are kept as they are on purpose (their calibration belongs to the pipeline). Nothing is converted here.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from numpy.lib.stride_tricks import sliding_window_view

from acquisition.devices.kinds import stamp_fields
from acquisition.schemas import topics as T
from acquisition.schemas.stamps import unwrap_ticks
from models.robot import ClockDescription, RobotDescription
from pipeline.clock import unwrap_stamps
from pipeline.tables import SessionTables, StageReport, columns

MISSING, PORT_STATUS, OUTLIER, DUPLICATE = "missing", "port_status", "outlier", "duplicate"

DEVICE_TICKS = "device_ticks"  # the unwrapped device counter this stage adds to each stamped stream
SEQUENCE_WRAP = 1 << 32  # seq and frame are uint32
SEQUENCE_COLUMNS = ("seq", "frame")
HOST_COLUMNS = ("log_time", "publish_time", "t")

# NDI port status bits (Aurora/Polaris API guide): a pose is only trusted on an occupied, enabled port that is
# inside the measurement volume and reports no processing fault
PORT_OCCUPIED, PORT_ENABLED = 0x01, 0x20
PORT_OUT_OF_VOLUME, PORT_PARTIALLY_OUT_OF_VOLUME = 0x40, 0x80
PORT_ALGORITHM_LIMITATION, PORT_PROCESSING_EXCEPTION = 0x100, 0x1000
PORT_FAULT_BITS = (
    PORT_OUT_OF_VOLUME | PORT_PARTIALLY_OUT_OF_VOLUME | PORT_ALGORITHM_LIMITATION | PORT_PROCESSING_EXCEPTION
)
PORT_REQUIRED_BITS = PORT_OCCUPIED | PORT_ENABLED

HAMPEL_SCALE = 1.4826  # MAD → standard deviation for Gaussian noise
SORTED_WINDOW_MAX = 15  # longer windows: np.median (the network's w² min/max passes cost more than a sort)


def clean(session: SessionTables, hampel_window: int = 7, hampel_sigmas: float = 4.0) -> SessionTables:
    """New tables without duplicates, MISSING/faulty tracker frames and outliers; counts in the report."""
    report = session.report.copy()
    streams = {}
    for topic, df in session.streams.items():
        df = clean_stream(topic, df, report, session.robot)
        if topic == T.TRACKER:
            df = clean_tracker(df, report, hampel_window, hampel_sigmas, topic)
        elif topic == T.PRESSURE:
            df = drop_outliers(df, "pressure", report, topic, hampel_window, hampel_sigmas)
        streams[topic] = df
    return session.replace(streams=streams, report=report)


def stamp_clock(robot: RobotDescription, topic: str) -> tuple[str, str] | None:
    """(device, stamp field) of the device clock that stamps ``topic`` on ``robot`` (its kind's ``stamps``;
    its tick and wrap are that device's ``clock`` in the robot description); None if none does."""
    return stamp_fields(robot).get(topic)


def device_ticks(df: pd.DataFrame, field: str, clock: ClockDescription) -> np.ndarray:
    """The stamp column ``field`` unwrapped (int64) by the tick and wrap of the device ``clock`` that wrote
    it, host log times guiding the unwrap (``clock.unwrap_stamps``)."""
    raw, host = df[field].to_numpy(dtype=np.int64), df["log_time"].to_numpy(dtype=np.int64)
    return unwrap_stamps(raw, host, clock.tick_s, clock.wrap)


def clean_stream(topic: str, df: pd.DataFrame, report: StageReport, robot: RobotDescription) -> pd.DataFrame:
    """Any stream: drop duplicates, sort by device sequence (late arrivals counted), add ``device_ticks`` when
    a device clock of ``robot`` stamps it."""
    sequence = next((c for c in SEQUENCE_COLUMNS if c in df.columns), None)
    payload = [c for c in df.columns if c not in HOST_COLUMNS and c != DEVICE_TICKS]
    duplicated = _duplicated(df, payload, sequence) if payload and len(df) else np.zeros(len(df), bool)
    report.remove(topic, DUPLICATE, int(duplicated.sum()))
    df = df[~duplicated]
    late = 0
    if sequence is not None and len(df):
        order_key = unwrap_ticks(df[sequence].to_numpy(), SEQUENCE_WRAP)
        late = int(np.count_nonzero(order_key[1:] < np.maximum.accumulate(order_key)[:-1]))
        if late:
            df = df.iloc[np.argsort(order_key, kind="stable")]
    df = df.reset_index(drop=True)
    stamped = stamp_clock(robot, topic)
    if stamped is not None and stamped[1] in df.columns:
        device, field = stamped
        df = df.assign(**{DEVICE_TICKS: device_ticks(df, field, robot.devices[device].clock)})
    report.values[f"clean/{topic}"] = {"out_of_order": late, "rows": len(df)}
    return df


def _duplicated(df: pd.DataFrame, payload: list[str], sequence: str | None) -> np.ndarray:
    """``df.duplicated(subset=payload)``: rows equal to an earlier one in every payload column. Two such rows
    share their sequence number, so only rows whose number recurs are compared (most streams: none)."""
    if sequence is None or sequence not in payload:
        return df.duplicated(subset=payload).to_numpy()
    _, inverse, counts = np.unique(df[sequence].to_numpy(), return_inverse=True, return_counts=True)
    recurs = counts[inverse.reshape(-1)] > 1
    out = np.zeros(len(df), bool)
    if recurs.any():
        out[recurs] = df[recurs].duplicated(subset=payload).to_numpy()
    return out


def clean_tracker(
    df: pd.DataFrame, report: StageReport, window: int, sigmas: float, topic: str = T.TRACKER
) -> pd.DataFrame:
    """Drop MISSING frames, then frames with port-status faults, then Hampel outliers on position."""
    position = columns(df, "position") if len(df) else np.zeros((0, 3))
    missing = np.isnan(position).any(axis=1)
    if "missing" in df.columns:
        missing |= df["missing"].to_numpy(dtype=bool)
    report.remove(topic, MISSING, int(missing.sum()))
    df = df[~missing]
    if "port_status" in df.columns:
        status = df["port_status"].to_numpy(dtype=np.int64)
        fault = ((status & PORT_FAULT_BITS) != 0) | ((status & PORT_REQUIRED_BITS) != PORT_REQUIRED_BITS)
        report.remove(topic, PORT_STATUS, int(fault.sum()))
        df = df[~fault]
    return drop_outliers(df.reset_index(drop=True), "position", report, topic, window, sigmas)


def drop_outliers(
    df: pd.DataFrame, field: str, report: StageReport, topic: str, window: int, sigmas: float
) -> pd.DataFrame:
    """Drop rows where any column of ``field`` (``field`` or ``field_<i>``) is a Hampel outlier."""
    if len(df) == 0:
        return df
    values = columns(df, field)
    outlier = np.zeros(len(df), dtype=bool)
    for k in range(values.shape[1]):
        outlier |= hampel_outliers(values[:, k], window, sigmas)
    report.remove(topic, OUTLIER, int(outlier.sum()))
    return df[~outlier].reset_index(drop=True)


def window_medians(columns: list[np.ndarray]) -> np.ndarray:
    """Row-wise median of the equal-length ``columns`` (one array per place in a window), equal to
    ``np.median(np.stack(columns, axis=1), axis=1)`` bit for bit where no row holds a NaN. Short windows are
    sorted by a network of element-wise min/max over whole columns (odd-even transposition: ``w`` passes),
    ~4× faster than ``np.median``'s per-row partition for the Hampel filter's 7-sample windows (7.4 → 1.9 ms
    on 66,000 samples)."""
    w = len(columns)
    if w > SORTED_WINDOW_MAX:
        return np.median(np.stack(columns, axis=1), axis=1)
    cols = list(columns)
    for p in range(w):
        for i in range(p % 2, w - 1, 2):
            cols[i], cols[i + 1] = np.minimum(cols[i], cols[i + 1]), np.maximum(cols[i], cols[i + 1])
    if w % 2:
        return np.array(cols[w // 2], dtype=np.float64)
    return (cols[w // 2 - 1] + cols[w // 2]) / 2.0  # np.median: the mean of the two middle values


def hampel_outliers(x: np.ndarray, window: int = 7, sigmas: float = 4.0) -> np.ndarray:
    """Samples further than ``sigmas``·1.4826·MAD from their window's median (centred windows of ``window``
    samples, shifted inward at the ends). The scale never falls below the whole signal's robust noise level
    (1.4826·median of |x − rolling median|) nor its resolution (smallest nonzero step): a 7-sample MAD
    alone flags ~2 % of pure Gaussian noise, and on quantised constant data it would flag every step."""
    x = np.asarray(x, dtype=np.float64)
    n = len(x)
    if window < 3 or n < window:
        return np.zeros(n, dtype=bool)
    windows = sliding_window_view(x, window)  # (n - window + 1, window)
    median = window_medians(list(windows.T))
    mad = window_medians([np.abs(column - median) for column in windows.T])
    if np.isnan(x).any():  # np.median's rule: a window holding a NaN has a NaN median (and MAD)
        nan_windows = sliding_window_view(np.isnan(x), window).any(axis=1)
        median[nan_windows] = mad[nan_windows] = np.nan
    at = np.clip(np.arange(n) - window // 2, 0, n - window)
    residual = np.abs(x - median[at])
    steps = np.abs(np.diff(x))
    steps = steps[steps > 0]
    finite = residual[np.isfinite(residual)]
    noise = HAMPEL_SCALE * float(np.median(finite)) if finite.size else 0.0
    scale = np.maximum(HAMPEL_SCALE * mad[at], max(noise, float(steps.min()) if steps.size else 0.0))
    with np.errstate(invalid="ignore"):
        return residual > sigmas * scale
