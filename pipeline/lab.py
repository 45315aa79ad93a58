"""The lab: one handle on a lab directory (a local folder or an fsspec store) that owns its stores.

    lab = Lab.open("lab")                      # or Lab.open("s3://bucket/prefix"); one StoreError if unusable
    lab.sessions.select("campaign")            # acquisition.recorder.sessions.SessionStore
    data, card = lab.datasets.load("campaign")
    path = lab.models.find("forward-best")
    lab.study("unmodelled")                    # a lab inside the lab, laid out the same way

This module is the one place that knows the lab's layout (``sessions/``, ``datasets/``, ``models/``,
``cache/``, ``figures/``, ``report/``, ``comparisons/`` …): every layer receives the Lab or one of its stores,
never a bare root from which it would derive them. A Lab and its stores hold only their root, so they pickle
whole: a cluster job receives the lab it works in.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

from acquisition.storage import LabPath, StoreError, check_store, is_local, lab_path, local_folder, upload

if TYPE_CHECKING:  # imported where used: opening a lab (every command does) needs neither torch, pandas
    # nor the sessions' readers
    import numpy as np
    import pandas as pd

    from acquisition.recorder.sessions import SessionStore
    from pipeline.cache import StageCache

# the lab's file primitives, for the layers above the pipeline (analysis writes figures and the report with
# them): they reach the storage through the Lab module, never below it
__all__ = [
    "ComparisonStore", "DatasetStore", "Lab", "LabPath", "ModelStore", "StoreError", "is_local",
    "local_folder", "upload",
]  # fmt: skip


def _datasets():
    from pipeline import datasets

    return datasets


def _model_store():
    from pipeline import model_store

    return model_store


@dataclass(frozen=True)
class DatasetStore:
    """``<lab>/datasets/<name>/<version>/``: built datasets, written once (``pipeline.datasets``)."""

    root: LabPath

    def path(self, name: str, version: str) -> LabPath:
        """The folder of dataset ``name@version`` (whether or not it exists)."""
        return self.root / name / version

    def names(self) -> list[str]:
        """The names of the datasets this lab holds (none where the store is empty)."""
        return sorted(p.name for p in self.root.glob("*") if p.is_dir()) if self.root.is_dir() else []

    def newest(self, name: str) -> str | None:
        """The version of ``name`` written last, None where there is none."""
        return _datasets().newest_version(self.root, name)

    def has(self, name: str, version: str) -> bool:
        """Is ``name@version`` there, whole (its card written)?"""
        return (self.path(name, version) / _datasets().CARD).is_file()

    def resolve(self, spec: str) -> tuple[str, str]:
        """(name, version) of ``name`` (its newest version) or ``name@version``; ``GridError`` otherwise."""
        from pipeline.grid import resolve_dataset

        return resolve_dataset(self, spec)

    def load(self, name: str, version: str | None = None, table: str | None = "data"):
        """(table or None, card) of ``name`` (the newest version when none is named)."""
        return _datasets().load_dataset(self.root, name, version, table)

    def write(self, name: str, version: str, tables: dict[str, pd.DataFrame], card: dict) -> LabPath:
        """Publish ``name@version`` whole (a version written before stays as it is)."""
        return _datasets().write_dataset(self.root, name, version, tables, card)

    def placement(self, reference: str, robot: str) -> np.ndarray:
        """The tracker placement (4×4, base → tracker) that dataset ``name[@version]`` fitted for
        ``robot``."""
        from pipeline.build import borrowed_placement

        return borrowed_placement(self, reference, robot)


@dataclass(frozen=True)
class ModelStore:
    """``<lab>/models/<name>/<version>/``: trained networks, content-addressed (``pipeline.model_store``)."""

    root: LabPath

    def path(self, name: str, version: str) -> LabPath:
        """The folder of model ``name`` at ``version`` (whether or not it exists)."""
        return self.root / name / version

    def find(self, version: str) -> LabPath:
        """The folder of ``version`` (a tag, a version id or a unique prefix of one)."""
        return _model_store().find(self.root, version)

    def tags(self) -> dict[str, str]:
        """Every tag: alias → full version id."""
        return _model_store().tags(self.root)

    def tag(self, name: str, version: str) -> str:
        """Point tag ``name`` at ``version``; the full version id."""
        return _model_store().tag(self.root, name, version)

    def save(self, name: str, version: str, model, card: dict) -> LabPath:
        """Publish a trained network and its card (``FileExistsError`` where that version is there)."""
        return _model_store().save_model(self.root, name, version, model, card)

    def load(self, version: str):
        """(network, card) of ``version``, every file checked against its card."""
        return _model_store().load_model(self.find(version))

    def onnx(self, version: str):
        """The ONNX export of ``version`` on ONNX Runtime, every file checked against its card."""
        return _model_store().load_onnx(self.find(version))

    def list(self) -> list[dict]:
        """Every version, oldest first, then the damaged ones (``model_store.list_models``)."""
        return _model_store().list_models(self.root)

    def compare(self, versions: list[str]) -> pd.DataFrame:
        """Versions side by side (``model_store.compare``)."""
        return _model_store().compare(self.root, versions)


@dataclass(frozen=True)
class ComparisonStore:
    """``<lab>/comparisons/<name>.json``: every model beside the floor (``pipeline.comparison``)."""

    root: LabPath

    def path(self, name: str) -> LabPath:
        """The file of comparison ``name``."""
        return self.root / f"{name}.json"


@dataclass(frozen=True)
class Lab:
    """One lab directory and its stores; ``root`` is a local ``Path`` or a ``UPath`` (see
    ``acquisition.storage``). Make it with :meth:`open`, which checks the place once."""

    root: LabPath

    @classmethod
    def open(cls, where: str | os.PathLike) -> Lab:
        """The lab at ``where`` (a folder, or an fsspec URL): one :class:`StoreError` naming the place and
        what to do where it cannot be used (a file, a store whose backend is missing or that does not
        answer). A local folder that does not exist yet is made when something is written."""
        root = lab_path(where)
        check_store(root)
        if is_local(root) and root.exists() and not root.is_dir():
            raise StoreError(f"{where}: not a directory (the lab is a folder of sessions, datasets, models, "
                             "figures)")  # fmt: skip
        return cls(root)

    @property
    def is_local(self) -> bool:
        """Is the lab a folder of this computer (recordings are written only into one)?"""
        return is_local(self.root)

    def study(self, name: str) -> Lab:
        """A lab inside this lab, laid out the same way (the main job's ``unmodelled/``)."""
        return Lab(self.root / name)

    @property
    def sessions(self) -> SessionStore:
        from acquisition.recorder.sessions import SessionStore

        return SessionStore(self.root / "sessions")

    @property
    def datasets(self) -> DatasetStore:
        return DatasetStore(self.root / "datasets")

    @property
    def models(self) -> ModelStore:
        return ModelStore(self.root / "models")

    @property
    def cache(self) -> StageCache:
        from pipeline.cache import StageCache

        return StageCache(self.root / "cache")

    @property
    def comparisons(self) -> ComparisonStore:
        return ComparisonStore(self.root / "comparisons")

    @property
    def figures(self) -> LabPath:
        """The folder of the figures (each PNG with its record of what it was made from)."""
        return self.root / "figures"

    @property
    def report(self) -> LabPath:
        """The folder of the report page."""
        return self.root / "report"

    @property
    def exports(self) -> LabPath:
        """The folder of exported datasets (`vslab sessions export`)."""
        return self.root / "exports"

    @property
    def rigs(self) -> LabPath:
        """The folder of the rigs' run directories, one per session."""
        return self.root / "rig"

    @property
    def twin(self) -> LabPath:
        """The folder of the twin's surveys."""
        return self.root / "twin"

    @property
    def mlflow(self) -> LabPath:
        """The folder of the local MLflow tracking store."""
        return self.root / "mlflow"

    def __str__(self) -> str:
        return str(self.root)
