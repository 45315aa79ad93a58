"""python-can's slcan interface, reading what the adapter sent in one call instead of a byte at a time.

python-can 4.6's ``slcanBus._read`` takes each byte with its own ``serial.read(1)`` (a ``select`` and a
``read`` system call per byte, ~22 per frame) and, on a quiet bus, polls every millisecond (the port's
1 ms timeout). On POPUP's bus (the tip IMU's board frames at 1 kHz) that cost the host ~35 % of a core
before any frame was used; on a busy machine the reader then fell behind, the adapter's buffer filled and
it dropped frames, an SDO answer among them (a drive seen as absent at set-up: CI, twice). Upstream has
merged the same remedy (python-can pull request 2028, not in a release yet): remove this class when the
pinned python-can reads in bulk.

:class:`SlcanBus` is ``slcanBus`` with ``_read`` replaced: wait in one ``select`` until bytes arrive (or the
caller's timeout passes), take every byte waiting, and hand out one line (a frame or a command's reply, up to
its CR, or BEL for an error) at a time, the rest kept for the next call; a frame line that does not parse
(slcan has no checksum: a byte garbled on the link) is dropped with a warning. Everything else (opening,
bitrate, writing, parsing a line into a ``can.Message``) is python-can's own.
"""

from __future__ import annotations

import logging
import os
import select
import time

from can.exceptions import CanOperationError
from can.interfaces.slcan import slcanBus

from acquisition.codecs.slcan import FRAME_STARTS, parse_frame
from acquisition.errors import CodecError

log = logging.getLogger(__name__)

_TERMINATORS = (slcanBus._OK[0], slcanBus._ERROR[0])  # CR ends a line, BEL is the adapter's error reply
_FRAME_STARTS = {bytes([c]) for c in FRAME_STARTS}


class SlcanBus(slcanBus):
    """An slcan adapter (``can.Bus(interface="slcan", ...)``'s arguments) read in bulk."""

    def _read(self, timeout: float | None) -> str | None:
        """The next line the adapter sent (its terminator included), or None when none is complete within
        ``timeout`` seconds (None: wait for one)."""
        port = self.serialPortOrig
        try:
            fd = port.fileno()
        except (AttributeError, OSError, ValueError):  # not a file descriptor (a pyserial URL handler)
            return super()._read(timeout)
        deadline = None if timeout is None else time.monotonic() + timeout
        abort = getattr(port, "pipe_abort_read_r", None)  # pyserial's cancel_read wakes a waiting read
        while True:
            line = self._line()
            if line is not None:
                return line
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                ready, _, _ = select.select([fd] if abort is None else [fd, abort], [], [], left)
                if abort is not None and abort in ready:
                    os.read(abort, 1000)
                    return None
                if fd in ready:
                    data = os.read(fd, max(port.in_waiting, 1))
                    if not data:  # readable but empty: the device went away (pyserial says the same)
                        raise CanOperationError(
                            "the slcan adapter reports data but returned none: unplugged?"
                        )
                    self._buffer.extend(data)
                    continue
            except InterruptedError:
                continue
            except OSError as exc:
                raise CanOperationError(f"could not read from the slcan adapter: {exc}") from exc
            return None  # the timeout passed with no line complete (what came of one is kept)

    def _line(self) -> str | None:
        """The first complete line of the buffer, taken out of it; None while none is complete. A frame line
        that does not parse (a byte garbled on the serial link: slcan carries no checksum) is dropped with a
        warning, never handed on: python-can would raise on it in its reading thread and stop canopen's
        reception, or, undecodable, keep it in its buffer and fail every read after."""
        buffer = self._buffer
        while True:
            ends = [i for i in (buffer.find(t) for t in _TERMINATORS) if i >= 0]
            if not ends:
                return None
            end = min(ends) + 1
            raw = bytes(buffer[:end])
            del buffer[:end]
            if raw[:1] in _FRAME_STARTS:
                try:
                    parse_frame(raw[:-1])
                except CodecError as exc:
                    log.warning("%s: dropped a garbled line from the adapter (%s)", self.channel_info, exc)
                    continue
            return raw.decode("ascii", errors="replace")
