"""The lab's report page: the figures and tables of :func:`analysis.lab_figures.all_figures`, each section
opening with what it shows and what to compare, one offline HTML file (``lab.report / "index.html"``)."""

from __future__ import annotations

from dataclasses import dataclass

import pandas as pd

from analysis.lab_figures import Results
from analysis.report import Report
from pipeline.lab import Lab, LabPath


def lab_report(lab: Lab, res: Results, timings: dict[str, float] | None = None) -> LabPath:
    """``lab.report / "index.html"`` from the figures and tables of :func:`all_figures`: the overview, then
    each of :data:`SECTIONS` that has a figure or a table, opening with its intro."""
    page = Report("vslab: the lab on its digital twin")
    tables = {"what the figures were made from": versions_table(res.versions)}
    if timings:
        tables["main job steps"] = pd.DataFrame({"time (s)": timings}).rename_axis("step")
    if res.missing:
        tables["not made (and why)"] = pd.DataFrame({"reason": res.missing}).rename_axis("figure or table")
    page.section("Overview", intro=OVERVIEW, tables=tables)
    for section in SECTIONS:
        figures = [res.figures[n] for n in section.figures if n in res.figures]
        tables = {k: v for k, v in res.tables.items() if k.startswith(section.tables)}
        text = "\n\n".join(v for k, v in res.texts.items() if k in section.tables)
        if figures or tables:
            page.section(section.title, intro=section.intro, text=text, figures=figures, tables=tables)
    return page.write(lab.report / "index.html")


def versions_table(versions: dict[str, str | dict]) -> pd.DataFrame:
    """What the figures were made from: one row per input, its version, and, for the settings a study was
    run with (a dict), those settings in words (``repetitions=2``; "defaults" when none)."""
    rows = {}
    for name, settings in versions.items():
        if not isinstance(settings, dict):
            rows[name] = {"version": settings, "settings": ""}
        else:
            words = ", ".join(f"{k}={v}" for k, v in sorted(settings.items())) or "defaults"
            rows[name] = {"version": None, "settings": words}
    table = pd.DataFrame.from_dict(rows, orient="index", columns=["version", "settings"]).rename_axis("input")
    return table if table["settings"].ne("").any() else table.drop(columns="settings")


@dataclass(frozen=True)
class ReportSection:
    """One section of the report: its title, its intro (what it shows, what to compare), the figures it
    shows (by name) and the tables it gathers (by the start of their key in ``Results.tables``)."""

    title: str
    intro: str
    figures: tuple[str, ...] = ()
    tables: tuple[str, ...] = ()


OVERVIEW = """Everything on this page was produced on the digital twin by vslab's main job: sessions recorded
through the device emulators and simulated in batches, the pipeline's datasets, the trained networks, and the
papers' experiments repeated with them. The papers' numbers stand beside ours where the papers give them; the
twin's parameters marked ASSUMED in configs/ are ours, so compare trends with the papers, not values."""

SECTIONS = [
    ReportSection(
        "The twin against your robot",
        """The description fitted to the lab's own arm (`vslab twin fit`): each value beside the nominal one,
        with its standard error and how far it moved, and what the data could not identify. Then how well it
        predicts data the fit did not see, beside the nominal description and the floor (`vslab twin
        check`), and what pretraining on it saves (`vslab twin curve`): the test error of a network against
        the measured rows it used, alone and pretrained on the twin's campaign. A fitted twin near the floor
        predicts what can be predicted; a change of many standard errors is your arm differing from the
        papers'.""",
        ("pretraining_curve",),
        ("your twin",),
    ),
    ReportSection(
        "The twin with unmodelled effects: every model beside the floor (mean tip error, mm; grouped split)",
        """Each model's mean tip error on the test sessions of the twin with creep, hysteresis and backlash
        on, beside the floor: the error no static model can go below (the same points visited twice). A model
        near the floor has learnt all that (q, p, i) can tell; only a model that reads the history can go
        below it.""",
        tables=("unmodelled effects",),
    ),
    ReportSection(
        "Real-time sessions (the devices' drivers against the twin's emulators)",
        """The sessions recorded in real time, one row per stream: messages, mean rate and drops. Compare each
        rate with its device's configured rate; any dropped message is a fault of the drivers or the bus.""",
        tables=("real-time sessions",),
    ),
    ReportSection(
        "Datasets and models (ours)",
        """The campaign dataset (clocks, tracker registration) and the forward models trained on it. Compare
        the networks' test error with the rigid model's and the PRBM grey box's; the registration residuals
        are the measurement's own error, below which no model's error means anything.""",
        ("clock_fits", "registration_vsl", "error_heatmaps", "learning_curves"),
        ("forward model", "registration"),
    ),
    ReportSection(
        "Seed 000, Experiment 1 (Fig. 5)",
        """The VSL arm's mean ± std paths under payloads of 0–100 g and pressures of 0.5–2 bar, beside the
        rigid arm, as in the paper's Fig. 5. Compare the trend: the error grows with the payload and as the
        pressure falls (the twin's stiffness is ASSUMED, so the sizes need not match).""",
        ("fig5",),
    ),
    ReportSection(
        "Seed 000, Experiment 2 (Figs. 6 and 7)",
        """The paper's two cases (25 g at 1.5 bar, 75 g at 0.5 bar) followed with model-based IK, static
        compensation and the hybrid inverse model, and the rigid arm. The paper gives no numbers here, only
        its findings from Fig. 7b; the second table puts them beside ours.""",
        ("fig6", "fig7a", "fig7b"),
        ("Experiment 2",),
    ),
    ReportSection(
        "Seed 001, POPUP link tests (Fig. 7, Table 1)",
        """The POPUP link's static loading/unloading curves and its Table 1 (damped frequency f_s, damping
        ratio ζ, stiffness k and k̂, damping ĉ per pressure), each of ours beside the paper's. The twin's
        link is configured from the paper's k̂ and ĉ, so the values should agree closely: this checks the
        analysis (the paper's procedure), not the twin.""",
        ("popup_fig7",),
        ("POPUP Table 1",),
    ),
    ReportSection(
        "Seed 001, target reaching (Figs. 12–13)",
        """The arm reaching a target with the rigid-body model's plan, and how far the soft arm's tip (PRBM)
        ends from the rigid one's. The paper reports 6.6 mm at the start and 24.4 mm at the target; our link
        masses are ASSUMED, so compare the growth along the path more than the millimetres.""",
        ("fig12_popup_reach_paths", "fig13_popup_reach_difference"),
        ("POPUP target reaching",),
    ),
    ReportSection(
        "Seed 001, visual servoing (Figs. 15–16)",
        """The same reach with the tip error measured on the soft arm itself (visual servoing) beside the
        plan on the rigid-body model. Compare the final tip errors: with servoing the soft arm should end on
        the target, as in the paper's Fig. 15.""",
        ("fig15_popup_visual_servoing_paths", "fig16_popup_visual_servoing_joints"),
        ("POPUP visual servoing",),
    ),
]
