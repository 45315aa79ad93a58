"""The data's reference: a session's topics and messages, the dataset's columns, the model card's fields.

Topics and messages come straight from ``acquisition.schemas`` (their field comments carry the units). The
columns and the card's fields are produced by the code itself at build time (D assembled from a few synthetic
rows, a card saved for a tiny network) and each must have a line in the tables below: a column or a field the
code adds or drops without its line here fails the build, so the page cannot drift."""

from __future__ import annotations

import re
import tempfile
from dataclasses import MISSING, fields
from pathlib import Path

import numpy as np
import pandas as pd

NONE = "—"
ROBOTS = ("vsl", "popup")  # the two robots of the papers; the others are variants of vsl with its topics

# D's columns (pipeline.datasets' docstring says the same): pattern → (unit, meaning)
COLUMNS = {
    r"x_[0-2]": ("m", "measured tip position, robot base frame (x, y, z)"),
    r"p_\d+": ("Pa", "gauge pressure of each link channel"),
    r"i_\d+": ("A", "current of each servo (Dynamixel servos)"),
    r"tau_\d+": ("N·m", "torque estimate of each joint drive (CiA 402 drives, in place of i_k)"),
    r"q_\d+": ("rad", "measured angle of each actuated joint, in the robot's joint order (encoders)"),
    r"qc_\d+": ("rad", "commanded joint angle: the servo goal in force (the inverse model's target)"),
    r"fk_[0-2]": ("m", "rigid forward kinematics of q"),
    r"ik_\d+": ("rad", "rigid closed-form IK of x; NaN out of reach or without a closed form (POPUP)"),
    r"payload_kg": ("kg", "payload hanging at the end-effector"),
    r"robot": (NONE, "robot description name"),
    r"session": (NONE, "session id"),
    r"plan": (NONE, "the plan the session ran, e.g. experiment1/curve/vsl-1bar/25g"),
    r"point": (NONE, "static point number, −1 for trajectory samples"),
    r"repetition": (NONE, "trajectory repetition, −1 for static points"),
    r"t": ("s", "time since the session's start"),
    r"split_random": (NONE, "train / val / test, rows dealt 70/15/15 at random (the paper's split)"),
    r"split_group": (NONE, "train / val / test, whole sessions (or repetitions) dealt so none spans two"),
}

# The model card's fields (pipeline.train.model_card, pipeline.model_store.save_model): key → meaning
CARD = {
    "name": "model name (its folder under models/)",
    "version": "version id: hash of the dataset version, the training config and the code version",
    "dataset": "the dataset it was trained on: name and version",
    "train_config": "the training configuration (fields below)",
    "seed": "random seed of the training",
    "metrics": "errors on the test part of the split (fields below)",
    "curves": "per epoch: epoch, train_loss, val_loss, val_error_mm (mm)",
    "best_epoch": "the epoch whose weights were kept (lowest validation loss)",
    "train_time_s": "training time, s",
    "epoch_time_s": "mean time of one epoch, s",
    "threads": "torch threads it trained with",
    "n_train": "rows of the training part",
    "n_val": "rows of the validation part",
    "net": "the network (fields below)",
    "code_version": "version of the model code that wrote it",
    "torch": "torch version",
    "created": "when it was saved (ISO 8601, UTC)",
    "files": "sha256 of each file of the version (weights, TorchScript, ONNX)",
    "card_sha256": "sha256 of the card itself, this field left out: an edited card is refused",
}
METRICS = {
    "direction": "forward or inverse",
    "n": "test rows",
    r"tip_(mean|median|p95|max)_mm": "tip position error (mm; inverse: of the rigid FK of q̂)",
    r"joint_(mean|median|p95|max)_mrad": "joint angle error (mrad; inverse nets)",
    "per_cell": "the same errors per cell (link pressure bin × payload)",
}


def _cell(text: object) -> str:
    return " ".join(str(text).split()).replace("|", "\\|") or NONE


def _row(*cells: object) -> str:
    return "| " + " | ".join(_cell(c) for c in cells) + " |"


def _matching(names: list[str], table: dict, what: str) -> dict[str, list[str]]:
    """Each pattern of ``table`` with the names it matches; ValueError where a name has no line or a line
    matches nothing (the page would be out of date)."""
    found = {p: [n for n in names if re.fullmatch(p, n)] for p in table}
    if missing := [n for n in names if not any(re.fullmatch(p, n) for p in table)]:
        raise ValueError(f"{what} {missing} have no line in docs/hooks/ref_data.py: document them there")
    if stale := [p for p, hit in found.items() if not hit]:
        raise ValueError(f"{what} {stale} in docs/hooks/ref_data.py are not made by the code any more")
    return found


def synthetic_d(robot_name: str, n: int = 4) -> pd.DataFrame:
    """D as ``pipeline.datasets`` assembles it from ``n`` rows of one robot's timeline columns."""
    from models.robot import load_robot
    from pipeline.datasets import add_splits, assemble

    robot = load_robot(robot_name)
    rng = np.random.default_rng(0)
    cols = {f"x_{k}": rng.uniform(0.1, 0.2, n) for k in range(3)}
    cols |= {f"pressure_{c}": np.zeros(n) for c in range(robot.pneumatics.channels)}
    for name in ("servo_position", "goal_position", "servo_current", "servo_torque", "stepper_position"):
        cols |= {f"{name}_{k}": np.zeros(n) for k in range(len(robot.joints))}
    return add_splits(assemble(pd.DataFrame(cols), robot).assign(robot=robot_name))


def dataset_columns() -> str:
    names = list(dict.fromkeys(c for r in ROBOTS for c in synthetic_d(r).columns))
    found = _matching(names, COLUMNS, "dataset columns")
    out = ["# Dataset columns", "", "The columns of D (`datasets/<name>/<version>/data.parquet`, and "
           "`trajectories.parquet` where the sessions ran trajectories, `moves.parquet` with `t_command` "
           "where they have settled points), as `pipeline.datasets` assembles "
           "them "
           "(SI units; `<k>` counts from 0 in the robot's order).", "",
           "| Column | Unit | Meaning |", "|---|---|---|"]  # fmt: skip
    out += [_row(", ".join(f"`{n}`" for n in found[p]), *COLUMNS[p]) for p in COLUMNS]
    return "\n".join(out) + "\n"


def model_card() -> str:
    """Saves a tiny inverse net with the card the grid writes, and documents every field it holds."""
    from models.hybrid import HybridNet, NetConfig
    from pipeline.model_store import load_card, save_model
    from pipeline.train import TrainConfig, TrainResult, metrics, model_card

    config = TrainConfig(NetConfig("inverse", (2,), name="tiny"))
    rows = synthetic_d("vsl")
    net = HybridNet(config.net).fit_scaler(np.random.default_rng(0).normal(size=(4, 7)), np.ones((4, 3)))
    result = TrainResult(net, config, [1.0], [1.0], [1.0], best_epoch=0)
    card = model_card(result, {"name": "d", "version": "0"}, metrics("inverse", np.zeros((4, 3)), rows), 1)
    with tempfile.TemporaryDirectory() as tmp:
        card = load_card(save_model(Path(tmp), "tiny", "0", result.model, card))
    out = ["# Model card", "", "`models/<name>/<version>/card.json`: what a trained network's version says "
           "of "
           "itself (lineage, configuration, metrics, curves, file hashes). Every read checks it.", "",
           "| Field | Meaning |", "|---|---|"]  # fmt: skip
    out += [_row(f"`{k}`", CARD[k]) for k in _matching(list(card), CARD, "model card fields")]
    out += ["", "A network trained by `vslab compare-models` also has `comparison`: the split, the datasets "
            "it was compared on and its rows of the comparison table."]  # fmt: skip
    found = _matching(list(card["metrics"]), METRICS, "model card metrics")
    out += ["", "## metrics", "", "| Field | Meaning |", "|---|---|"]
    out += [_row(", ".join(f"`{n}`" for n in found[p]), METRICS[p]) for p in METRICS]
    for key, cls in (("train_config", TrainConfig), ("net", NetConfig)):
        out += ["", f"## {key}", "", f"`{cls.__module__}.{cls.__name__}`: {_cell(cls.__doc__ or NONE)}", "",
                "| Field | Type | Default |", "|---|---|---|"]  # fmt: skip
        for f in fields(cls):
            default = f.default if f.default_factory is MISSING else f.default_factory()
            out.append(
                _row(f"`{f.name}`", f"`{f.type}`", "required" if default is MISSING else f"`{default}`")
            )
    return "\n".join(out) + "\n"


def _message_rows(messages: dict[str, dict[str, object]]) -> list[str]:
    out = []
    for name, per_robot in messages.items():
        first = next(iter(per_robot.values()))
        out += [f"### `{name}`", "", _cell(first.doc or NONE), "", "| Field | Type | Unit, meaning |",
                "|---|---|---|"]  # fmt: skip
        for k, field in enumerate(first.fields):
            counts = {r: m.fields[k].count for r, m in per_robot.items()}
            kinds = sorted({f"{field.type}[{c}]" if c else field.type for c in counts.values()})
            kind = (
                kinds[0]
                if len(kinds) == 1
                else ", ".join(f"{field.type}[{c}] ({r})" for r, c in counts.items())
            )
            out.append(_row(f"`{field.name}`", kind, field.doc or NONE))
        out.append("")
    return out


def topics() -> str:
    from acquisition.schemas.events import EVENT_SCHEMA, EVENT_SCHEMA_NAME
    from acquisition.schemas.scene import Scene
    from acquisition.schemas.topics import MESSAGE_ENCODING, SCHEMA_ENCODING, session_topics
    from models.robot import load_robot

    robots = {name: load_robot(name) for name in ROBOTS}
    table: dict[str, tuple[str, list[str]]] = {}
    messages: dict[str, dict[str, object]] = {}
    for name, robot in robots.items():
        for topic in session_topics(robot).values():
            table.setdefault(topic.name, (topic.schema_name, []))[1].append(name)
            if topic.message is not None:
                messages.setdefault(topic.message.name, {})[name] = topic.message
    standard = {
        topic: schema for robot in robots.values() for topic, (schema, _) in Scene(robot).schemas().items()
    }
    out = ["# Session topics", "", "Every topic a session may hold, by robot. Messages are "
           f"`{MESSAGE_ENCODING}` "
           f"with `{SCHEMA_ENCODING}` schemas (the schema text stored in each file says the array lengths). "
           "`log_time` is the host receive time (ns); the device's own stamp is in the payload.", "",
           "| Topic | Message | Robots |", "|---|---|---|"]  # fmt: skip
    out += [_row(f"`{t}`", f"`{schema}`", ", ".join(r)) for t, (schema, r) in sorted(table.items())]
    out += ["", "## Standard topics", "", "Derived from the measured ones for Foxglove and ROS tools "
            "(`acquisition.schemas.scene`); the pipeline does not read them.", "",
            "| Topic | Message |", "|---|---|"]  # fmt: skip
    out += [_row(f"`{t}`", f"`{s}`") for t, s in sorted(standard.items())]
    out += ["", "## Messages", "", *_message_rows(messages)]
    out += [f"### `{EVENT_SCHEMA_NAME}`", "", "```text", EVENT_SCHEMA.rstrip(), "```", ""]
    return "\n".join(out)
