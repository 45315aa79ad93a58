"""Trained networks, content-addressed: ``<lab>/models/<name>/<version>/``.

A version is the hash of the dataset version, the training configuration (seed included) and the code version:
training again from the same inputs gives the same id, so a grid skips work it has already done. A version
directory holds ``weights.safetensors`` (the state dict, tensors only), ``card.json`` (lineage, config,
metrics, curves) and ``export/model.ts`` (TorchScript for the control loop: (n, 7) float64 → (n, 3) float64).
It is written whole in a temporary directory and renamed in; an existing version is never overwritten.
Loading never unpickles anything: the config comes from the JSON card, the tensors from safetensors.

Integrity: the card records the sha256 of each file beside it (``files``) and of itself (``card_sha256``: of
its JSON content without that field). Every read checks them: a version whose card is unreadable, lacks a
field or was edited, or whose files are missing or differ from their hashes, is damaged
(:class:`ModelIntegrityError`, naming the file and what is wrong) and is never loaded.
"""

from __future__ import annotations

import copy
import datetime
import hashlib
import io
import json
import logging
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import safetensors.torch
import torch
from safetensors.torch import save_file

from acquisition.storage import LabPath, is_local, publish
from models.hybrid import HybridNet, NetConfig
from pipeline.cache import digest, stage_version
from pipeline.errors import PipelineError
from pipeline.exports import OnnxModel, onnx_bytes, torchscript

log = logging.getLogger(__name__)

WEIGHTS, CARD, EXPORT, ONNX = "weights.safetensors", "card.json", "export/model.ts", "export/model.onnx"
FILES = (WEIGHTS, EXPORT, ONNX)  # what a card's ``files`` hashes cover (``card_sha256`` covers the card)
REQUIRED = (WEIGHTS, EXPORT)  # a card written before the ONNX export lists only these
CARD_FIELDS = {"name": str, "version": str, "net": dict, "files": dict, "card_sha256": str}
SHA256 = re.compile(r"[0-9a-f]{64}")
VERSION = re.compile(r"[0-9A-Za-z][0-9A-Za-z_-]*")  # what `find` takes: a version id or a prefix of one
TAGS_FILE = "tags.json"  # <lab>/models/tags.json: alias → version (`vslab models tag NAME VERSION`)
TAG = re.compile(r"[a-z][a-z0-9_-]*")
# The tags the main job's grid (configs/train/lab.yaml) gives its networks: Experiment 2 and the figures use
# them. FORWARD: Fig. 6's hybrid forward prediction; INVERSE: Experiment 2's hybrid commands.
FORWARD, INVERSE = "forward", "inverse"
LAB_TAGS = (FORWARD, INVERSE, "forward-ensemble", "forward-paper")
HEADLINE = ("tip_mean_mm",)  # the test metric a listing shows (the first one present)
P95 = ("tip_p95_mm",)


class ModelStoreError(PipelineError, ValueError):
    """The model store's own files (the tags) cannot be used."""


class ModelIntegrityError(PipelineError, ValueError):
    """A model version that cannot be trusted: a file missing or unreadable, a card that is not valid JSON,
    lacks a field or was edited, a file whose bytes differ from the card's hash. Names the file and why."""

    def __init__(self, directory: Path, file: str, problem: str) -> None:
        self.directory, self.file, self.problem = directory, file, problem
        model = f"{self.directory.parent.name}/{self.directory.name}"
        super().__init__(
            f"{self.directory / file}: {problem}: model {model} is damaged and is not loaded (restore the "
            "file from a copy, or delete the model's folder and train it again)"
        )

    @property
    def reason(self) -> str:
        """``file: what is wrong`` (a listing's short form)."""
        return f"{self.file}: {self.problem}"


def model_version(dataset_version: str, config, **context: str) -> str:
    """The version id of a model of ``dataset_version`` trained with ``config`` (TrainConfig or its dict);
    ``context`` (e.g. the comparison it was trained for, whose table its card carries) makes it another
    version of the same training."""
    cfg = config if isinstance(config, dict) else config.to_dict()
    what = {"dataset": dataset_version, "config": cfg, "code": stage_version("model")}
    return digest(what | ({"context": context} if context else {}))[:16]


def save_model(root: Path, name: str, version: str, model: HybridNet, card: dict) -> Path:
    """Publish ``<root>/<name>/<version>/`` whole (weights, card, TorchScript, ONNX); FileExistsError if it
    exists (another worker may have written the same version first: theirs stays)."""
    final = root / name / version
    if final.exists():
        raise FileExistsError(f"model {name}/{version} already exists at {final}")
    if any(t.device.type != "cpu" for t in model.state_dict().values()):
        model = copy.deepcopy(model).cpu()  # the files are for CPU loading; the caller's model stays put

    def fill(folder: Path) -> None:
        state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
        save_file(state, folder / WEIGHTS)
        (folder / EXPORT).parent.mkdir()
        torchscript(model).save(str(folder / EXPORT))
        (folder / ONNX).write_bytes(onnx_bytes(model))
        full = {
            "name": name, "version": version, **jsonable(card), "net": _net_config(model, card).to_dict(),
            "code_version": stage_version("model"), "torch": torch.__version__,
            "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "files": {f: file_sha256(folder / f) for f in FILES},
        }  # fmt: skip
        full = json.loads(json.dumps(full))  # hashed as it will read back (tuples → lists, …)
        full["card_sha256"] = card_digest(full)
        (folder / CARD).write_text(json.dumps(full, indent=1))

    if not publish(final, fill, CARD):
        raise FileExistsError(f"model {name}/{version} already exists at {final}")
    return final


def _net_config(model: HybridNet, card: dict) -> NetConfig:
    config = getattr(model, "config", None)
    if isinstance(config, NetConfig):
        return config
    return NetConfig.from_dict(card["train_config"]["net"])


def card_digest(card: dict) -> str:
    """The sha256 a card records of itself: of its JSON content (keys sorted), ``card_sha256`` left out."""
    return digest({k: v for k, v in card.items() if k != "card_sha256"})


def load_card(path: Path) -> dict:
    """A model's card (``path``: its version directory), checked: valid JSON, every field, its own hash, the
    directory it is in. :class:`ModelIntegrityError` otherwise (the files beside it: :func:`check_model`)."""
    try:
        text = (path / CARD).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ModelIntegrityError(path, CARD, "missing") from None
    except UnicodeDecodeError:
        raise ModelIntegrityError(path, CARD, "not valid JSON (not even UTF-8 text)") from None
    except OSError as exc:
        raise ModelIntegrityError(path, CARD, f"cannot be read ({_why(exc)})") from None
    if not text.strip():
        raise ModelIntegrityError(path, CARD, "empty file")
    try:
        card = json.loads(text)
    except ValueError as exc:  # JSONDecodeError, or a number too long to convert
        raise ModelIntegrityError(path, CARD, f"not valid JSON ({exc})") from None
    if not isinstance(card, dict):
        raise ModelIntegrityError(path, CARD, f"expected a JSON object, found {type(card).__name__}")
    if missing := [k for k in CARD_FIELDS if k not in card]:
        older = " (written before vslab checked its models: train it again)" if "files" in card else ""
        raise ModelIntegrityError(path, CARD, f"missing field(s) {missing}{older}")
    if wrong := [k for k, kind in CARD_FIELDS.items() if not isinstance(card[k], kind)]:
        raise ModelIntegrityError(path, CARD, f"field(s) {wrong} of the wrong type")
    if card_digest(card) != card["card_sha256"]:
        raise ModelIntegrityError(path, CARD, "changed since it was written (its card_sha256 does not match)")
    if (card["name"], card["version"]) != (path.parent.name, path.name):
        raise ModelIntegrityError(path, CARD, f"is the card of {card['name']}/{card['version']}, not of "
                                              f"{path.parent.name}/{path.name}")  # fmt: skip
    return card


def file_sha256(path: Path) -> str:
    """sha256 of one file's bytes, as a card records it."""
    with path.open("rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def check_model(path: Path) -> dict:
    """The card of a version directory once every file is checked against it (:class:`ModelIntegrityError`
    names the first file that is missing, unreadable or not the one the card recorded)."""
    card = load_card(path)
    files = card["files"]
    hashes = files.values()
    listed = set(files)
    if not set(REQUIRED) <= listed <= set(FILES) or not all(
        isinstance(h, str) and SHA256.fullmatch(h) for h in hashes
    ):
        raise ModelIntegrityError(path, CARD, f"'files' must hold a sha256 of each of {list(FILES)}")
    for name in sorted(files):
        try:
            actual = file_sha256(path / name)
        except FileNotFoundError:
            raise ModelIntegrityError(path, name, "missing") from None
        except OSError as exc:
            raise ModelIntegrityError(path, name, f"cannot be read ({_why(exc)})") from None
        if actual != files[name]:
            why = f"not the bytes the card recorded (sha256 {actual[:12]}…, not {files[name][:12]}…)"
            raise ModelIntegrityError(path, name, why)
    return card


def load_model(path: Path) -> tuple[HybridNet, dict]:
    """The network and its card from a version directory, every file checked first (:func:`check_model`):
    config from JSON, tensors from safetensors. A damaged version: :class:`ModelIntegrityError`."""
    card = check_model(path)
    try:
        config = NetConfig.from_dict(card["net"])
    except (TypeError, ValueError) as exc:
        raise ModelIntegrityError(path, CARD, f"'net' is not a network configuration ({exc})") from None
    try:
        tensors = safetensors.torch.load((path / WEIGHTS).read_bytes())
    except Exception as exc:  # safetensors' own error type (a Rust exception), or OSError
        raise ModelIntegrityError(path, WEIGHTS, f"not a safetensors file ({_why(exc)})") from None
    try:
        model = HybridNet.from_state(config, tensors)
    except (RuntimeError, ValueError) as exc:  # other names or shapes than the card's net; NaNs; no scaler
        raise ModelIntegrityError(path, WEIGHTS, f"does not fit the card's net {config.hidden}: "
                                                 f"{_why(exc)}") from None  # fmt: skip
    return model.eval(), card


def load_exported(path: Path) -> torch.jit.ScriptModule:
    """The TorchScript export of a version directory: ``module(x: float64 (n, 7)) -> float64 (n, 3)``; every
    file is checked first (:func:`check_model`)."""
    check_model(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        try:
            return torch.jit.load(io.BytesIO((path / EXPORT).read_bytes()), map_location="cpu").eval()
        except RuntimeError as exc:
            raise ModelIntegrityError(path, EXPORT, f"not a TorchScript file ({_why(exc)})") from None


def load_onnx(path: Path) -> OnnxModel:
    """The ONNX export of a version directory, run by ONNX Runtime (:class:`pipeline.exports.OnnxModel`);
    every file is checked first (:func:`check_model`). A model saved before vslab exported ONNX has none:
    :class:`ModelIntegrityError` says so."""
    card = check_model(path)
    if ONNX not in card["files"]:
        raise ModelIntegrityError(path, ONNX, "never written (a model saved before vslab exported ONNX: "
                                              "train it again)")  # fmt: skip
    try:
        return OnnxModel((path / ONNX).read_bytes())
    except Exception as exc:  # onnxruntime's own error types (a C++ exception): no common base to catch
        raise ModelIntegrityError(path, ONNX, f"not an ONNX model ONNX Runtime runs ({_why(exc)})") from None


def find(root: Path, version: str) -> Path:
    """The directory of ``version`` (a tag, or a version id: a unique prefix of it will do) under ``root``: a
    folder, whatever state its files are in (loading checks them). FileNotFoundError / ValueError with the
    reason otherwise."""
    version = tags(root).get(version, version) if isinstance(version, str) else version
    if not isinstance(version, str) or not VERSION.fullmatch(version):
        raise ValueError(f"{version!r} is not a model version (letters, digits, '-' and '_'; see "
                         "`vslab models list`)")  # fmt: skip
    hits = [p for p in version_dirs(root) if p.name.startswith(version)]
    if not hits:
        raise FileNotFoundError(f"no model version {version!r} under {root} (see `vslab models list`)")
    if len(hits) > 1:
        raise ValueError(f"model version {version!r} is ambiguous: {', '.join(p.name for p in hits)}")
    return hits[0]


def tags(root: Path) -> dict[str, str]:
    """Every tag of the model store under ``root``: alias → full version id (``{}`` where none was set)."""
    path = root / TAGS_FILE
    if not path.is_file():
        return {}
    try:
        found = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelStoreError(f"{path}: unreadable ({type(exc).__name__}); tag the models again") from None
    if not isinstance(found, dict) or not all(isinstance(v, str) for v in found.values()):
        raise ModelStoreError(f"{path}: not a mapping of tag → version; tag the models again")
    return found


def tag(root: Path, name: str, version: str) -> str:
    """Point tag ``name`` at model ``version`` (checked first; a tag that exists is moved); returns the full
    version id. The tags file is replaced whole, never half written."""
    if not isinstance(name, str) or not TAG.fullmatch(name):
        raise ValueError(f"{name!r} is not a tag name (a lower-case letter, then lower-case letters, digits, "
                         "'-' or '_')")  # fmt: skip
    before = tags(root)
    path = find(root, version)
    check_model(path)
    current = before | {name: path.name}
    if current == before:  # already so: the file stays as it is (what the figures read has not changed)
        return path.name
    text = json.dumps(dict(sorted(current.items())), indent=1) + "\n"
    if is_local(root):
        tmp = root / f".{TAGS_FILE}.tmp"
        tmp.write_text(text)
        tmp.replace(root / TAGS_FILE)
    else:  # one object written in one request: a reader sees the old file or the new one
        (root / TAGS_FILE).write_text(text)
    return path.name


def version_dirs(root: Path) -> list[Path]:
    """Every ``<root>/<name>/<version>/`` folder (not the hidden ones a save is writing)."""
    if not is_local(root):  # a store: the versions whose card is there (one listing, not a request each)
        return sorted(card.parent for card in root.glob(f"*/*/{CARD}"))
    if not root.is_dir():
        return []
    return sorted(v for n in root.iterdir() if n.is_dir() and not n.name.startswith(".")
                  for v in n.iterdir() if v.is_dir() and not v.name.startswith("."))  # fmt: skip


def _why(exc: BaseException) -> str:
    """An exception's reason on one line (torch's "Error(s) in …:" heading joined to its first detail)."""
    lines = [ln.strip() for ln in (getattr(exc, "strerror", None) or str(exc)).splitlines() if ln.strip()]
    if not lines:
        return type(exc).__name__
    return f"{lines[0]} {lines[1]}" if lines[0].endswith(":") and len(lines) > 1 else lines[0]


def metric(metrics: dict, names: tuple[str, ...]) -> float:
    """The first of ``names`` present in ``metrics`` (NaN if none)."""
    return next((float(metrics[n]) for n in names if n in metrics), float("nan"))


def summary(card: dict) -> dict:
    """One row for a listing (fields a card lacks are None / NaN)."""
    train, metrics, dataset = (_mapping(card.get(k)) for k in ("train_config", "metrics", "dataset"))
    return {
        "name": card["name"], "version": card["version"], "direction": card["net"].get("direction"),
        "preset": card["net"].get("name"), "dataset": f"{dataset.get('name')}@{dataset.get('version')}",
        "split": train.get("split"), "seed": train.get("seed"), "test_mean_mm": metric(metrics, HEADLINE),
        "test_p95_mm": metric(metrics, P95), "epochs": len(card.get("curves", [])),
        "train_time_s": card.get("train_time_s"), "created": card.get("created"),
    }  # fmt: skip


def _mapping(value) -> dict:
    return value if isinstance(value, dict) else {}


def list_models(root: Path) -> list[dict]:
    """Every model version under ``root``, oldest first, each checked (:func:`check_model`); then the damaged
    ones, each as ``{"name", "version", "damaged": why}``: a listing shows them and goes on."""
    good, damaged = [], []
    for path in version_dirs(root):
        try:
            good.append(summary(check_model(path)))
        except ModelIntegrityError as exc:
            damaged.append({"name": path.parent.name, "version": path.name, "damaged": exc.reason})
    good.sort(key=lambda r: (str(r["created"] or ""), r["name"], r["version"]))
    return good + damaged


def compare(root: Path, versions: list[str]) -> pd.DataFrame:
    """Versions side by side: lineage, configuration and every scalar test metric (one row each)."""
    rows = []
    for version in versions:
        card = check_model(find(root, version))
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


@dataclass(frozen=True)
class ModelStore:
    """``<lab>/models/<name>/<version>/``: trained networks, content-addressed (``lab.models``)."""

    root: LabPath

    def path(self, name: str, version: str) -> LabPath:
        """The folder of model ``name`` at ``version`` (whether or not it exists)."""
        return self.root / name / version

    def find(self, version: str) -> LabPath:
        """The folder of ``version`` (a tag, a version id or a unique prefix of one)."""
        return find(self.root, version)

    def tags(self) -> dict[str, str]:
        """Every tag: alias → full version id."""
        return tags(self.root)

    def tag(self, name: str, version: str) -> str:
        """Point tag ``name`` at ``version``; the full version id."""
        return tag(self.root, name, version)

    def save(self, name: str, version: str, model: HybridNet, card: dict) -> LabPath:
        """Publish a trained network and its card (``FileExistsError`` where that version is there)."""
        return save_model(self.root, name, version, model, card)

    def load(self, version: str) -> tuple[HybridNet, dict]:
        """(network, card) of ``version``, every file checked against its card."""
        return load_model(self.find(version))

    def inverse_onnx(self, version: str) -> tuple[OnnxModel, str]:
        """(model, full version id) of the inverse network ``version`` (a tag or a unique prefix) as the
        control loop runs it: its ONNX export on ONNX Runtime, every file checked against its card first.
        FileNotFoundError for an unknown version; ValueError for an ambiguous, damaged or forward one, or one
        saved without an ONNX export."""
        path = self.find(version)
        direction = load_card(path)["net"].get("direction")
        if direction != "inverse":
            raise ValueError(f"a {direction} model; hybrid commands need an inverse one")
        return load_onnx(path), path.name

    def onnx(self, version: str) -> OnnxModel:
        """The ONNX export of ``version`` on ONNX Runtime, every file checked against its card."""
        return load_onnx(self.find(version))

    def list(self) -> list[dict]:
        """Every version, oldest first, then the damaged ones (:func:`list_models`)."""
        return list_models(self.root)

    def compare(self, versions: list[str]) -> pd.DataFrame:
        """Versions side by side (:func:`compare`)."""
        return compare(self.root, versions)
