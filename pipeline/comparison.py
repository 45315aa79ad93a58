"""Every model of the arm on the same rows, beside the floor (issue 19's table).

On one split's test part (by default ``split_group``: no session in two parts), forward and inverse, overall
and per pressure × payload cell, the mean tip error (mm) of:
- ``rigid``: the rigid model; ``grey box``: the PRBM with k(p) fitted to the training rows;
- ``paper net``, ``residual net``, ``small residual net``: the hybrid networks (trained here, on the same
  split);
- ``gbr``: gradient boosting on the 7 inputs, and ``history``: the same with the points' history
  (``pipeline.history``) — the pair shows what the history adds;
- ``floor``: what no static map of (q, p, i) predicts, measured from the campaign's shuffled repeat
  (``pipeline.floor``), when a repeat is given. An inverse model is scored at the tip (the rigid FK of its
  command against that of the command that landed the tip), against the inverse floor (the joints it does
  not read left in).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from datetime import UTC, datetime
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from acquisition.storage import LabPath
from models import kinematics
from models.hybrid import FORWARD_TARGETS, INVERSE_TARGETS, preset
from pipeline import baselines, metrics
from pipeline.floor import repeat_floor
from pipeline.history import HistoryModel, with_history
from pipeline.train import HybridRegressor, TrainConfig

if TYPE_CHECKING:
    from pipeline.model_store import ModelStore

log = logging.getLogger(__name__)

DIRECTIONS = ("forward", "inverse")
NETS = {"paper net": "paper", "residual net": "residual", "small residual net": "small-residual"}
BASELINES = {
    "rigid": lambda d: baselines.RigidModel(direction=d),
    "grey box": lambda d: baselines.PrbmGreyBox(direction=d),
    "gbr": lambda d: baselines.SklearnBaseline("gbr", direction=d),
    "history": lambda d: HistoryModel(direction=d),
}
# What each direction's models read, and when it is measured (the comparison's card and the report say it)
INPUTS = {
    "forward": "the joints q, pressures p and currents i measured at the point, once the move has landed",
    "inverse": "the tip wanted, and the pressures p and currents i measured after the move has landed there: "
    "the currents at the landed point carry the payload's load (a payload sensor a controller has only "
    "after moving; with the previous point's currents the inverse error rises, 0.60 → 1.09 mm)",
}
ALL = "all"  # the cell label of the whole test part
UNMODELLED = "unmodelled"  # the main job's comparison: its name in its lab's comparisons


def _errors_mm(direction: str, pred: np.ndarray, rows: pd.DataFrame, lengths) -> np.ndarray:
    if direction == "forward":
        return metrics.tip_errors(pred, rows[list(FORWARD_TARGETS)].to_numpy(float))
    target = rows[list(INVERSE_TARGETS)].to_numpy(float)
    return metrics.tip_errors(kinematics.vsl_fk(pred, lengths), kinematics.vsl_fk(target, lengths))


def _records(model: str, direction: str, report: dict) -> list[dict]:
    rows = [{"direction": direction, "model": model, "cell": ALL, "n": report["summary"]["n"],
             "tip_mm_mean": report["summary"]["mean"]}]  # fmt: skip
    for c in report["per_cell"]:
        cell = f"{c['pressure_bin']} / {c['payload_g']} g"
        rows.append({"direction": direction, "model": model, "cell": cell, "n": int(c["n"]),
                     "tip_mm_mean": float(c["tip_mm_mean"])})  # fmt: skip
    return rows


def compare_models(data: pd.DataFrame, lengths: kinematics.ArmLengths, repeat: pd.DataFrame | None = None,
                   split: str = "split_group", train: dict | None = None, seed: int = 0,
                   say: Callable[[str], None] = log.info,
                   nets: dict[tuple[str, str], HybridRegressor] | None = None) -> pd.DataFrame:  # fmt: skip
    """The comparison as long records: ``direction``, ``model``, ``cell`` (``"all"`` or ``"<pressure bin> /
    <payload> g"``), ``n`` and ``tip_mm_mean``. ``train``: TrainConfig fields for the networks (e.g.
    ``max_epochs``); ``repeat``: the campaign's repeat, for the floor; ``nets``: given a dict, the trained
    networks go in it by (direction, model) (for :func:`save_compared`)."""
    d = with_history(data)
    rows = baselines.part_of(d, split, "train")
    test = baselines.part_of(d, split, "test")
    out = []

    def add(name: str, direction: str, report: dict) -> None:
        out.extend(_records(name, direction, report))
        say(f"{direction} {name}: {report['summary']['mean']:.3f} mm")

    floors = {}  # first: a repeat that is not one fails before any model is fitted
    if repeat is not None:
        floors = {way: repeat_floor(data, repeat, lengths, split, direction=way) for way in DIRECTIONS}
    for direction in DIRECTIONS:
        for name, make in BASELINES.items():
            pred = make(direction).fit(rows).predict(test)
            add(name, direction, metrics.tip_report(_errors_mm(direction, pred, test, lengths), test))
        for name, preset_name in NETS.items():
            config = TrainConfig(preset(direction, preset_name), split=split, seed=seed, **(train or {}))
            net = HybridRegressor(config).fit(d)
            if nets is not None:
                nets[(direction, name)] = net
            pred = net.predict(test)
            add(name, direction, metrics.tip_report(_errors_mm(direction, pred, test, lengths), test))
        if direction in floors:
            add("floor", direction, floors[direction])
    return pd.DataFrame(out)


def wide_tables(table: pd.DataFrame) -> dict[str, pd.DataFrame]:
    """Per direction, the comparison as a table: the cells as rows (the whole test part first, then each
    pressure × payload cell), ``n`` (the cell's test points) and the models as columns (mean tip error,
    mm)."""
    out = {}
    for direction, rows in table.groupby("direction", sort=False):
        models = list(dict.fromkeys(rows["model"]))
        cells = [ALL, *[c for c in dict.fromkeys(rows["cell"]) if c != ALL]]
        wide = rows.pivot(index="cell", columns="model", values="tip_mm_mean").loc[cells, models]
        wide.insert(0, "n", rows.drop_duplicates("cell").set_index("cell")["n"].loc[cells])
        wide.columns.name = None
        out[str(direction)] = wide
    return out


def comparison_markdown(table: pd.DataFrame) -> str:
    """:func:`wide_tables` as Markdown (mm, three decimals), each followed by what its models read."""
    parts = []
    for direction, wide in wide_tables(table).items():
        lines = [
            f"| {direction} | " + " | ".join(wide.columns) + " |",
            "|" + "---|" * (len(wide.columns) + 1),
        ]
        for cell, row in wide.iterrows():
            values = [str(int(row["n"])), *("" if np.isnan(v) else f"{v:.3f}" for v in row.iloc[1:])]
            lines.append(f"| {cell} | " + " | ".join(values) + " |")
        parts.append("\n".join(lines) + f"\n\n{direction} models read {INPUTS[str(direction)]}.")
    return "\n\n".join(parts) + "\n"


def save_compared(path: LabPath, models: ModelStore, data: pd.DataFrame, dataset: dict[str, str],
                  table: pd.DataFrame, nets: dict[tuple[str, str], HybridRegressor],
                  made_from: dict[str, str], split: str,
                  extra: dict[str, list[dict]] | None = None) -> list[dict]:  # fmt: skip
    """A comparison kept: its networks (``compare_models(..., nets=…)``, trained on ``data``, the dataset
    ``dataset`` = {name, version}) in the model store ``models``, each card carrying the comparison of its
    direction (``comparison``: the split, ``made_from``, the model's own row name and every record: the
    other models and the floor), then the comparison's card at ``path`` (:func:`save_comparison`, its
    ``models`` the networks saved, beside ``extra``). A network's version is the training's plus the
    comparison's ``made_from``, so the same training outside a comparison stays another version; one already
    saved stays as it is. Returns the networks saved ({name, version} each)."""
    from pipeline.model_store import model_version
    from pipeline.train import evaluate, model_card

    saved, cards = [], []
    for (direction, model), net in nets.items():
        config = net.config
        name = f"{direction}-{config.net.name}"
        version = model_version(dataset["version"], config, comparison=json.dumps(made_from, sort_keys=True))
        records = table[table["direction"] == direction].to_dict("records")
        card = model_card(net.history_, dataset, evaluate(net.net_, data, config.split, "test"), net.threads)
        card["comparison"] = {
            "split": config.split,
            "made_from": made_from,
            "model": model,
            "records": records,
        }
        saved.append({"name": name, "version": version})
        cards.append(card)
    comparison = comparison_card(table, made_from, split, (extra or {}) | {"models": saved})
    for entry, net, card in zip(saved, nets.values(), cards, strict=True):  # the networks, then the card
        try:
            models.save(entry["name"], entry["version"], net.net_, card)
        except FileExistsError:
            pass
    _write_card(path, comparison)
    return saved


def save_comparison(path: LabPath, table: pd.DataFrame, made_from: dict[str, str], split: str,
                    extra: dict[str, list[dict]] | None = None) -> None:  # fmt: skip
    """A comparison kept without its networks: its card (:func:`comparison_card`) at ``path`` (JSON)."""
    _write_card(path, comparison_card(table, made_from, split, extra))


def comparison_card(table: pd.DataFrame, made_from: dict[str, str], split: str,
                    extra: dict[str, list[dict]] | None = None) -> dict:  # fmt: skip
    """The comparison's card: what it was made from (``made_from``: dataset versions), the split, when, its
    records, what each direction's models read (``inputs``: :data:`INPUTS`), and ``extra`` tables as records
    (the main job adds its Experiment 2 on the same twin)."""
    created = datetime.now(UTC).isoformat(timespec="seconds")
    return {"made_from": made_from, "split": split, "created": created, "inputs": INPUTS,
            "records": table.to_dict("records"), **(extra or {})}  # fmt: skip


def _write_card(path: LabPath, card: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(card, indent=1, allow_nan=True))


def load_comparison(path: LabPath) -> tuple[pd.DataFrame, dict]:
    """(records as a DataFrame, the card) of :func:`save_comparison`'s file. A card written before
    ``made_from`` had its name (``sources``) is read under the name it has now."""
    card = json.loads(path.read_text())
    if "made_from" not in card and "sources" in card:
        card["made_from"] = card.pop("sources")
    return pd.DataFrame(card["records"]), card
