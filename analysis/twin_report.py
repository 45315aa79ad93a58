"""The report's section "the twin against your robot" (issue 33), from what the lab's twin folder holds
(``pipeline.lab.TwinStore``): each fitted description's values beside the nominal ones with their standard
errors and what could not be identified (`vslab twin fit` keeps its ``fitted`` block there), the newest
check of each (`vslab twin check`) and the pretraining curve (`vslab twin curve`), drawn again here from its
table."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pandas as pd

from analysis.figure_files import save_figure
from pipeline.lab import Lab

TABLES = "your twin"  # the start of every table key of this section


def twin_against_robot(lab: Lab, res, out: Path) -> None:
    """Fill ``res`` (``analysis.lab_figures.Results``) with this section's tables, texts and the curve's
    figure: what the lab's twin folder holds (a lab whose twin was never fitted has no such section)."""
    for fitted in _records(lab.twin.fits(), res):
        name = fitted["name"]
        res.tables[f"{TABLES}: {name}, fitted beside nominal"] = fitted_table(fitted["parameters"])
        if "dataset" in fitted:  # the VSL arm: fitted to a dataset of settled points
            res.versions[f"dataset fitted, {name}"] = fitted["dataset"]
            words = [f"`{name}` ({fitted['file']}) was fitted to {fitted['points']:,} settled points of "
                     f"{fitted['sessions']} sessions of {fitted['dataset']}; the tracked tip's residual is "
                     f"{fitted['residual_rms_mm']:.3f} mm per axis."]  # fmt: skip
            if field := fitted.get("tracker_field"):  # the tracker's field distortion, fitted beside the arm
                words.append(f"The tracker's field is distorted: {field['rms_mm']:.2g} mm per axis over "
                             f"{field['length_scale_mm']:.0f} mm, fitted beside the arm; its map is in the "
                             "description.")  # fmt: skip
        else:  # the POPUP arm: fitted to its link tests
            res.versions[f"link tests fitted, {name}"] = fitted["link_tests"]
            words = [f"`{name}` ({fitted['file']}) was fitted to {fitted['static_holds']:,} static holds and "
                     f"{fitted['taps']:,} taps of the lab's {fitted['link_tests']}."]  # fmt: skip
        if fitted["not_identifiable"]:
            words.append("Not identifiable, left nominal: " + "; ".join(
                f"{n} ({why})" for n, why in fitted["not_identifiable"].items()) + ".")  # fmt: skip
        res.texts[f"{TABLES}: {name}, fitted beside nominal"] = " ".join(words)
    for record in _records(lab.twin.checks(), res):
        names = record["names"]
        if record.get("kind") == "link tests":  # the POPUP arm: its link tests run on each twin
            table = link_test_check_table(pd.DataFrame(record["table"]), names)
            res.tables[f"{TABLES}: {names['checked']} checked on the lab's link tests"] = table
            continue
        table = check_table(pd.DataFrame(record["table"]), names)
        res.tables[f"{TABLES}: {names['checked']} checked on {record['made_from']['dataset']}"] = table
    for record in _records([lab.twin.curve] if lab.twin.curve.exists() else [], res):
        curve = pd.DataFrame(record["curve"])
        drawn = pretraining_curve(curve, out, made_from=record["made_from"])
        res.figures["pretraining_curve"] = drawn["png"]
        res.tables[f"{TABLES}: pretraining curve, {record['net']}"] = curve_table(curve)


def _records(paths, res) -> list[dict]:
    """The JSON records at ``paths``; one that cannot be read is left out, its file and why in
    ``res.missing`` (the rest of the section is made)."""
    out = []
    for path in paths:
        try:
            out.append(json.loads(path.read_text()))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            res.missing[f"the twin against your robot: {path}"] = f"not a readable record ({exc})"
    return out


def fitted_table(parameters: dict[str, dict]) -> pd.DataFrame:
    """One row per fitted parameter (a ``fitted`` block's ``parameters``: value, stderr, nominal): nominal,
    fitted, its standard error and how far it moved (% and SE)."""
    rows = {
        name: {"nominal": v["nominal"], "fitted": v["value"], "standard error": v["stderr"],
               "change (%)": 100 * (v["value"] / v["nominal"] - 1) if v["nominal"] else math.nan,
               "change (SE)": (v["value"] - v["nominal"]) / v["stderr"] if v["stderr"] else math.nan}
        for name, v in parameters.items()
    }  # fmt: skip
    return pd.DataFrame.from_dict(rows, orient="index").rename_axis("parameter (SI units)")


def check_table(table: pd.DataFrame, names: dict[str, str]) -> pd.DataFrame:
    """The check per pressure × payload cell: each description's mean distance (mm) and the floor's."""
    shown = pd.DataFrame({
        "pressure": table["pressure_bin"],
        "payload (g)": ["all" if g < 0 else f"{g:g}" for g in table["payload_g"]],
        "points": table["n"],
        f"{names['nominal']} (mm)": table["nominal_mm_mean"],
        f"{names['checked']} (mm)": table["checked_mm_mean"],
    })  # fmt: skip
    if "floor_mm_mean" in table:
        shown["floor (mm)"] = table["floor_mm_mean"]
        shown[f"{names['checked']} / floor"] = table["checked_mm_mean"] / table["floor_mm_mean"]
    return shown.set_index(["pressure", "payload (g)"])


def link_test_check_table(table: pd.DataFrame, names: dict[str, str]) -> pd.DataFrame:
    """The POPUP check per pressure and quantity (``pipeline.popup_check``): the lab's value and standard
    error, each twin's value and its distance (% of the lab's)."""
    shown = pd.DataFrame({
        "pressure (kPa)": table["pressure_kpa"], "quantity": table["quantity"],
        "measured": table["measured"], "standard error": table["se"],
        names["nominal"]: table["nominal"], f"{names['nominal']} (%)": table["nominal_pct"],
        names["checked"]: table["checked"], f"{names['checked']} (%)": table["checked_pct"],
    })  # fmt: skip
    return shown.set_index(["pressure (kPa)", "quantity"])


def curve_table(curve: pd.DataFrame) -> pd.DataFrame:
    """The curve's rows: measured rows used, and the test errors of each net."""
    shown = pd.DataFrame({
        "measured rows": [f"{f:.0%}" if f else "none (twin only)" for f in curve["fraction"]],
        "train rows": curve["train_rows"], "val rows": curve["val_rows"],
        "alone (mm)": curve["measured_only_tip_mean_mm"],
        "pretrained, fine-tuned (mm)": curve["fine_tuned_tip_mean_mm"],
    })  # fmt: skip
    return shown.set_index("measured rows")


def pretraining_curve(curve: pd.DataFrame, out_dir: Path, name: str = "pretraining_curve",
                      made_from: dict | None = None) -> dict:  # fmt: skip
    """Test error against the measured rows used (``pipeline.pretrain.learning_curve``'s table, log–log): the
    net trained on them alone beside the net pretrained on the twin's campaign and fine-tuned on them, and
    the pretrained net alone (no measured row) as a level line."""
    import matplotlib

    matplotlib.use("Agg")  # files only, as every figure of analysis/
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    rows = curve[curve["fraction"] > 0]
    used = (rows["train_rows"] + rows["val_rows"]).to_numpy()
    fig, ax = plt.subplots(figsize=(5.2, 3.6), layout="constrained")
    ax.plot(used, rows["measured_only_tip_mean_mm"], "o-", color="tab:orange", label="measured rows alone")
    ax.plot(used, rows["fine_tuned_tip_mean_mm"], "s-", color="tab:blue", label="twin-pretrained, fine-tuned")
    twin_only = curve.loc[curve["fraction"] == 0, "fine_tuned_tip_mean_mm"]
    if len(twin_only):
        ax.axhline(float(twin_only.iloc[0]), ls=":", color="tab:gray", label="twin-pretrained only")
    for n, f, e in zip(used, rows["fraction"], rows["measured_only_tip_mean_mm"], strict=True):
        ax.annotate(f"{f:.0%}", (n, e), xytext=(0, 6), textcoords="offset points", ha="center", fontsize=7,
                    color="tab:gray")  # fmt: skip
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.margins(x=0.08, y=0.12)  # room for the labels
    for axis in (ax.yaxis.set_major_formatter, ax.yaxis.set_minor_formatter):
        axis(matplotlib.ticker.FormatStrFormatter("%.2g"))
    ax.set_xlabel("measured rows used (train + val)")
    ax.set_ylabel("test tip error, mean (mm)")
    ax.legend(fontsize=8)
    plotted = {"rows": used, "measured_only": rows["measured_only_tip_mean_mm"].to_numpy(),
               "fine_tuned": rows["fine_tuned_tip_mean_mm"].to_numpy()}  # fmt: skip
    return {"png": save_figure(fig, out_dir, name, made_from), "curve": plotted}
