"""A daemon's status block: a few words in shared memory that the supervisor reads to watch it.

The daemon writes its pid, a heartbeat (monotonic ns, every loop), its phase, whether its device answers,
the scheduling it got, how far it ever fell behind a polled device's schedule, and its last error; the
supervisor only reads. A file on tmpfs like the rings, so it outlives the daemon: the supervisor reads why a
daemon died after it has gone.
"""

from __future__ import annotations

import enum
import mmap
import os
from pathlib import Path

import numpy as np

from acquisition.recorder.ring import map_file, unmap

_WORDS = 8
_TEXT = 512
_PID, _HEARTBEAT, _PHASE, _CONNECTED, _STARTS, _REFUSED, _FAULTS, _BEHIND = range(8)
_ERROR, _PRIORITY, _REFUSAL, _FAULT = 0, 1, 2, 3  # text fields
_TEXTS = 4


class Phase(enum.IntEnum):
    STARTING = 0
    CONNECTING = 1  # first connection attempt under way
    STREAMING = 2
    GAP = 3  # the device is lost; reconnecting
    CLOSED = 4  # exited in order


class _Word:
    """A word of the status block, read as an attribute of type ``kind`` (the daemon writes ``words``)."""

    def __init__(self, k: int, kind: type = int) -> None:
        self.k, self.kind = k, kind

    def __get__(self, status: DaemonStatus | None, owner: type | None = None):
        return self if status is None else self.kind(status.words[self.k])

    def __set__(self, status: DaemonStatus, value: object) -> None:
        raise AttributeError("the supervisor only reads a daemon's status words")


class _Text:
    """A text field of the status block, read and written as an attribute (UTF-8, cut to fit)."""

    def __init__(self, k: int) -> None:
        self.k = k

    def __get__(self, status: DaemonStatus | None, owner: type | None = None) -> str:
        return self if status is None else status._get(self.k)  # type: ignore[return-value]

    def __set__(self, status: DaemonStatus, text: str) -> None:
        status._set(self.k, text)


class DaemonStatus:
    """The status block of one daemon, in the file ``path``."""

    def __init__(self, path: Path, mm: mmap.mmap) -> None:
        self.path = Path(path)
        self._mm = mm
        self.words = np.ndarray((_WORDS,), np.int64, buffer=mm, offset=0)
        self._text = np.ndarray((_TEXTS, _TEXT), np.uint8, buffer=mm, offset=_WORDS * 8)

    @classmethod
    def create(cls, path: Path) -> DaemonStatus:
        path = Path(path)
        with open(path, "wb") as f:
            f.truncate(_WORDS * 8 + _TEXTS * _TEXT)
        return cls.attach(path)

    @classmethod
    def attach(cls, path: Path) -> DaemonStatus:
        return cls(path, map_file(path))

    def close(self) -> None:
        self.words = self._text = None  # type: ignore[assignment]
        unmap(self._mm)

    # the daemon's side
    def begin(self) -> None:
        """A new daemon process took over this device."""
        self.words[_PID] = os.getpid()
        self.words[_STARTS] += 1
        self.words[_CONNECTED] = 0
        self.phase = Phase.STARTING
        self.beat(0)

    def beat(self, now_ns: int) -> None:
        self.words[_HEARTBEAT] = now_ns

    @property
    def phase(self) -> Phase:
        return Phase(int(self.words[_PHASE]))

    @phase.setter
    def phase(self, value: Phase) -> None:
        self.words[_PHASE] = int(value)
        self.words[_CONNECTED] = int(value == Phase.STREAMING)

    error = _Text(_ERROR)  # the daemon's last error
    priority = _Text(_PRIORITY)  # the scheduling it got

    def refuse(self, why: str) -> None:
        """The command guard refused a command (counted; the last reason kept)."""
        self._set(_REFUSAL, why)
        self.words[_REFUSED] += 1

    @property
    def refusals(self) -> tuple[int, str]:
        """How many commands were refused, and why the last one was."""
        return int(self.words[_REFUSED]), self._get(_REFUSAL)

    def fault(self, why: str) -> None:
        """The device reported a fault while streaming (counted; the last one kept)."""
        self._set(_FAULT, why)
        self.words[_FAULTS] += 1

    def behind(self, late_ns: int) -> None:
        """A poll was taken ``late_ns`` after its slot was due; the most is kept (µs)."""
        late_us = late_ns // 1000
        if late_us > self.words[_BEHIND]:
            self.words[_BEHIND] = late_us

    @property
    def faults(self) -> tuple[int, str]:
        """How many faults the device reported, and the last one."""
        return int(self.words[_FAULTS]), self._get(_FAULT)

    # the supervisor's side
    pid = _Word(_PID)
    heartbeat_ns = _Word(_HEARTBEAT)
    connected = _Word(_CONNECTED, bool)
    starts = _Word(_STARTS)

    @property
    def behind_ms(self) -> float:
        """The most a polled daemon's schedule ran ahead of it, of all its processes (ms): past
        ``MAX_LAG_S`` it skipped slots, which count lost."""
        return int(self.words[_BEHIND]) / 1e3

    def _get(self, k: int) -> str:
        raw = bytes(self._text[k])
        return raw.split(b"\0", 1)[0].decode("utf-8", "replace")

    def _set(self, k: int, text: str) -> None:
        raw = text.encode("utf-8")[: _TEXT - 1]
        self._text[k, :] = 0
        self._text[k, : len(raw)] = np.frombuffer(raw, np.uint8)
