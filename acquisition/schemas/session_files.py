"""Reading a session folder: its ``session.json`` and what its MCAP parts hold (streams, rates, drops).

``<sessions>/<id>/`` holds the MCAP parts and ``session.json``. A folder that is not a readable session (no
or a damaged ``session.json``, no parts, a part that is not MCAP) raises ``SessionError``, one line naming
the file, what is wrong and what to do; nothing here writes to it. A torn part (its writer was killed) is
listed, not an error (``recorder.sessions.recover_session`` mends it).

This is the session format's reading side, beside the card's layout (``session_card``) and the MCAP reader:
the pipeline reads sessions through it, never through the recorder that writes them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from acquisition.errors import AcquisitionError
from acquisition.schemas.mcap_reader import (
    MAGIC,
    READ_ERRORS,
    damaged_chunks,
    first_line,
    read_summary,
    topic_spans,
)
from acquisition.schemas.scene import STANDARD_TOPICS
from acquisition.schemas.session_card import (
    SESSION_CARD,
    SessionCardError,
    as_current,
    readable_parts,
    schema_version,
)
from acquisition.storage import LabPath, as_path

CARD_FIELDS = ("robot", "experiment")  # what every session.json names (the writer always writes them)


class SessionError(AcquisitionError, ValueError):
    """A folder under ``sessions/`` that is not a readable session: ``path`` (the file or folder), ``reason``
    (what is wrong) and ``hint`` (what to do), said in one line."""

    def __init__(self, path: str | Path, reason: str, hint: str = "") -> None:
        self.path, self.reason, self.hint = as_path(path), reason, hint
        super().__init__(f"{path}: {reason}" + (f"; {hint}" if hint else ""))


def read_card(directory: LabPath) -> dict:
    """A session's ``session.json`` as a dict; ``SessionError`` when it is missing, empty, not JSON
    (truncated, garbled) or lacks the fields every session has (robot, experiment). A version-1 card is
    read with the current keys (``session_card.as_current``)."""
    path = directory / SESSION_CARD
    aside = f"move the folder out of {directory.parent} (or restore session.json from a backup)"
    if not path.is_file():
        raise SessionError(directory, f"not a recorded session: no {SESSION_CARD}", aside)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise SessionError(path, f"cannot be read ({exc.strerror or exc})", "check its permissions") from exc
    if not raw.strip():
        raise SessionError(path, "empty file", aside)
    try:
        card = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise SessionError(path, f"not text (byte {exc.start} is not UTF-8): garbled", aside) from exc
    except json.JSONDecodeError as exc:
        raise SessionError(
            path, f"not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg}): truncated or edited?",
            aside,
        ) from exc  # fmt: skip
    if not isinstance(card, dict):
        raise SessionError(path, f"expected a JSON object, found {type(card).__name__}", aside)
    try:
        schema_version(card)
    except SessionCardError as exc:
        raise SessionError(path, str(exc)) from exc
    card = as_current(card)
    missing = [k for k in CARD_FIELDS if not isinstance(card.get(k), str) or not card[k]]
    if missing:
        raise SessionError(path, f"no {' or '.join(repr(k) for k in missing)} field", aside)
    return card


@dataclass
class StreamInfo:
    topic: str
    messages: int = 0
    start_ns: int | None = None
    end_ns: int | None = None
    expected: int | None = None  # the recorder's account (session.json); None for files without one
    lost: int = 0
    dropped: int = 0
    gaps: int = 0

    @property
    def duration_s(self) -> float:
        return 0.0 if self.start_ns is None else (self.end_ns - self.start_ns) / 1e9

    @property
    def rate_hz(self) -> float:
        return (self.messages - 1) / self.duration_s if self.duration_s > 0 else 0.0


@dataclass
class SessionInfo:
    id: str
    directory: Path
    robot: str = "?"
    experiment: str = "?"
    status: str = "?"  # recording (or killed), complete; "bad" when ``problem`` says why
    parts: list[Path] = field(default_factory=list)
    torn: list[Path] = field(default_factory=list)  # parts without a summary and no recovered copy
    streams: dict[str, StreamInfo] = field(default_factory=dict)
    problem: str = ""  # why the folder is not a readable session (list_sessions); "" for a good one
    damaged: list[str] = field(default_factory=list)  # "<part>: damaged chunk at byte …", one per chunk

    @property
    def duration_s(self) -> float:
        starts = [s.start_ns for s in self.streams.values() if s.start_ns is not None]
        ends = [s.end_ns for s in self.streams.values() if s.end_ns is not None]
        return (max(ends) - min(starts)) / 1e9 if starts else 0.0

    @property
    def dropped(self) -> int:
        return sum(s.dropped for s in self.streams.values())

    @property
    def lost(self) -> int:
        return sum(s.lost for s in self.streams.values())


def session_info(directory: LabPath) -> SessionInfo:
    """What a session holds, from its ``session.json`` and its parts' summaries. ``SessionError`` when the
    folder is not a readable session; a torn part (no readable summary or indexes) is not an error: it is
    listed in ``torn`` (``recover_session`` mends it)."""
    if not directory.is_dir():
        raise SessionError(directory, "no such session folder")
    card = read_card(directory)
    status = str(card.get("status", "?"))
    info = SessionInfo(directory.name, directory, card["robot"], card["experiment"], status)
    info.parts = readable_parts(directory)
    if not info.parts:
        raise SessionError(directory, "no MCAP parts (*.mcap)", "nothing was recorded: remove the folder")
    for part in info.parts:
        _check_part(part)
        streams = _part_streams(part)
        if streams is None:
            info.torn.append(part)
            continue
        info.damaged += _part_damage(part)
        for topic, (messages, lo, hi) in streams.items():
            if topic in STANDARD_TOPICS:  # derived from the measured streams (the arm for a viewer)
                continue
            s = info.streams.setdefault(topic, StreamInfo(topic))
            s.messages += messages
            if lo is not None:
                s.start_ns = lo if s.start_ns is None else min(s.start_ns, lo)
                s.end_ns = hi if s.end_ns is None else max(s.end_ns, hi)
    _add_counters(info, card.get("counters") or {}, directory / SESSION_CARD)
    return info


def _check_part(part: Path) -> None:
    """``SessionError`` for a part that holds no MCAP at all (empty, or another kind of file)."""
    try:
        with part.open("rb") as f:
            head = f.read(len(MAGIC))
    except OSError as exc:
        raise SessionError(part, f"cannot be read ({exc.strerror or exc})", "check its permissions") from exc
    if not head:
        raise SessionError(part, "empty file (0 bytes): no data", "move it out of the session folder")
    if head != MAGIC:
        raise SessionError(part, "not an MCAP file (no MCAP magic)", "move it out of the session folder")


def _part_streams(part: Path) -> dict[str, tuple[int, int | None, int | None]] | None:
    """Per topic of one part: (messages, first log time, last log time) from its summary and message
    indexes; None when either cannot be read (a torn or damaged part)."""
    try:
        with part.open("rb") as f:
            return topic_spans(f)
    except OSError:
        return None


def _part_damage(part: Path) -> list[str]:
    """One line per chunk of a whole part that fails its CRC or index check (``damaged_chunks``): its
    messages are lost to every reader, so listing the session says so."""
    try:
        with part.open("rb") as f:
            summary = read_summary(f)
            damaged = [] if summary is None else damaged_chunks(f, summary)
            return [f"{part}: {d.describe(summary)}" for d in damaged]
    except READ_ERRORS as exc:
        return [f"{part}: its chunks cannot be checked ({first_line(exc)})"]


def _add_counters(info: SessionInfo, counters: object, card: Path) -> None:
    """The recorder's account (session.json ``counters``) onto the streams the parts hold."""
    try:
        for topic, c in dict(counters).items():
            if topic in info.streams:
                s = info.streams[topic]
                s.expected = None if c.get("expected") is None else int(c["expected"])
                s.lost, s.dropped, s.gaps = (int(c.get(k, 0)) for k in ("lost", "dropped", "gaps"))
    except (TypeError, ValueError, AttributeError) as exc:
        raise SessionError(card, f"bad 'counters' ({exc})", "restore session.json from a backup") from exc
