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
from pipeline.dataset_store import DatasetStore

if TYPE_CHECKING:  # imported where used: opening a lab (every command does) needs neither torch, pandas
    # nor the sessions' readers

    from acquisition.recorder.sessions import SessionStore
    from pipeline.cache import StageCache
    from pipeline.model_store import ModelStore

# the lab's file primitives, for the layers above the pipeline (analysis writes figures and the report with
# them): they reach the storage through the Lab module, never below it
__all__ = [
    "ComparisonStore", "DatasetStore", "Lab", "LabPath", "StoreError", "TwinStore", "is_local",
    "local_folder", "upload",
]  # fmt: skip


@dataclass(frozen=True)
class ComparisonStore:
    """``<lab>/comparisons/<name>.json``: every model beside the floor (``pipeline.comparison``)."""

    root: LabPath

    def path(self, name: str) -> LabPath:
        """The file of comparison ``name``."""
        return self.root / f"{name}.json"


@dataclass(frozen=True)
class TwinStore:
    """``<lab>/twin/``: the twin of the lab's own robot. The descriptions ``vslab twin fit`` writes, the
    checks of them (``vslab twin check``) and the pretraining curve (``vslab twin curve``), each a file the
    report reads; the twin's surveys; and one study per description whose campaign was simulated for
    pretraining (``pipeline.pretrain``)."""

    root: LabPath

    def fitted(self, robot: str) -> LabPath:
        """The description fitted to the lab's robot, by its nominal description's name."""
        return self.root / f"{robot}_fitted.yaml"

    def fit(self, robot: str) -> LabPath:
        """What the report shows of the description ``robot`` (its name) fitted here: its ``fitted`` block."""
        return self.root / f"fit-{robot}.json"

    def fits(self) -> list[LabPath]:
        return sorted(self.root.glob("fit-*.json")) if self.root.exists() else []

    def check(self, robot: str) -> LabPath:
        """The newest check of description ``robot`` (its name)."""
        return self.root / f"check-{robot}.json"

    def checks(self) -> list[LabPath]:
        return sorted(self.root.glob("check-*.json")) if self.root.exists() else []

    @property
    def curve(self) -> LabPath:
        """The newest pretraining curve (its table and what it was made from)."""
        return self.root / "pretraining_curve.json"

    def survey(self, robot: str, trajectory: str) -> LabPath:
        return self.root / f"survey_{robot}_{trajectory}.json"

    def campaigns(self, key: str) -> Lab:
        """The lab in which the twin's campaign of one description (``key``: its name and digest) is
        simulated."""
        return Lab(self.root / key)


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
        from pipeline.model_store import ModelStore  # torch: imported where a command uses models

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
    def twin(self) -> TwinStore:
        return TwinStore(self.root / "twin")

    @property
    def mlflow(self) -> LabPath:
        """The folder of the local MLflow tracking store."""
        return self.root / "mlflow"

    def __str__(self) -> str:
        return str(self.root)
