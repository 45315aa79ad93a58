"""The device base: an idempotent open/close lifecycle, context management and bounded retries.

A driver fills ``_open``/``_close`` and writes its own finished read/command methods on top of
:meth:`Device._retrying`. Drivers know nothing about the twin: they talk to a port path, which may be real
hardware or an emulator's pseudo-terminal.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TypeVar

from acquisition.errors import DeviceError, DeviceNotFoundError, DeviceProtocolError, DeviceTimeoutError

log = logging.getLogger(__name__)
Answer = TypeVar("Answer")  # what an attempt on the device returns


def host_now_ns() -> int:
    """Host receive time: int64 ns on the monotonic clock every driver stamps with."""
    return time.monotonic_ns()


class Device:
    """Base of every driver: ``with Driver(port) as dev: ...``; ``close()`` is idempotent."""

    kind = "device"

    def __init__(self, port: str, retries: int = 2) -> None:
        self.port = port
        self.retries = retries
        self._is_open = False

    @property
    def is_open(self) -> bool:
        return self._is_open

    def open(self) -> None:
        """Open the port and check the device answers; raises DeviceNotFoundError if it does not."""
        if self._is_open:
            return
        try:
            self._open()
        except DeviceError:
            self._safe_close()
            raise
        except OSError as exc:
            self._safe_close()
            raise DeviceNotFoundError(f"{self.kind} on {self.port}: cannot open port ({exc})") from exc
        self._is_open = True

    def close(self) -> None:
        """Release the port (safe to call twice)."""
        if self._is_open:
            self._safe_close()
            self._is_open = False

    def reconnect(self) -> None:
        """Close and open again (after an unplug); raises DeviceNotFoundError while it is still away."""
        self.close()
        self.open()

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _safe_close(self) -> None:
        try:
            self._close()
        except (OSError, DeviceError) as exc:  # closing a vanished port must not hide the real error
            log.debug("%s on %s: error while closing: %s", self.kind, self.port, exc)

    def _retrying(self, what: str, attempt: Callable[[], Answer]) -> Answer:
        """Run ``attempt`` up to 1 + retries times on timeouts and corrupted replies, then re-raise."""
        for tries in range(self.retries + 1):
            try:
                return attempt()
            except (DeviceTimeoutError, DeviceProtocolError) as exc:
                if tries == self.retries:
                    raise type(exc)(
                        f"{self.kind} on {self.port}: {what}: {exc} (after {tries + 1} attempts)"
                    ) from exc
                log.info("%s on %s: %s failed (%s), retrying", self.kind, self.port, what, exc)
        raise AssertionError("unreachable")

    # hooks
    def _open(self) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        raise NotImplementedError
