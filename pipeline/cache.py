"""Content addresses: what a stage's output depends on, hashed, so unchanged work is never done twice.

A stage output's key is the hash of its inputs' hashes, its parameters and the code version; it is stored
under ``<lab>/cache/<stage>/<key>/``. Writes go to a temporary directory renamed into place, so a killed
build never leaves a half-written entry that a later build would trust.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterable
from functools import cache
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
CODE_DIRS = ("pipeline", "models", "acquisition/schemas")  # what a stage's output can depend on


def digest(value: object) -> str:
    """sha256 of a JSON-able value (keys sorted): parameters, lists of hashes."""
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()


def file_hash(paths: Iterable[Path], block: int = 1 << 22) -> str:
    """sha256 over the bytes of ``paths`` in the given order (streamed)."""
    h = hashlib.sha256()
    for path in paths:
        with open(path, "rb") as f:
            while chunk := f.read(block):
                h.update(chunk)
    return h.hexdigest()


@cache
def code_version() -> str:
    """Hash of the source the pipeline's results depend on (its own code, the models, the schemas): changes
    when that code changes, not when a comment elsewhere does; no git needed."""
    files = sorted(p for d in CODE_DIRS for p in (ROOT / d).rglob("*.py"))
    h = hashlib.sha256()
    for p in files:
        h.update(str(p.relative_to(ROOT)).encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def stage_key(stage: str, inputs: list[str], parameters: dict) -> str:
    """The cache key of one stage run."""
    return digest({"stage": stage, "inputs": inputs, "parameters": parameters, "code": code_version()})[:24]


class StageCache:
    """``<root>/<stage>/<key>/`` holding Parquet tables and a JSON record per entry."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    def path(self, stage: str, key: str) -> Path:
        return self.root / stage / key

    def has(self, stage: str, key: str) -> bool:
        return (self.path(stage, key) / "record.json").is_file()

    def load(self, stage: str, key: str) -> tuple[dict[str, pd.DataFrame], dict]:
        entry = self.path(stage, key)
        record = json.loads((entry / "record.json").read_text())
        tables = {name: pd.read_parquet(entry / f"{name}.parquet") for name in record["tables"]}
        return tables, record

    def store(self, stage: str, key: str, tables: dict[str, pd.DataFrame], record: dict) -> Path:
        final = self.path(stage, key)
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{key}-", dir=final.parent))
        try:
            for name, df in tables.items():
                df.to_parquet(tmp / f"{name}.parquet", index=False)
            (tmp / "record.json").write_text(
                json.dumps({**record, "tables": sorted(tables)}, indent=1, default=str)
            )
            if final.exists():  # another process finished the same work first: keep theirs
                shutil.rmtree(tmp)
            else:
                os.replace(tmp, final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return final
