"""Every figure and table of a lab directory, from its newest datasets and models (or named versions); the
report page that gathers them is :mod:`analysis.lab_report`. Each figure records which versions it used
(``<figure>.json`` beside it).

    lab = Lab.open("lab")
    results = all_figures(lab)      # writes lab.figures
    page = lab_report(lab, results)  # writes lab.report / "index.html"
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from analysis import diagnostics, vsl_paths
from analysis.twin_report import twin_against_robot
from pipeline.lab import Lab, LabPath, local_folder, upload
from pipeline.model_store import FORWARD, LAB_TAGS
from pipeline.session_index import SessionError

log = logging.getLogger(__name__)


@dataclass
class Results:
    figures: dict[str, Path] = field(default_factory=dict)  # name → PNG
    tables: dict[str, pd.DataFrame] = field(default_factory=dict)
    versions: dict[str, str | dict] = field(default_factory=dict)  # made from: versions, a study's settings
    missing: dict[str, str] = field(default_factory=dict)  # figure → why it could not be made
    texts: dict[str, str] = field(default_factory=dict)  # table key → what the section says about it


FIGURE_INPUTS = "inputs.json"  # in the report's folder: what the figures and report were made from


def figure_inputs(lab: Lab) -> dict | None:
    """What the figures and the report are made from: every file of the lab (path, size, modification
    time) but its caches and what they write themselves, and the code that draws them. Equal twice: nothing
    to redraw. None on a lab that is not a local folder (a store's listing costs more than the drawing it
    saves)."""
    if not lab.is_local:
        return None
    from pipeline.cache import code_version

    theirs = (Path(lab.figures), Path(lab.report))
    files = []
    for path in sorted(Path(lab.root).rglob("*")):
        if "cache" in path.relative_to(lab.root).parts or any(path.is_relative_to(d) for d in theirs):
            continue
        if path.is_file():
            stat = path.stat()
            files.append([path.relative_to(lab.root).as_posix(), stat.st_size, stat.st_mtime_ns])
    return {"code": code_version("analysis.lab_figures"), "files": files}


def tagged_model(lab: Lab, tag: str) -> tuple[str, LabPath] | None:
    """(version, directory) of the model the store's ``tag`` names (``pipeline.model_store.LAB_TAGS``: the
    main job's), or None where no such tag is set."""
    if tag not in lab.models.tags():
        return None
    path = lab.models.find(tag)
    return path.name, path


def all_figures(lab: Lab, out: LabPath | None = None) -> Results:
    """Make every figure that the lab's data allow; what cannot be made is listed with its reason. On a
    store the figures are drawn into a local folder, then uploaded (each figure's record after its files)."""
    out = out or lab.figures
    with local_folder(out) as folder:
        res = _all_figures(lab, folder)
        if folder != out:
            upload(folder, out, "*.json")
            res.figures = {k: out / png.relative_to(folder).as_posix() for k, png in res.figures.items()}
    return res


def _all_figures(lab: Lab, out: Path) -> Results:
    res = Results()
    datasets = {}
    for name in ("campaign", "experiment1", "experiment2"):
        try:
            data, card = lab.datasets.load(name)
            trajectories = (
                lab.datasets.load(name, card["version"], table="trajectories")[0]
                if card["counts"].get("rows_trajectories") else None
            )  # fmt: skip
            datasets[name] = (data, trajectories, card)
            res.versions[f"dataset {name}"] = card["version"]
        except FileNotFoundError as exc:
            res.missing[f"dataset {name}"] = str(exc)
    forward = tagged_model(lab, FORWARD)
    for label, step in (
        ("models", lambda: _models(lab, datasets, res, out)),
        ("experiment1", lambda: _experiment1(datasets, forward, res, out)),
        ("experiment2", lambda: _experiment2(datasets, res, out)),
        ("real-time sessions", lambda: _realtime(lab, res)),
        ("unmodelled effects", lambda: _unmodelled(lab, res)),
        ("popup", lambda: _popup(lab, res, out)),
        ("the twin against your robot", lambda: twin_against_robot(lab, res, out)),
    ):
        try:
            step()
        except Exception as exc:  # one figure's failure must not lose the others; it is reported
            res.missing[label] = f"{type(exc).__name__}: {exc}"
            log.debug("figures %s failed", label, exc_info=True)  # the caller shows res.missing
    return res


def _unmodelled(lab: Lab, res: Results) -> None:
    """The comparison the main job made on the twin with its unmodelled effects (``pipeline.comparison``)."""
    from pipeline.comparison import INPUTS, UNMODELLED, load_comparison, wide_tables

    path = lab.comparisons.path(UNMODELLED)
    if not path.exists():
        res.missing["unmodelled effects"] = f"no comparison at {path} (the main job makes it)"
        return
    table, card = load_comparison(path)
    for direction, wide in wide_tables(table).items():
        wide = wide.rename(columns={"n": "test points"}).rename(columns=lambda c: _in_mm(c, "test points"))
        res.tables[f"unmodelled effects: {direction} models, mean tip error"] = wide.rename_axis("cell")
    inputs = card.get("inputs", INPUTS)  # a card written before it said so: the models read the same
    res.texts["unmodelled effects"] = "\n\n".join(f"The {d} models read {inputs[d]}." for d in inputs)
    if card.get("experiment2"):
        paths = pd.DataFrame(card["experiment2"]).drop(columns=["session"], errors="ignore")
        res.tables["unmodelled effects: Experiment 2, distance to the desired path"] = _path_table(paths)
    for name, version in card["made_from"].items():  # training, paths: the settings, recorded as JSON
        settings = recorded_settings(version)
        if settings is None:
            res.versions[f"dataset {name}, vsl_unmodelled"] = version
        else:
            res.versions[f"settings {name}, vsl_unmodelled"] = settings


def _in_mm(column: str, *besides: str) -> str:
    """A model's column of mean tip errors headed with its unit (the columns ``besides`` stay)."""
    return column if column in besides else f"{column} (mm)"


def _path_table(errors: pd.DataFrame) -> pd.DataFrame:
    """Path errors per session (``vsl_paths.path_errors``) as the report shows them: the command mode in
    words, the errors in mm, and ``n`` named for what it counts."""
    out = errors.rename(columns={"n": "tracked points", "mode": "command"})
    if "command" in out:
        out["command"] = out["command"].map(lambda m: vsl_paths.MODE_LABELS.get(m, m))
    return out


def _models(lab: Lab, datasets: dict, res: Results, out: Path) -> None:
    from pipeline import baselines
    from pipeline.model_store import load_card
    from pipeline.train import evaluate_rigid

    data = datasets["campaign"][0]
    grids, cards, rows = {}, {}, []
    grids["rigid model"] = diagnostics.cell_grid(evaluate_rigid(data, "forward")["per_cell"])
    grey = baselines.PrbmGreyBox().fit(data[data["split_random"] == "train"])
    grey_eval = baselines.evaluate_forward(grey, data)
    grids["PRBM grey box"] = diagnostics.cell_grid(grey_eval["per_cell"])
    rows.append({"model": "rigid model", **_headline(evaluate_rigid(data, "forward"))})
    rows.append({"model": "PRBM grey box (k(p) fitted)", **_summary_mm(grey_eval["summary"])})
    for tag in (t for t in LAB_TAGS if t.startswith(FORWARD)):  # the forward networks the main job trained
        found = tagged_model(lab, tag)
        if found is None:
            continue
        card = load_card(found[1])
        name = card["name"]
        cards[name] = card
        res.versions[f"model {name}"] = found[0]
        rows.append({"model": name, **_headline(card["metrics"])})
        if tag == FORWARD:
            grids["hybrid (small residual)"] = diagnostics.cell_grid(card["metrics"]["per_cell"])
    res.tables["forward model: test error, campaign, random split"] = pd.DataFrame(rows).set_index("model")
    versions = {k: v for k, v in res.versions.items() if k.startswith(("dataset campaign", "model"))}
    for fig in (diagnostics.error_heatmaps(grids, out, made_from=versions),
                diagnostics.learning_curves(cards, out, made_from=versions)):  # fmt: skip
        res.figures[fig["png"].stem] = fig["png"]
    clocks = diagnostics.clock_fits(datasets["campaign"][2]["sessions"], out, made_from=versions)
    res.figures["clock_fits"] = clocks["png"]
    registration = datasets["campaign"][2]["registration"]
    res.tables["registration (tracker → base), campaign"] = registration_table(registration)
    from models.robot import load_robot

    for robot_name, fitted in registration.items():
        if "selected" not in fitted:  # borrowed from another dataset: its residuals are that one's
            continue
        name = f"registration_{robot_name}"
        reg = diagnostics.registration_residuals(data, load_robot(robot_name), fitted, out, name, versions)
        res.figures[name] = reg["png"]


def registration_table(registration: dict) -> pd.DataFrame:
    """One row per robot of a dataset card's registration: points used (counts), whether the model's tip was
    corrected for the links' static deflection, residuals in mm (all static points, and the selected ones the
    transform was fitted on)."""
    rows = {}
    for robot, r in registration.items():
        res_all, res_sel = r.get("residuals", {}), r.get("residuals_selected", {})
        rows[robot] = {
            "static points": r.get("points"), "selected points": r.get("selected"),
            "trimmed points": r.get("trimmed"), "model corrected for deflection": r.get("deflection"),
            "rms, all (mm)": 1e3 * res_all.get("rms_m", np.nan),
            "rms, selected (mm)": 1e3 * res_sel.get("rms_m", np.nan),
            "p95, selected (mm)": 1e3 * res_sel.get("p95_m", np.nan),
            "max, selected (mm)": 1e3 * res_sel.get("max_m", np.nan),
        }  # fmt: skip
    return pd.DataFrame.from_dict(rows, orient="index").rename_axis("robot")


HEADLINE = ("mean", "median", "p95", "max")  # the tip error statistics of the forward model table (mm)


def _headline(metrics: dict) -> dict:
    return {f"{k} (mm)": metrics.get(f"tip_{k}_mm") for k in HEADLINE}


def _summary_mm(summary: dict) -> dict:
    return {f"{k} (mm)": summary.get(k) for k in HEADLINE}


def _experiment1(datasets: dict, forward, res: Results, out: Path) -> None:
    from analysis import vsl_figures
    from pipeline.model_store import load_model

    trajectories = datasets["experiment1"][1]
    versions = {"dataset experiment1": res.versions["dataset experiment1"]}
    _pngs(res, vsl_figures.fig5(trajectories, out, versions))
    if forward is not None:
        model, _ = load_model(forward[1])
        _pngs(res, vsl_figures.fig6(trajectories, model, out, versions | {"model forward": forward[0]}))


def _pngs(res: Results, figure) -> None:
    """The PNGs a figure function wrote (it writes its own PDFs and version records)."""
    for path in figure.paths:
        if Path(path).suffix == ".png":
            res.figures[Path(path).stem] = Path(path)


def _experiment2(datasets: dict, res: Results, out: Path) -> None:
    from analysis import vsl_figures

    data = datasets["experiment2"][0]
    _pngs(res, vsl_figures.fig7(data, out, {"dataset experiment2": res.versions["dataset experiment2"]}))
    errors = vsl_paths.path_errors(data)
    res.tables["Experiment 2: distance to the desired path"] = _path_table(errors)
    res.tables["Experiment 2: the paper's findings (Fig. 7b) beside ours"] = experiment2_claims(errors)


# Seed 000 gives no numbers for Experiment 2, only its findings from Fig. 7b (Sec. "Results"): (finding,
# the mean path error that should be lower, the one it should be lower than; each "robot/mode").
EXPERIMENT2_CLAIMS = [
    ("hybrid inverse beats model-based IK on the VSL arm", "vsl/hybrid", "vsl/ik"),
    ("hybrid VSL arm beats the rigid arm with model-based IK", "vsl/hybrid", "vsl_rigid/ik"),
    ("static compensation beats model-based IK on the VSL arm", "vsl/static", "vsl/ik"),
]


def experiment2_claims(errors: pd.DataFrame) -> pd.DataFrame:
    """Each finding "A beats B" of seed 000's Experiment 2 that our sessions can test: the paper's verdict
    ("yes"), ours, and our mean path errors of A and B (mm, over the sessions of each robot and command
    mode)."""
    means = errors.assign(key=errors["robot"].astype(str) + "/" + errors["mode"].astype(str))
    means = means.groupby("key")["mean_mm"].mean()
    rows = {}
    for finding, better, worse in EXPERIMENT2_CLAIMS:
        if better in means and worse in means:
            ours = "yes" if means[better] < means[worse] else "no"
            rows[finding] = [ours, means[better], means[worse]]
    columns = ["this twin", "the first, ours (mm)", "the second, ours (mm)"]
    table = pd.DataFrame.from_dict(rows, orient="index", columns=columns).rename_axis("finding: A beats B")
    table.insert(0, "paper", "yes")
    return table


def _popup(lab: Lab, res: Results, out: Path) -> None:
    from analysis import popup_tests
    from pipeline import link_tests

    static, _ = lab.sessions.select("popup_static", runner="simulated")
    impact, _ = lab.sessions.select("popup_impact", runner="simulated")
    curves = link_tests.link_static_curves(static)
    fig = popup_tests.figure7(curves, out)
    assert fig, "no static curves to plot"
    res.figures["popup_fig7"] = out / "fig7_popup_hysteresis.png"  # figure7 records its sessions beside it
    table = popup_tests.table1(link_tests.static_stiffness(curves), link_tests.impact_parameters(impact))
    res.tables["POPUP Table 1: ours (twin) beside the paper's"] = popup_tests.table1_report(table)
    inertia = float(table["inertia_kgm2"].iloc[0])
    res.texts["POPUP Table 1"] = (
        f"Our moment of inertia of the link about its hinge, from all pressures: I = {inertia:.4f} kg·m². "
        "The paper's Table 1 lists no ζ; its column is the ζ its f_s, ĉ and k̂ imply."
    )
    from analysis import popup_reach
    from models.robot import load_robot

    result = popup_reach.reach(load_robot("popup"))
    made_from = {"robot": "popup", "task": popup_reach.TASK}
    for png in popup_reach.figures_12_13(result, out, made_from)["png"]:
        res.figures[png.stem] = png
    servoed = popup_reach.reach(load_robot("popup"), visual_servoing=True)
    vs = popup_reach.figures_15_16(result, servoed, out, made_from)
    for png in vs["png"]:
        res.figures[png.stem] = png
    res.tables["POPUP visual servoing (Figs. 15–16): final tip error"] = pd.DataFrame(
        {"RBM-based control (mm)": [1e3 * float(np.linalg.norm(result.prbm[-1] - result.target))],
         "visual servoing (mm)": [vs["final_error_mm"]]}, index=pd.Index(["soft arm to target"], name="tip"),
    )  # fmt: skip
    d = result.difference_mm
    res.tables["POPUP target reaching (Figs. 12–13): RBM–PRBM tip difference"] = pd.DataFrame(
        {"this twin (mm)": [d[0], d[-1]], "paper (mm)": [popup_reach.PAPER["difference_start_mm"],
                                                         popup_reach.PAPER["difference_target_mm"]]},
        index=pd.Index(["at the start", "at the target"], name="where"),
    )  # fmt: skip


def realtime_sessions(lab: Lab) -> pd.DataFrame:
    """The sessions recorded in real time (through the devices' drivers: the rig or hardware), one row per
    stream: messages, rate and drops, read from the MCAP summaries; empty when there are none."""
    rows = []
    selected, bad = lab.sessions.select("all", runner="real-time")
    for why in bad.values():  # a damaged session is left out of the table, and named
        log.warning("left out of the real-time sessions: %s", why)
    for directory in selected:
        try:
            meta, info = lab.sessions.card(directory), lab.sessions.info(directory)
        except SessionError as exc:
            log.warning("left out of the real-time sessions: %s", exc)
            continue
        for topic, s in sorted(info.streams.items()):
            if s.messages == 0:  # a topic of the robot's layout that this bench has no device for
                continue
            rows.append({"session": info.id, "plan": meta.get("plan", ""), "status": info.status,
                         "topic": topic, "messages": s.messages, "rate (Hz)": round(s.rate_hz, 1),
                         "dropped messages": s.dropped})  # fmt: skip
    columns = ["session", "plan", "status", "topic", "messages", "rate (Hz)", "dropped messages"]
    return pd.DataFrame(rows, columns=columns).set_index(["session", "topic"])


def _realtime(lab: Lab, res: Results) -> None:
    table = realtime_sessions(lab)
    if len(table):
        res.tables["real-time sessions"] = table


def recorded_settings(value: str) -> dict | None:
    """The settings a "version" that is a JSON object holds (``{"repetitions": 2}``), None for a version."""
    import json

    try:
        parsed = json.loads(value)
    except (TypeError, ValueError):
        return None
    return parsed if isinstance(parsed, dict) else None
