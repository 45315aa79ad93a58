"""Tip-error metrics on numbers small enough to check by hand."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pipeline import metrics


def test_tip_errors_are_euclidean_mm():
    pred = np.array([[0.0, 0.0, 0.0], [0.003, 0.004, 0.0], [1.0, 1.0, 1.0]])
    true = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 1.0, 1.012]])
    np.testing.assert_allclose(metrics.tip_errors(pred, true), [0.0, 5.0, 12.0], atol=1e-9)
    with pytest.raises(ValueError, match="must both be"):
        metrics.tip_errors(pred[:, :2], true[:, :2])


def test_summary_exact_and_ignores_nan():
    s = metrics.summary([1.0, 2.0, 3.0, 4.0, np.nan])
    assert s == {"mean": 2.5, "median": 2.5, "p95": pytest.approx(3.85), "max": 4.0, "n": 4}
    assert metrics.summary([np.nan])["n"] == 0


def test_per_cell_bins_payloads_and_counts():
    # (pressure bar, payload kg, error mm): two in the first cell, one on the last bin's closed upper edge,
    # one below the first edge (dropped), one NaN error (dropped), payloads snapped to the nearest gram value
    points = [
        (0.6, 0.0, 1.0),
        (0.99, 0.004, 3.0),
        (1.2, 0.049, 5.0),
        (2.0, 0.1, 7.0),
        (1.5, 0.07, 9.0),
        (0.3, 0.0, 100.0),
        (0.7, 0.0, np.nan),
    ]
    p_bar, m_kg, e = (np.array(c) for c in zip(*points, strict=True))
    mean = metrics.per_cell(e, p_bar * 1e5, m_kg)
    count = metrics.per_cell(e, p_bar * 1e5, m_kg, value="count")
    assert list(mean.index) == ["0.5–1.0 bar", "1.0–1.5 bar", "1.5–2.0 bar"]
    assert list(mean.columns) == [0, 25, 50, 75, 100]
    assert mean.loc["0.5–1.0 bar", 0] == 2.0 and count.loc["0.5–1.0 bar", 0] == 2
    assert mean.loc["1.0–1.5 bar", 50] == 5.0
    assert mean.loc["1.5–2.0 bar", 100] == 7.0 and mean.loc["1.5–2.0 bar", 75] == 9.0
    assert int(count.to_numpy().sum()) == 5 and int(np.isfinite(mean.to_numpy()).sum()) == 4
    long = metrics.per_cell_long(e, p_bar * 1e5, m_kg)
    assert list(long.columns) == ["pressure_bin", "payload_g", "mean_mm", "count"] and len(long) == 15
    assert long["count"].sum() == 5
    with pytest.raises(ValueError, match="value must be"):
        metrics.per_cell(e, p_bar * 1e5, m_kg, value="median")


def test_per_cell_custom_edges():
    mean = metrics.per_cell(
        [2.0, 4.0], [0.6e5, 1.6e5], [0.0, 0.0], pressure_edges_bar=(0.5, 2.0), payloads_g=(0,)
    )
    assert mean.shape == (1, 1) and mean.iloc[0, 0] == 3.0


def test_cell_records_one_format_for_cards_and_baselines():
    """Records per non-empty cell with both error series; pressures just outside the grid join the end
    bins; the means are those of a plain group-by."""
    rng = np.random.default_rng(5)
    n = 400
    p_bar = rng.uniform(0.48, 2.02, n)
    grams = rng.choice([0, 50, 100], n)
    tip, joint = rng.exponential(1.0, n), rng.exponential(3.0, n)
    records = metrics.cell_records({"tip_mm": tip, "joint_mrad": joint}, p_bar * 1e5, grams / 1e3)
    assert sum(r["n"] for r in records) == n
    assert {r["payload_g"] for r in records} == {0, 50, 100}
    b = np.clip(np.searchsorted([1.0, 1.5], p_bar, side="right"), 0, 2)  # bins [.5,1) [1,1.5) [1.5,2]
    lo = np.array([0.5, 1.0, 1.5])[b]
    for r in records:
        sel = (lo == r["pressure_lo_bar"]) & (grams == r["payload_g"])
        assert r["pressure_hi_bar"] == r["pressure_lo_bar"] + 0.5 and r["n"] == sel.sum()
        assert r["tip_mm_mean"] == pytest.approx(tip[sel].mean())
        assert r["joint_mrad_mean"] == pytest.approx(joint[sel].mean())
        assert r["pressure_bin"] == f"{r['pressure_lo_bar']:.1f}–{r['pressure_hi_bar']:.1f} bar"
    rows = pd.DataFrame({"p_0": [1e5, 2e5], "p_1": [1.2e5, 1.8e5]})
    np.testing.assert_allclose(metrics.cell_pressure_pa(rows), [1.1e5, 1.9e5])
