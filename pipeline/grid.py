"""Grid training: models × datasets × splits × seeds (``configs/train/grid.yaml``), one job each.

A job's model version is known before it trains (:func:`pipeline.registry.model_version`), so a job whose
version exists is skipped: running the same grid twice trains nothing the second time. Jobs run on any
``concurrent.futures.Executor`` (local processes by default, each with cores / workers torch threads; a
distributed engine's executor with shared lab storage) through the top-level function :func:`train_job`.
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import logging
import multiprocessing
import os
from collections.abc import Callable
from pathlib import Path

import yaml

from models.hybrid import NetConfig, preset
from pipeline.build import InlineExecutor
from pipeline.registry import CARD, jsonable, load_card, metric, model_version, save_model
from pipeline.train import TrainConfig

log = logging.getLogger(__name__)

GRID_KEYS = ("models", "datasets", "splits", "seeds", "train")
TRAIN_KEYS = tuple(f.name for f in dataclasses.fields(TrainConfig) if f.name not in ("net", "split", "seed"))
NET_KEYS = tuple(f.name for f in dataclasses.fields(NetConfig) if f.name not in ("direction", "name"))


class GridError(ValueError):
    """A grid file or override that cannot be used (names what and where)."""


def load_grid(path: Path, overrides: dict | None = None) -> dict:
    """The grid of a YAML file, with ``overrides``: a grid key (``seeds=[0,1]``) or a training field
    (``max_epochs=5``, also ``train.max_epochs=5``)."""
    path = Path(path)
    if not path.is_file():
        raise GridError(f"no grid file at {path}")
    grid = yaml.safe_load(path.read_text()) or {}
    if unknown := sorted(set(grid) - set(GRID_KEYS)):
        raise GridError(f"{path}: unknown keys {unknown} (known: {list(GRID_KEYS)})")
    grid.setdefault("train", {})
    for key, value in (overrides or {}).items():
        key = key.removeprefix("train.")
        if key in GRID_KEYS:
            grid[key] = value
        elif key in TRAIN_KEYS:
            grid["train"][key] = value
        else:
            raise GridError(
                f"--set {key}: not a grid key {list(GRID_KEYS)} nor a training field {TRAIN_KEYS}"
            )
    return grid


def resolve_dataset(root: Path, spec: str) -> tuple[str, str]:
    """(name, version) of ``name`` (its newest version under ``root``) or ``name@version``."""
    name, _, version = str(spec).partition("@")
    if version:
        if not (Path(root) / name / version / "card.json").is_file():
            raise GridError(f"no dataset {name}@{version} under {root}")
        return name, version
    cards = sorted((Path(root) / name).glob("*/card.json"), key=lambda p: p.stat().st_mtime)
    if not cards:
        raise GridError(f"no dataset {name!r} under {root} (build one: `vslab build --name {name}`)")
    return name, cards[-1].parent.name


def _net(entry: dict) -> NetConfig:
    entry = dict(entry)
    try:
        net = preset(entry.pop("direction"), entry.pop("preset"))
    except KeyError as exc:
        raise GridError(f"grid model {entry}: {exc}") from None
    if unknown := sorted(set(entry) - set(NET_KEYS)):
        raise GridError(f"grid model: unknown fields {unknown} (a preset takes {list(NET_KEYS)})")
    return dataclasses.replace(net, **entry)


def expand(lab: Path, grid: dict) -> list[dict]:
    """The grid's jobs (JSON-able dicts): dataset, TrainConfig dict, model name and version."""
    train = grid.get("train", {})
    if unknown := sorted(set(train) - set(TRAIN_KEYS)):
        raise GridError(f"grid train: unknown fields {unknown} (known: {list(TRAIN_KEYS)})")
    jobs = []
    for spec in grid.get("datasets", []):
        dataset, dataset_version = resolve_dataset(Path(lab) / "datasets", spec)
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
                    jobs.append({
                        "name": name, "version": model_version(dataset_version, config),
                        "dataset": {"name": dataset, "version": dataset_version}, "config": config.to_dict(),
                    })  # fmt: skip
    return list({job["version"]: job for job in jobs}.values())  # the same job listed twice runs once


def _summary(job: dict, card: dict, status: str) -> dict:
    m = card.get("metrics", {})
    return {"name": job["name"], "version": job["version"], "status": status,
            "dataset": f"{job['dataset']['name']}@{job['dataset']['version']}",
            "split": job["config"]["split"], "seed": job["config"]["seed"],
            "test_mean_mm": metric(m, ("tip_mean_mm",)), "test_p95_mm": metric(m, ("tip_p95_mm",)),
            "train_time_s": card.get("train_time_s", float("nan")),
            "epochs": len(card.get("curves", []))}  # fmt: skip


def train_job(job: dict, lab: str, threads: int = 1) -> dict:
    """Train, evaluate (test part of the job's split) and save one job (top-level: any executor runs it)."""
    from pipeline.datasets import load_dataset
    from pipeline.train import evaluate, train

    root = Path(lab) / "models"
    existing = root / job["name"] / job["version"]
    if (existing / CARD).is_file():
        return _summary(job, load_card(existing), "existing")
    data, _ = load_dataset(Path(lab) / "datasets", job["dataset"]["name"], job["dataset"]["version"])
    config = TrainConfig.from_dict(job["config"])
    result = train(data, config, threads=threads, device="cpu")
    metrics = evaluate(result.model, data, config.split, "test")
    losses = zip(result.train_loss, result.val_loss, result.val_error_mm, strict=True)
    curves = [
        {"epoch": k, "train_loss": a, "val_loss": b, "val_error_mm": c} for k, (a, b, c) in enumerate(losses)
    ]
    card = {
        "dataset": job["dataset"], "train_config": config.to_dict(), "seed": config.seed,
        "metrics": metrics, "curves": curves, "best_epoch": result.best_epoch,
        "train_time_s": result.train_time_s, "epoch_time_s": result.epoch_time_s, "threads": threads,
        "n_train": result.n_train, "n_val": result.n_val,
    }  # fmt: skip
    try:
        save_model(root, job["name"], job["version"], result.model, card)
    except FileExistsError:  # another worker finished the same version first: keep theirs
        return _summary(job, load_card(existing), "existing")
    return _summary(job, jsonable(card), "trained")


def run_grid(
    lab: Path,
    grid: dict,
    executor: cf.Executor | None = None,
    progress: Callable[[int, int, dict], None] | None = None,
    workers: int | None = None,
) -> list[dict]:
    """Train every job of ``grid`` whose version is not in ``<lab>/models`` yet; one summary per job, in grid
    order (``status``: "trained" or "existing"). ``progress(done, total, summary)`` after each job."""
    jobs = expand(lab, grid)
    root = Path(lab) / "models"
    results: dict[str, dict] = {}
    todo = []
    for job in jobs:
        path = root / job["name"] / job["version"]
        if (path / CARD).is_file():
            results[job["version"]] = _summary(job, load_card(path), "existing")
        else:
            todo.append(job)
    cores = os.cpu_count() or 1
    workers = workers or max(1, min(len(todo), cores))
    own = executor is None
    if own:
        executor = (cf.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("forkserver"))
                    if workers > 1 and len(todo) > 1 else InlineExecutor())  # fmt: skip
    threads = max(1, cores // workers)
    for done, summary in enumerate(list(results.values()), 1):
        if progress:
            progress(done, len(jobs), summary)
    done = len(results)
    try:
        futures = {executor.submit(train_job, job, str(lab), threads): job for job in todo}
        for future in cf.as_completed(futures):
            summary = future.result()
            results[summary["version"]] = summary
            done += 1
            log.debug("%s %s: %s", summary["name"], summary["version"], summary["status"])
            if progress:
                progress(done, len(jobs), summary)
    finally:
        if own:
            executor.shutdown(cancel_futures=True)
    return [results[job["version"]] for job in jobs]
