"""Path statistics behind seed 000's Figures 5–7: plan fields, repetitions resampled onto a common parameter,
mean ± std paths, the commanded path and the position error to the desired path (SI throughout).

Repetitions are resampled onto the fraction of repetition time u ∈ [0, 1] (every repetition of a plan follows
the same timed set-points, so equal u is the same set-point), then averaged point by point. The std is the
population std (ddof = 0) over the repetitions.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pandas as pd

from models import kinematics, trajectories
from models.robot import AnthropomorphicKinematics, load_robot

X, FK, QC = ["x_0", "x_1", "x_2"], ["fk_0", "fk_1", "fk_2"], ["qc_0", "qc_1", "qc_2"]
N_RESAMPLE = 200
MODE_LABELS = {"ik": "model-based IK", "hybrid": "hybrid inverse", "static": "static comp.",
               "history": "history-aware hybrid"}  # fmt: skip


@lru_cache(maxsize=8)
def arm_lengths(robot: str = "vsl") -> kinematics.ArmLengths:
    """l1, l2, l3 of an anthropomorphic robot description (configs/robots/<robot>.yaml)."""
    kin = load_robot(robot).kinematics
    if not isinstance(kin, AnthropomorphicKinematics):
        raise ValueError(f"robot {robot!r} is not the anthropomorphic VSL arm")
    return kin.arm()


def desired_path(trajectory: str = "curve", speed: float = 0.02, n_per_segment: int = 400) -> np.ndarray:
    """(m, 3) the desired Experiment 1 path of the VSL arm (the distance reference of Fig. 7b)."""
    return trajectories.experiment1(trajectory, arm_lengths("vsl"), speed, n_per_segment).x


def plan_fields(df: pd.DataFrame) -> pd.DataFrame:
    """``experiment``, ``trajectory``, ``arm``, ``payload_g``, ``pressure_bar`` (NaN: rigid arm), ``mode``
    ("" in Experiment 1) of each row, parsed from ``plan`` (``experiment2/curve/vsl-0.5bar/75g/ik``)."""
    parts = df["plan"].astype(str).str.split("/", expand=True).reindex(columns=range(5)).astype(object)
    return pd.DataFrame(
        {
            "experiment": parts[0],
            "trajectory": parts[1],
            "arm": parts[2],
            "payload_g": pd.to_numeric(parts[3].str.removesuffix("g"), errors="coerce"),
            "pressure_bar": pd.to_numeric(parts[2].str.extract(r"-([\d.]+)bar$")[0], errors="coerce"),
            "mode": parts[4].fillna(""),
        },
        index=df.index,
    )


def with_plan_fields(df: pd.DataFrame) -> pd.DataFrame:
    """The repetition rows of ``df`` with :func:`plan_fields` added."""
    rows = df[df["repetition"] >= 0]
    return pd.concat([rows, plan_fields(rows)], axis=1)


def resample(df: pd.DataFrame, cols: list[str], n: int = N_RESAMPLE) -> np.ndarray:
    """(R, n, len(cols)): each (session, repetition) of ``df`` interpolated at u = linspace(0, 1, n) of its
    repetition time."""
    u = np.linspace(0.0, 1.0, n)
    out = []
    for _, g in df.sort_values("t").groupby(["session", "repetition"], sort=True):
        t = g["t"].to_numpy(float)
        tu = (t - t[0]) / max(t[-1] - t[0], 1e-12)
        values = g[cols].to_numpy(float)
        out.append(np.stack([np.interp(u, tu, values[:, k]) for k in range(len(cols))], axis=-1))
    return np.stack(out) if out else np.empty((0, n, len(cols)))


def mean_std_path(df: pd.DataFrame, cols: list[str], n: int = N_RESAMPLE) -> dict[str, np.ndarray]:
    """Mean and std (n, len(cols)) over the repetitions of ``df`` (resampled), and their count."""
    stack = resample(df, cols, n)
    return {"mean": stack.mean(axis=0), "std": stack.std(axis=0), "repetitions": np.int64(len(stack))}


def commanded_tip(df: pd.DataFrame) -> np.ndarray:
    """(n, 3) the rigid FK of the commanded joint angles qc of each row (its robot's lengths)."""
    out = np.full((len(df), 3), np.nan)
    robots = df["robot"].to_numpy()
    for robot in np.unique(robots):
        mine = robots == robot
        out[mine] = kinematics.vsl_fk(df.loc[mine, QC].to_numpy(float), arm_lengths(str(robot)))
    return out


def position_errors(df: pd.DataFrame, path: np.ndarray) -> np.ndarray:
    """(n,) m: distance from each measured tip x to the polyline ``path`` (seed 000's position error)."""
    return trajectories.distance_to_path(df[X].to_numpy(float), path)


def error_groups(experiment2_df: pd.DataFrame, path: np.ndarray | None = None) -> pd.DataFrame:
    """Experiment 2 repetition rows with plan fields and ``error_m`` (distance to the desired path)."""
    rows = with_plan_fields(experiment2_df)
    if path is None:
        path = desired_path(str(rows["trajectory"].iloc[0]) if len(rows) else "curve")
    return rows.assign(error_m=position_errors(rows, path))


def path_errors(experiment2_df: pd.DataFrame, path: np.ndarray | None = None) -> pd.DataFrame:
    """Per session (robot, payload, pressure, command mode): mean, median, p95 and max position error, mm."""
    rows = error_groups(experiment2_df, path)
    keys = ["session", "robot", "payload_g", "pressure_bar", "mode"]
    grouped = rows.assign(error_mm=rows["error_m"] * 1e3).groupby(keys, dropna=False)["error_mm"]
    out = grouped.agg(
        mean_mm="mean", median_mm="median", p95_mm=lambda e: np.percentile(e, 95), max_mm="max", n="size"
    )
    return out.reset_index()


def box_stats(errors: np.ndarray, label: str) -> dict:
    """Fig. 7b's box of one group: box 25–75 %, whiskers the range (min–max), median and mean; m."""
    q1, med, q3 = np.percentile(errors, [25, 50, 75])
    return {"label": label, "q1": q1, "med": med, "q3": q3, "whislo": float(np.min(errors)),
            "whishi": float(np.max(errors)), "mean": float(np.mean(errors)), "fliers": np.empty(0),
            "n": len(errors)}  # fmt: skip
