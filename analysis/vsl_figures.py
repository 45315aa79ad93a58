"""Seed 000's Figures 5, 6, 7a and 7b from Experiment 1/2 datasets (and a trained forward model).

Each function writes ``<stem>.pdf`` + ``<stem>.png`` and ``<stem>.json`` (the dataset/model versions it was
given and the code version) into ``out_dir`` and returns a :class:`FigureResult` whose ``data`` holds what was
plotted, in SI (m): mean/std paths ``(n, 2)`` in the XZ plane, box statistics. Millimetres only on the axes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from analysis import vsl_paths as vp
from analysis.figure_files import save_figure
from models.hybrid import FORWARD_INPUTS
from models.trajectories import EXPERIMENT1_NAMES

MM = 1e3
XZ = [0, 2]
COLORS = {"servo": "tab:blue", "rigid": "tab:red", 0.5: "tab:green", 1.0: "tab:purple", 1.5: "goldenrod",
          2.0: "tab:orange", "ik": "tab:green", "hybrid": "tab:red", "static": "tab:blue",
          "history": "tab:brown", "model": "tab:green", "actual": "tab:blue",
          "forward": "tab:purple"}  # fmt: skip
FIG5_LABELS = {"servo": "servo (FK of encoders)", "rigid": "rigid arm"}
FIG6_CASES = ((25, 1.5), (75, 0.5))  # seed 000 Fig. 6: (payload g, pressure bar), left and right


@dataclass
class FigureResult:
    """Files written, the plotted data (SI) and the record of input versions."""

    paths: list[Path]
    data: dict
    record: dict = field(default_factory=dict)


def _subplots(nrows: int = 1, ncols: int = 1, figsize=(6.0, 4.0), **kw):
    """A figure not owned by pyplot (no GUI backend, nothing to close) and its axes."""
    fig = Figure(figsize=figsize, layout="constrained")
    return fig, fig.subplots(nrows, ncols, **kw)


def _save(fig, out_dir: Path, stem: str, versions: dict) -> tuple[list[Path], dict]:
    png = save_figure(fig, out_dir, stem, versions)
    record = json.loads(png.with_suffix(".json").read_text())
    return [png.with_suffix(".pdf"), png, png.with_suffix(".json")], record


def _line(ax, stats: dict, color, label: str, style: str = "-", zorder: float = 2, every: int = 12) -> None:
    """Mean path (mm) with ± std bars in x and z at every ``every``-th resampled point."""
    m, s = stats["mean"][:, XZ] * MM, stats["std"][:, XZ] * MM
    ax.plot(m[:, 0], m[:, 1], style, color=color, lw=1.4, label=label, zorder=zorder)
    k = slice(0, None, every)
    ax.errorbar(m[k, 0], m[k, 1], xerr=s[k, 0], yerr=s[k, 1], fmt="none", ecolor=color, alpha=0.5, lw=0.8)


def _xz_axes(ax, title: str) -> None:
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)


def fig5_data(trajectories_df: pd.DataFrame, n: int = vp.N_RESAMPLE) -> dict:
    """{trajectory: {payload_g: {line: {mean, std (n, 3) m, repetitions}}}}; lines: ``servo`` (rigid FK of
    the encoders, every arm of the cell pooled), ``rigid`` (the rigid arm), and each VSL pressure (bar)."""
    rows = vp.with_plan_fields(trajectories_df)
    rows = rows[rows["experiment"] == "experiment1"]
    out: dict = {}
    for (name, grams), cell in rows.groupby(["trajectory", "payload_g"], sort=True):
        lines = {"servo": vp.mean_std_path(cell, vp.FK, n)}
        rigid = cell[cell["pressure_bar"].isna()]
        if len(rigid):
            lines["rigid"] = vp.mean_std_path(rigid, vp.X, n)
        for bar, g in cell.dropna(subset=["pressure_bar"]).groupby("pressure_bar", sort=True):
            lines[float(bar)] = vp.mean_std_path(g, vp.X, n)
        out.setdefault(name, {})[float(grams)] = lines
    return out


def fig5(
    trajectories_df: pd.DataFrame, out_dir: Path, versions: dict, stem: str = "fig5", n: int = vp.N_RESAMPLE
) -> FigureResult:
    """Fig. 5: Experiment 1, trajectory (rows) × payload (columns): servo path, rigid arm and the VSL at each
    pressure, mean ± std over the repetitions in the XZ plane."""
    data = fig5_data(trajectories_df, n)
    names = [t for t in EXPERIMENT1_NAMES if t in data]
    payloads = sorted({g for t in names for g in data[t]})
    fig, axes = _subplots(len(names), len(payloads), figsize=(2.8 * len(payloads) + 0.6, 2.9 * len(names)),
                             squeeze=False)  # fmt: skip
    for i, name in enumerate(names):
        for j, grams in enumerate(payloads):
            ax = axes[i, j]
            for line, stats in data[name].get(grams, {}).items():
                label = FIG5_LABELS.get(line) or f"VSL {line:g} bar"
                style = "--" if line == "servo" else "-"  # dashed: the rigid arm's path lies on it
                _line(ax, stats, COLORS.get(line, None), label, style, zorder=3 if line == "servo" else 2)
            _xz_axes(ax, f"({'abc'[EXPERIMENT1_NAMES.index(name)]}) {name}, {grams:g} g")
    handles, labels = _unique_handles(axes)
    ncol = min(len(labels), max(2, len(payloads)))
    fig.legend(handles, labels, loc="outside lower center", ncol=ncol, fontsize=8, title="mean ± std")
    paths, record = _save(fig, out_dir, stem, versions)
    return FigureResult(paths, data, record)


def _unique_handles(axes):
    seen: dict = {}
    for ax in np.ravel(axes):
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            seen.setdefault(lab, h)
    return list(seen.values()), list(seen)


def fig6_data(trajectories_df: pd.DataFrame, forward_model, cases=FIG6_CASES, trajectory: str = "curve",
              n: int = vp.N_RESAMPLE) -> dict:  # fmt: skip
    """{"<g>g/<bar>bar": {model, forward, actual: {mean, std, repetitions}}}: the VSL arm's rows of the case
    under model-based commands (Experiment 1, or Experiment 2's ``ik``); ``forward`` is
    ``forward_model.predict`` of each row's FORWARD_INPUTS, resampled like the rest."""
    rows = vp.with_plan_fields(trajectories_df)
    rows = rows[(rows["trajectory"] == trajectory) & rows["mode"].isin(["", "ik"])]
    out = {}
    for grams, bar in cases:
        case = rows[np.isclose(rows["payload_g"], grams) & np.isclose(rows["pressure_bar"], bar)]
        if not len(case):
            raise ValueError(f"no {trajectory} rows of the VSL arm at {grams:g} g / {bar:g} bar")
        pred = np.asarray(forward_model.predict(case[list(FORWARD_INPUTS)].to_numpy(np.float32)), float)
        case = case.assign(**{f"h_{k}": pred[:, k] for k in range(3)})
        out[f"{grams:g}g/{bar:g}bar"] = {
            "model": vp.mean_std_path(case, vp.FK, n),
            "forward": vp.mean_std_path(case, ["h_0", "h_1", "h_2"], n),
            "actual": vp.mean_std_path(case, vp.X, n),
        }
    return out


def fig6(trajectories_df: pd.DataFrame, forward_model, out_dir: Path, versions: dict, cases=FIG6_CASES,
         stem: str = "fig6", n: int = vp.N_RESAMPLE) -> FigureResult:  # fmt: skip
    """Fig. 6: the curve at each case: model-based FK path, hybrid forward prediction, actual (mean ± std)."""
    data = fig6_data(trajectories_df, forward_model, cases, n=n)
    fig, axes = _subplots(1, len(data), figsize=(4.2 * len(data), 4.4), squeeze=False)
    labels = {"model": "model-based FK", "forward": "hybrid forward model", "actual": "actual (mean ± std)"}
    for ax, (case, lines) in zip(axes[0], data.items(), strict=True):
        for line, stats in lines.items():
            _line(
                ax,
                stats,
                COLORS[line],
                labels[line],
                "--" if line == "forward" else "-",
                3 - (line == "actual"),
            )
        grams, bar = case.split("/")
        _xz_axes(ax, f"curve, {grams.removesuffix('g')} g, {bar.removesuffix('bar')} bar")
    handles, names = _unique_handles(axes)
    fig.legend(handles, names, loc="outside lower center", ncol=len(names))
    paths, record = _save(fig, out_dir, stem, versions)
    return FigureResult(paths, data, record)


def fig7_data(experiment2_df: pd.DataFrame, path: np.ndarray | None = None, n: int = vp.N_RESAMPLE) -> dict:
    """{"desired": (m, 3), "paths": {case: {mode: {mean, std}, "<mode>/commanded": {mean, std}}},
    "boxes": [box_stats…]} — paths of the VSL arm per command mode (the commanded path, rigid FK of qc, for
    compensated modes); boxes: per case, the VSL arm per mode and the rigid arm (model-based IK), in m."""
    rows = vp.error_groups(experiment2_df, path)
    trajectory = str(rows["trajectory"].iloc[0]) if len(rows) else "curve"
    desired = vp.desired_path(trajectory) if path is None else np.asarray(path, float)
    rows = rows.assign(**{f"c_{k}": v for k, v in enumerate(vp.commanded_tip(rows).T)})
    vsl = rows.dropna(subset=["pressure_bar"])
    order = {m: k for k, m in enumerate(vp.MODE_LABELS)}
    out: dict = {"desired": desired, "paths": {}, "boxes": []}
    for (grams, bar), case in vsl.groupby(["payload_g", "pressure_bar"], sort=True):
        key = f"{grams:g}g/{bar:g}bar"
        lines = out["paths"][key] = {}
        for mode in sorted(case["mode"].unique(), key=lambda m: order.get(m, 99)):
            g = case[case["mode"] == mode]
            lines[mode] = vp.mean_std_path(g, vp.X, n)
            if mode != "ik":
                lines[f"{mode}/commanded"] = vp.mean_std_path(g, ["c_0", "c_1", "c_2"], n)
            label = f"{key}\nVSL {mode}"
            out["boxes"].append(vp.box_stats(g["error_m"].to_numpy(), label))
        rigid = rows[rows["pressure_bar"].isna() & np.isclose(rows["payload_g"], grams)]
        if len(rigid):
            # the rigid arm has no pressure: its box is labelled by the payload alone
            out["boxes"].append(vp.box_stats(rigid["error_m"].to_numpy(), f"{grams:g}g\nrigid ik"))
    return out


def fig7(experiment2_df: pd.DataFrame, out_dir: Path, versions: dict, path: np.ndarray | None = None,
         stem: str = "fig7", n: int = vp.N_RESAMPLE) -> FigureResult:  # fmt: skip
    """Fig. 7a (desired, actual paths per command mode, compensation path dashed) and Fig. 7b (position error
    boxes: box 25–75 %, whiskers min–max, median line, mean marked) as ``<stem>a`` and ``<stem>b``."""
    data = fig7_data(experiment2_df, path, n)
    cases = data["paths"]
    width = max(6.0, 4.4 * len(cases))
    fig, axes = _subplots(1, len(cases), figsize=(width, 5.0), squeeze=False)
    desired = data["desired"][:, XZ] * MM
    for ax, (case, lines) in zip(axes[0], cases.items(), strict=True):
        ax.plot(desired[:, 0], desired[:, 1], color="black", lw=1.0, label="desired path")
        for line, stats in lines.items():
            mode, _, commanded = line.partition("/")
            label = f"{vp.MODE_LABELS.get(mode, mode)}: " + ("command (dashed)" if commanded else "actual")
            style = "--" if commanded else "-"
            ax.plot(*(stats["mean"][:, XZ] * MM).T, style, color=COLORS.get(mode), lw=1.3, label=label)
        grams, bar = case.split("/")
        _xz_axes(ax, f"(a) curve, {grams.removesuffix('g')} g, {bar.removesuffix('bar')} bar")
    handles, names = _unique_handles(axes)
    fig.legend(handles, names, loc="outside lower center", ncol=2, fontsize=8)
    paths_a, record = _save(fig, out_dir, f"{stem}a", versions)

    boxes = data["boxes"]
    fig, ax = _subplots(figsize=(max(5.0, 1.2 * len(boxes) + 1.0), 4.2))
    mm_boxes = [{k: (v * MM if k not in ("label", "n") else v) for k, v in b.items()} for b in boxes]
    mean_style = {"marker": "D", "markersize": 5, "markerfacecolor": "black", "markeredgecolor": "black"}
    art = ax.bxp(mm_boxes, showmeans=True, patch_artist=True, meanprops=mean_style,
                 medianprops={"color": "black"})  # fmt: skip
    for patch, b in zip(art["boxes"], boxes, strict=True):
        mode = b["label"].split()[-1]
        rigid = b["label"].split("\n")[-1].startswith("rigid")
        patch.set_facecolor("tab:gray" if rigid else COLORS.get(mode))
        patch.set_alpha(0.6)
    ax.set_ylabel("position error (mm)")
    ax.set_title("(b) position error: distance to the desired path", fontsize=9)
    key = [Line2D([], [], ls="none", **mean_style), Line2D([], [], color="black")]
    ax.legend(key, ["mean", "median"], title="box 25–75 %, whiskers min–max", fontsize=7, title_fontsize=7)
    ax.tick_params(axis="x", labelsize=8)
    ax.grid(axis="y", alpha=0.3)
    paths_b, _ = _save(fig, out_dir, f"{stem}b", versions)
    return FigureResult(paths_a + paths_b, data, record)
