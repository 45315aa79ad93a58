"""Test helper: twin campaign sessions → timelines at tracker frames (what pipeline.sync will produce), by
nearest-in-log-time joins (good enough at static points: the twin's clocks drift only a little)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.ingest import ingest_session
from pipeline.tables import SessionTables
from twin.runner import TWIN_TRUTH
from twin.sensors import rotation_from_rpy


def timeline(s: SessionTables) -> pd.DataFrame:
    """Tracker frames with the nearest servo, pressure and stepper samples (columns as pipeline.sync)."""
    tracker = s.streams["/tracker/pose"]
    out = pd.DataFrame({"log_time": tracker["log_time"].to_numpy(np.int64)})
    out = out.assign(**{f"tracker_position_{k}": tracker[f"position_{k}"].to_numpy(float) for k in range(3)})
    joins = {
        "/servo/state": {"position": "servo_position", "current": "servo_current"},
        "/pressure/measured": {"pressure": "pressure"},
        "/stepper/state": {"position": "stepper_position"},
    }
    for topic, names in joins.items():
        df = s.streams[topic]
        cols = {c: names[c.rsplit("_", 1)[0]] + "_" + c.rsplit("_", 1)[1] for c in df.columns
                if c.rsplit("_", 1)[0] in names and c.rsplit("_", 1)[-1].isdigit()}  # fmt: skip
        right = df[["log_time", *cols]].rename(columns=cols).sort_values("log_time")
        out = pd.merge_asof(out, right, on="log_time", direction="nearest")
    out.insert(0, "t", (out.pop("log_time").to_numpy(np.int64) - s.t0_ns) * 1e-9)
    return out


def sessions(directory: Path) -> list[SessionTables]:
    return [ingest_session(d) for d in sorted(Path(directory).iterdir()) if d.is_dir()]


def true_base_to_tracker(s: SessionTables) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of p_tracker = R p_base + t, from the twin's truth in the session metadata."""
    placement = json.loads(s.metadata[TWIN_TRUTH])["base_to_tracker"]
    return rotation_from_rpy(*placement["rpy_rad"]), np.asarray(placement["translation_m"], float)
