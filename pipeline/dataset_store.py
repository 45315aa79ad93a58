"""The lab's datasets: ``<lab>/datasets/<name>/<version>/``, each version written once, whole.

A version folder holds ``<table>.parquet`` for each table (``data`` is D; ``trajectories`` where the sessions
ran them; ``moves``, the moves into the settled points, where they have some) and ``card.json`` (what made
it: sessions, parameters, code version, the tracker registration it fitted). The version is the hash of
those inputs (``pipeline.datasets.dataset_version``), so building the same inputs again finds it. The Lab
makes the store (``lab.datasets``); this module is what it does.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING

from acquisition.storage import LabPath, publish, read_parquet, write_parquet
from pipeline.errors import PipelineError

if TYPE_CHECKING:  # imported where used: the Lab makes this store on every command, which needs neither
    import pandas as pd

CARD = "card.json"  # a dataset version's manifest


class DatasetError(PipelineError, ValueError):
    """A dataset named that the store does not hold, or whose card cannot be read: the message says which
    and what to do."""


class DatasetNotFound(DatasetError, FileNotFoundError):
    """No dataset of that name, or not that version of it."""


@dataclass(frozen=True)
class DatasetStore:
    """``<lab>/datasets/``: built datasets by name and version."""

    root: LabPath

    def path(self, name: str, version: str) -> LabPath:
        """The folder of dataset ``name@version`` (whether or not it exists)."""
        return self.root / name / version

    def names(self) -> list[str]:
        """The names of the datasets this lab holds (none where the store is empty)."""
        return sorted(p.name for p in self.root.glob("*") if p.is_dir()) if self.root.is_dir() else []

    def has(self, name: str, version: str) -> bool:
        """Is ``name@version`` there, whole (its card written)?"""
        return (self.path(name, version) / CARD).is_file()

    def newest(self, name: str) -> str | None:
        """The version of ``name`` written last, by the ``created`` time its card records (not by the files'
        modification times, which a copy or a backup changes; only a card older than that field falls back to
        its file's); None where there is none."""
        created = []
        for card in (self.root / name).glob(f"*/{CARD}"):
            try:
                when = json.loads(card.read_text()).get("created")
                when = when or datetime.fromtimestamp(card.stat().st_mtime, UTC).isoformat(
                    timespec="microseconds"
                )
            except (OSError, ValueError, AttributeError):  # a damaged card is not a candidate
                continue
            created.append((str(when), card.parent.name))
        return max(created)[1] if created else None

    def resolve(self, spec: str) -> tuple[str, str]:
        """(name, version) of ``name`` (its newest version) or ``name@version``; ``DatasetError`` naming the
        datasets there otherwise."""
        name, _, version = str(spec).partition("@")
        if not name:
            raise DatasetError(f"{spec!r} names no dataset: give NAME or NAME@VERSION")
        if version and self.has(name, version):
            return name, version
        if not version and (version := self.newest(name)) is not None:
            return name, version
        what = f"{name}@{spec.partition('@')[2]}" if "@" in str(spec) else repr(name)
        there = ", ".join(self.names()) or "none"
        raise DatasetNotFound(f"no dataset {what} under {self.root} (datasets there: {there}); build it: "
                              f"`vslab build --name {name}`")  # fmt: skip

    def load(self, name: str, version: str | None = None, table: str | None = "data"):
        """(table or None, card) of ``name`` (the newest version when none is named); ``data`` is D,
        ``trajectories`` the repetitions, ``moves`` the moves into the points, None only the card.
        ``DatasetError`` where it is not there or its card cannot be read."""
        name, version = self.resolve(f"{name}@{version}" if version else name)
        path = self.path(name, version)
        try:
            card = json.loads((path / CARD).read_text())
        except (OSError, ValueError) as exc:
            why = f"{type(exc).__name__}: {exc}"
            raise DatasetError(f"dataset {name}@{version}: its {CARD} under {self.root} cannot be read "
                               f"({why}); build that dataset again") from exc  # fmt: skip
        if not isinstance(card, dict):
            raise DatasetError(f"dataset {name}@{version}: its {CARD} under {self.root} is not a JSON object")
        return (read_parquet(path / f"{table}.parquet") if table else None), card

    def write(self, name: str, version: str, tables: dict[str, pd.DataFrame], card: dict) -> LabPath:
        """Publish ``name@version``: each table and the card written whole in a temporary folder, then renamed
        in (a killed build leaves no half dataset; a version written before, same inputs, stays as it is)."""

        from pipeline.datasets import SPLITS

        def fill(folder) -> None:
            for table, df in tables.items():
                write_parquet(df, folder / f"{table}.parquet")
            data = tables["data"]
            split = data["split_random"]
            counts = {"rows": len(data)} | {f"rows_{s}": int((split == s).sum()) for s in SPLITS}
            counts |= {f"rows_{t}": len(df) for t, df in tables.items() if t != "data"}
            created = datetime.now(UTC).isoformat(timespec="microseconds")
            whole = {"name": name, "version": version, "created": created, **card, "counts": counts}
            (folder / CARD).write_text(json.dumps(whole, indent=1, default=str))

        final = self.path(name, version)
        publish(final, fill, CARD)
        return final

    def registrations(self, reference: str) -> tuple[str, dict]:
        """(``name@version``, the tracker registrations its card holds, robot → summary) of dataset
        ``name[@version]``: what a build borrows (``pipeline.registration.borrowed_placement`` takes one
        robot's placement of them); ``DatasetError`` where it is not there or its card cannot be read."""
        _, card = self.load(*_split(reference), table=None)
        where = f"{card.get('name') or reference.partition('@')[0]}@{card.get('version')}"
        fitted = card.get("registration") or {}
        return where, fitted if isinstance(fitted, dict) else {}


def _split(reference: str) -> tuple[str, str | None]:
    name, _, version = str(reference).partition("@")
    return name, version or None
