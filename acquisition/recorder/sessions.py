"""The sessions of a lab directory: what each holds (streams, rates, drops) and whether it is whole.

``lab/sessions/<id>/`` holds the MCAP parts and ``session.json``. A part without a readable summary is torn
(its writer was killed): ``recover_session`` writes ``<part>.recovered.mcap`` beside it and never edits it.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError
from mcap.reader import make_reader

from acquisition.recorder.recover import RECOVERED_SUFFIX, RecoveryReport, recover, recovered_path
from acquisition.recorder.writer import SESSION_CARD


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
    protocol: str = "?"
    status: str = "?"  # recording (or killed), complete
    parts: list[Path] = field(default_factory=list)
    torn: list[Path] = field(default_factory=list)  # parts without a summary and no recovered copy
    streams: dict[str, StreamInfo] = field(default_factory=dict)

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


def readable_parts(directory: Path) -> list[Path]:
    """The parts to read: each original part, or its recovered copy where one exists."""
    parts = sorted(p for p in directory.glob("*.mcap") if not p.name.endswith(RECOVERED_SUFFIX))
    return [recovered_path(p) if recovered_path(p).exists() else p for p in parts]


def session_info(directory: Path) -> SessionInfo:
    directory = Path(directory)
    info = SessionInfo(directory.name, directory)
    card_path = directory / SESSION_CARD
    counters = {}
    if card_path.is_file():
        card = json.loads(card_path.read_text())
        info.robot, info.protocol = card.get("robot", "?"), card.get("protocol", "?")
        info.status = card.get("status", "?")
        counters = card.get("counters", {})
    info.parts = readable_parts(directory)
    for part in info.parts:
        try:
            with open(part, "rb") as f:
                summary = make_reader(f).get_summary()
        except (McapError, struct.error, OSError, EOFError):
            summary = None
        if summary is None or summary.statistics is None:
            info.torn.append(part)
            continue
        for cid, channel in summary.channels.items():
            stream = info.streams.setdefault(channel.topic, StreamInfo(channel.topic))
            stream.messages += summary.statistics.channel_message_counts.get(cid, 0)
        _stream_spans(part, summary, info.streams)
    for topic, c in counters.items():
        if topic in info.streams:
            stream = info.streams[topic]
            stream.expected = c.get("expected")
            stream.lost, stream.dropped, stream.gaps = (int(c.get(k, 0)) for k in ("lost", "dropped", "gaps"))
    return info


def _stream_spans(part: Path, summary, streams: dict[str, StreamInfo]) -> None:
    """Each topic's first and last log time, from the message indexes of the chunks that hold it."""
    with open(part, "rb") as f:
        for ci in summary.chunk_indexes:
            for cid, offset in ci.message_index_offsets.items():
                f.seek(offset + 9)
                _channel, length = struct.unpack("<HI", f.read(6))
                pairs = np.frombuffer(f.read(length), dtype="<u8").reshape(-1, 2)
                if len(pairs) == 0:
                    continue
                s = streams[summary.channels[cid].topic]
                lo, hi = int(pairs[:, 0].min()), int(pairs[:, 0].max())
                s.start_ns = lo if s.start_ns is None else min(s.start_ns, lo)
                s.end_ns = hi if s.end_ns is None else max(s.end_ns, hi)


def list_sessions(sessions_dir: Path) -> list[SessionInfo]:
    """Every session under ``sessions_dir`` (directories holding MCAP parts), by id."""
    sessions_dir = Path(sessions_dir)
    if not sessions_dir.is_dir():
        return []
    return [session_info(d) for d in sorted(sessions_dir.iterdir()) if d.is_dir() and any(d.glob("*.mcap"))]


def recover_session(directory: Path) -> list[RecoveryReport]:
    """Recover every torn part of a session (each into a new ``.recovered.mcap`` file)."""
    return [recover(part) for part in session_info(directory).torn]
