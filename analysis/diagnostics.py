"""Our figures beside the papers': error heatmaps per pressure × payload, learning curves, clock-fit and
registration diagnostics. Each function writes PDF + PNG and returns the plotted numbers (for tests)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from analysis.figure_files import save_figure


def cell_grid(per_cell: list[dict]) -> pd.DataFrame:
    """Per-cell records (``pipeline.metrics.cell_records``: model cards, baseline reports) as a pressure-bin ×
    payload table of mean tip error (mm)."""
    df = pd.DataFrame(per_cell)
    bins = ["pressure_lo_bar", "pressure_hi_bar"]
    grid = df.pivot_table(index=bins, columns="payload_g", values="tip_mm_mean")
    grid.index = [f"{lo:g}–{hi:g}" for lo, hi in grid.index]  # sorted by pressure, then labelled
    return grid


def error_heatmaps(
    grids: dict[str, pd.DataFrame], out_dir: Path, name: str = "error_heatmaps", made_from: dict | None = None
) -> dict:
    """One heatmap per model (rigid, hybrid, baselines): mean tip error (mm) per pressure bin × payload, on a
    shared colour scale, each cell annotated."""
    vmax = max(float(np.nanmax(g.to_numpy())) for g in grids.values())
    fig, axes = plt.subplots(1, len(grids), figsize=(3.6 * len(grids), 3.2), squeeze=False, sharey=True)
    for ax, (label, grid) in zip(axes[0], grids.items(), strict=True):
        image = ax.imshow(grid.to_numpy(), vmin=0.0, vmax=vmax, cmap="viridis", aspect="auto")
        ax.set_xticks(range(grid.shape[1]), [f"{c:g}" for c in grid.columns])
        ax.set_yticks(range(grid.shape[0]), [f"{r} bar" for r in grid.index])
        ax.set_xlabel("payload (g)")
        ax.set_title(label)
        for (r, c), v in np.ndenumerate(grid.to_numpy()):
            ax.text(
                c, r, f"{v:.2f}", ha="center", va="center", color="w" if v < 0.6 * vmax else "k", fontsize=8
            )
    axes[0][0].set_ylabel("link pressure")
    fig.colorbar(image, ax=axes[0].tolist(), label="mean tip error (mm)", shrink=0.9)
    return {"png": save_figure(fig, out_dir, name, made_from, tight=True), "grids": grids}


def learning_curves(
    cards: dict[str, dict], out_dir: Path, name: str = "learning_curves", made_from: dict | None = None
) -> dict:
    """Training and validation loss per epoch of each model card (log scale), one panel per model (their
    targets differ: a residual net learns the correction, the paper's net the whole pose), the best epoch
    marked (epochs counted from 1 on the axis)."""
    runs = {}
    for label, card in cards.items():
        curves = pd.DataFrame(card.get("curves") or [])  # one record per epoch (from 0)
        if "val_loss" in curves:
            runs[label] = (card, curves)
    fig, axes = plt.subplots(1, max(len(runs), 1), figsize=(3.6 * max(len(runs), 1) + 0.6, 3.4),
                             squeeze=False, layout="constrained")  # fmt: skip
    plotted = {}
    for ax, (label, (card, curves)) in zip(axes[0], runs.items(), strict=False):
        epochs, val = curves["epoch"].to_numpy() + 1, curves["val_loss"].to_numpy(float)
        train = curves["train_loss"].to_numpy(float) if "train_loss" in curves else np.zeros(0)
        ax.plot(epochs, val, color="tab:blue", label="validation")
        if len(train):
            ax.plot(epochs, train, ls=":", color="tab:orange", label="training")
        best = int(card.get("best_epoch", int(np.argmin(val)))) + 1
        ax.plot([best], [val[best - 1]], "o", color="tab:blue", label=f"best (epoch {best})")
        plotted[label] = {"train": train, "val": val, "best_epoch": best}
        ax.set_yscale("log")
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("epoch")
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("loss (MSE of standardised targets)")
    return {"png": save_figure(fig, out_dir, name, made_from, tight=True), "curves": plotted}


def clock_fits(
    sessions: dict[str, dict], out_dir: Path, name: str = "clock_fits", made_from: dict | None = None
) -> dict:
    """From a dataset card's sessions: each device's fitted drift (ppm) and jitter p95 (ms), per session."""
    rows = [
        {"session": sid, "device": key.split("/", 1)[1], "drift_ppm": v["drift_ppm"],
         "jitter_p95_ms": 1e3 * v["jitter_p95_s"]}
        for sid, s in sessions.items() for key, v in s.get("values", {}).items() if key.startswith("clock/")
    ]  # fmt: skip
    df = pd.DataFrame(rows)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.4))
    devices = sorted(df["device"].unique()) if len(df) else []
    for k, device in enumerate(devices):
        d = df[df["device"] == device]
        jitter = np.random.default_rng(k).uniform(-0.15, 0.15, len(d))
        a1.plot(k + jitter, d["drift_ppm"], "o", ms=3)
        a2.plot(k + jitter, d["jitter_p95_ms"], "o", ms=3)
    for ax, label in ((a1, "fitted drift (ppm)"), (a2, "receive jitter, p95 (ms)")):
        ax.set_xticks(range(len(devices)), devices, rotation=20)
        ax.set_ylabel(label)
    a1.set_title("device clocks against host time")
    return {"png": save_figure(fig, out_dir, name, made_from, tight=True), "table": df}


def registration_residuals(data: pd.DataFrame, robot, registration: dict, out_dir: Path,
                           name: str = "registration", made_from: dict | None = None) -> dict:  # fmt: skip
    """How well the tracker's registered tip agrees with the robot model at the dataset's static points.

    Residual = measured tip in the base frame (the registered tracker, ``x_*``) − the model's tip at the
    measured joints with the links' static deflection at the measured pressures and payload
    (``pipeline.registration.model_tip``). Left: |residual| against the sag the model predicts, the points the
    registration was fitted on (the ``selected`` least-sagging ones, from the dataset card) marked off; right:
    the residual's components over those points. Returns ``{"sag_mm", "residual_mm" (n, 3), "selected"}``."""
    from pipeline.registration import model_tip
    from pipeline.tables import columns

    rows = data[data["robot"] == robot.name]
    q, p = columns(rows, "q"), columns(rows, "p")
    payload = rows["payload_kg"].to_numpy(float)
    tip = model_tip(robot, q, p, payload)
    residual = 1e3 * (columns(rows, "x") - tip)
    sag = 1e3 * np.linalg.norm(tip - model_tip(robot, q), axis=1)
    n_selected = int(registration.get("selected", len(rows)))
    selected = np.zeros(len(rows), bool)
    selected[np.argsort(sag, kind="stable")[:n_selected]] = True
    norm = np.linalg.norm(residual, axis=1)

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.8), layout="constrained")
    a1.plot(sag[~selected], norm[~selected], ".", ms=2, color="tab:gray", alpha=0.5, rasterized=True,
            label="other static points")  # fmt: skip
    a1.plot(sag[selected], norm[selected], ".", ms=2, color="tab:blue", alpha=0.5, rasterized=True,
            label=f"fitted on ({n_selected} least sag)")  # fmt: skip
    a1.set_xlabel("sag the model predicts (mm)")
    a1.set_ylabel("|measured − model tip| (mm)")
    a1.set_title(f"{robot.name}: registration residuals", fontsize=10)
    a1.legend(fontsize=8, markerscale=4)
    a1.grid(alpha=0.3)
    edges = np.linspace(-1.0, 1.0, 41)
    for k, axis in enumerate("xyz"):
        r = residual[selected, k]
        a2.hist(np.clip(r, edges[0], edges[-1]), bins=edges, histtype="step", lw=1.3,
                label=f"{axis}: mean {r.mean():+.3f}, std {r.std():.3f}")  # fmt: skip
    a2.set_xlabel("residual component, fitted points (mm)")
    a2.set_ylabel("points")
    a2.legend(fontsize=8)
    a2.grid(alpha=0.3)
    return {
        "png": save_figure(fig, out_dir, name, made_from, tight=True),
        "sag_mm": sag,
        "residual_mm": residual,
        "selected": selected,
    }
