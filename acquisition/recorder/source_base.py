"""What every source shares (``Source``, ``Row``, ``SEQ_MODULO``, :func:`make_source`): a module of its own,
so that the sources of each bus (``sources``, ``can_source``, a lab's own kinds) build on it without importing
one another, and a daemon imports only its own device's source (its kind names it)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from acquisition.command_guard import CommandGuard
from acquisition.devices import kinds
from acquisition.schemas import topics as T
from acquisition.schemas.cdr import FixedMessage
from acquisition.schemas.topic_rows import SEQ_MODULO
from models.robot import DeviceSpec, RobotDescription

__all__ = ["SEQ_MODULO", "Row", "Source", "make_source", "source_class"]


@dataclass(frozen=True)
class Row:
    """One message of ``topic``: host receive time, the number it is counted by (None: a command, which is
    not a sampled stream), and its bytes (one row of the topic's message dtype)."""

    topic: str
    host_ns: int
    seq: int | None
    data: np.ndarray


class Source:
    """Base of every source; a subclass names its ``driver`` and fills the hooks."""

    driver: ClassVar[str] = ""
    polled: ClassVar[bool] = True
    slot_numbered: ClassVar[bool] = False  # samples numbered by poll slot (continuous across reconnections)
    sampled_topics: ClassVar[tuple[str, ...]] = ()  # streams counted against their sequence numbers
    command_topics: ClassVar[tuple[str, ...]] = ()  # commands recorded as sent

    def __init__(self, robot: RobotDescription, name: str, spec: DeviceSpec, port: str,
                 rate_hz: float) -> None:  # fmt: skip
        self.robot, self.name, self.spec, self.port = robot, name, spec, port
        self.rate_hz = float(rate_hz)
        self.guard = CommandGuard(robot)
        topics = T.session_topics(robot)
        self.messages: dict[str, FixedMessage] = {}
        for topic in (*self.sampled_topics, *self.command_topics):
            if topic not in topics or topics[topic].message is None:
                raise ValueError(
                    f"{robot.name}: {name} ({self.driver}) writes {topic}, not a topic of this robot"
                )
            self.messages[topic] = topics[topic].message
        self._rows = {topic: m.empty(1) for topic, m in self.messages.items()}

    @property
    def topics(self) -> tuple[str, ...]:
        return (*self.sampled_topics, *self.command_topics)

    @property
    def poll_hz(self) -> float:
        """How often a polled source is read (default: its rate)."""
        return self.rate_hz

    @property
    def sampled_rates_hz(self) -> dict[str, float]:
        """Each sampled stream's rate (default: the source's; a bus whose boards send on their own clocks
        says each stream's): what its ring is sized by."""
        return dict.fromkeys(self.sampled_topics, self.rate_hz)

    def row(self, topic: str, host_ns: int, number: int | None, **values: object) -> Row:
        """A row of ``topic`` with ``values`` set, counted as sample ``number`` (None: a command); its bytes
        are its own (a read may return several rows before any reaches a ring)."""
        rows = self._rows[topic]
        for field, value in values.items():
            rows[field] = value
        return Row(topic, host_ns, number, rows.view(np.uint8).copy())

    # hooks ------------------------------------------------------------------------------------
    def open(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def fileno(self) -> int | None:
        """A descriptor that becomes readable when a streamed source has data (None: polled)."""
        return None

    def read(self, slot: int) -> list[Row]:
        """Take what the device has: one poll (``slot`` numbers it) or every line that arrived."""
        raise NotImplementedError

    def command(self, cmd: dict) -> list[Row]:
        """Carry out one command (a dict with ``op``); returns the rows recording it as sent. A command the
        guard refuses raises :class:`~acquisition.command_guard.CommandRefused` before any byte is sent."""
        raise ValueError(f"{self.name} takes no command {cmd.get('op')!r}")

    def safe(self) -> None:
        """Leave the device safe (the supervisor is gone, or a safe stop): default nothing to do."""


def source_class(driver: str) -> type[Source]:
    """The recorder's source of the device kind ``driver`` (imported now); a kind without one cannot be
    recorded on a port of its own (a board on another device's bus) and is a ValueError."""
    kind = kinds.get(driver)
    if kind.source is None:
        raise ValueError(f"device kind {driver!r} has no recording source of its own")
    cls = kinds.resolve(kind.source)
    if not (isinstance(cls, type) and issubclass(cls, Source)):
        raise ValueError(f"device kind {driver!r}: its source {kind.source!r} is not a Source")
    return cls


def make_source(robot: RobotDescription, name: str, port: str, rate_hz: float | None = None) -> Source:
    """The source of device ``name`` of ``robot`` on ``port`` (its configured rate unless ``rate_hz``)."""
    spec = robot.devices.get(name)
    if spec is None:
        raise ValueError(f"{robot.name} has no device {name!r} (its devices: {', '.join(robot.devices)})")
    try:
        cls = source_class(spec.driver)
    except ValueError as exc:
        raise ValueError(f"{robot.name}: device {name} cannot be recorded: {exc}") from None
    rate = rate_hz or spec.rate_hz
    if not rate or rate <= 0:
        raise ValueError(f"{robot.name}: device {name} has no rate_hz to read it at")
    return cls(robot, name, spec, port, rate)
