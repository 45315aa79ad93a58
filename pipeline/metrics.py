"""Tip-error metrics of seed 000 (V): Euclidean tip errors in mm, their summary, and the table of mean errors
per link pressure × payload cell (the paper's comparison grid: 0.5–2 bar, 0–100 g).

Inputs are SI (m, Pa, kg); outputs are in lab units with the unit in the name or the label (mm, bar, g).
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike

PRESSURE_EDGES_BAR = (0.5, 1.0, 1.5, 2.0)
PAYLOADS_G = (0, 25, 50, 75, 100)
PA_PER_BAR = 1e5


def tip_errors(pred: ArrayLike, true: ArrayLike) -> np.ndarray:
    """Euclidean distance (mm) between predicted and true tip positions, both (n, 3) in m."""
    pred, true = np.asarray(pred, float), np.asarray(true, float)
    if pred.shape != true.shape or pred.ndim != 2 or pred.shape[1] != 3:
        raise ValueError(f"pred and true must both be (n, 3), got {pred.shape} and {true.shape}")
    return np.linalg.norm(pred - true, axis=1) * 1e3


def summary(errors_mm: ArrayLike) -> dict[str, float]:
    """mean, median, p95, max (mm) and n of the finite errors (NaN stats when there are none)."""
    e = np.asarray(errors_mm, float).ravel()
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {"mean": np.nan, "median": np.nan, "p95": np.nan, "max": np.nan, "n": 0}
    return {
        "mean": float(e.mean()),
        "median": float(np.median(e)),
        "p95": float(np.percentile(e, 95)),
        "max": float(e.max()),
        "n": int(e.size),
    }


def pressure_labels(edges_bar: Sequence[float] = PRESSURE_EDGES_BAR) -> list[str]:
    """Bin labels like "0.5–1.0 bar" for consecutive edges."""
    return [f"{lo:.1f}–{hi:.1f} bar" for lo, hi in itertools.pairwise(edges_bar)]


def per_cell_long(
    errors_mm: ArrayLike,
    pressure_pa: ArrayLike,
    payload_kg: ArrayLike,
    pressure_edges_bar: Sequence[float] = PRESSURE_EDGES_BAR,
    payloads_g: Sequence[int] = PAYLOADS_G,
) -> pd.DataFrame:
    """Long table, one row per pressure bin × payload: ``pressure_bin``, ``payload_g``, ``mean_mm``,
    ``count``.

    Pressure bins are [lo, hi) except the last, which includes its upper edge; pressures outside every bin
    and non-finite errors are left out. Payloads go to the nearest listed value (grams).
    """
    e = np.asarray(errors_mm, float).ravel()
    p_bar = np.asarray(pressure_pa, float).ravel() / PA_PER_BAR
    m_g = np.asarray(payload_kg, float).ravel() * 1e3
    if not (e.shape == p_bar.shape == m_g.shape):
        raise ValueError(
            f"errors, pressures and payloads differ in length: {e.size}, {p_bar.size}, {m_g.size}"
        )
    edges = np.asarray(pressure_edges_bar, float)
    grams = np.asarray(payloads_g)
    labels = pressure_labels(pressure_edges_bar)
    b = np.searchsorted(edges, p_bar, side="right") - 1
    b = np.where(p_bar == edges[-1], len(labels) - 1, b)  # the last bin is closed on the right
    ok = np.isfinite(e) & (b >= 0) & (b < len(labels))
    col = np.argmin(np.abs(m_g[:, None] - grams[None, :]), axis=1)
    cell = b[ok] * len(grams) + col[ok]
    n_cells = len(labels) * len(grams)
    count = np.bincount(cell, minlength=n_cells)
    total = np.bincount(cell, weights=e[ok], minlength=n_cells)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return pd.DataFrame(
        {
            "pressure_bin": np.repeat(labels, len(grams)),
            "payload_g": np.tile(grams, len(labels)),
            "mean_mm": mean,
            "count": count.astype(int),
        }
    )


def per_cell(
    errors_mm: ArrayLike,
    pressure_pa: ArrayLike,
    payload_kg: ArrayLike,
    pressure_edges_bar: Sequence[float] = PRESSURE_EDGES_BAR,
    payloads_g: Sequence[int] = PAYLOADS_G,
    value: str = "mean_mm",
) -> pd.DataFrame:
    """Mean tip error (mm) per pressure bin (rows, "0.5–1.0 bar") × payload (columns, grams); NaN = empty.

    ``value="count"`` gives the number of points behind each mean instead (same binning, same shape); the
    long form with both is :func:`per_cell_long`.
    """
    long = per_cell_long(errors_mm, pressure_pa, payload_kg, pressure_edges_bar, payloads_g)
    if value not in ("mean_mm", "count"):
        raise ValueError(f"value must be 'mean_mm' or 'count', got {value!r}")
    table = long.pivot(index="pressure_bin", columns="payload_g", values=value)
    table = table.loc[pressure_labels(pressure_edges_bar), list(payloads_g)]
    table.index.name, table.columns.name = "pressure", "payload_g"
    return table


def cell_pressure_pa(rows: pd.DataFrame) -> np.ndarray:
    """The pressure a row of D is binned by: the mean of its link pressures ``p_*`` (the protocols drive
    both VSL links alike, so this is either of them up to the regulators' noise)."""
    cols = [c for c in rows.columns if c.startswith("p_") and c[2:].isdigit()]
    if not cols:
        raise KeyError("no link pressure columns p_0, p_1, … in the rows")
    return rows[cols].to_numpy(float).mean(axis=1)


def cell_records(
    errors: Mapping[str, ArrayLike],
    pressure_pa: ArrayLike,
    payload_kg: ArrayLike,
    pressure_edges_bar: Sequence[float] = PRESSURE_EDGES_BAR,
    payloads_g: Sequence[int] = PAYLOADS_G,
) -> list[dict]:
    """The per-cell table as JSON-ready records, the one format of model cards and baseline reports: per
    non-empty pressure bin × payload, ``pressure_bin`` (label), ``pressure_lo_bar``, ``pressure_hi_bar``,
    ``payload_g``, ``n`` and ``<name>_mean`` for each error series of ``errors`` (e.g. ``tip_mm``).

    Measured pressures just outside the grid (regulator noise around 0.5 or 2 bar) join the end bins."""
    edges = np.asarray(pressure_edges_bar, float)
    p = np.clip(np.asarray(pressure_pa, float), edges[0] * PA_PER_BAR, edges[-1] * PA_PER_BAR)
    table, keys = None, ["pressure_bin", "payload_g"]
    for name, e in errors.items():
        long = per_cell_long(e, p, payload_kg, pressure_edges_bar, payloads_g)
        long = long.rename(columns={"mean_mm": f"{name}_mean", "count": "n"})
        table = long if table is None else table.merge(long.drop(columns="n"), on=keys)
    if table is None:
        return []
    labels = pressure_labels(pressure_edges_bar)
    lo_hi = dict(zip(labels, itertools.pairwise(pressure_edges_bar), strict=True))
    table.insert(1, "pressure_lo_bar", [lo_hi[b][0] for b in table["pressure_bin"]])
    table.insert(2, "pressure_hi_bar", [lo_hi[b][1] for b in table["pressure_bin"]])
    table["payload_g"] = table["payload_g"].astype(int)
    return table[table["n"] > 0].to_dict("records")


def tip_report(errors_mm: ArrayLike, rows: pd.DataFrame) -> dict:
    """A model's (or the floor's) tip errors (mm) on ``rows`` of D: ``summary`` and ``per_cell`` records (the
    baseline reports' and the comparison table's one format)."""
    cells = cell_records({"tip_mm": errors_mm}, cell_pressure_pa(rows), rows["payload_kg"].to_numpy(float))
    return {"summary": summary(errors_mm), "per_cell": cells}
