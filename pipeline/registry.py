"""Trained networks, content-addressed: ``<lab>/models/<name>/<version>/``.

A version is the hash of the dataset version, the training configuration (seed included) and the code version:
training again from the same inputs gives the same id, so a grid skips work it has already done. A version
directory holds ``weights.safetensors`` (the state dict, tensors only), ``card.json`` (lineage, config,
metrics, curves) and ``export/model.ts`` (TorchScript for the control loop: (n, 7) float64 → (n, 3) float64).
It is written whole in a temporary directory and renamed in; an existing version is never overwritten.
Loading never unpickles anything: the config comes from the JSON card, the tensors from safetensors.
"""

from __future__ import annotations

import copy
import datetime
import json
import logging
import os
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from safetensors.torch import load_file, save_file

from models.hybrid import HybridNet, NetConfig
from pipeline.cache import code_version, digest, file_hash

log = logging.getLogger(__name__)

WEIGHTS, CARD, EXPORT = "weights.safetensors", "card.json", "export/model.ts"
HEADLINE = ("tip_mean_mm",)  # the test metric a listing shows (the first one present)
P95 = ("tip_p95_mm",)


def model_version(dataset_version: str, config) -> str:
    """The version id of a model of ``dataset_version`` trained with ``config`` (TrainConfig or its dict)."""
    cfg = config if isinstance(config, dict) else config.to_dict()
    return digest({"dataset": dataset_version, "config": cfg, "code": code_version()})[:16]


class _Exported(torch.nn.Module):
    """What the control loop calls: float64 (n, 7) raw SI inputs in, float64 (n, 3) raw SI outputs out."""

    def __init__(self, net: torch.nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x.to(torch.float64)).to(torch.float64)


def export(model: HybridNet) -> torch.jit.ScriptModule:
    """The TorchScript of ``model`` (traced and frozen: weights become constants, no Python needed)."""
    example = torch.zeros(4, 7, dtype=torch.float64)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", torch.jit.TracerWarning)  # the fitted check becomes a constant: it is
        warnings.simplefilter("ignore", DeprecationWarning)  # TorchScript: still what a C++/RT loop can load
        traced = torch.jit.trace(_Exported(model.eval()).eval(), example, check_inputs=[(example[:1],)])
        return torch.jit.freeze(traced)


def save_model(root: Path, name: str, version: str, model: HybridNet, card: dict) -> Path:
    """Write ``<root>/<name>/<version>/`` (weights, card, TorchScript); FileExistsError if it exists."""
    final = Path(root) / name / version
    if final.exists():
        raise FileExistsError(f"model {name}/{version} already exists at {final}")
    final.parent.mkdir(parents=True, exist_ok=True)
    if any(t.device.type != "cpu" for t in model.state_dict().values()):
        model = copy.deepcopy(model).cpu()  # the files are for CPU loading; the caller's model stays put
    tmp = Path(tempfile.mkdtemp(prefix=f".{version}-", dir=final.parent))
    try:
        state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
        save_file(state, tmp / WEIGHTS)
        (tmp / EXPORT).parent.mkdir()
        export(model).save(str(tmp / EXPORT))
        full = {
            "name": name, "version": version, **jsonable(card), "net": _net_config(model, card).to_dict(),
            "code_version": code_version(), "torch": torch.__version__,
            "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "files": {f: file_hash([tmp / f]) for f in (WEIGHTS, EXPORT)},
        }  # fmt: skip
        (tmp / CARD).write_text(json.dumps(full, indent=1))
        os.rename(tmp, final)  # fails if another process wrote this version first: theirs stays
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if final.exists():
            raise FileExistsError(f"model {name}/{version} already exists at {final}") from exc
        raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def _net_config(model: HybridNet, card: dict) -> NetConfig:
    config = getattr(model, "config", None)
    if isinstance(config, NetConfig):
        return config
    return NetConfig.from_dict(card["train_config"]["net"])


def load_card(path: Path) -> dict:
    """A model's card (``path``: its version directory)."""
    return json.loads((Path(path) / CARD).read_text())


def load_model(path: Path) -> tuple[HybridNet, dict]:
    """The network and its card from a version directory: config from JSON, tensors from safetensors."""
    card = load_card(path)
    model = HybridNet.from_state(NetConfig.from_dict(card["net"]), load_file(Path(path) / WEIGHTS))
    return model.eval(), card


def load_exported(path: Path) -> torch.jit.ScriptModule:
    """The TorchScript export of a version directory: ``module(x: float64 (n, 7)) -> float64 (n, 3)``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return torch.jit.load(str(Path(path) / EXPORT), map_location="cpu").eval()


def find(root: Path, version: str) -> Path:
    """The directory of ``version`` (a unique prefix of it will do) under ``root``."""
    hits = sorted(p.parent for p in Path(root).glob(f"*/{version}*/{CARD}"))
    if not hits:
        raise FileNotFoundError(f"no model version {version!r} under {root} (see `vslab models list`)")
    if len(hits) > 1:
        raise ValueError(f"model version {version!r} is ambiguous: {', '.join(p.name for p in hits)}")
    return hits[0]


def metric(metrics: dict, names: tuple[str, ...]) -> float:
    """The first of ``names`` present in ``metrics`` (NaN if none)."""
    return next((float(metrics[n]) for n in names if n in metrics), float("nan"))


def summary(card: dict) -> dict:
    """One row for a listing."""
    train, metrics = card.get("train_config", {}), card.get("metrics", {})
    dataset = card.get("dataset", {})
    return {
        "name": card["name"], "version": card["version"], "direction": card["net"].get("direction"),
        "preset": card["net"].get("name"), "dataset": f"{dataset.get('name')}@{dataset.get('version')}",
        "split": train.get("split"), "seed": train.get("seed"), "test_mean_mm": metric(metrics, HEADLINE),
        "test_p95_mm": metric(metrics, P95), "epochs": len(card.get("curves", [])),
        "train_time_s": card.get("train_time_s"), "created": card.get("created"),
    }  # fmt: skip


def list_models(root: Path) -> list[dict]:
    """Every model version under ``root``, oldest first."""
    cards = [json.loads(p.read_text()) for p in Path(root).glob(f"*/*/{CARD}")]
    return [summary(c) for c in sorted(cards, key=lambda c: (c.get("created", ""), c["name"], c["version"]))]


def compare(root: Path, versions: list[str]) -> pd.DataFrame:
    """Versions side by side: lineage, configuration and every scalar test metric (one row each)."""
    rows = []
    for version in versions:
        card = load_card(find(root, version))
        row = {k: v for k, v in summary(card).items() if not k.startswith("test_")}  # all metrics follow
        row |= {f"net.{k}": _cell(v) for k, v in card["net"].items() if k not in ("direction", "name")}
        row |= {k: v for k, v in card.get("train_config", {}).items() if k not in ("net", "split", "seed")}
        row |= {k: v for k, v in card.get("metrics", {}).items() if isinstance(v, int | float)}
        row["best_epoch"] = card.get("best_epoch")
        rows.append(row)
    return pd.DataFrame(rows).set_index("version")


def _cell(value):
    return "×".join(map(str, value)) if isinstance(value, list | tuple) else value


def jsonable(value):
    """``value`` with numpy scalars/arrays, tuples and DataFrames turned into plain JSON types."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, pd.DataFrame):
        return jsonable(value.reset_index().to_dict("records"))
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value
