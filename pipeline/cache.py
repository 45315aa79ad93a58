"""Content addresses: what a stage's output depends on, hashed, so unchanged work is never done twice.

A stage output's key is the hash of its inputs' hashes, its parameters and its code version (the code it runs,
docstrings and comments left out, so only a change of behaviour re-versions it); it is stored
under ``<lab>/cache/<stage>/<key>/``. Writes go to a temporary directory renamed into place, so a killed
build never leaves a half-written entry that a later build would trust.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from pathlib import Path

import pandas as pd

from acquisition.code_version import PACKAGES, _normalised, _tree_version  # noqa: F401 (tests clear their caches)
from acquisition.storage import LabPath, publish, read_parquet, remove, write_parquet

ROOT = Path(__file__).resolve().parents[1]
# What each stage's output is made by: its modules and, through their imports, everything they use.
STAGE_MODULES = {
    "session": ("pipeline.build",),  # ingest → clean → sync → segment of one session
    "dataset": ("pipeline.build", "pipeline.datasets"),  # registration, D, splits
    "model": ("pipeline.train", "pipeline.model_store"),  # fit, evaluate, save
    "figure": ("analysis.lab_figures",),
}
RECORD = "record.json"  # a cache entry's manifest


def digest(value: object) -> str:
    """sha256 of a JSON-able value (keys sorted): parameters, lists of hashes."""
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()


def file_hash(paths: Iterable[Path], block: int = 1 << 22) -> str:
    """sha256 over the bytes of ``paths`` in the given order (streamed)."""
    h = hashlib.sha256()
    for path in paths:
        with path.open("rb") as f:
            while chunk := f.read(block):
                h.update(chunk)
    return h.hexdigest()


_ALL_STAGES = tuple(sorted({m for ms in STAGE_MODULES.values() for m in ms}))


def code_version(*modules: str, root: Path | None = None) -> str:
    """Hash of the code that ``modules`` run: theirs and every project module they import, transitively (and
    the packages holding them), each as its syntax tree without docstrings and comments. A docstring or
    comment edit leaves it as it was; a change of what the code does changes it. No modules: the code of
    every stage. ``root``: the checkout whose code is read (this one by default)."""
    return _tree_version(modules or _ALL_STAGES, Path(ROOT if root is None else root))


def stage_version(stage: str, root: Path | None = None) -> str:
    """The code version of one stage (a key of ``STAGE_MODULES``), of the code under ``root`` (this
    checkout's by default)."""
    return code_version(*STAGE_MODULES[stage], root=root)


def stage_key(stage: str, inputs: list[str], parameters: dict) -> str:
    """The cache key of one stage run."""
    return digest({"stage": stage, "inputs": inputs, "parameters": parameters, "code": stage_version(stage)})[
        :24
    ]


class StageCache:
    """``<root>/<stage>/<key>/`` holding Parquet tables and a JSON record per entry."""

    def __init__(self, root: LabPath) -> None:
        self.root = root

    def path(self, stage: str, key: str) -> Path:
        return self.root / stage / key

    def has(self, stage: str, key: str) -> bool:
        return (self.path(stage, key) / RECORD).is_file()

    def discard(self, stage: str, key: str) -> None:
        """Remove one entry (a damaged one, to be made again)."""
        remove(self.path(stage, key))

    def load(self, stage: str, key: str) -> tuple[dict[str, pd.DataFrame], dict]:
        entry = self.path(stage, key)
        record = json.loads((entry / RECORD).read_text())
        tables = {name: read_parquet(entry / f"{name}.parquet") for name in record["tables"]}
        return tables, record

    def store(self, stage: str, key: str, tables: dict[str, pd.DataFrame], record: dict) -> Path:
        """Publish one entry whole (another process that finished the same work first keeps theirs)."""

        def fill(folder: Path) -> None:
            for name, df in tables.items():
                write_parquet(df, folder / f"{name}.parquet")
            whole = {**record, "tables": sorted(tables)}
            (folder / RECORD).write_text(json.dumps(whole, indent=1, default=str))

        final = self.path(stage, key)
        publish(final, fill, RECORD)
        return final
