"""The tables the pipeline's stages pass along, and the report each stage adds to.

A stage is a function ``stage(SessionTables, **parameters) -> SessionTables`` (or a table derived from one):
it never edits its input in place, it counts every row it removes, by stream and reason, and it says what it
found (a clock fit, a registration residual) in ``report.values``.

Stream tables (pandas, one per topic): ``log_time`` (int64 ns, host receive time), ``publish_time`` (ns),
then the message's fields in SI units, array fields flattened to one column per element named
``<field>_<i>`` (``position_0``, ``position_1``, …; order: the robot's servo ids / channels). Stages that put
samples on the host timeline add ``t`` (float64 s since the session's first log time, ``t0_ns``).
The events table: ``log_time``, ``kind`` (int, ``EventKind``, exported here: the table's readers need its
codes and read sessions through the pipeline), ``index``, ``value``, ``label``, ``text``.
"""

from __future__ import annotations

import dataclasses
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from acquisition.schemas.events import EventKind
from acquisition.schemas.session_card import session_parameters
from models.robot import RobotDescription

__all__ = ["EVENT_COLUMNS", "EventKind", "SessionTables", "StageReport", "columns"]

EVENT_COLUMNS = ("log_time", "kind", "index", "value", "label", "text")


@dataclass
class StageReport:
    """What the stages did to one session: rows removed per stream and reason, warnings, fitted values."""

    removed: dict[str, dict[str, int]] = field(default_factory=lambda: defaultdict(dict))
    warnings: list[str] = field(default_factory=list)
    values: dict[str, object] = field(default_factory=dict)  # e.g. "clock/pressure_board": {...}

    def remove(self, stream: str, reason: str, rows: int) -> None:
        """Count ``rows`` removed from ``stream`` for ``reason`` (adds to what is already counted)."""
        if rows:
            by_reason = self.removed.setdefault(stream, {})
            by_reason[reason] = by_reason.get(reason, 0) + int(rows)

    def removed_total(self) -> int:
        return sum(n for reasons in self.removed.values() for n in reasons.values())

    def copy(self) -> StageReport:
        return StageReport(
            {k: dict(v) for k, v in self.removed.items()}, list(self.warnings), dict(self.values)
        )

    def as_dict(self) -> dict:
        return {"removed": {k: dict(v) for k, v in self.removed.items()}, "warnings": list(self.warnings),
                "values": self.values}  # fmt: skip


@dataclass
class SessionTables:
    """One session as tables: its streams by topic, its events, the robot it recorded, its metadata."""

    session_id: str
    robot: RobotDescription
    metadata: dict[str, str]
    streams: dict[str, pd.DataFrame]
    events: pd.DataFrame
    report: StageReport = field(default_factory=StageReport)
    content_hash: str = ""  # content hash of the session's MCAP parts (ingest sets it)

    @property
    def t0_ns(self) -> int:
        """The session's first host log time: ``t`` columns count seconds from here."""
        starts = [int(df["log_time"].iloc[0]) for df in self.streams.values() if len(df)]
        if len(self.events):
            starts.append(int(self.events["log_time"].iloc[0]))
        return min(starts) if starts else 0

    @property
    def parameters(self) -> dict:
        """What the session's plan was asked for (its experiment's parameters), of any schema version."""
        return session_parameters(self.metadata)

    def replace(self, **changes) -> SessionTables:
        """A copy with some fields changed; the report is copied so stages never share one."""
        changes.setdefault("report", self.report.copy())
        changes.setdefault("streams", dict(self.streams))
        return dataclasses.replace(self, **changes)


def columns(df: pd.DataFrame, name: str) -> np.ndarray:
    """An array field back as (n, k) float64 from its flattened ``<name>_<i>`` columns (or (n, 1) for a
    scalar column ``name``)."""
    if name in df.columns:
        return df[name].to_numpy(dtype=float).reshape(-1, 1)
    cols = sorted((c for c in df.columns if c.rsplit("_", 1)[0] == name and c.rsplit("_", 1)[-1].isdigit()),
                  key=lambda c: int(c.rsplit("_", 1)[1]))  # fmt: skip
    if not cols:
        raise KeyError(f"no column {name!r} or {name}_0… in {list(df.columns)}")
    return df[cols].to_numpy(dtype=float)
