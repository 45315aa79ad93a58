"""A session writer's writes gathered over some seconds of simulated time, then written a topic at a time.

The simulated-time runner hands every session a window (1 s) of rows per topic at a time: at ~5 topics per
session and 128 sessions a window, the writer's fixed cost per call (checks, counters, the MCAP batch, the
standard topics) outweighed the rows it wrote. Gathered over ``span_s`` the same messages are written in
~10× fewer calls. Every topic's messages keep their order and sequence numbers; only their order between
topics inside the file changes (MCAP readers sort by log time).
"""

from __future__ import annotations

import numpy as np

from acquisition.recorder.writer import SessionWriter
from acquisition.schemas.events import Event


class BufferedSessionWriter:
    """``write`` and ``event`` as :class:`SessionWriter`'s; ``flush_if_due(now_s)`` writes what was gathered
    once ``span_s`` of simulated time has passed since the last write, ``close`` writes the rest."""

    def __init__(self, writer: SessionWriter, span_s: float) -> None:
        self.writer = writer
        self.span_s = span_s
        self.topics = writer.topics
        self._rows: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
        self._events: list[tuple[Event, int]] = []
        self._since_s = 0.0

    def write(self, topic: str, log_time_ns: np.ndarray, rows: np.ndarray) -> None:
        if len(rows):
            self._rows.setdefault(topic, []).append((np.asarray(log_time_ns, np.int64), rows))

    def event(self, event: Event, log_time_ns: int) -> None:
        self._events.append((event, log_time_ns))

    def flush_if_due(self, now_s: float) -> None:
        if now_s - self._since_s >= self.span_s:
            self.flush()
            self._since_s = now_s

    def flush(self) -> None:
        """Write what was gathered: each topic's rows in one call, in the order the topics first came, then
        the events."""
        gathered, self._rows = self._rows, {}
        for topic, parts in gathered.items():
            self.writer.write(topic, *(parts[0] if len(parts) == 1 else _joined(parts)))
        events, self._events = self._events, []
        for event, log_time_ns in events:
            self.writer.event(event, log_time_ns)

    def close(self, status: str) -> None:
        """Write the rest and close the session (``SessionWriter.close``); a session whose writing failed is
        closed as failed, what was gathered lost with it."""
        try:
            if self.writer.failure is None:  # a failed writer takes nothing more
                self.flush()
        finally:
            self.writer.close(status)


def _joined(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """One topic's gathered (log times, rows), end to end; the rows keep their exact dtype (a structured
    dtype's layout is the message's)."""
    rows = np.empty(sum(len(r) for _, r in parts), dtype=parts[0][1].dtype)
    lo = 0
    for _, r in parts:
        rows[lo : lo + len(r)] = r
        lo += len(r)
    return np.concatenate([t for t, _ in parts]), rows
