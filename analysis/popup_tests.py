"""Seed 001's link tests on the POPUP arm: Table 1 (static k, damped frequency, damping) and Figure 7 (static
loading/unloading characteristic) from ``popup_static`` / ``popup_impact`` sessions.

The measurements themselves (the static curves, the taps' free oscillations, Table 1's estimates) are
``pipeline.link_tests``'s; this module sets them beside the paper's values and draws Figure 7.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from analysis.figure_files import save_figure
from pipeline.link_tests import table1_estimates

# Seed 001, Table 1 ("Test results: estimated parameters"), transcribed from the paper text (seeds/001_*.txt,
# Sec. "Experiments"); k is N/A (no static test) above 50 kPa.
PAPER_TABLE1 = pd.DataFrame(
    {
        "pressure_kpa": [10, 20, 30, 40, 50, 60, 70, 80, 90],
        "f_s_hz": [15.04, 15.63, 15.94, 16.17, 16.44, 16.56, 16.65, 16.83, 16.93],
        "c_hat": [0.557, 0.547, 0.463, 0.450, 0.433, 0.429, 0.412, 0.407, 0.406],
        "k": [296, 346, 348, 389, 407, np.nan, np.nan, np.nan, np.nan],
        "k_hat": [321, 347, 360, 370, 382, 388, 392, 401, 405],
    }
)


def table1(static_k: pd.DataFrame, impact: pd.DataFrame) -> pd.DataFrame:
    """Table 1 (``pipeline.link_tests.table1_estimates``) with the paper's values alongside."""
    paper = PAPER_TABLE1.rename(
        columns={c: f"paper_{c}" for c in PAPER_TABLE1.columns if c != "pressure_kpa"}
    )
    return table1_estimates(static_k, impact).merge(paper, on="pressure_kpa", how="left")


def table1_side_by_side(table: pd.DataFrame) -> pd.DataFrame:
    """Table 1 as text cells "ours / paper's" for f_s, k, k̂, ĉ (N/A where a test has no value), our ζ,
    indexed by pressure (kPa)."""

    def pair(a, b, fmt):
        return " / ".join("N/A" if pd.isna(v) else format(v, fmt) for v in (a, b))

    rows = {
        f"{r.pressure_kpa:g}": {
            "f_s (Hz)": pair(r.f_s_hz, r.paper_f_s_hz, ".2f"),
            "ζ": f"{r.zeta:.4f}",
            "k (N·m/rad)": pair(r.k, r.paper_k, ".0f"),
            "k̂ (N·m/rad)": pair(r.k_hat, r.paper_k_hat, ".0f"),
            "ĉ (N·m·s/rad)": pair(r.c_hat, r.paper_c_hat, ".3f"),
        }
        for r in table.itertuples()
    }
    return pd.DataFrame.from_dict(rows, orient="index").rename_axis("p (kPa)")


def paper_zeta(table: pd.DataFrame) -> pd.Series:
    """The damping ratio ζ the paper's Table 1 implies (it lists f_s, ĉ and k̂, not ζ): with ĉ = 2ζ√(k̂I),
    k̂ = I ω_n² and ω_n = 2π f_s / √(1 − ζ²), ζ√(1 − ζ²) = a := π ĉ f_s / k̂, so ζ² = (1 − √(1 − 4a²)) / 2."""
    a = np.pi * table["paper_c_hat"] * table["paper_f_s_hz"] / table["paper_k_hat"]
    return np.sqrt((1 - np.sqrt(1 - 4 * a**2)) / 2)


# The report's Table 1: (header, our column, the paper's column, format spec), columns of :func:`table1`.
TABLE1_COLUMNS = [
    ("f_s (Hz)", "f_s_hz", "paper_f_s_hz", ".2f"),
    ("ζ", "zeta", "paper_zeta", ".3f"),
    ("k (N·m/rad)", "k", "paper_k", ".0f"),
    ("k̂ (N·m/rad)", "k_hat", "paper_k_hat", ".0f"),
    ("ĉ (N·m·s/rad)", "c_hat", "paper_c_hat", ".3f"),
]


def table1_report(table: pd.DataFrame) -> pd.DataFrame:
    """Table 1 for the report: per pressure (kPa), each parameter ours and the paper's side by side (the
    paper's "name, paper (unit)" column beside ours; NaN where a test has no value, e.g. k above 50 kPa),
    numeric, with each column's format in ``attrs["formats"]``."""
    table = table.assign(paper_zeta=paper_zeta(table))
    out, formats = pd.DataFrame(index=pd.Index(table["pressure_kpa"].to_numpy(), name="p (kPa)")), {}
    for title, ours, paper, spec in TABLE1_COLUMNS:
        name, unit = title.removesuffix(")").rsplit(" (", 1) if "(" in title else (title, "")
        paper_title = f"{name}, paper" + (f" ({unit})" if unit else "")
        out[title], out[paper_title] = table[ours].to_numpy(), table[paper].to_numpy()
        formats |= {title: spec, paper_title: spec}
    out.attrs["formats"] = formats | {"p (kPa)": ".0f"}
    return out


def table1_markdown(table: pd.DataFrame) -> str:
    """Table 1 as a Markdown table: ours / the paper's for f_s, k, k̂, ĉ, and our ζ."""
    side = table1_side_by_side(table)
    header = [side.index.name, *side.columns]
    lines = ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    lines += ["| " + " | ".join([p, *row]) + " |" for p, row in zip(side.index, side.to_numpy(), strict=True)]
    return "\n".join(lines) + "\n\nEach cell: this work / seed 001 Table 1.\n"


def figure7(curves: pd.DataFrame, out_dir: Path) -> dict:
    """Figure 7: torque [N·m] against angular deflection [deg] per pressure, loading solid, unloading dashed
    (drawn from the loading branch's top point), mean of the runs with ±1 std error bars in δ, M_w(p) dotted
    (the end of the linear range). Writes
    ``fig7_popup_hysteresis.{pdf,png}`` (+ ``.json`` with the sessions); returns the plotted arrays:
    ``{(pressure_kpa, branch): {"x_deg", "xerr_deg", "y_nm"}}``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(7.2, 5.2), layout="constrained")
    colours = plt.get_cmap("viridis")(np.linspace(0.0, 0.85, curves["pressure_pa"].nunique()))
    data: dict = {}
    for colour, (p, c) in zip(colours, curves.groupby("pressure_pa"), strict=True):
        load, unload = c[c["branch"] == "loading"], c[c["branch"] == "unloading"]
        for branch, part, style in (
            ("loading", load, "-"),
            ("unloading", pd.concat([load.iloc[-1:], unload]), "--"),
        ):
            x, xerr = np.degrees(part["delta_rad"].to_numpy()), np.degrees(part["delta_std_rad"].to_numpy())
            y = part["torque_nm"].to_numpy()
            label = f"{p / 1e3:g} kPa" if branch == "loading" else None
            ax.errorbar(x, y, xerr=np.nan_to_num(xerr), color=colour, ls=style, marker="o", ms=3, capsize=2,
                        label=label)  # fmt: skip
            data[(p / 1e3, branch)] = {"x_deg": x, "xerr_deg": xerr, "y_nm": y}
        x_all = np.degrees(c["delta_rad"].to_numpy())
        ax.hlines(c["wrinkling_moment_nm"].iloc[0], x_all.min(), x_all.max(), color=colour, ls=":", lw=1.0)
    ax.plot([], [], "k-", label="loading")
    ax.plot([], [], "k--", label="unloading")
    ax.plot([], [], "k:", lw=0.8, label="wrinkling moment $M_w(p)$")
    ax.set_xlabel("angular deflection δ (deg)")
    ax.set_ylabel("torque τ (N·m)")
    ax.set_title("Link 2 static characteristic (mean of runs, ±1 std)", fontsize=10)
    ax.grid(alpha=0.3, axis="x")
    ax.legend(fontsize=8, loc="upper left")
    save_figure(fig, out_dir, "fig7_popup_hysteresis", {"sessions": curves.attrs.get("sessions", [])},
                arm_m=float(curves["arm_m"].iloc[0]), x="delta (deg)", y="torque (N m)")  # fmt: skip
    return data
