"""Grid training: models × datasets × splits × seeds (``configs/train/grid.yaml``), one job each.

A job's model version is known before it trains (:func:`pipeline.model_store.model_version`), so a job whose
version exists is skipped: running the same grid twice trains nothing the second time. Jobs run on any
``concurrent.futures.Executor`` through the top-level function :func:`train_job`: by default the small nets
in local processes of one torch thread each, then each large net in this process on every core
(:func:`_rounds`); given workers, threads or an executor (a distributed engine's, with shared lab storage),
every job at once as asked.
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import itertools
import logging
import math
import multiprocessing
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from models.hybrid import NetConfig, preset
from models.yaml_files import read_yaml
from pipeline.build import InlineExecutor
from pipeline.dataset_store import DatasetError
from pipeline.datasets import SPLIT_COLUMNS
from pipeline.errors import PipelineError
from pipeline.model_store import CARD, TAG, check_model, jsonable, load_card, metric, model_version
from pipeline.train import TrainConfig

if TYPE_CHECKING:
    from pipeline.lab import Lab

log = logging.getLogger(__name__)

GRID_KEYS = ("models", "datasets", "splits", "seeds", "train")
TRAIN_KEYS = tuple(f.name for f in dataclasses.fields(TrainConfig) if f.name not in ("net", "split", "seed"))
NET_KEYS = tuple(f.name for f in dataclasses.fields(NetConfig) if f.name not in ("direction", "name"))


class GridError(PipelineError, ValueError):
    """A grid file or override that cannot be used (names what and where)."""


def load_grid(path: Path, overrides: dict | None = None) -> dict:
    """The grid of a YAML file, with ``overrides``: a grid key (``seeds=[0,1]``) or a training field
    (``max_epochs=5``, also ``train.max_epochs=5``). Checked whole (:func:`check_grid`): a file that cannot
    be read or a value of the wrong kind is one :class:`GridError` naming the file (or --set) and the key."""
    path = Path(path)
    if path.is_dir():
        raise GridError(f"{path}: a folder, not a grid file (a YAML file like configs/train/grid.yaml)")
    if not path.is_file():
        raise GridError(f"no grid file at {path}")
    grid = read_yaml(path, GridError)
    if grid is None:
        raise GridError(f"{path}: empty (a grid names its {list(GRID_KEYS)}; see configs/train/grid.yaml)")
    if not isinstance(grid, dict):
        raise GridError(f"{path}: expected a mapping of {list(GRID_KEYS)}, found {_kind(grid)}")
    if unknown := sorted(set(grid) - set(GRID_KEYS), key=str):
        raise GridError(f"{path}: unknown keys {unknown} (known: {list(GRID_KEYS)})")
    grid = dict(grid)
    if grid.get("train") is None:
        grid["train"] = {}
    if not isinstance(grid["train"], dict):
        raise GridError(f"{path}: train: expected a mapping of training fields {list(TRAIN_KEYS)}")
    grid["train"] = dict(grid["train"])
    where = {key: f"{path}: {key}" for key in grid} | {
        f"train.{key}": f"{path}: train.{key}" for key in grid["train"]
    }
    for key, value in (overrides or {}).items():
        field = key.removeprefix("train.")
        if field in GRID_KEYS:
            grid[field] = value
            where[field] = f"--set {key}"
            if field == "train" and isinstance(value, dict):
                where |= {f"train.{k}": f"--set {key}: {k}" for k in value}
        elif field in TRAIN_KEYS:
            grid["train"][field] = value
            where[f"train.{field}"] = f"--set {key}"
        else:
            raise GridError(
                f"--set {key}: not a grid key {list(GRID_KEYS)} nor a training field {list(TRAIN_KEYS)}"
            )
    check_grid(grid, where)
    return grid


# each training field: (an integer?, its smallest value, that value itself allowed?)
TRAIN_LIMITS = {"lr": (False, 0, False), "batch_size": (True, 1, True), "max_epochs": (True, 1, True),
                "patience": (True, 0, True), "weight_decay": (False, 0, True)}  # fmt: skip
DATASET = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*(@[A-Za-z0-9_][A-Za-z0-9_.-]*)?")


def check_grid(grid: dict, where: dict[str, str] | None = None) -> None:
    """Every value of ``grid`` of the kind a training job takes; :class:`GridError` names the first that is
    not (``where``: key → where it came from, a file's key or a ``--set``)."""
    where = where or {}

    def fail(key: str, problem: str) -> None:
        raise GridError(f"{where.get(key, key)}: {problem}")

    for key in ("models", "datasets", "splits", "seeds"):
        if key in grid and (not isinstance(grid[key], list) or not grid[key]):
            fail(key, f"expected a non-empty [list], found {_kind(grid[key])}")
    for k, entry in enumerate(grid.get("models", [])):
        _check_model(entry, lambda problem, k=k: fail("models", f"model {k}: {problem}"))
    for spec in grid.get("datasets", []):
        if not isinstance(spec, str) or not DATASET.fullmatch(spec):
            fail("datasets", f"{spec!r} is not a dataset name or name@version")
    for split in grid.get("splits", []):
        if split not in SPLIT_COLUMNS:
            fail("splits", f"{split!r} is not a split (known: {list(SPLIT_COLUMNS)})")
    for seed in grid.get("seeds", []):
        if not _integer(seed) or seed < 0:
            fail("seeds", f"{seed!r} is not a seed (an integer ≥ 0)")
    train = grid.get("train", {})
    if not isinstance(train, dict):
        fail("train", f"expected a mapping of training fields {list(TRAIN_KEYS)}, found {_kind(train)}")
    if unknown := sorted(set(train) - set(TRAIN_KEYS), key=str):
        fail("train", f"unknown training field(s) {unknown} (known: {list(TRAIN_KEYS)})")
    for key, value in train.items():
        integer, least, inclusive = TRAIN_LIMITS.get(key, (False, 0, True))
        fits = _integer(value) if integer else _number(value)
        if not fits or value < least or (value == least and not inclusive):
            bound = f"{'≥' if inclusive else '>'} {least}"
            fail(f"train.{key}", f"{value!r}: expected {'an integer' if integer else 'a number'} {bound}")


def _check_model(entry, fail) -> None:
    if not isinstance(entry, dict):
        fail(f"expected a mapping {{direction, preset, …}}, found {_kind(entry)}")
    if not isinstance(entry.get("direction"), str) or not isinstance(entry.get("preset"), str):
        fail("needs a direction (forward or inverse) and a preset name")
    try:
        preset(entry["direction"], entry["preset"])
    except KeyError as exc:
        fail(exc.args[0])
    if unknown := sorted(set(entry) - {"direction", "preset", "tag", *NET_KEYS}, key=str):
        fail(f"unknown field(s) {unknown} (a preset takes {list(NET_KEYS)}; any model a tag)")
    if "tag" in entry and not (isinstance(entry["tag"], str) and TAG.fullmatch(entry["tag"])):
        fail(f"tag: {entry['tag']!r}: expected a tag name (lower-case letters, digits, - and _)")
    hidden = entry.get("hidden", [1])
    if not isinstance(hidden, list) or not hidden or not all(_integer(h) and h >= 1 for h in hidden):
        fail(f"hidden: {hidden!r}: expected a [list] of layer widths (integers ≥ 1)")
    if not isinstance(entry.get("residual", False), bool):
        fail(f"residual: {entry['residual']!r}: expected true or false")
    if not _integer(entry.get("ensemble", 1)) or entry.get("ensemble", 1) < 1:
        fail(f"ensemble: {entry['ensemble']!r}: expected an integer ≥ 1")
    if not isinstance(entry.get("name", ""), str):
        fail(f"name: {entry['name']!r}: expected text")


def _integer(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _number(value) -> bool:
    return (_integer(value) or isinstance(value, float)) and math.isfinite(value)


def _kind(value) -> str:
    names = {dict: "a mapping", list: "a list", str: "text", bool: "true/false", int: "an integer",
             float: "a number", type(None): "nothing"}  # fmt: skip
    shown = "" if value is None else f" ({value!r:.40})"
    return names.get(type(value), f"a {type(value).__name__}") + shown


def _net(entry: dict) -> NetConfig:
    entry = {k: v for k, v in entry.items() if k != "tag"}
    try:
        net = preset(entry.pop("direction"), entry.pop("preset"))
    except KeyError as exc:
        raise GridError(f"grid model {entry}: {exc}") from None
    if unknown := sorted(set(entry) - set(NET_KEYS)):
        raise GridError(f"grid model: unknown fields {unknown} (a preset takes {list(NET_KEYS)})")
    return dataclasses.replace(net, **entry)


def expand(lab: Lab, grid: dict, pretrain: dict | None = None) -> list[dict]:
    """The grid's jobs (JSON-able dicts): dataset, TrainConfig dict, model name and version. ``pretrain``
    (``{"dataset": "NAME[@VERSION]", "robot": description}``: a twin's campaign, ``pipeline.pretrain``):
    each job first trains its net on that dataset (a model of its own, ``pretrain.version``), then fine-tunes
    it on the job's dataset: another version than the job's without pretraining."""
    train = grid.get("train", {})
    if unknown := sorted(set(train) - set(TRAIN_KEYS)):
        raise GridError(f"grid train: unknown fields {unknown} (known: {list(TRAIN_KEYS)})")
    jobs = []
    tagged = [e["tag"] for e in grid.get("models", []) if "tag" in e]
    if len(tagged) != len(set(tagged)):
        raise GridError(f"grid models: a tag names one network, and {sorted(tagged)} repeat one")
    each = len(grid.get("datasets", [])) * len(grid.get("splits", [0])) * len(grid.get("seeds", [0]))
    if tagged and each > 1:
        raise GridError("grid models: a tag names one network: tag the models of a grid of one dataset, "
                        "one split and one seed")  # fmt: skip
    twin = None
    if pretrain is not None:
        try:
            twin = dict(zip(("name", "version"), lab.datasets.resolve(pretrain["dataset"]), strict=True))
        except DatasetError as exc:
            raise GridError(f"pretraining dataset {pretrain['dataset']}: {exc}") from None
    for spec in grid.get("datasets", []):
        try:
            dataset, dataset_version = lab.datasets.resolve(spec)
        except DatasetError as exc:
            raise GridError(f"grid dataset {spec}: {exc}") from None
        for entry in grid.get("models", []):
            net = _net(entry)
            for split in grid.get("splits", ["split_random"]):
                for seed in grid.get("seeds", [0]):
                    try:
                        config = TrainConfig(net=net, split=split, seed=int(seed), **train)
                    except (TypeError, ValueError) as exc:
                        raise GridError(
                            f"grid job {net.direction}-{net.name} {split} seed {seed}: {exc}"
                        ) from None
                    name = f"{net.direction}-{net.name}"
                    job = {
                        "name": name, "version": model_version(dataset_version, config),
                        "dataset": {"name": dataset, "version": dataset_version}, "config": config.to_dict(),
                    } | ({"tag": entry["tag"]} if "tag" in entry else {})  # fmt: skip
                    if twin is not None:
                        first = model_version(twin["version"], config)
                        job["pretrain"] = {"version": first, "dataset": twin, "robot": str(pretrain["robot"])}
                        job["version"] = model_version(dataset_version, config, pretrained=first)
                    jobs.append(job)
    return list({job["version"]: job for job in jobs}.values())  # the same job listed twice runs once


def _summary(job: dict, card: dict, status: str) -> dict:
    m = card.get("metrics", {})
    return {"name": job["name"], "version": job["version"], "status": status,
            "dataset": f"{job['dataset']['name']}@{job['dataset']['version']}",
            "split": job["config"]["split"], "seed": job["config"]["seed"],
            "test_mean_mm": metric(m, ("tip_mean_mm",)), "test_p95_mm": metric(m, ("tip_p95_mm",)),
            "train_time_s": card.get("train_time_s", float("nan")),
            "epochs": len(card.get("curves", []))}  # fmt: skip


def train_job(job: dict, lab: Lab, threads: int = 1) -> dict:
    """Train, evaluate (test part of the job's split) and save one job into ``lab`` (top-level, its arguments
    pickle: any executor runs it); a job with ``pretrain`` starts from the net its twin's campaign trained
    (trained and saved first where it is not in ``lab.models`` yet)."""
    from pipeline.train import evaluate, model_card, train

    existing = lab.models.path(job["name"], job["version"])
    if (existing / CARD).is_file():
        return _summary(job, load_card(existing), "existing")
    pretrained, noted = None, {}
    if "pretrain" in job:
        pretrained = _pretrained(job, lab, threads)
        pre = job["pretrain"]
        twin = f"{pre['dataset']['name']}@{pre['dataset']['version']}"
        noted = {"pretrained": {"model": pre["version"], "robot": pre["robot"], "dataset": twin}}
    data, _ = lab.datasets.load(job["dataset"]["name"], job["dataset"]["version"])
    config = TrainConfig.from_dict(job["config"])
    result = train(data, config, threads=threads, device="cpu", pretrained=pretrained)
    card = model_card(result, job["dataset"], evaluate(result.model, data, config.split, "test"), threads)
    try:
        lab.models.save(job["name"], job["version"], result.model, card | noted)
    except FileExistsError:  # another worker finished the same version first: keep theirs
        return _summary(job, load_card(existing), "existing")
    return _summary(job, jsonable(card | noted), "trained")


def _pretrained(job: dict, lab: Lab, threads: int):
    """The net of ``job``'s config trained on its twin's campaign (``job["pretrain"]``): from ``lab.models``,
    or trained, scored on the campaign's test part and saved there first."""
    from pipeline.train import evaluate, model_card, train

    pre = job["pretrain"]
    if (lab.models.path(job["name"], pre["version"]) / CARD).is_file():
        return lab.models.load(pre["version"])[0]
    data, _ = lab.datasets.load(pre["dataset"]["name"], pre["dataset"]["version"])
    config = TrainConfig.from_dict(job["config"])
    result = train(data, config, threads=threads, device="cpu", robot=pre["robot"])
    scores = evaluate(result.model, data, config.split, "test", robot=pre["robot"])
    try:
        lab.models.save(job["name"], pre["version"], result.model, model_card(result, pre["dataset"], scores,
                                                                              threads))  # fmt: skip
    except FileExistsError:  # another job pretrained the same net first
        return lab.models.load(pre["version"])[0]
    return result.model


HEAVY_WEIGHTS = 100_000  # a net this large computes more than it waits: torch's threads speed it up


def net_weights(net: NetConfig) -> int:
    """The number of weights and biases of a net (every member of an ensemble)."""
    widths = [len(net.inputs), *net.hidden, len(net.targets)]
    return net.ensemble * sum(a * b + b for a, b in itertools.pairwise(widths))


def _rounds(todo: list[dict], executor: cf.Executor | None, workers: int | None, threads: int | None):
    """(jobs, executor, torch threads per job) in the order they run. Given an executor, a worker count or a
    thread count: every job at once, as asked. Otherwise the small nets first, side by side on one core each
    (a small net waits on torch's per-operation overhead, which threads do not share out), then each large
    net alone on every core (measured on 2 cores: the paper's net 1.9× faster on two threads than on one,
    the same weights bit for bit; the quick main job's four nets 65 → 41 s)."""
    cores = os.cpu_count() or 1
    if executor is not None or workers or threads:
        workers = workers or max(1, min(len(todo), cores))
        yield todo, executor or _pool(workers, len(todo)), threads or max(1, cores // workers)
        return
    small, large = [], []
    for job in todo:
        heavy = net_weights(TrainConfig.from_dict(job["config"]).net) >= HEAVY_WEIGHTS
        (large if heavy else small).append(job)
    if small:
        yield small, _pool(min(len(small), cores), len(small)), 1
    for job in large:
        yield [job], InlineExecutor(), cores


def _pool(workers: int, jobs: int) -> cf.Executor:
    """Processes for ``jobs`` jobs (forkserver: nothing of this process's threads is forked), or this one."""
    if workers > 1 and jobs > 1:
        return cf.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("forkserver"))
    return InlineExecutor()


def run_grid(
    lab: Lab,
    grid: dict,
    executor: cf.Executor | None = None,
    progress: Callable[[int, int, dict], None] | None = None,
    workers: int | None = None,
    threads: int | None = None,
    pretrain: dict | None = None,
) -> list[dict]:
    """Train every job of ``grid`` whose version is not in ``lab.models`` yet; one summary per job, in grid
    order (``status``: "trained" or "existing"). ``progress(done, total, summary)`` after each job.
    ``workers``, ``threads``: processes and torch threads per job (default: the small nets side by side,
    then each large one on every core, :func:`_rounds`; a cluster's workers take 1 thread each). A model of
    the grid with a ``tag`` gets it in ``lab.models`` once every job is done (the main job's grid tags the
    networks the figures and Experiment 2 use). ``pretrain``: each net pretrained on a twin's campaign first
    (:func:`expand`)."""
    jobs = expand(lab, grid, pretrain)
    results: dict[str, dict] = {}
    todo = []
    for job in jobs:
        path = lab.models.path(job["name"], job["version"])
        if (path / CARD).is_file():  # an existing version, its files checked (a damaged one: one error)
            results[job["version"]] = _summary(job, check_model(path), "existing")
        else:
            todo.append(job)
    for done, summary in enumerate(list(results.values()), 1):
        if progress:
            progress(done, len(jobs), summary)
    done = len(results)
    for batch, batch_executor, batch_threads in _rounds(todo, executor, workers, threads):
        try:
            futures = {batch_executor.submit(train_job, job, lab, batch_threads): job for job in batch}
            for future in cf.as_completed(futures):
                summary = future.result()
                results[summary["version"]] = summary
                done += 1
                log.debug("%s %s: %s", summary["name"], summary["version"], summary["status"])
                if progress:
                    progress(done, len(jobs), summary)
        finally:
            if batch_executor is not executor:
                batch_executor.shutdown(cancel_futures=True)
    for job in jobs:  # a tag moves only once the whole grid is trained
        if "tag" in job:
            lab.models.tag(job["tag"], job["version"])
            results[job["version"]]["tag"] = job["tag"]
    return [results[job["version"]] for job in jobs]
