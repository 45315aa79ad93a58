"""One MCAP writer per session: zstd chunks, flushed at least every ``flush_s``, rotated by size or duration.

The writer is single-threaded by design (``SessionWriter``): the real-time recorder feeds it from one thread
that drains the device workers' queue, the simulated-time runner calls it directly. Each part file is
complete on its own: schemas, channels and the session metadata are written into every part.

Beside the measured topics, each part carries what Foxglove's 3D panel shows the arm from
(``acquisition.schemas.scene``): the URDF as an attachment, ``/robot_description`` and ``/tf_static`` at the
part's first message, ``/tf`` and ``/joint_states`` (50 Hz) and ``/tracker/tip`` as the streams come in.

    with SessionWriter(directory, robot, session_id="s1", experiment="experiment1") as w:
        w.write(topics.SERVO_STATE, log_time_ns, rows)      # rows: structured array of the topic's message
        w.event(Event(EventKind.NOTE, text="hello"), log_time_ns)
"""

from __future__ import annotations

import json
import logging
import os
import platform
import time
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from acquisition.errors import AcquisitionError
from acquisition.schemas import Event, EventKind, FixedMessage
from acquisition.schemas.mcap_writer import MCAP_LIBRARY_VERSION, BatchMcapWriter
from acquisition.schemas.scene import URDF_ATTACHMENT, Batch, Scene, SceneStream
from acquisition.schemas.session_card import (
    COUNTERS_METADATA,
    SCHEMA_VERSION,
    SESSION_CARD,
    SESSION_METADATA,
    as_metadata,
)
from acquisition.schemas.topics import EVENTS, MESSAGE_ENCODING, SCHEMA_ENCODING, Topic, session_topics
from models.robot import RobotDescription

PROFILE = "ros2"  # Foxglove and ROS 2 tools take the files as ros2 bags
RESERVE = ".writer-reserve"  # room set aside at open, freed when the disk fills: to end the session in words
RESERVE_BYTES = 128 * 1024

log = logging.getLogger(__name__)


class WriteFailed(AcquisitionError, OSError):
    """The session could not be written (a full disk, an I/O error): it was ended, marked failed."""


def vslab_version() -> str:
    try:
        from importlib.metadata import version

        return version("vslab")
    except Exception:  # running from a source tree without an install
        return "unknown"


@dataclass
class StreamCounters:
    """Samples per topic: expected from the device (its rate, its sequence numbers), received from it, lost
    (expected, never received: gaps, skipped polls), written to the file, dropped (received, never written:
    a full ring, a killed writer), and the gaps the stream had. ``expected = received + lost`` and
    ``received = written + dropped`` once the session is closed."""

    expected: int = 0
    received: int = 0
    lost: int = 0
    written: int = 0
    dropped: int = 0
    gaps: int = 0
    first_ns: int | None = None
    last_ns: int | None = None

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class RotationPolicy:
    """Start a new part when the current one passes ``max_bytes`` or spans ``max_seconds`` of log time."""

    max_bytes: int | None = 512 * 1024**2
    max_seconds: float | None = None


@dataclass
class _Part:
    path: Path
    file: object
    writer: BatchMcapWriter
    channels: dict[str, int] = field(default_factory=dict)
    first_ns: int | None = None
    static_written: bool = False  # /robot_description and /tf_static, at the part's first message


class SessionWriter:
    """Writes a session's topics into ``<directory>/<session_id>_<part>.mcap`` files."""

    def __init__(
        self,
        directory: Path,
        robot: RobotDescription,
        session_id: str,
        experiment: str = "manual",
        metadata: dict[str, str] | None = None,
        topics: dict[str, Topic] | None = None,
        chunk_size: int = 1 << 20,
        flush_s: float = 0.5,
        rotation: RotationPolicy | None = None,
        clock=time.monotonic,
        resume: bool = False,
        standard_topics: bool = True,  # the arm for Foxglove (/tf, /joint_states, …; the URDF attached)
        standard_batch_s: float = 0.5,  # the standard topics made this many seconds of samples at a time
        compress_in: Executor | None = None,  # threads that compress its chunks (BatchMcapWriter's)
    ) -> None:
        self.directory = Path(directory)
        self.robot = robot
        self.session_id = session_id
        self.topics = session_topics(robot) if topics is None else topics
        self.chunk_size = chunk_size
        self.compress_in = compress_in
        self.flush_s = flush_s
        self.rotation = rotation or RotationPolicy()
        self.clock = clock
        self.counters = {name: StreamCounters() for name in self.topics}
        self.metadata = {
            "schema_version": str(SCHEMA_VERSION),
            "session_id": session_id,
            "robot": robot.name,
            "experiment": experiment,
            "robot_description": robot.model_dump_json(),
            "vslab_version": vslab_version(),
            "mcap_version": MCAP_LIBRARY_VERSION,
            "python_version": platform.python_version(),
            **as_metadata(metadata or {}),
        }
        # resume: a writer restarted after its predecessor was killed goes on in a new part after the old ones
        self.parts: list[Path] = (
            sorted(self.directory.glob(f"{session_id}_[0-9][0-9][0-9].mcap")) if resume else []
        )
        self._part: _Part | None = None
        self._last_flush = clock()
        self._sequence: dict[str, int] = dict.fromkeys(self.topics, 0)
        self._scene = Scene(robot) if standard_topics else None
        # a writer fed in batches of standard_batch_s waits that long twice for a stepper's reports
        self._stream = (SceneStream(self._scene, batch_s=standard_batch_s,
                                    max_wait_s=max(2.0, 2 * standard_batch_s))
                        if self._scene is not None else None)  # fmt: skip
        self._last_ns = 0  # the latest log time written
        self.failure: str | None = None  # why the session stopped being written (then nothing more is)

    # ------------------------------------------------------------------------------------ lifecycle
    def __enter__(self) -> SessionWriter:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def open(self) -> None:
        if self._part is None:
            self.directory.mkdir(parents=True, exist_ok=True)
            self._reserve()
            self._guarded(self._start_part)
            self._guarded(self._write_card, "recording")

    def close(self, status: str = "complete") -> None:
        """Finish the open part: summary, indexes and the final counters as metadata; ``status``: the card's
        (``refused``: a plan refused before anything of it ran, see ``session_card.STATUSES``). A session
        whose writing failed stays ``failed``."""
        if self.failure is not None:
            self._write_card("failed")  # the final account, where the disk still takes it
            return
        if self._part is not None:
            self._guarded(self._close_part)
            self._write_card(status)
            (self.directory / RESERVE).unlink(missing_ok=True)

    def _close_part(self) -> None:
        if self._stream is not None:
            self._write_standard(self._stream.finish())
        self._part.writer.add_metadata(
            COUNTERS_METADATA, {k: json.dumps(c.as_dict()) for k, c in self.counters.items()}
        )
        self._finish_part()

    def _reserve(self) -> None:
        """Set room aside for ending the session in words should the disk fill (see ``_fail``)."""
        path = self.directory / RESERVE
        if not path.exists():
            with open(path, "wb") as f:
                os.posix_fallocate(f.fileno(), 0, RESERVE_BYTES)

    def _guarded(self, step, *args):
        """Run one step that writes; one that fails ends the session (``_fail``) and raises WriteFailed."""
        if self.failure is not None:
            raise WriteFailed(self.failure)
        try:
            return step(*args)
        except OSError as exc:
            self._fail(exc)
            raise WriteFailed(self.failure) from exc

    def _fail(self, exc: OSError) -> None:
        """A write failed: free the reserve, cut the open part back to its last flush (whole records), end it
        with an event saying why and its summary where there is room, and mark the session failed. No new
        part is started: a full disk costs only what could not be written."""
        self.failure = f"writing {self.directory} failed: {exc.strerror or exc}"
        (self.directory / RESERVE).unlink(missing_ok=True)  # first: room for the log, the summary, the card
        log.error("%s; the session ends here", self.failure)
        part, self._part = self._part, None
        if part is not None:
            seq = self._sequence[EVENTS]
            end = Event(EventKind.NOTE, label="writer", text=self.failure).encode()
            whole = part.writer.salvage((part.channels[EVENTS], self._last_ns, end, seq))
            if whole:  # the note is in the file: in the account too
                c = self.counters[EVENTS]
                c.written += 1
                c.received = c.expected = max(c.received, c.written + c.dropped)
            size = part.file.tell()
            part.file.close()
            if size == 0:  # nothing of it was ever whole: no empty part is left
                part.path.unlink(missing_ok=True)
                self.parts.remove(part.path)
            elif not whole:
                log.error("%s: no room for its summary; `vslab sessions recover` reads it", part.path)
        try:
            self._write_card("failed")
        except OSError as card_exc:
            log.error("session.json could not be rewritten: %s", card_exc)

    def write_card(self, status: str = "recording") -> None:
        """Rewrite ``session.json`` now (a long recording keeps it current for whoever looks)."""
        self._guarded(self._write_card, status)

    def _write_card(self, status: str) -> None:
        """``session.json`` beside the parts: what the session is, and how far it got."""
        card = {k: v for k, v in self.metadata.items() if k != "robot_description"}
        card |= {
            "schema_version": SCHEMA_VERSION,
            "status": status,
            **({"failure": self.failure} if self.failure is not None else {}),
            "parts": [p.name for p in self.parts],
            "counters": {k: c.as_dict() for k, c in self.counters.items()},
        }
        tmp = self.directory / "session.json.tmp"
        tmp.write_text(json.dumps(card, indent=2) + "\n")
        tmp.replace(self.directory / SESSION_CARD)

    def note_received(self, topic: str, n: int = 1) -> None:
        """A worker took ``n`` samples of ``topic`` from its device (written or not)."""
        c = self.counters[topic]
        c.received += n
        c.expected = max(c.expected, c.received + c.lost)

    def note_dropped(self, topic: str, n: int = 1) -> None:
        """``n`` received samples of ``topic`` will never be written (queue full, encode error)."""
        self.counters[topic].dropped += n

    def _start_part(self) -> None:
        path = self.directory / f"{self.session_id}_{len(self.parts):03d}.mcap"
        f = open(path, "xb", buffering=0)  # unbuffered: a failed write leaves nothing pending (see _fail)
        self.parts.append(path)
        self._part = _Part(
            path, f, BatchMcapWriter(f, chunk_size=self.chunk_size, compress_in=self.compress_in)
        )
        writer = self._part.writer
        writer.start(profile=PROFILE, library=f"vslab {self.metadata['vslab_version']}")
        part = self._part
        for name, topic in self.topics.items():
            schema_id = writer.register_schema(topic.schema_name, SCHEMA_ENCODING, topic.schema_text.encode())
            part.channels[name] = writer.register_channel(name, MESSAGE_ENCODING, schema_id)
        if self._scene is not None:
            for name, (schema_name, text) in self._scene.schemas().items():
                schema_id = writer.register_schema(schema_name, SCHEMA_ENCODING, text.encode())
                part.channels[name] = writer.register_channel(name, MESSAGE_ENCODING, schema_id, derived=True)
            writer.add_attachment(URDF_ATTACHMENT, "application/xml", self._scene.urdf.encode())
        writer.add_metadata(SESSION_METADATA, {**self.metadata, "part": str(len(self.parts) - 1)})
        writer.flush()

    def _finish_part(self) -> None:
        part = self._part
        part.writer.finish()  # a failure here leaves it open, for _fail to cut back to its last flush
        part.file.close()
        self._part = None

    # ------------------------------------------------------------------------------------- writing
    def write(self, topic: str, log_time_ns: np.ndarray, rows: np.ndarray, publish_time_ns=None) -> None:
        """Write messages of one topic (see ``_write``); a write that fails ends the session: WriteFailed."""
        self._guarded(self._write, topic, log_time_ns, rows, publish_time_ns)

    def _write(self, topic: str, log_time_ns: np.ndarray, rows: np.ndarray, publish_time_ns=None) -> None:
        """Write messages of one topic: ``rows`` a structured array of its message type (see
        ``FixedMessage.pack``), ``log_time_ns`` the host receive times, ``publish_time_ns`` the device times
        in ns when known (default: the log times)."""
        message = self._message(topic)
        if rows.dtype != message.dtype:
            raise ValueError(f"{topic}: rows are not {message.name} messages")
        log_time = np.asarray(log_time_ns, dtype=np.int64)
        if len(log_time) != len(rows):
            raise ValueError(f"{topic}: {len(log_time)} log times for {len(rows)} messages")
        if len(rows) == 0:
            return
        publish = log_time if publish_time_ns is None else np.asarray(publish_time_ns, dtype=np.int64)
        if publish.shape != log_time.shape:
            raise ValueError(f"{topic}: {publish.shape} publish times for {len(rows)} messages")
        self._rotate_if_due(int(log_time[0]))
        seq0 = self._sequence[topic]
        sequence = np.arange(seq0, seq0 + len(rows), dtype=np.uint32)
        payload = message.canonical_bytes(rows)
        if self._stream is not None and not self._part.static_written:
            self._write_standard(self._scene.static(int(log_time.min())))
            self._part.static_written = True
        self._part.writer.add_batch(self._part.channels[topic], log_time, publish, sequence, payload)
        self._sequence[topic] = seq0 + len(rows)
        self._count(topic, log_time)
        if self._stream is not None:
            self._write_standard(self._stream.feed(topic, log_time, rows))
        self.flush_if_due()

    def _write_standard(self, batches: list[Batch]) -> None:
        """Messages of the standard topics (derived from the measured ones: not counted as streams)."""
        part = self._part
        for b in batches:
            if not len(b):
                continue
            seq0 = self._sequence.get(b.topic, 0)
            if isinstance(b.payloads, np.ndarray):
                sequence = np.arange(seq0, seq0 + len(b), dtype=np.uint32)
                part.writer.add_batch(part.channels[b.topic], b.log_time, b.log_time, sequence, b.payloads)
            else:
                for i, (t, data) in enumerate(zip(b.log_time.tolist(), b.payloads, strict=True)):
                    part.writer.add_message(part.channels[b.topic], t, bytes(data), t, seq0 + i)
            self._sequence[b.topic] = seq0 + len(b)

    def event(self, event: Event, log_time_ns: int) -> None:
        """Write one event (plan marker, payload change, device gap, note)."""
        self._guarded(self._event, event, log_time_ns)

    def _event(self, event: Event, log_time_ns: int) -> None:
        self._rotate_if_due(log_time_ns)
        seq = self._sequence[EVENTS]
        self._part.writer.add_message(
            self._part.channels[EVENTS], log_time_ns, event.encode(), log_time_ns, seq
        )
        self._sequence[EVENTS] = seq + 1
        self._count(EVENTS, np.array([log_time_ns]))
        self.flush_if_due()

    def _message(self, topic: str) -> FixedMessage:
        try:
            message = self.topics[topic].message
        except KeyError:
            raise ValueError(f"session of {self.robot.name} has no topic {topic!r}") from None
        if message is None:
            raise ValueError(f"{topic} is written with event()")
        if self._part is None:
            raise RuntimeError("the session writer is not open")
        return message

    def _count(self, topic: str, log_time: np.ndarray) -> None:
        c = self.counters[topic]
        c.written += len(log_time)
        c.received = max(c.received, c.written + c.dropped)  # direct writers (the simulator) do not note
        c.expected = max(c.expected, c.received + c.lost)
        first, last = int(log_time.min()), int(log_time.max())
        self._last_ns = max(self._last_ns, last)
        c.first_ns = first if c.first_ns is None else min(c.first_ns, first)
        c.last_ns = last if c.last_ns is None else max(c.last_ns, last)
        part = self._part
        part.first_ns = first if part.first_ns is None else min(part.first_ns, first)

    def flush_if_due(self) -> None:
        now = self.clock()
        if now - self._last_flush >= self.flush_s:
            self.flush()

    def flush(self) -> None:
        """Close the open chunk and push it to the file: what a kill can no longer take away."""
        if self._part is not None:
            self._guarded(self._part.writer.flush)
        self._last_flush = self.clock()

    def _rotate_if_due(self, log_time_ns: int) -> None:
        part, policy = self._part, self.rotation
        if part is None:
            raise RuntimeError("the session writer is not open")
        too_big = policy.max_bytes is not None and part.file.tell() >= policy.max_bytes
        too_long = (
            policy.max_seconds is not None
            and part.first_ns is not None
            and log_time_ns - part.first_ns >= policy.max_seconds * 1e9
        )
        if too_big or too_long:
            if self._stream is not None:  # each part whole: the arm of its own samples in it
                self._write_standard(self._stream.finish())
            self._finish_part()
            self._start_part()
