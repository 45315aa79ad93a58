"""NDI Aurora driver on scikit-surgerynditracker 1.0.6 (ndicapi underneath): one frame per ``read()``.

The library does the handshake (probe, INIT, COMM, PHSR/PINIT/PENA for every wired tool, VER) and picks
``TX:0801`` or ``BX:0801`` from the firmware revision. ``get_frame()`` returns, per tool, the port handle, a
host timestamp (``time.time()``, not used here: we stamp with :func:`host_now_ns`), the tracker frame number,
a 1×7 array (q0 qx qy qz, x y z in mm) with ``use quaternions`` and the RMS error in mm; MISSING or DISABLED
tools come back as NaN. It gives no port status and never checks ndicapi's error code after TX/BX, so this
driver reads both from ndicapi's cached reply of the same frame (``ndiGet{TX,BX}PortStatus`` /
``ndiGetError``) through the library's ``_device``, ``_capture_string`` and ``_state`` (private in 1.0.6).

Use the frame number, not the host clock, to time samples (fit host ≈ a + b·frame; ~40 Hz on an Aurora).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import numpy as np

from acquisition.devices.base import Device, host_now_ns
from acquisition.errors import (
    DeviceDisconnectedError,
    DeviceNotFoundError,
    DeviceProtocolError,
    DeviceReplyError,
    DeviceTimeoutError,
)

MM = 1e-3  # the wire's millimetres → metres

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrackerFrame:
    """One tool at one tracker frame: position in m, quaternion (q0, qx, qy, qz), RMS error in m.

    ``missing`` frames carry NaN position, quaternion and error (never a zero pose). ``port_status`` holds the
    NDI port status bits (0x01 occupied, 0x10 initialized, 0x20 enabled, 0x40 out of volume, ...).
    """

    host_ns: int
    frame: int
    port_handle: int
    position_m: np.ndarray
    quaternion: np.ndarray
    rms_error: float
    port_status: int
    missing: bool


def _first_line(exc: BaseException) -> str:
    """The first non-empty line of an exception message (the library's are multi-line)."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return lines[0] if lines else type(exc).__name__


class Tracker(Device):
    """NDI Aurora on a serial port path: ``with Tracker("/dev/ttyUSB0") as trk: frame = trk.read()``."""

    kind = "NDI Aurora"

    def __init__(self, port: str, retries: int = 2) -> None:
        super().__init__(str(port), retries)
        self._ndi = None
        self._handles: list[int] = []

    @property
    def port_handles(self) -> list[int]:
        """Port handles of the wired tools found at open."""
        return list(self._handles)

    # lifecycle
    def _open(self) -> None:
        """Connect (probe, init, enable tools) and start tracking."""
        from sksurgerynditracker.nditracker import NDITracker  # imports ndicapy: only when a tracker is used

        config = {"tracker type": "aurora", "serial port": self.port, "use quaternions": True}
        # ndicapi's probe gives the device 0.2 s to answer its first INIT before it falls back to a serial
        # break; a port that exists is probed once more (seen once in ~16 CI runs: the rig's emulator on a
        # busy VM answered late), which costs a port without a tracker at most ~5 s more
        for attempt in range(2):
            try:
                self._ndi = NDITracker(config)
                break
            except (OSError, ValueError, KeyError) as exc:
                if attempt or not os.path.exists(self.port):
                    raise DeviceNotFoundError(
                        f"{self.kind} on {self.port}: no tracker answered ({_first_line(exc)})"
                    ) from exc
                log.warning("%s on %s: the probe went unanswered (%s); probing once more", self.kind,
                            self.port, _first_line(exc))  # fmt: skip
        self._handles, _ = self._ndi.get_tool_descriptions()
        if not self._handles:
            raise DeviceNotFoundError(
                f"{self.kind} on {self.port}: no wired tool found (PHSR lists no handles)"
            )
        self._start_tracking()
        log.info(
            "%s on %s: tracking %d tool(s) with %s", self.kind, self.port, len(self._handles), self._mode()
        )

    def _start_tracking(self) -> None:
        """TSTART, releasing the port exactly once on failure (``NDITracker.start_tracking`` closes it on an
        ERROR reply but not when ndicapy raises OSError for a port error)."""
        import ndicapy

        device = self._ndi._device
        try:
            ndicapy.ndiCommand(device, "TSTART:")
            code = ndicapy.ndiGetError(device)
            problem = "" if code == ndicapy.NDI_OKAY else ndicapy.ndiErrorString(code)
        except OSError as exc:
            problem = _first_line(exc)
        if problem:
            self._close()
            raise DeviceNotFoundError(f"{self.kind} on {self.port}: cannot start tracking ({problem})")
        self._ndi._state = "tracking"

    def _close(self) -> None:
        """TSTOP (best effort) and release the port exactly once (see :meth:`_start_tracking`)."""
        import ndicapy

        ndi, self._ndi = self._ndi, None
        if ndi is None:
            return
        try:
            ndicapy.ndiCommand(ndi._device, "TSTOP:")
        except OSError as exc:  # the port is gone: still release it below
            log.warning("%s on %s: TSTOP failed: %s", self.kind, self.port, _first_line(exc))
        ndi._state = "ready"
        ndi.close()

    def _mode(self) -> str:
        """``TX`` or ``BX``: the reply format the library chose from the firmware revision."""
        return "BX" if str(getattr(self._ndi, "_capture_string", "TX")).startswith("BX") else "TX"

    # reading
    def read(self) -> TrackerFrame:
        """The next frame of the first tool."""
        return self.read_all()[0]

    def read_all(self) -> list[TrackerFrame]:
        """The next frame of every tool (one TX/BX exchange)."""
        if self._ndi is None:
            raise DeviceDisconnectedError(f"{self.kind} on {self.port}: not open")
        return self._retrying("reading a frame", self._read_once)

    def _read_once(self) -> list[TrackerFrame]:
        """One ``get_frame()``, checked for ndicapi errors, converted to SI."""
        import ndicapy

        try:
            handles, _, frames, tracking, quality = self._ndi.get_frame()
        except OSError as exc:  # ndicapy 3.7.6 on a port error: "Error 0x0104: Serial port write error"
            code = ndicapy.ndiGetError(self._ndi._device)
            if code in (ndicapy.NDI_TIMEOUT, ndicapy.NDI_BAD_CRC):
                self._check_error(ndicapy, code)
            raise DeviceDisconnectedError(f"{self.kind} on {self.port}: {_first_line(exc)}") from exc
        host_ns = host_now_ns()
        device = self._ndi._device
        self._check_error(ndicapy, ndicapy.ndiGetError(device))
        get_status = ndicapy.ndiGetBXPortStatus if self._mode() == "BX" else ndicapy.ndiGetTXPortStatus
        out = []
        for handle, frame, pose, rms in zip(handles, frames, tracking, quality, strict=True):
            pose = np.asarray(pose, dtype=float).reshape(7)
            missing = bool(np.isnan(pose).any())
            out.append(
                TrackerFrame(
                    host_ns=host_ns,
                    frame=int(frame),
                    port_handle=int(handle),
                    position_m=np.full(3, np.nan) if missing else pose[4:7] * MM,
                    quaternion=np.full(4, np.nan) if missing else pose[0:4].copy(),
                    rms_error=float("nan") if missing else float(rms) * MM,
                    port_status=int(get_status(device, bytes([handle]))),
                    missing=missing,
                )
            )
        return out

    def _check_error(self, ndicapy, code: int) -> None:
        """Map ndicapi's error code after a frame to the project's errors."""
        if code == ndicapy.NDI_OKAY:
            return
        text = ndicapy.ndiErrorString(code)
        where = f"{self.kind} on {self.port}"
        if code == ndicapy.NDI_BAD_CRC:
            raise DeviceProtocolError(f"{where}: {text}")
        if code == ndicapy.NDI_TIMEOUT:
            raise DeviceTimeoutError(f"{where}: {text}")
        if code in (ndicapy.NDI_READ_ERROR, ndicapy.NDI_WRITE_ERROR, ndicapy.NDI_OPEN_ERROR):
            raise DeviceDisconnectedError(f"{where}: {text} (error 0x{code:X})")
        raise DeviceReplyError(f"{where}: {text} (error 0x{code:02X})")
