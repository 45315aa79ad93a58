"""Our diagnostic figures plot exactly the numbers they are given (or compute from a dataset)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from analysis import diagnostics
from models.robot import load_robot
from models.statics import static_deflection
from pipeline.dataset_store import DatasetStore


def _card(seed):
    rng = np.random.default_rng(seed)
    val = np.exp(-np.arange(30) / 8) + rng.uniform(0, 0.01, 30)
    curves = [{"epoch": e, "train_loss": 1.1 * v, "val_loss": v} for e, v in enumerate(val)]
    per_cell = [{"pressure_lo_bar": lo, "pressure_hi_bar": lo + 0.5, "payload_g": g, "n": 10,
                 "tip_mm_mean": lo + g / 100} for lo in (0.5, 1.0, 1.5) for g in (0, 50, 100)]  # fmt: skip
    return {"curves": curves, "best_epoch": int(np.argmin(val)), "metrics": {"per_cell": per_cell}}


def test_heatmaps_and_learning_curves_plot_the_cards_numbers(tmp_path):
    cards = {"rigid": _card(0), "hybrid": _card(1)}
    grids = {k: diagnostics.cell_grid(c["metrics"]["per_cell"]) for k, c in cards.items()}
    assert grids["rigid"].loc["1–1.5", 50] == 1.5 and list(grids["rigid"].columns) == [0, 50, 100]
    assert list(grids["rigid"].index) == ["0.5–1", "1–1.5", "1.5–2"]  # by pressure, not alphabetically
    heat = diagnostics.error_heatmaps(grids, tmp_path)
    assert heat["png"].stat().st_size > 5000 and (tmp_path / "error_heatmaps.pdf").is_file()
    curves = diagnostics.learning_curves(cards, tmp_path)
    val = np.array([r["val_loss"] for r in cards["hybrid"]["curves"]])
    np.testing.assert_array_equal(curves["curves"]["hybrid"]["val"], val)
    assert curves["curves"]["hybrid"]["best_epoch"] == int(np.argmin(val)) + 1


def test_clock_fit_table_from_a_dataset_card(tmp_path):
    sessions = {f"s{k}": {"values": {"clock/tracker": {"drift_ppm": 10.0 * k, "jitter_p95_s": 0.002},
                                     "clock/servo_bus": {"drift_ppm": -5.0, "jitter_p95_s": 0.001}}}
                for k in range(3)}  # fmt: skip
    out = diagnostics.clock_fits(sessions, tmp_path)
    table = out["table"]
    assert len(table) == 6 and set(table["device"]) == {"tracker", "servo_bus"}
    assert table.loc[table["device"] == "tracker", "drift_ppm"].tolist() == [0.0, 10.0, 20.0]
    assert isinstance(table, pd.DataFrame) and out["png"].is_file()


def test_registration_residuals_are_the_cards_on_the_fitted_points(campaign_dataset, tmp_path):
    """The figure's residuals are the registered tip minus the model's deflected tip, and over the points the
    registration was fitted on they give back the dataset card's residual statistics."""
    lab, version, data = campaign_dataset
    _, card = DatasetStore(lab / "datasets").load("campaign", version)
    fitted = card["registration"]["vsl"]
    vsl = load_robot("vsl")
    out = diagnostics.registration_residuals(data, vsl, fitted, tmp_path)
    q = data[["q_0", "q_1", "q_2"]].to_numpy()
    delta, _ = static_deflection(vsl, q, data[["p_0", "p_1"]].to_numpy(), data["payload_kg"].to_numpy())
    expected = 1e3 * (data[["x_0", "x_1", "x_2"]].to_numpy() - vsl.chain().position(q, delta))
    np.testing.assert_allclose(out["residual_mm"], expected, atol=1e-9)
    sel = out["selected"]
    assert sel.sum() == fitted["selected"]
    rms = np.sqrt(np.mean(np.sum(expected[sel] ** 2, axis=1)))
    assert rms == pytest.approx(1e3 * fitted["residuals_selected"]["rms_m"], rel=1e-6)
    assert out["sag_mm"][sel].max() <= out["sag_mm"][~sel].min()  # the least-sagging points
    assert out["png"].stat().st_size > 10_000 and (tmp_path / "registration.pdf").is_file()
